"""Offscreen preview images of a mesh, rendered with numpy alone (no display, no GPU).

Open3D's ``OffscreenRenderer`` needs EGL or Vulkan, which headless machines (like our CI) often
lack, so the preview is drawn by a small software rasteriser: vertices are projected with a
pinhole camera, every triangle's pixels are enumerated inside its bounding box (triangles are
grouped by box size so the work stays vectorised), inverse depth is interpolated for a z-buffer,
and the nearest fragment of each pixel is shaded with the interpolated vertex normal (a head light
plus a key light, two-sided) times the interpolated vertex colour.

Camera convention as everywhere: ``T_world_cam`` camera-to-world, x right, y down, z forward.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from stereopath.device.errors import StereopathError
from stereopath.device.formats.fileio import write_atomic

log = logging.getLogger(__name__)

MAX_FRAGMENTS_PER_CHUNK = 4_000_000
BACKGROUND_RGB = (255, 255, 255)  # where no triangle covers a pixel
NEAR_M = 1e-3  # triangles with a vertex nearer to the camera than this (or behind it) are not drawn


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """``T_world_cam`` of a camera at ``eye`` looking at ``target`` with image-up along ``up``."""
    eye = np.asarray(eye, float)
    z = np.asarray(target, float) - eye
    n = np.linalg.norm(z)
    if n < 1e-12:
        raise StereopathError("look_at: eye and target coincide")
    z /= n
    up = np.asarray(up, float)
    x = np.cross(-up, z)  # camera y ~ -up (down), x = y cross z (right)
    if np.linalg.norm(x) < 1e-9:  # up parallel to the view direction: pick any perpendicular
        x = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, eye
    return T


def preview_camera(vertices: np.ndarray, size: tuple[int, int] = (960, 720), fov_deg: float = 45.0,
                   view_dir: np.ndarray | None = None, up: np.ndarray | None = None,
                   target: np.ndarray | None = None, elevation_deg: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """``(K, T_world_cam)`` framing ``vertices`` robustly (median centre, 90 % of them in view).

    ``view_dir`` is the world direction the preview camera looks along (default: down the
    vertices' smallest principal axis); ``up`` the world direction shown upwards;
    ``elevation_deg`` tilts the view further down towards ``-up`` (a view from above).
    """
    v = np.asarray(vertices, float).reshape(-1, 3)
    if len(v) == 0:
        raise StereopathError("preview_camera: no vertices")
    centre = np.median(v, axis=0) if target is None else np.asarray(target, float)
    radius = max(float(np.percentile(np.linalg.norm(v - centre, axis=1), 90)), 1e-3)
    if view_dir is None:
        c = np.cov((v - v.mean(axis=0)).T) if len(v) > 3 else np.eye(3)
        _, vecs = np.linalg.eigh(c)
        view_dir = vecs[:, 0]
    d = np.asarray(view_dir, float)
    d /= max(np.linalg.norm(d), 1e-12)
    if up is None:
        up = np.array([0.0, 0.0, 1.0]) if abs(d[2]) < 0.95 else np.array([0.0, 1.0, 0.0])
    up = np.asarray(up, float)
    up = up / max(np.linalg.norm(up), 1e-12)
    if elevation_deg:
        side = np.cross(d, up)
        if np.linalg.norm(side) > 1e-6:
            horiz = d - up * float(np.dot(d, up))
            horiz /= max(np.linalg.norm(horiz), 1e-12)
            angle = np.arcsin(np.clip(-np.dot(d, up), -1.0, 1.0)) + np.radians(elevation_deg)
            angle = np.clip(angle, np.radians(-80), np.radians(80))
            d = horiz * np.cos(angle) - up * np.sin(angle)
    w, h = size
    f = 0.5 * min(w, h) / np.tan(np.radians(fov_deg) / 2)
    dist = radius / np.sin(np.radians(fov_deg) / 2) * 1.05
    T = look_at(centre - d * dist, centre, up)
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])
    return K, T


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals."""
    v = np.asarray(vertices, float)
    t = np.asarray(triangles, np.int64)
    fn = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    n = np.zeros_like(v)
    for k in range(3):
        np.add.at(n, t[:, k], fn)
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return n / np.maximum(norm, 1e-12)


def _fragments(px: np.ndarray, py: np.ndarray, iz: np.ndarray, tri: np.ndarray, size: tuple[int, int]):
    """All covered pixel centres of the triangles ``tri``: (pixel index, inverse depth, triangle, b1, b2)."""
    w, h = size
    x, y = px[tri], py[tri]  # (N, 3)
    x0 = np.clip(np.ceil(x.min(axis=1)), 0, w).astype(np.int64)
    x1 = np.clip(np.floor(x.max(axis=1)), -1, w - 1).astype(np.int64)
    y0 = np.clip(np.ceil(y.min(axis=1)), 0, h).astype(np.int64)
    y1 = np.clip(np.floor(y.max(axis=1)), -1, h - 1).astype(np.int64)
    bw, bh = x1 - x0 + 1, y1 - y0 + 1
    keep = (bw > 0) & (bh > 0)
    den = (x[:, 1] - x[:, 0]) * (y[:, 2] - y[:, 0]) - (x[:, 2] - x[:, 0]) * (y[:, 1] - y[:, 0])
    keep &= np.abs(den) > 1e-12
    span = np.maximum(bw, bh)
    out = []
    ids = np.nonzero(keep)[0]
    if len(ids) == 0:
        return out
    s_bin = np.ceil(np.log2(np.maximum(span[ids], 1))).astype(int)
    for b in np.unique(s_bin):
        s = 1 << int(b)
        sel_all = ids[s_bin == b]
        chunk = max(1, MAX_FRAGMENTS_PER_CHUNK // (s * s))
        oy, ox = np.mgrid[0:s, 0:s]
        ox, oy = ox.reshape(1, -1), oy.reshape(1, -1)
        for c0 in range(0, len(sel_all), chunk):
            sel = sel_all[c0:c0 + chunk]
            qx = x0[sel, None] + ox
            qy = y0[sel, None] + oy
            inside_box = (qx <= x1[sel, None]) & (qy <= y1[sel, None])
            xa, ya = x[sel], y[sel]
            d = den[sel, None]
            # barycentric coordinates of (qx, qy)
            b1 = ((qx - xa[:, 0:1]) * (ya[:, 2:3] - ya[:, 0:1]) - (xa[:, 2:3] - xa[:, 0:1]) * (qy - ya[:, 0:1])) / d
            b2 = ((xa[:, 1:2] - xa[:, 0:1]) * (qy - ya[:, 0:1]) - (qx - xa[:, 0:1]) * (ya[:, 1:2] - ya[:, 0:1])) / d
            b0 = 1.0 - b1 - b2
            eps = -1e-6
            inside = inside_box & (b0 >= eps) & (b1 >= eps) & (b2 >= eps)
            r, cidx = np.nonzero(inside)
            if len(r) == 0:
                continue
            t = sel[r]
            bb1, bb2 = b1[r, cidx], b2[r, cidx]
            zi = iz[tri[t, 0]] * (1 - bb1 - bb2) + iz[tri[t, 1]] * bb1 + iz[tri[t, 2]] * bb2
            out.append((qy[r, cidx] * w + qx[r, cidx], zi, t, bb1, bb2))
    return out


def render_mesh(vertices: np.ndarray, triangles: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray,
                size: tuple[int, int] = (960, 720), vertex_colors: np.ndarray | None = None,
                normals: np.ndarray | None = None) -> np.ndarray:
    """(H, W, 3) uint8 RGB image of a triangle mesh (colours in [0, 1], optional)."""
    v = np.asarray(vertices, float).reshape(-1, 3)
    tri = np.asarray(triangles, np.int64).reshape(-1, 3)
    w, h = int(size[0]), int(size[1])
    img = np.empty((h, w, 3), np.uint8)
    img[:] = np.asarray(BACKGROUND_RGB, np.uint8)
    if len(v) == 0 or len(tri) == 0:
        return img
    if normals is None:
        normals = vertex_normals(v, tri)
    T_cw = np.linalg.inv(np.asarray(T_world_cam, float))
    pc = v @ T_cw[:3, :3].T + T_cw[:3, 3]
    nc = np.asarray(normals, float) @ T_cw[:3, :3].T
    z = pc[:, 2]
    in_front = z > NEAR_M
    tri = tri[in_front[tri].all(axis=1)]
    if len(tri) == 0:
        return img
    zs = np.where(in_front, z, 1.0)
    px = K[0, 0] * pc[:, 0] / zs + K[0, 2]
    py = K[1, 1] * pc[:, 1] / zs + K[1, 2]
    iz = 1.0 / zs
    frags = _fragments(px, py, iz, tri, (w, h))
    if not frags:
        return img
    pix = np.concatenate([f[0] for f in frags])
    zi = np.concatenate([f[1] for f in frags])
    tid = np.concatenate([f[2] for f in frags])
    b1 = np.concatenate([f[3] for f in frags])
    b2 = np.concatenate([f[4] for f in frags])
    order = np.lexsort((-zi, pix))  # by pixel, nearest (largest inverse depth) first
    pix_sorted = pix[order]
    first = np.ones(len(order), bool)
    first[1:] = pix_sorted[1:] != pix_sorted[:-1]
    win = order[first]
    p, t, c1, c2 = pix[win], tid[win], b1[win], b2[win]
    c0 = 1.0 - c1 - c2
    # perspective-correct weights
    ia, ib, ic = iz[tri[t, 0]] * c0, iz[tri[t, 1]] * c1, iz[tri[t, 2]] * c2
    s = ia + ib + ic
    wa, wb, wc = ia / s, ib / s, ic / s

    def interp(attr: np.ndarray) -> np.ndarray:
        return attr[tri[t, 0]] * wa[:, None] + attr[tri[t, 1]] * wb[:, None] + attr[tri[t, 2]] * wc[:, None]

    n = interp(nc)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    pts = interp(pc)
    view = -pts / np.maximum(np.linalg.norm(pts, axis=1, keepdims=True), 1e-12)
    key = np.array([-0.4, -0.6, -0.7])
    key /= np.linalg.norm(key)
    lambert = 0.55 * np.abs(np.sum(n * view, axis=1)) + 0.3 * np.abs(n @ key)
    shade = np.clip(0.18 + lambert, 0.0, 1.0)
    if vertex_colors is not None and len(vertex_colors) == len(v):
        base = np.clip(interp(np.asarray(vertex_colors, float)), 0.0, 1.0)
        base = 0.25 + 0.75 * base  # keep dark texture readable
    else:
        base = np.full((len(p), 3), (0.78, 0.80, 0.85))
    rgb = np.clip(base * shade[:, None] * 255.0 + 0.5, 0, 255).astype(np.uint8)
    img.reshape(-1, 3)[p] = rgb
    return img


def render_mesh_preview(mesh, size: tuple[int, int] = (960, 720), view_dir: np.ndarray | None = None,
                        up: np.ndarray | None = None, target: np.ndarray | None = None,
                        use_colors: bool = True, elevation_deg: float = 0.0) -> np.ndarray:
    """Preview of a legacy Open3D mesh (or anything with ``vertices``/``triangles`` arrays)."""
    v = np.asarray(mesh.vertices, float)
    t = np.asarray(mesh.triangles, np.int64)
    if len(v) == 0 or len(t) == 0:
        raise StereopathError("cannot render a preview of an empty mesh")
    colors = None
    if use_colors and hasattr(mesh, "has_vertex_colors") and mesh.has_vertex_colors():
        colors = np.asarray(mesh.vertex_colors, float)
    normals = np.asarray(mesh.vertex_normals, float) if getattr(mesh, "has_vertex_normals", lambda: False)() else None
    K, T = preview_camera(v, size=size, view_dir=view_dir, up=up, target=target, elevation_deg=elevation_deg)
    return render_mesh(v, t, K, T, size=size, vertex_colors=colors, normals=normals)


def write_png(image_rgb: np.ndarray, path: str | Path) -> Path:
    """Write an RGB uint8 image as PNG atomically (temporary file, then rename)."""
    import cv2

    p = Path(path)
    ok, buf = cv2.imencode(".png", cv2.cvtColor(np.ascontiguousarray(image_rgb), cv2.COLOR_RGB2BGR))
    if not ok:
        raise StereopathError(f"could not encode {p}")
    write_atomic(p, buf.tobytes(), fsync=False)
    return p
