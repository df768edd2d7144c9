"""Open a recorded or simulated sequence from a source spec.

Specs: ``sim[:SEED]`` (the built-in simulated scan), ``kitti:SEQDIR``,
``euroc:MAV0DIR``, ``session:DIR`` (our ASL recordings).  Every sequence has
``rig``, ``frames()``, ``imu`` (or None), ``groundtruth`` (or None), ``len()``
and ``label``.
"""

from __future__ import annotations

from typing import Any

from stereopath.device.errors import ConfigError


class SimSequence:
    """The simulator behind the common sequence interface."""

    def __init__(self, seed: int = 0, frames: int | None = None, **overrides: Any) -> None:
        from stereopath.device.sim.session import SimConfig, open_sim

        kwargs: dict[str, Any] = {"seed": seed, **overrides}
        if frames is not None:
            kwargs["frames"] = frames
        self._sess = open_sim(SimConfig(**kwargs))
        self.label = f"sim:{seed}"

    def __getattr__(self, name: str) -> Any:
        return getattr(self._sess, name)

    def __len__(self) -> int:
        return len(self._sess.t_ns)

    def frames(self, limit: int | None = None):
        n = len(self) if limit is None else min(limit, len(self))
        for i in range(n):
            yield self._sess.render(i)


def open_sequence(spec: str, frames: int | None = None, **sim_overrides: Any):
    kind, _, arg = spec.partition(":")
    if kind == "sim":
        try:
            seed = int(arg) if arg else 0
        except ValueError:
            raise ConfigError(f"source {spec!r}: the sim seed must be an integer") from None
        return SimSequence(seed=seed, frames=frames, **sim_overrides)
    if kind in ("kitti", "euroc", "session"):
        if not arg:
            raise ConfigError(f"source {spec!r}: give a directory, e.g. {kind}:/path/to/data")
        from stereopath.device.formats import open_source

        seq = open_source(spec)
        if not hasattr(seq, "label"):
            try:
                seq.label = spec
            except AttributeError:
                pass
        return seq
    raise ConfigError(f"unknown source {spec!r}; use sim[:SEED], kitti:DIR, euroc:DIR or session:DIR")
