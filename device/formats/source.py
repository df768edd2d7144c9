"""``open_source(spec)``: the one grammar and opener of a source spec, for every caller.

Specs: ``kitti:DIR`` (a KITTI odometry sequence folder), ``euroc:DIR`` (an ASL ``mav0`` folder or
the folder containing it), ``session:DIR`` (one of our recordings), ``sim[:SEED or key=value,...]``
(the simulator, see :mod:`stereopath.device.sim.source`).  The replay source, the evaluation
commands, the mapper and the reprocessor all open sequences here.  Other schemes plug in through an
explicit :func:`register_source` call (never at import): an opener receives the text after the
colon (``""`` when there is none) plus any settings, and returns an object with the sequence
interface of :mod:`stereopath.device.formats.sequence`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable

from stereopath.device.errors import DatasetError

if TYPE_CHECKING:
    from stereopath.device.formats.sequence import StereoSequence

Opener = Callable[..., "StereoSequence"]


def _no_settings(scheme: str, settings: dict[str, object]) -> None:
    if settings:
        raise DatasetError(f"source {scheme}: takes no settings (got {', '.join(sorted(settings))})")


def _kitti(arg: str, **settings: object) -> StereoSequence:
    from stereopath.device.formats.kitti import open_kitti

    _no_settings("kitti", settings)
    return open_kitti(arg, spec=f"kitti:{arg}")


def _euroc(arg: str, **settings: object) -> StereoSequence:
    from stereopath.device.formats.asl import open_asl

    _no_settings("euroc", settings)
    return open_asl(arg, spec=f"euroc:{arg}")


def _session(arg: str, **settings: object) -> StereoSequence:
    from stereopath.device.formats.asl import open_session

    _no_settings("session", settings)
    return open_session(arg)


def _sim(arg: str, **settings: object) -> StereoSequence:
    from stereopath.device.sim.source import open_sim_spec  # sim[:SEED or key=value,...]

    return open_sim_spec(arg, **settings)


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


def open_source(spec: str, **settings: object) -> StereoSequence:
    """Open the sequence named by ``spec`` (see the module doc).

    ``settings`` go to the opener: the simulator takes :class:`~stereopath.device.sim.session.SimConfig`
    fields (``open_source("sim:3", frames=40)``); the recorded formats take none.
    """
    scheme, arg = parse_spec(spec)
    opener = _OPENERS.get(scheme)
    if opener is None:
        raise DatasetError(f"source {spec!r}: unknown scheme {scheme!r} (known: {', '.join(source_schemes())})")
    if scheme in ("kitti", "euroc", "session") and not arg:
        raise DatasetError(f"source {spec!r}: {scheme} needs a folder, e.g. {scheme}:/path/to/it")
    return opener(arg, **settings)
