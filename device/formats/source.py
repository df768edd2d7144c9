"""``open_source(spec)``: one string names any recorded sequence.

Specs: ``kitti:DIR`` (a KITTI odometry sequence folder), ``euroc:DIR`` (an ASL ``mav0`` folder or
the folder containing it), ``session:DIR`` (one of our recordings), ``sim[:SEED]`` (the simulator,
see :mod:`stereopath.device.sim.source`).  Other schemes plug in through :func:`register_source`: an opener
receives the text after the colon (``""`` when there is none) and returns an object with the
sequence interface of :mod:`stereopath.device.formats.sequence`.
"""

from __future__ import annotations

from typing import Any, Callable

from stereopath.device.errors import DatasetError

Opener = Callable[[str], Any]


def _kitti(arg: str) -> Any:
    from stereopath.device.formats.kitti import open_kitti

    return open_kitti(arg, spec=f"kitti:{arg}")


def _euroc(arg: str) -> Any:
    from stereopath.device.formats.asl import open_asl

    return open_asl(arg, spec=f"euroc:{arg}")


def _session(arg: str) -> Any:
    from stereopath.device.formats.asl import open_session

    return open_session(arg)


def _sim(arg: str) -> Any:
    from stereopath.device.sim.source import open_sim_spec  # sim[:SEED or key=value,...]

    return open_sim_spec(arg)


# scheme -> opener(ARG); more sources plug in here or through register_source (imports inside the
# openers so that importing this module stays cheap).
_OPENERS: dict[str, Opener] = {"kitti": _kitti, "euroc": _euroc, "session": _session, "sim": _sim}


def register_source(scheme: str, opener: Opener) -> None:
    """Make ``open_source(f"{scheme}:ARG")`` call ``opener(ARG)``."""
    _OPENERS[scheme] = opener


def source_schemes() -> list[str]:
    return sorted(_OPENERS)


def parse_spec(spec: str) -> tuple[str, str]:
    """``"kitti:/a/b"`` -> ``("kitti", "/a/b")``; ``"sim"`` -> ``("sim", "")``."""
    scheme, sep, arg = str(spec).partition(":")
    scheme = scheme.strip().lower()
    if not scheme or (not sep and scheme not in _OPENERS):
        raise DatasetError(f"source {spec!r}: expected SCHEME:ARG with SCHEME one of {', '.join(source_schemes())}")
    return scheme, arg


def open_source(spec: str) -> Any:
    """Open the sequence named by ``spec`` (see the module doc)."""
    scheme, arg = parse_spec(spec)
    opener = _OPENERS.get(scheme)
    if opener is None:
        raise DatasetError(f"source {spec!r}: unknown scheme {scheme!r} (known: {', '.join(source_schemes())})")
    if scheme in ("kitti", "euroc", "session") and not arg:
        raise DatasetError(f"source {spec!r}: {scheme} needs a folder, e.g. {scheme}:/path/to/it")
    return opener(arg)
