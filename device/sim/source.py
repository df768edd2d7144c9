"""``open_source("sim[:ARG]")``: the simulator as a recorded-sequence source.

``ARG`` is empty (defaults), a seed (``sim:3``) or comma-separated ``key=value`` settings of
:class:`stereopath.device.sim.session.SimConfig`'s top-level scalar fields (``sim:seed=3,frames=100,trajectory=orbit``).  The opener of
:mod:`stereopath.device.formats.source` calls :func:`open_sim_spec` for the ``sim`` scheme.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from stereopath.device.errors import ConfigError

if TYPE_CHECKING:
    from stereopath.device.sim.session import SimSession


def parse_sim_spec(arg: str) -> dict[str, bool | int | float | str]:
    """``"3"`` -> ``{"seed": 3}``; ``"seed=3,frames=10,motion_blur=true"`` -> typed mapping."""
    import dataclasses
    import typing

    from stereopath.device.sim.session import SimConfig

    arg = arg.strip()
    if not arg:
        return {}
    if "=" not in arg:
        try:
            return {"seed": int(arg)}
        except ValueError:
            raise ConfigError(f"sim source {arg!r}: expected a seed or key=value settings") from None
    hints = typing.get_type_hints(SimConfig)
    known = {f.name for f in dataclasses.fields(SimConfig) if hints[f.name] in (bool, int, float, str)}
    out: dict[str, bool | int | float | str] = {}
    for item in arg.split(","):
        key, sep, text = item.partition("=")
        key, text = key.strip(), text.strip()
        if not sep or key not in known:
            raise ConfigError(f"sim source: unknown setting {item.strip()!r} (known: {', '.join(sorted(known))})")
        tp = hints[key]
        try:
            if tp is bool:
                if text.lower() not in ("true", "false", "1", "0", "yes", "no"):
                    raise ValueError(text)
                out[key] = text.lower() in ("true", "1", "yes")
            elif tp is int:
                out[key] = int(text)
            elif tp is float:
                out[key] = float(text)
            else:
                out[key] = text
        except ValueError:
            raise ConfigError(f"sim source: {key} = {text!r} is not a valid {tp.__name__}") from None
    return out


def open_sim_spec(arg: str, **settings: object) -> SimSession:
    """The simulated session named by ``arg``; ``settings`` (SimConfig fields) override the spec's."""
    from stereopath.device.sim.session import open_sim

    sess = open_sim(**{**parse_sim_spec(arg), **settings})
    sess.spec = f"sim:{arg}" if arg else "sim"
    return sess
