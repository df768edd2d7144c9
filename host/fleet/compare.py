"""Do two reprocessing output folders hold the same results?

Compared byte for byte: ``trajectory.tum``, ``mesh.ply``, ``cloud.ply``; every array of the
stage files (``stages/*.npz``: estimate, tracks, ba) except the per-frame times; their JSON
``stats``/``meta`` records, ``report.json`` and ``map.json`` with their timing fields removed
(wall and CPU times differ from run to run, so those records can never be equal between two
runs, fleet or not; neither can the ``.npz`` files themselves, whose zip entries carry the time
they were written).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

from stereopath.host.evaluation.report import JsonValue

if TYPE_CHECKING:
    import numpy as np

BYTE_FILES = ("trajectory.tum",)
PLY_FILES = ("mesh.ply", "cloud.ply")
_TIMES = ("frame_ms",)  # per-frame times: left out
_RECORDS = ("stats", "meta")  # JSON records: compared without their timing fields


def _timing(key: str) -> bool:
    return (key.endswith(("_s", "_ms")) or "_ms_" in key or "seconds" in key or "timings" in key
            or key in ("finished_utc", "stages"))


def _untimed(v: JsonValue) -> JsonValue:
    if isinstance(v, dict):
        return {k: _untimed(x) for k, x in v.items() if not _timing(str(k))}
    if isinstance(v, list):
        return [_untimed(x) for x in v]
    return v


def npz_contents(path: Path) -> dict[str, Any]:
    """A stage file's arrays, its JSON records as untimed values, without the per-frame times."""
    import numpy as np

    with np.load(path, allow_pickle=False) as z:
        return {k: _untimed(json.loads(str(z[k]))) if k in _RECORDS else z[k] for k in z.files if k not in _TIMES}


def _same(x: np.ndarray | dict[str, JsonValue], y: np.ndarray | dict[str, JsonValue]) -> bool:
    if isinstance(x, dict) or isinstance(y, dict):
        return x == y
    return x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes()


def _rows(*arrays: np.ndarray) -> np.ndarray:
    import numpy as np

    cols = [np.asarray(x, np.float64).reshape(len(arrays[0]), -1) for x in arrays if len(x)]
    return np.hstack(cols) if cols else np.zeros((0, 0))


def ply_canonical(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """A PLY's elements in a canonical order: (vertex rows, triangle rows) as float arrays.

    Vertex rows are position, normal, colour, sorted; triangles are rewritten with the sorted
    vertex ranks, rotated to start at their smallest rank (orientation kept), and sorted.
    Vertices whose rows are equal share one rank: marching cubes can emit the same vertex twice,
    and which copy a triangle uses depends on the order the threads wrote them in, not on the model.
    So this compares the geometry (which positions, normals and colours each triangle joins), not
    which copies of a duplicated vertex the triangles share.
    """
    import numpy as np
    import open3d as o3d

    with open(path, "rb") as f:
        header = f.read(4096).split(b"end_header")[0]
    mesh = o3d.io.read_triangle_mesh(str(path)) if b"element face" in header else None
    if mesh is not None and len(mesh.triangles):
        v = _rows(np.asarray(mesh.vertices), np.asarray(mesh.vertex_normals), np.asarray(mesh.vertex_colors))
        tri = np.asarray(mesh.triangles)
    else:
        pc = o3d.io.read_point_cloud(str(path))
        v = _rows(np.asarray(pc.points), np.asarray(pc.normals), np.asarray(pc.colors))
        tri = np.zeros((0, 3), np.int64)
    order = np.lexsort(v.T[::-1]) if len(v) else np.zeros(0, np.int64)
    rank = np.empty(len(v), np.int64)
    if len(v):  # the rank of a row: how many distinct rows sort before it
        vs = v[order]
        rank[order] = np.cumsum(np.r_[False, np.any(vs[1:] != vs[:-1], axis=1)])
    t = rank[tri] if len(tri) else tri
    if len(t):  # each triangle at its lexicographically smallest rotation (ranks may repeat in one)
        best = t.copy()
        for k in (1, 2):
            c = np.roll(t, -k, axis=1)
            less = (c[:, 0] < best[:, 0]) | ((c[:, 0] == best[:, 0]) & (
                (c[:, 1] < best[:, 1]) | ((c[:, 1] == best[:, 1]) & (c[:, 2] < best[:, 2]))))
            best[less] = c[less]
        t = best[np.lexsort(best.T[::-1])]
    return v[order], t


def _unlabelled(record: dict[str, Any]) -> dict[str, Any]:
    """``record`` without its ``source`` label, and the label's path replaced in every text."""
    src = record.get("source")

    def walk(v: JsonValue) -> JsonValue:
        if isinstance(v, dict):
            return {k: walk(x) for k, x in v.items() if k != "source"}
        if isinstance(v, list):
            return [walk(x) for x in v]
        return v.replace(src, "<source>") if isinstance(v, str) and isinstance(src, str) and src else v

    return walk(record)


def differences(a: str | Path, b: str | Path, ignore_source: bool = False) -> list[str]:
    """What differs between output folders ``a`` and ``b`` (``[]``: the same results).

    ``ignore_source``: leave out the ``source`` labels (the session path as the process that
    reprocessed it saw it: another path on a cluster worker that sees the data elsewhere), also
    where a message quotes that path.
    """
    a, b = Path(a), Path(b)
    diffs: list[str] = []
    for name in BYTE_FILES:
        fa, fb = a / name, b / name
        if fa.is_file() != fb.is_file():
            diffs.append(f"{name}: only in {'the first' if fa.is_file() else 'the second'}")
        elif fa.is_file() and fa.read_bytes() != fb.read_bytes():
            diffs.append(f"{name}: bytes differ")
    for name in PLY_FILES:
        fa, fb = a / name, b / name
        if fa.is_file() != fb.is_file():
            diffs.append(f"{name}: only in {'the first' if fa.is_file() else 'the second'}")
        elif fa.is_file() and fa.read_bytes() != fb.read_bytes():
            (va, ta), (vb, tb) = ply_canonical(fa), ply_canonical(fb)
            if va.shape != vb.shape or va.tobytes() != vb.tobytes() or ta.shape != tb.shape \
                    or ta.tobytes() != tb.tobytes():
                diffs.append(f"{name}: elements differ")
    na = sorted(p.name for p in (a / "stages").glob("*.npz"))
    nb = sorted(p.name for p in (b / "stages").glob("*.npz"))
    if na != nb:
        diffs.append(f"stage files differ: {na} vs {nb}")
    for name in set(na) & set(nb):
        xa, xb = npz_contents(a / "stages" / name), npz_contents(b / "stages" / name)
        if sorted(xa) != sorted(xb):
            diffs.append(f"stages/{name}: arrays {sorted(xa)} vs {sorted(xb)}")
            continue
        for k in xa:
            if not _same(xa[k], xb[k]):
                diffs.append(f"stages/{name}: {k} differs")
    for name in ("report.json", "map.json"):
        fa, fb = a / name, b / name
        if fa.is_file() != fb.is_file():
            diffs.append(f"{name}: only in {'the first' if fa.is_file() else 'the second'}")
        elif fa.is_file():
            ja, jb = _untimed(json.loads(fa.read_text())), _untimed(json.loads(fb.read_text()))
            if ignore_source:
                ja, jb = _unlabelled(ja), _unlabelled(jb)
            if ja != jb:
                keys = sorted(k for k in set(ja) | set(jb) if ja.get(k) != jb.get(k))
                diffs.append(f"{name}: differs in {', '.join(keys)}")
    return diffs
