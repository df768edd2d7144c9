"""Do two reprocessing output folders hold the same results?

Compared byte for byte: ``trajectory.tum``, ``mesh.ply``, ``cloud.ply``; every array of the
stage files (``stages/*.npz``) except the JSON ``stats``/``meta`` records and per-frame times; ``report.json`` and
``map.json`` with their timing fields removed (wall and CPU times differ from run to run, so
those files can never be byte-identical between two runs, fleet or not).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

BYTE_FILES = ("trajectory.tum", "mesh.ply", "cloud.ply")
_UNTIMED_ARRAYS = ("stats", "meta", "frame_ms")  # JSON records with timings, per-frame times


def _timing(key: str) -> bool:
    return key.endswith(("_s", "_ms")) or "seconds" in key or "timings" in key or key == "finished_utc"


def _untimed(v: Any) -> Any:
    if isinstance(v, dict):
        return {k: _untimed(x) for k, x in v.items() if not _timing(str(k))}
    if isinstance(v, list):
        return [_untimed(x) for x in v]
    return v


def _npz_arrays(path: Path) -> dict[str, Any]:
    import numpy as np

    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files if k not in _UNTIMED_ARRAYS}


def differences(a: str | Path, b: str | Path) -> list[str]:
    """What differs between output folders ``a`` and ``b`` (``[]``: the same results)."""
    a, b = Path(a), Path(b)
    diffs: list[str] = []
    for name in BYTE_FILES:
        fa, fb = a / name, b / name
        if fa.is_file() != fb.is_file():
            diffs.append(f"{name}: only in {'the first' if fa.is_file() else 'the second'}")
        elif fa.is_file() and fa.read_bytes() != fb.read_bytes():
            diffs.append(f"{name}: bytes differ")
    na = sorted(p.name for p in (a / "stages").glob("*.npz"))
    nb = sorted(p.name for p in (b / "stages").glob("*.npz"))
    if na != nb:
        diffs.append(f"stage files differ: {na} vs {nb}")
    for name in set(na) & set(nb):
        xa, xb = _npz_arrays(a / "stages" / name), _npz_arrays(b / "stages" / name)
        if sorted(xa) != sorted(xb):
            diffs.append(f"stages/{name}: arrays {sorted(xa)} vs {sorted(xb)}")
            continue
        for k in xa:
            if xa[k].dtype != xb[k].dtype or xa[k].shape != xb[k].shape or xa[k].tobytes() != xb[k].tobytes():
                diffs.append(f"stages/{name}: array {k} differs")
    for name in ("report.json", "map.json"):
        fa, fb = a / name, b / name
        if fa.is_file() != fb.is_file():
            diffs.append(f"{name}: only in {'the first' if fa.is_file() else 'the second'}")
        elif fa.is_file():
            ja, jb = _untimed(json.loads(fa.read_text())), _untimed(json.loads(fb.read_text()))
            if ja != jb:
                keys = sorted(k for k in set(ja) | set(jb) if ja.get(k) != jb.get(k))
                diffs.append(f"{name}: differs in {', '.join(keys)}")
    return diffs
