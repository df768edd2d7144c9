"""GTSAM, imported when a solver runs (it is a large library), with the error that says how to install it."""

from __future__ import annotations

from types import ModuleType

from stereopath.device.errors import ConfigError


def import_gtsam() -> ModuleType:
    """The ``gtsam`` module, or a ConfigError saying how to install it."""
    try:
        import gtsam
    except ImportError as exc:  # pragma: no cover - depends on the installation
        raise ConfigError("the offline back end needs GTSAM: pip install 'stereopath[host]' (gtsam>=4.3)") from exc
    return gtsam
