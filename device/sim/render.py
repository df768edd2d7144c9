"""Rendering the scene from the rig's cameras: exact perspective of textured planes with a z-buffer.

Method (per view, all cameras pinhole; a camera with distortion is rendered on a larger pinhole
canvas first and then resampled through its distortion model):

* Scene quads are cut into render *tiles* (at most ``tile_m`` on a side, texel counts multiples
  of the mip factor) so that each tile can use its own mip level.  Every tile keeps, per mip
  level, a source image: texture values with a one-texel border of the neighbouring texels, and
  two coverage channels, 255 inside the tile's columns resp. rows and 0 on that border (four
  channels in all: OpenCV warps 4-channel images fastest).
* For a camera ``K, T_world_cam`` the plane of a tile maps texture coordinates to pixels by the
  homography ``H = K [R r1, R r2, R r3 + t]`` (ray-plane intersection in closed form), and its
  inverse depth ``1/z`` is an affine function of the pixel coordinates.  Tiles facing away or
  outside the view frustum are culled; for the rest, ``cv2.warpPerspective`` resamples the
  source over the tile's projected bounding box (bilinear), the two interpolated coverage channels
  (each a linear ramp across the tile edge) >= 0.45 decide which pixel centres lie on the tile
  (sub-pixel exact silhouettes, no cracks at shared edges or corners), and a
  per-pixel inverse-depth test keeps the nearest surface.  Tiles crossing the near plane are
  clipped (bounding box) and tested against ``1/near``.  Tiles are drawn nearest first and one
  whose whole bounding box already holds nearer surfaces is skipped.
* Mip maps: each level is the previous one blurred (Gaussian, sigma 0.6) and averaged 2x2, so
  level-L texel centres stay exactly where the texture geometry says.
* Mip level per tile: the texel footprint of one pixel at the tile's centre,
  ``r^2 / (f h texel)`` (``r`` distance, ``h`` plane distance), ``level = floor(log2 + bias)``.
  Stereo pairs use cam0's choice for both eyes so that the two images sample the same level.
* Photometry (``render``): gain (exposure drift) times optional vignetting, Gaussian noise,
  rounding to 8 bits.  The noise comes from a few pre-drawn banks shifted by a random offset per
  frame and eye (deterministic for the seed and frame key; cheap).

``render_view`` returns the noise-free image and the depth (metres along the camera z axis,
0 where no surface was hit).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from stereopath.device.core.geometry import invert_pose
from stereopath.device.core.rig import CameraModel, Rig
from stereopath.device.sim.scene import Scene

log = logging.getLogger(__name__)

MAX_LEVELS = 5  # mip levels 0..4 (1/16 resolution)
_NOISE_BANKS = 3
_NOISE_PAD = 48
# coverage threshold: 0.5 minus a hair (~0.05 texel) so that neighbouring tiles and faces that share an
# edge overlap instead of leaving one-pixel cracks (the depth test resolves the overlap)
_COVERAGE_MIN = 115


@dataclass
class _Tiles:
    """Render tiles as stacked arrays (T tiles, L = MAX_LEVELS)."""

    names: list[str]
    corners: np.ndarray   # (T, 4, 3) world
    origin: np.ndarray    # (T, 3) a point of the plane
    normal: np.ndarray    # (T, 3) unit normal of the visible side
    texel_m: np.ndarray   # (T,) geometric-mean texel size at level 0
    levels: np.ndarray    # (T,) number of mip levels available
    M: np.ndarray         # (T, L, 3, 3): world point = M @ (s, t, 1) for source pixel (s, t)
    src: list[list[np.ndarray]]  # [tile][level] (h+2, w+2, 4) uint8: value, coverage u, coverage v, 0


def _mip_chain(tex: np.ndarray, levels: int) -> list[np.ndarray]:
    out = [tex]
    for _ in range(levels - 1):
        t = out[-1]
        h, w = t.shape
        out.append(cv2.resize(cv2.GaussianBlur(t, (0, 0), 0.6), (w // 2, h // 2), interpolation=cv2.INTER_AREA))
    return out


def _split(n_units: int, parts: int) -> list[int]:
    parts = max(1, min(parts, n_units))
    base = np.full(parts, n_units // parts)
    base[: n_units % parts] += 1
    return [int(v) for v in base]


def _build_tiles(scene: Scene, tile_m: float) -> _Tiles:
    names, corners, origin, normal, texel_m, nlev, Ms, srcs = [], [], [], [], [], [], [], []
    for q in scene.quads:
        tex = scene.textures[q.texture_id]
        if tex.dtype != np.uint8 or tex.ndim != 2:
            raise ValueError(f"quad {q.name!r}: texture must be a 2-D uint8 array")
        th, tw = tex.shape
        L = 0
        while L < MAX_LEVELS - 1 and th % (2 ** (L + 1)) == 0 and tw % (2 ** (L + 1)) == 0:
            L += 1
        levels = L + 1
        unit = 2 ** L
        chain = [cv2.copyMakeBorder(t, 1, 1, 1, 1, cv2.BORDER_REPLICATE) for t in _mip_chain(tex, levels)]
        lu, lv = q.size_m
        uh, vh = q.u / lu, q.v / lv
        mpt_u, mpt_v = lu / tw, lv / th
        n = q.normal
        cols = _split(tw // unit, int(np.ceil(lu / tile_m - 1e-9)))
        rows = _split(th // unit, int(np.ceil(lv / tile_m - 1e-9)))
        t0 = 0
        for ri, nr in enumerate(rows):
            t1 = t0 + nr * unit
            s0 = 0
            for ci, nc in enumerate(cols):
                s1 = s0 + nc * unit
                o = q.origin + s0 * mpt_u * uh + t0 * mpt_v * vh
                eu = (s1 - s0) * mpt_u * uh
                ev = (t1 - t0) * mpt_v * vh
                names.append(q.name if len(rows) * len(cols) == 1 else f"{q.name}[{ri},{ci}]")
                corners.append([o, o + eu, o + eu + ev, o + ev])
                origin.append(o)
                normal.append(n)
                texel_m.append(np.sqrt(mpt_u * mpt_v))
                nlev.append(levels)
                M = np.zeros((MAX_LEVELS, 3, 3))
                tile_src = []
                for lev in range(MAX_LEVELS):
                    le = min(lev, levels - 1)
                    sc = 2 ** le
                    a0, a1, b0, b1 = s0 // sc, s1 // sc, t0 // sc, t1 // sc
                    M[lev, :, 0] = sc * mpt_u * uh
                    M[lev, :, 1] = sc * mpt_v * vh
                    M[lev, :, 2] = q.origin + (a0 - 0.5) * sc * mpt_u * uh + (b0 - 0.5) * sc * mpt_v * vh
                    if lev < levels:
                        val = chain[le][b0:b1 + 2, a0:a1 + 2]
                        four = np.zeros(val.shape + (4,), np.uint8)
                        four[:, :, 0] = val
                        four[:, 1:-1, 1] = 255  # inside along u (columns)
                        four[1:-1, :, 2] = 255  # inside along v (rows)
                        tile_src.append(four)
                Ms.append(M)
                srcs.append(tile_src)
                s0 = s1
            t0 = t1
    return _Tiles(names, np.asarray(corners, float).reshape(-1, 4, 3), np.asarray(origin, float).reshape(-1, 3),
                  np.asarray(normal, float).reshape(-1, 3), np.asarray(texel_m, float), np.asarray(nlev, int),
                  np.asarray(Ms, float).reshape(-1, MAX_LEVELS, 3, 3), srcs)


def _clip_near(poly: np.ndarray, near: float) -> np.ndarray:
    """Sutherland-Hodgman clip of a convex polygon (N, 3) in camera coordinates to ``z >= near``."""
    out = []
    n = len(poly)
    for i in range(n):
        a, b = poly[i], poly[(i + 1) % n]
        ina, inb = a[2] >= near, b[2] >= near
        if ina:
            out.append(a)
        if ina != inb:
            s = (near - a[2]) / (b[2] - a[2])
            out.append(a + s * (b - a))
    return np.asarray(out).reshape(-1, 3)


class _DistortionWarp:
    """Renders a distorted camera through a larger ideal pinhole canvas and a remap."""

    def __init__(self, cam: CameraModel) -> None:
        w, h = cam.size
        xs, ys = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        pts = np.stack([xs.ravel(), ys.ravel()], 1).reshape(-1, 1, 2)
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10)
        if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4.x
            und = cv2.undistortPointsIter(pts, cam.K, cam.dist, None, None, crit).reshape(-1, 2)
        else:  # OpenCV 5: criteria is a keyword of undistortPoints
            und = cv2.undistortPoints(pts, cam.K, cam.dist, R=None, P=None, criteria=crit).reshape(-1, 2)
        # polish with Newton-like fixed-point steps on the forward model (exact to ~1e-6 px)
        for _ in range(3):
            obj = np.concatenate([und, np.ones((len(und), 1))], 1)
            proj = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), cam.K, cam.dist)[0].reshape(-1, 2)
            resid = pts.reshape(-1, 2) - proj
            und = und + resid / np.array([cam.fx, cam.fy])
        fx, fy = cam.fx, cam.fy
        px = und[:, 0] * fx
        py = und[:, 1] * fy
        margin = 2.0
        cx = -float(px.min()) + margin
        cy = -float(py.min()) + margin
        self.size = (int(np.ceil(px.max() + cx + margin)) + 1, int(np.ceil(py.max() + cy + margin)) + 1)
        self.K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
        self.mapx = (px + cx).reshape(h, w).astype(np.float32)
        self.mapy = (py + cy).reshape(h, w).astype(np.float32)

    def apply(self, img: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        out = cv2.remap(img, self.mapx, self.mapy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        d = cv2.remap(depth, self.mapx, self.mapy, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
        return out, d


@dataclass(frozen=True)
class RenderDetail:
    """How a :class:`Renderer` samples the scene: ``lod_bias`` shifts the mip level choice (positive =
    blurrier); ``tile_m`` the largest render tile side; ``near_m`` the near plane; ``background`` the
    grey level where no surface is seen."""

    lod_bias: float = 0.25
    tile_m: float = 1.0
    near_m: float = 0.05
    background: int = 0


class Renderer:
    """Renders ``scene`` for ``rig`` (see the module doc).

    ``noise_sigma`` (DN) is the photometric noise of :meth:`render`; ``vignetting`` the relative
    brightness loss in the image corners (0 = none); ``detail`` the sampling settings.
    A renderer keeps scratch buffers: use one per thread.
    """

    def __init__(self, scene: Scene, rig: Rig, *, noise_sigma: float = 2.0, seed: int = 0,
                 vignetting: float = 0.0, detail: RenderDetail = RenderDetail()) -> None:
        if noise_sigma < 0:
            raise ValueError("noise_sigma must be >= 0")
        if detail.near_m <= 0:
            raise ValueError("near_m must be > 0")
        self.scene = scene
        self.rig = rig
        self.noise_sigma = float(noise_sigma)
        self.seed = int(seed)
        self.vignetting = float(vignetting)
        self.lod_bias = float(detail.lod_bias)
        self.near_m = float(detail.near_m)
        self.background = int(detail.background)
        tile_m = float(detail.tile_m)
        cache = scene.__dict__.setdefault("_render_tiles", {})  # tiles depend on the scene only
        if tile_m not in cache:
            cache[tile_m] = _build_tiles(scene, tile_m)
        self.tiles = cache[tile_m]
        self._distortion: dict[int, _DistortionWarp] = {}
        self._noise: tuple[np.ndarray, np.ndarray] | None = None
        self._vignette: dict[tuple[int, int], np.ndarray] = {}
        self._grids: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
        self._scratch = np.zeros((0, 0), np.float32)
        log.debug("renderer: %d quads -> %d tiles", len(scene.quads), len(self.tiles.names))

    # ------------------------------------------------------------------ geometry

    def lod_levels(self, K: np.ndarray, T_world_cam: np.ndarray) -> np.ndarray:
        """(T,) mip level of every tile for a camera with intrinsics ``K`` at ``T_world_cam``."""
        tl = self.tiles
        T_cw = invert_pose(np.asarray(T_world_cam, float))
        centre = tl.corners.mean(axis=1) @ T_cw[:3, :3].T + T_cw[:3, 3]
        r2 = np.einsum("ij,ij->i", centre, centre)
        C = np.asarray(T_world_cam, float)[:3, 3]
        h = np.abs(np.einsum("ij,ij->i", tl.normal, C - tl.origin))
        f = 0.5 * (float(K[0, 0]) + float(K[1, 1]))
        fp = r2 / (f * np.maximum(h, 1e-6) * tl.texel_m)
        lev = np.floor(np.log2(np.maximum(fp, 1e-6)) + self.lod_bias)
        return np.clip(lev, 0, tl.levels - 1).astype(int)

    def _grid(self, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        if size not in self._grids:
            self._grids[size] = (np.arange(size[0], dtype=np.float32), np.arange(size[1], dtype=np.float32))
        return self._grids[size]

    def _cull(self, K: np.ndarray, size: tuple[int, int], R: np.ndarray, t: np.ndarray,
              C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Tiles facing the camera and not wholly outside the view frustum: (indices, corners in camera frame)."""
        w, h = size
        tl = self.tiles
        fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
        facing = np.einsum("ij,ij->i", tl.normal, C - tl.origin) > 1e-9
        idx = np.nonzero(facing)[0]
        if len(idx) == 0:
            return idx, np.zeros((0, 4, 3))
        Xc = tl.corners[idx] @ R.T + t  # (n, 4, 3)
        m = 2.0
        planes = np.array([
            [0.0, 0.0, 1.0, -self.near_m],
            [fx, 0.0, cx + 0.5 + m, 0.0],
            [-fx, 0.0, w - 0.5 + m - cx, 0.0],
            [0.0, fy, cy + 0.5 + m, 0.0],
            [0.0, -fy, h - 0.5 + m - cy, 0.0],
        ])
        dist = Xc @ planes[:, :3].T + planes[:, 3]  # (n, 4, 5)
        keep = ~np.any(np.all(dist < 0, axis=1), axis=1)
        return idx[keep], Xc[keep]

    def _tile_window(self, K: np.ndarray, size: tuple[int, int], Xc: np.ndarray, crosses: bool,
                     box: np.ndarray, zmin: float) -> tuple[int, int, int, int, float] | None:
        """Pixel window ``(x0, x1, y0, y1)`` of a tile and its largest inverse depth (None: nothing to draw)."""
        w, h = size
        fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
        if crosses:
            poly = _clip_near(Xc, self.near_m)
            if len(poly) < 3:
                return None
            u = fx * poly[:, 0] / poly[:, 2] + cx
            v = fy * poly[:, 1] / poly[:, 2] + cy
            bx = (np.floor(u.min()) - 1, np.ceil(u.max()) + 2, np.floor(v.min()) - 1, np.ceil(v.max()) + 2)
            w_max = 1.0 / float(poly[:, 2].min())
        else:
            bx = box
            w_max = 1.0 / float(zmin)
        x0, x1 = max(0, int(bx[0])), min(w, int(bx[1]))
        y0, y1 = max(0, int(bx[2])), min(h, int(bx[3]))
        if x1 <= x0 or y1 <= y0:
            return None
        return x0, x1, y0, y1, w_max

    def _draw_tile(self, img: np.ndarray, zbuf: np.ndarray, window: tuple[int, int, int, int], H: np.ndarray,
                   r: np.ndarray, src: np.ndarray, grid: tuple[np.ndarray, np.ndarray], clip_near: bool) -> None:
        """Warp one tile's texture into ``window`` and keep its pixels that are nearer than the z-buffer."""
        x0, x1, y0, y1 = window
        xs, ys = grid
        Hk = H.copy()
        Hk[0] -= x0 * Hk[2]
        Hk[1] -= y0 * Hk[2]
        bw, bh = x1 - x0, y1 - y0
        warped = cv2.warpPerspective(src, Hk, (bw, bh), flags=cv2.INTER_LINEAR,
                                     borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        wz = self._scratch[:bh, :bw]
        col = (r[1] * ys[y0:y1] + r[2]).astype(np.float32)
        row = (r[0] * xs[x0:x1]).astype(np.float32)
        np.add(col[:, None], row[None, :], out=wz)
        zb = zbuf[y0:y1, x0:x1]
        cond = warped[:, :, 1] >= _COVERAGE_MIN
        cond &= warped[:, :, 2] >= _COVERAGE_MIN
        cond &= wz > zb
        if clip_near:
            cond &= wz < 1.0 / self.near_m
        np.copyto(img[y0:y1, x0:x1], warped[:, :, 0], where=cond)
        np.copyto(zb, wz, where=cond)

    def _rasterize(self, K: np.ndarray, size: tuple[int, int], T_world_cam: np.ndarray,
                   levels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Noise-free image (uint8) and inverse depth (float32, 0 = nothing) of an ideal pinhole camera."""
        w, h = size
        tl = self.tiles
        T_wc = np.asarray(T_world_cam, float)
        T_cw = invert_pose(T_wc)
        R, t = T_cw[:3, :3], T_cw[:3, 3]
        fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
        img = np.full((h, w), self.background, np.uint8)
        zbuf = np.zeros((h, w), np.float32)
        if self._scratch.shape[0] < h or self._scratch.shape[1] < w:
            self._scratch = np.empty((max(h, self._scratch.shape[0]), max(w, self._scratch.shape[1])), np.float32)
        idx, Xc = self._cull(K, size, R, t, T_wc[:3, 3])
        if len(idx) == 0:
            return img, zbuf
        crosses = np.any(Xc[:, :, 2] < self.near_m, axis=1)

        # plane of each tile in camera coordinates -> inverse depth 1/z = r . (x, y, 1)
        n_c = tl.normal[idx] @ R.T
        d_c = np.einsum("ij,ij->i", n_c, tl.origin[idx] @ R.T + t)
        r = (n_c @ np.linalg.inv(K)) / d_c[:, None]  # (n, 3)
        # homographies source pixel -> image pixel
        lev = levels[idx]
        G = np.einsum("ij,njk->nik", R, tl.M[idx, lev])
        G[:, :, 2] += t
        H = np.einsum("ij,njk->nik", K, G)

        # bounding boxes (vectorised for tiles entirely in front of the near plane)
        with np.errstate(divide="ignore", invalid="ignore"):
            U = fx * Xc[:, :, 0] / Xc[:, :, 2] + cx
            V = fy * Xc[:, :, 1] / Xc[:, :, 2] + cy
        zmin = Xc[:, :, 2].min(axis=1)
        boxes = np.stack([np.floor(U.min(1)) - 1, np.ceil(U.max(1)) + 2, np.floor(V.min(1)) - 1, np.ceil(V.max(1)) + 2], 1)
        grid = self._grid(size)
        # nearest first, so that fully hidden tiles can be skipped by a cheap z-buffer test
        for k in np.argsort(zmin):
            win = self._tile_window(K, size, Xc[k], bool(crosses[k]), boxes[k], zmin[k])
            if win is None:
                continue
            x0, x1, y0, y1, w_max = win
            if w_max < float(zbuf[y0:y1, x0:x1].min()):  # every pixel already has a nearer surface
                continue
            self._draw_tile(img, zbuf, (x0, x1, y0, y1), H[k], r[k], tl.src[idx[k]][lev[k]], grid, bool(crosses[k]))
        return img, zbuf

    def render_view(self, K: np.ndarray, size: tuple[int, int], T_world_cam: np.ndarray,
                    dist: np.ndarray | None = None, levels: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Noise-free ``(image uint8 (h, w), depth float32 (h, w))`` of a camera ``K``, ``size = (w, h)``.

        ``depth`` is metres along the camera's z axis (0 where nothing was hit).  ``dist`` are
        OpenCV distortion coefficients (None or zeros: ideal pinhole); ``levels`` a mip level per
        render tile (default: chosen for this camera).
        """
        K = np.asarray(K, float)
        size = (int(size[0]), int(size[1]))
        if dist is not None and np.any(np.asarray(dist) != 0):
            key = hash((K.tobytes(), np.asarray(dist, float).tobytes(), size))
            if key not in self._distortion:
                self._distortion[key] = _DistortionWarp(CameraModel(K, np.asarray(dist, float).reshape(-1), size))
            dw = self._distortion[key]
            if levels is None:
                levels = self.lod_levels(dw.K, T_world_cam)
            img, inv = self._rasterize(dw.K, dw.size, T_world_cam, levels)
            return dw.apply(img, _depth_from_inverse(inv))
        if levels is None:
            levels = self.lod_levels(K, T_world_cam)
        img, inv = self._rasterize(K, size, T_world_cam, levels)
        return img, _depth_from_inverse(inv)

    def _render_pair(self, T_world_cam0: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        rig = self.rig
        levels = self.lod_levels(rig.cam0.K, T_world_cam0)
        left, depth0 = self.render_view(rig.cam0.K, rig.cam0.size, T_world_cam0, rig.cam0.dist, levels)
        T_world_cam1 = np.asarray(T_world_cam0, float) @ rig.T_cam0_cam1
        right, _ = self.render_view(rig.cam1.K, rig.cam1.size, T_world_cam1, rig.cam1.dist, levels)
        return left, right, depth0

    # ------------------------------------------------------------------ photometry

    def _noise_banks(self) -> tuple[np.ndarray, np.ndarray]:
        if self._noise is None:
            w = max(self.rig.cam0.size[0], self.rig.cam1.size[0]) + _NOISE_PAD
            h = max(self.rig.cam0.size[1], self.rig.cam1.size[1]) + _NOISE_PAD
            rng = np.random.default_rng([self.seed & 0xFFFFFFFF, 0x5EED, 1])
            f = rng.standard_normal((_NOISE_BANKS, h, w), dtype=np.float32) * np.float32(self.noise_sigma)
            self._noise = (f, np.round(f).astype(np.int16))
        return self._noise

    def _vignette_map(self, size: tuple[int, int]) -> np.ndarray:
        if size not in self._vignette:
            w, h = size
            x = (np.arange(w, dtype=np.float32) - (w - 1) / 2) / (w / 2)
            y = (np.arange(h, dtype=np.float32) - (h - 1) / 2) / (h / 2)
            r2 = (x[None, :] ** 2 + y[:, None] ** 2) / 2.0  # 1 in the corners
            self._vignette[size] = (1.0 - self.vignetting * r2).astype(np.float32)
        return self._vignette[size]

    def photometric(self, img: np.ndarray, key: int, eye: int, gain: float = 1.0, noise: bool = True) -> np.ndarray:
        """Gain, vignetting and noise applied to a noise-free render (``key`` selects the noise draw).

        ``img`` is uint8 or float32 (an averaged, motion-blurred render); the result is rounded to
        the nearest integer and saturated to uint8.
        """
        h, w = img.shape
        scale: float | np.ndarray | None = None
        if self.vignetting != 0.0:
            scale = self._vignette_map((w, h)) * np.float32(gain)
        elif gain != 1.0:
            scale = float(gain)
        if scale is not None:
            img = cv2.multiply(img, scale, dtype=cv2.CV_32F)
        if self.noise_sigma == 0.0 or not noise:
            if img.dtype == np.uint8:
                return img.copy()
            return cv2.add(img, np.zeros_like(img), dtype=cv2.CV_8U)
        fbank, ibank = self._noise_banks()
        rng = np.random.default_rng([self.seed & 0xFFFFFFFF, int(key) & 0xFFFFFFFF, int(eye), 0xA0153])
        b = int(rng.integers(0, _NOISE_BANKS))
        oy = int(rng.integers(0, fbank.shape[1] - h + 1))
        ox = int(rng.integers(0, fbank.shape[2] - w + 1))
        if img.dtype == np.uint8:
            return cv2.add(img, ibank[b, oy:oy + h, ox:ox + w], dtype=cv2.CV_8U)
        return cv2.add(img.astype(np.float32, copy=False), fbank[b, oy:oy + h, ox:ox + w], dtype=cv2.CV_8U)

    def render(self, T_world_cam0: np.ndarray, *, key: int = 0, gains: tuple[float, float] = (1.0, 1.0),
               noise: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(left uint8, right uint8, depth0 float32)`` of the rig at ``T_world_cam0``.

        ``T_world_cam0`` may also be a stack ``(S, 4, 4)`` of poses spread over the exposure:
        the images are then the average of the sub-frame renders (motion blur) and the depth is
        that of the middle pose.  ``key`` selects the noise realisation (e.g. the frame index),
        ``gains`` the exposure gain of each eye.
        """
        T = np.asarray(T_world_cam0, float)
        if T.shape == (4, 4):
            left, right, depth0 = self._render_pair(T)
        elif T.ndim == 3 and T.shape[1:] == (4, 4) and len(T) >= 1:
            accl = accr = None
            depth0 = None
            mid = len(T) // 2
            for j, Tj in enumerate(T):
                l, r, d = self._render_pair(Tj)
                accl = l.astype(np.float32) if accl is None else accl + l
                accr = r.astype(np.float32) if accr is None else accr + r
                if j == mid:
                    depth0 = d
            left, right = accl / len(T), accr / len(T)
        else:
            raise ValueError(f"T_world_cam0 must be (4, 4) or (S, 4, 4), got {T.shape}")
        left = self.photometric(left, key, 0, gains[0], noise)
        right = self.photometric(right, key, 1, gains[1], noise)
        return left, right, depth0


def _depth_from_inverse(inv: np.ndarray) -> np.ndarray:
    depth = np.zeros_like(inv)
    np.divide(1.0, inv, out=depth, where=inv > 0)
    return depth
