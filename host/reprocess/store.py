"""The stage store of ``host reprocess`` (``OUT/stages/``) and the small file helpers it uses.

Every stage's result is written atomically (a temporary file, then a rename) and recorded in
``manifest.json`` with a key: a hash of the stage's inputs and settings.  A later run reuses a
stage whose key and files are still there.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import shutil
import time
import zipfile
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from stereopath.device.formats.fileio import replacing, write_text_atomic

log = logging.getLogger(__name__)

MANIFEST = "manifest.json"
PIPELINE_VERSION = 7  # bump when a stage's computation changes (invalidates stored stages)


def plain(v: Any) -> Any:
    """``v`` as JSON-serialisable Python values (dataclasses, arrays and NumPy scalars unpacked)."""
    if dataclasses.is_dataclass(v) and not isinstance(v, type):
        return plain(dataclasses.asdict(v))
    if isinstance(v, dict):
        return {str(k): plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [plain(x) for x in v]
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, np.generic):
        return v.item()
    return v


def stage_key(*parts: Any) -> str:
    """A short hash of ``parts`` (the identity of a stage's inputs and settings)."""
    text = json.dumps(plain(list(parts)), sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def atomic_write_text(path: Path, text: str) -> None:
    write_text_atomic(path, text, fsync=False)


def save_npz(path: Path, **arrays: Any) -> None:
    """``np.savez`` into a temporary file, then rename (a reader never sees half a file)."""
    with replacing(path) as tmp:
        np.savez(tmp, **arrays)


# what reading a damaged .npz raises: a file cut short or with a damaged directory (BadZipFile), a
# damaged member (BadZipFile: bad CRC, zlib.error), a member cut short (EOFError, ValueError), not an npz at all
UNREADABLE = (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile, zlib.error)


def load_npz(path: Path) -> dict[str, np.ndarray] | None:
    """The arrays of ``path``, or None (logged) when it cannot be read."""
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except UNREADABLE as exc:
        log.warning("%s unreadable (%s): recomputing", path, exc)
        return None


def json_array(obj: Any) -> np.ndarray:
    """``obj`` as a 0-d string array (JSON) for an ``.npz`` file."""
    return np.array(json.dumps(plain(obj)))


def meta(arrs: dict[str, np.ndarray], key: str) -> Any:
    """The JSON value stored by :func:`json_array` under ``key``."""
    return json.loads(str(arrs[key]))


def stored_stats(path: Path) -> dict[str, Any]:
    """The ``stats`` entry of a stored stage file ({} when unreadable)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            return json.loads(str(z["stats"]))
    except UNREADABLE:
        return {}


def copy_atomic(src: Path, dst: Path) -> None:
    """``dst`` becomes a copy of ``src`` (a hard link when the file system allows) by rename."""
    if dst.exists() and os.path.samefile(src, dst):
        return  # already that file (rename would be a no-op and leave the temporary link behind)
    with replacing(dst) as tmp:
        if tmp.exists():
            tmp.unlink()
        try:
            os.link(src, tmp)
        except OSError:
            shutil.copyfile(src, tmp)


def sequence_identity(seq: Any) -> str:
    """Which recording ``seq`` is, whatever path names it: a session's id (its manifest), else its kind and
    resolved path (a relative path, a link, ``..`` or a cluster node's own mount of it name the same one)."""
    man = getattr(seq, "manifest", None)
    sid = man.get("session_id") if isinstance(man, dict) else None
    if isinstance(sid, str) and sid:
        return f"session-id:{sid}"
    kind, sep, path = str(getattr(seq, "spec", "")).partition(":")
    return f"{kind}:{Path(path).resolve()}" if sep and path else f"{kind}{sep}{path}"


def sequence_fingerprint(seq: Any) -> dict[str, Any]:
    """What identifies a sequence's input data cheaply: which recording (:func:`sequence_identity`), frame
    times, rig, IMU extent."""
    from stereopath.device.core.rig import rig_to_dict

    t = np.asarray(seq.t_ns, np.int64)
    imu = getattr(seq, "imu", None)
    return {
        "recording": sequence_identity(seq),
        "frames": int(len(t)),
        "t_ns_sha": hashlib.sha256(t.tobytes()).hexdigest()[:16],
        "rig": stage_key(rig_to_dict(seq.rig)),
        "imu": None if imu is None or not len(imu) else [int(len(imu)), int(imu.t_ns[0]), int(imu.t_ns[-1])],
    }


class StageStore:
    """``OUT/stages/``: stage files plus a manifest of finished stages and their keys."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.path = root / MANIFEST
        self.data: dict[str, Any] = {"format": "stereopath-reprocess", "version": PIPELINE_VERSION, "stages": {}}
        if self.path.is_file():
            try:
                d = json.loads(self.path.read_text())
                if isinstance(d, dict) and isinstance(d.get("stages"), dict):
                    if d.get("version") == PIPELINE_VERSION:
                        self.data = d
                    else:  # its stages' keys hold the old version: none would be reused, none is listed
                        log.info("%s was written by pipeline version %s (now %d): every stage is recomputed",
                                 self.path, d.get("version"), PIPELINE_VERSION)
            except (json.JSONDecodeError, UnicodeDecodeError):
                log.warning("%s is unreadable; all stages will be recomputed", self.path)

    def done(self, name: str, key: str) -> bool:
        ent = self.data["stages"].get(name)
        if not ent or ent.get("key") != key:
            return False
        return all((self.root / f).exists() for f in ent.get("files", []))

    def finish(self, name: str, key: str, files: list[str], seconds: float, settings: Any,
               memory: dict[str, float] | None = None, cpu_seconds: float | None = None,
               cpu_steps: dict[str, float] | None = None) -> None:
        """Record a finished stage (``memory``: its peak resident set and held structures, MB;
        ``cpu_seconds``: the process's CPU time over the stage, user + system, every thread;
        ``cpu_steps``: that of its named steps)."""
        self.data["stages"][name] = {
            "key": key, "files": files, "seconds": round(seconds, 3), "settings": plain(settings),
            "finished_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        }
        if cpu_seconds is not None:
            self.data["stages"][name]["cpu_seconds"] = round(cpu_seconds, 3)
        if cpu_steps:
            self.data["stages"][name]["cpu_steps"] = {k: round(v, 3) for k, v in cpu_steps.items()}
        if memory:
            self.data["stages"][name]["memory"] = memory
        self.root.mkdir(parents=True, exist_ok=True)
        atomic_write_text(self.path, json.dumps(self.data, indent=2) + "\n")

    def forget(self, name: str) -> None:
        if self.data["stages"].pop(name, None) is not None:
            atomic_write_text(self.path, json.dumps(self.data, indent=2) + "\n")

    def seconds(self, name: str) -> float:
        return float(self.data["stages"].get(name, {}).get("seconds", 0.0))
