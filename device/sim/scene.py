"""The simulated world: textured planar rectangles (quads) forming a table-top scan scene.

World frame: metres, right-handed, **z up**, gravity ``(0, 0, -9.81)`` m/s^2.

Default scene (:func:`table_top_scene`), all sizes in metres:

* a room ``x, y in [-2, 2]``, ``z in [0, 2.6]``: floor, four walls, ceiling (textures ~4-8 mm/texel);
* a table centred on the origin: a 1.2 x 0.8 x 0.04 top whose upper face is at ``z = 0.75``
  (1 mm/texel) on four 5 x 5 cm legs;
* six objects standing on the table (:data:`OBJECTS`): three cardboard boxes and three books (one
  stacked on another), 0.1-0.36 m, printed with text and shapes (0.6 mm/texel).

A :class:`Quad` is ``origin + a * u + b * v`` for ``a, b in [0, 1]``; its texture's column axis runs
along ``u`` and its row axis along ``v``.  The visible side is the one its :attr:`Quad.normal`
(``v x u``, normalised) points into: seen from there, ``u`` goes right and ``v`` goes down, so the
printed text reads normally.  Each quad has its own texture (``Scene.textures[texture_id]``) whose
size fixes the texel size: ``|u| / width`` by ``|v| / height`` metres.

The objects are kept as :class:`BoxGeometry` (``Scene.boxes``) for mesh-accuracy tests, and
:func:`ground_truth_surfaces` / :func:`point_to_scene_distance` give the true surfaces.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from stereopath.device.core.geometry import rot_z

ROOM_HALF_M = 2.0
ROOM_HEIGHT_M = 2.6
TABLE_TOP_Z_M = 0.75
TABLE_SIZE_M = (1.2, 0.8, 0.04)
TARGET_WORLD = np.array([0.0, 0.0, 0.85])  # where the default trajectories look
GRAVITY_WORLD = np.array([0.0, 0.0, -9.81])
TEXEL_MULTIPLE = 16  # texture sides are multiples of this (mip-maps down to 1/16)

# name, texture style, centre x, centre y, yaw (deg), size x, size y, size z, base z
OBJECTS: tuple[tuple[str, str, float, float, float, float, float, float, float], ...] = (
    ("box_large", "box", -0.28, 0.10, 10.0, 0.36, 0.24, 0.22, TABLE_TOP_Z_M),
    ("box_tall", "box", 0.32, 0.18, -25.0, 0.12, 0.12, 0.30, TABLE_TOP_Z_M),
    ("box_small", "box", 0.05, 0.22, 40.0, 0.15, 0.10, 0.10, TABLE_TOP_Z_M),
    ("book_a", "book", 0.18, -0.18, 35.0, 0.24, 0.17, 0.035, TABLE_TOP_Z_M),
    ("book_c", "book", -0.25, -0.25, -8.0, 0.28, 0.20, 0.045, TABLE_TOP_Z_M),
    ("book_b", "book", -0.23, -0.24, 14.0, 0.21, 0.15, 0.030, TABLE_TOP_Z_M + 0.045),
)


@dataclass(frozen=True, eq=False)
class Quad:
    """A textured rectangle ``origin + a*u + b*v`` (a, b in [0, 1]); ``u`` must be orthogonal to ``v``."""

    origin: np.ndarray
    u: np.ndarray
    v: np.ndarray
    texture_id: int
    metres_per_texel: float
    name: str = ""

    @property
    def normal(self) -> np.ndarray:
        """Unit normal of the visible side (``v x u``)."""
        n = np.cross(self.v, self.u)
        return n / np.linalg.norm(n)

    @property
    def corners(self) -> np.ndarray:
        """(4, 3): origin, origin+u, origin+u+v, origin+v."""
        o, u, v = self.origin, self.u, self.v
        return np.array([o, o + u, o + u + v, o + v])

    @property
    def size_m(self) -> tuple[float, float]:
        return float(np.linalg.norm(self.u)), float(np.linalg.norm(self.v))

    @property
    def center(self) -> np.ndarray:
        return self.origin + 0.5 * (self.u + self.v)


@dataclass(frozen=True, eq=False)
class BoxGeometry:
    """A rectangular box: ``T_world_box`` puts the box frame's origin at the centre of its bottom face
    (x, y along the box sides, z up); ``size`` is (x, y, z) extent in metres."""

    name: str
    T_world_box: np.ndarray
    size: np.ndarray

    def corners_world(self) -> np.ndarray:
        """(8, 3) corners: bottom four (counter-clockwise from -x-y), then the top four."""
        lx, ly, lz = self.size
        xy = np.array([[-lx, -ly], [lx, -ly], [lx, ly], [-lx, ly]]) / 2
        local = np.concatenate([np.c_[xy, np.zeros(4)], np.c_[xy, np.full(4, lz)]])
        return local @ self.T_world_box[:3, :3].T + self.T_world_box[:3, 3]

    def contains(self, points: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Boolean (N,): points inside the box grown by ``margin``."""
        p = np.asarray(points, float).reshape(-1, 3)
        local = (p - self.T_world_box[:3, 3]) @ self.T_world_box[:3, :3]
        lx, ly, lz = self.size
        return ((np.abs(local[:, 0]) <= lx / 2 + margin) & (np.abs(local[:, 1]) <= ly / 2 + margin)
                & (local[:, 2] >= -margin) & (local[:, 2] <= lz + margin))

    def face_quads(self, bottom: bool = False) -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray]]:
        """Outward faces as ``(face name, origin, u, v)`` in the world (text upright on the sides)."""
        R, t = self.T_world_box[:3, :3], self.T_world_box[:3, 3]
        ex, ey, ez = R[:, 0], R[:, 1], R[:, 2]
        lx, ly, lz = self.size
        faces = [
            ("top", t + ez * lz, ez, ey, lx, ly),
            ("+x", t + ex * lx / 2 + ez * lz / 2, ex, ez, ly, lz),
            ("-x", t - ex * lx / 2 + ez * lz / 2, -ex, ez, ly, lz),
            ("+y", t + ey * ly / 2 + ez * lz / 2, ey, ez, lx, lz),
            ("-y", t - ey * ly / 2 + ez * lz / 2, -ey, ez, lx, lz),
        ]
        if bottom:
            faces.append(("bottom", t, -ez, ey, lx, ly))
        return [(name, *facing_quad(c, n, up, w, h)) for name, c, n, up, w, h in faces]


def facing_quad(center: np.ndarray, normal: np.ndarray, up: np.ndarray, width: float,
                height: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(origin, u, v)`` of a rectangle seen from the ``normal`` side with ``up`` pointing up."""
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    up = np.asarray(up, float)
    up = up - n * float(np.dot(up, n))
    up /= np.linalg.norm(up)
    right = np.cross(-n, up)
    c = np.asarray(center, float)
    origin = c - right * width / 2 + up * height / 2
    return origin, right * width, -up * height


@dataclass(eq=False)
class Scene:
    """Quads with their textures, plus the boxes (objects and table parts) they were built from."""

    quads: list[Quad]
    textures: list[np.ndarray]
    boxes: list[BoxGeometry] = field(default_factory=list)
    name: str = "scene"

    def __post_init__(self) -> None:
        for q in self.quads:
            if not 0 <= q.texture_id < len(self.textures):
                raise ValueError(f"quad {q.name!r}: texture id {q.texture_id} out of range")
            if abs(float(np.dot(q.u, q.v))) > 1e-9 * np.linalg.norm(q.u) * np.linalg.norm(q.v) + 1e-12:
                raise ValueError(f"quad {q.name!r}: u and v must be orthogonal")

    def box(self, name: str) -> BoxGeometry:
        for b in self.boxes:
            if b.name == name:
                return b
        raise KeyError(name)

    @property
    def objects(self) -> list[BoxGeometry]:
        """The boxes standing on the table (not the table parts)."""
        return [b for b in self.boxes if not b.name.startswith("table")]


def texture_shape(width_m: float, height_m: float, metres_per_texel: float,
                  multiple: int = TEXEL_MULTIPLE) -> tuple[int, int]:
    """(rows, cols) of a texture covering ``width_m x height_m`` at about ``metres_per_texel``."""
    cols = multiple * max(1, int(round(width_m / metres_per_texel / multiple)))
    rows = multiple * max(1, int(round(height_m / metres_per_texel / multiple)))
    return rows, cols


def _shade(normal: np.ndarray) -> float:
    """Baked Lambert shading of a face under a soft light from above."""
    light = np.array([0.35, 0.25, 1.0])
    light /= np.linalg.norm(light)
    return float(0.6 + 0.4 * max(0.0, float(np.dot(normal, light))))


def _box_pose(cx: float, cy: float, yaw_deg: float, z: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rot_z(np.radians(yaw_deg))
    T[:3, 3] = (cx, cy, z)
    return T


class _Builder:
    def __init__(self, seed: int, f_px: float) -> None:
        self.seed = int(seed)
        self.f_px = f_px
        self.quads: list[Quad] = []
        self.textures: list[np.ndarray] = []

    def add(self, name: str, origin, u, v, style: str, mpt: float, view_dist_m: float, shading: float | None = None) -> None:
        from stereopath.device.sim.textures import make_texture

        q_u, q_v = np.asarray(u, float), np.asarray(v, float)
        shape = texture_shape(np.linalg.norm(q_u), np.linalg.norm(q_v), mpt)
        quad = Quad(np.asarray(origin, float), q_u, q_v, len(self.textures), mpt, name)
        shade = _shade(quad.normal) if shading is None else shading
        texel_px = view_dist_m / (self.f_px * mpt)
        self.textures.append(make_texture(self.seed, shape, style, key=len(self.textures), shading=shade,
                                          texel_px=texel_px))
        self.quads.append(quad)


def table_top_scene(seed: int = 0, focal_px: float = 500.0) -> Scene:
    """The default scene (see the module doc); textures depend on ``seed``, geometry does not."""
    b = _Builder(seed, focal_px)
    H, R = ROOM_HEIGHT_M, ROOM_HALF_M
    z = np.array([0.0, 0.0, 1.0])
    # room: floor, ceiling, walls (normals point inwards)
    b.add("floor", *facing_quad((0, 0, 0), z, (0, 1, 0), 2 * R, 2 * R), "floor", 0.004, 1.8)
    b.add("ceiling", *facing_quad((0, 0, H), -z, (0, 1, 0), 2 * R, 2 * R), "wall", 0.008, 2.5)
    for name, n in (("wall_north", (0, -1, 0)), ("wall_south", (0, 1, 0)), ("wall_east", (-1, 0, 0)),
                    ("wall_west", (1, 0, 0))):
        c = -np.asarray(n, float) * R + z * H / 2
        b.add(name, *facing_quad(c, n, z, 2 * R, H), "wall", 0.004, 2.8)
    boxes: list[BoxGeometry] = []
    # table: top slab and four legs
    tx, ty, tz = TABLE_SIZE_M
    top = BoxGeometry("table_top", _box_pose(0, 0, 0, TABLE_TOP_Z_M - tz), np.array([tx, ty, tz]))
    boxes.append(top)
    for fname, o, u, v in top.face_quads(bottom=True):
        if fname == "top":
            b.add("table_top.top", o, u, v, "wood", 0.001, 0.9)
        else:
            b.add(f"table_top.{fname}", o, u, v, "wood", 0.001, 0.9)
    leg = 0.05
    for i, (sx, sy) in enumerate(((1, 1), (-1, 1), (-1, -1), (1, -1))):
        g = BoxGeometry(f"table_leg{i}", _box_pose(sx * (tx / 2 - 0.05), sy * (ty / 2 - 0.05), 0, 0.0),
                        np.array([leg, leg, TABLE_TOP_Z_M - tz]))
        boxes.append(g)
        for fname, o, u, v in g.face_quads():
            if fname != "top":
                b.add(f"{g.name}.{fname}", o, u, v, "wood", 0.002, 1.5)
    # objects on the table
    for name, style, cx, cy, yaw, lx, ly, lz, base in OBJECTS:
        g = BoxGeometry(name, _box_pose(cx, cy, yaw, base), np.array([lx, ly, lz]))
        boxes.append(g)
        for fname, o, u, v in g.face_quads():
            b.add(f"{name}.{fname}", o, u, v, style, 0.0006, 0.8)
    return Scene(b.quads, b.textures, boxes, name="table_top")


def ground_truth_surfaces(scene: Scene) -> list[tuple[str, np.ndarray]]:
    """``(name, corners (4, 3))`` of every true surface of the scene (world frame)."""
    return [(q.name, q.corners) for q in scene.quads]


def point_to_scene_distance(scene: Scene, points: np.ndarray) -> np.ndarray:
    """(N,) distance in metres from each point to the nearest scene surface (rectangle)."""
    p = np.asarray(points, float).reshape(-1, 3)
    best = np.full(len(p), np.inf)
    for q in scene.quads:
        d = p - q.origin
        a = np.clip(d @ q.u / float(q.u @ q.u), 0.0, 1.0)
        c = np.clip(d @ q.v / float(q.v @ q.v), 0.0, 1.0)
        closest = q.origin + a[:, None] * q.u + c[:, None] * q.v
        np.minimum(best, np.linalg.norm(p - closest, axis=1), out=best)
    return best


def sample_surface_points(scene: Scene, spacing_m: float = 0.01, names: tuple[str, ...] | None = None) -> np.ndarray:
    """(N, 3) points on a regular grid over the surfaces (all, or those whose name starts with one of ``names``)."""
    out = []
    for q in scene.quads:
        if names is not None and not q.name.startswith(names):
            continue
        lu, lv = q.size_m
        a = (np.arange(max(1, int(lu / spacing_m))) + 0.5) / max(1, int(lu / spacing_m))
        c = (np.arange(max(1, int(lv / spacing_m))) + 0.5) / max(1, int(lv / spacing_m))
        A, C = np.meshgrid(a, c)
        out.append(q.origin + A.reshape(-1, 1) * q.u + C.reshape(-1, 1) * q.v)
    return np.concatenate(out) if out else np.zeros((0, 3))
