"""The output folder of an export: refused when it holds anything (unless ``force``), written whole or not at all.

Everything is written into a hidden folder beside ``--out`` (the temporary name of
:func:`stereopath.device.formats.fileio.temp_path`: same file system, so the last step is one
rename); only when the export finished is it renamed to ``--out``.  With ``force`` an existing
``--out`` is moved aside first and removed after the rename.  A failure or Ctrl-C removes the
temporary folder and leaves ``--out`` as it was.
"""

from __future__ import annotations

import logging
import os
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from stereopath.device.errors import ConfigError
from stereopath.device.formats.fileio import check_out_folder, fsync_dir, temp_path

log = logging.getLogger(__name__)


def check_export_out(out: str | Path, force: bool, inputs: list[str | Path] = ()) -> Path:
    """``out`` checked before any work: not an input, not a recorded session, writable, and empty
    unless ``force`` (ConfigError naming the folder otherwise)."""
    p = Path(out)
    check_out_folder(p, option="--out", inputs=inputs, not_a_session=True)
    if p.is_dir() and any(p.iterdir()) and not force:
        raise ConfigError(f"--out {p}: exists and is not empty; give a new folder or --force to replace it")
    return p


@contextmanager
def staged_folder(out: str | Path) -> Iterator[Path]:
    """``with staged_folder(out) as tmp: write into tmp``; ``tmp`` becomes ``out`` when the block succeeds."""
    dst = Path(out).absolute()
    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_path(dst)
    if tmp.exists():  # left by a killed run of this same process id
        shutil.rmtree(tmp)
    tmp.mkdir()
    try:
        yield tmp
        old = None
        if dst.exists():
            old = dst.with_name(f".{dst.name}.{os.getpid()}.old.tmp")
            os.replace(dst, old)
        try:
            os.replace(tmp, dst)
        except BaseException:
            if old is not None:  # put the previous export back
                os.replace(old, dst)
            raise
        fsync_dir(dst.parent)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
