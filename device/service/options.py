"""The run's configuration: command-line overrides over the file, file-system checks, live reload split."""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, TypeVar

from stereopath.device.core.config import as_dict, replace
from stereopath.device.errors import ConfigError
from stereopath.device.settings import DeviceConfig, SourceSettings, load_device_config

_T = TypeVar("_T")

CREDENTIAL_NAME = "server.key_secret"     # LoadCredential= name of the device's CURVE secret key
SOURCE_CHOICES = ("sim", "picamera2", "depthai", "replay")


@dataclass(frozen=True)
class RunOptions:
    """Command-line overrides of ``stereopath device run`` (``None`` = keep the file's value)."""

    source: str | None = None        # sim | replay:SPEC | picamera2 | depthai
    imu: str | None = None           # mpu6050 | emulated | source | none
    out: str | None = None           # the session folder itself (default recorder.dir/<session id>)
    duration_s: float | None = None  # stop after this long (s)
    frames: int | None = None        # stop after this many stereo pairs
    stream: bool | None = None       # False = --no-stream
    insecure: bool | None = None     # True = --insecure (loopback only)
    status_file: str | None = None
    drain_s: float | None = None
    wait_for_host_s: float = 0.0     # before capturing, wait up to this long for a host to connect (demo)

    def __post_init__(self) -> None:
        if self.duration_s is not None and not self.duration_s > 0:
            raise ConfigError(f"--duration = {self.duration_s} must be > 0")
        if self.frames is not None and self.frames < 1:
            raise ConfigError(f"--frames = {self.frames} must be >= 1")
        if self.drain_s is not None and not self.drain_s >= 0:  # also refuses nan
            raise ConfigError(f"--drain = {self.drain_s} must be >= 0")
        if not self.wait_for_host_s >= 0:
            raise ConfigError(f"--wait-for-host = {self.wait_for_host_s} must be >= 0")


def _with(obj: _T, **changes: object) -> _T:
    return replace(obj, **changes) if changes else obj


def _source_override(src: SourceSettings, spec: str) -> SourceSettings:
    """``src`` with the ``--source`` spec applied: sim | replay:SPEC | picamera2 | depthai."""
    if spec.startswith("replay:"):
        path = spec[len("replay:"):]
        if not path:
            raise ConfigError("--source replay:SPEC needs a recording, e.g. replay:session:/path/to/session")
        return _with(src, backend="replay", replay=_with(src.replay, path=path))
    if spec in SOURCE_CHOICES:
        return _with(src, backend=spec)
    raise ConfigError(f"--source {spec!r} is not one of sim, replay:SPEC, picamera2, depthai")


def apply_options(cfg: DeviceConfig, opts: RunOptions) -> DeviceConfig:
    """The configuration with the command-line overrides applied (validated like the file)."""
    src, imu = cfg.source, cfg.imu
    if opts.source is not None:
        src = _source_override(src, opts.source)
        if opts.imu is None and src.recorded:
            imu = _with(imu, backend="source")  # the recording's / simulator's own IMU, on the frames' clock
    if opts.imu is not None:
        imu = _with(imu, backend=opts.imu)
    stream_changes: dict[str, Any] = {}
    if opts.stream is not None:
        stream_changes["enabled"] = opts.stream
    if opts.insecure:
        stream_changes["insecure"] = True
    if opts.drain_s is not None:
        stream_changes["drain_s"] = opts.drain_s
    service = cfg.service if opts.status_file is None else _with(cfg.service, status_file=opts.status_file)
    return dataclasses.replace(cfg, source=src, imu=imu, stream=_with(cfg.stream, **stream_changes), service=service)


def load_config(path: str | Path | None, opts: RunOptions) -> DeviceConfig:
    """Defaults < file < command line."""
    return apply_options(load_device_config(path), opts)


def secret_key_path(cfg: DeviceConfig, environ: Mapping[str, str] | None = None) -> Path:
    """The device's CURVE secret key: the systemd credential when present, else ``keys.server_secret``."""
    env = os.environ if environ is None else environ
    cred_dir = env.get("CREDENTIALS_DIRECTORY")
    if cred_dir and (Path(cred_dir) / CREDENTIAL_NAME).is_file():
        return Path(cred_dir) / CREDENTIAL_NAME
    return Path(cfg.keys.server_secret)


def _check_keys(cfg: DeviceConfig, environ: Mapping[str, str] | None) -> None:
    secret = secret_key_path(cfg, environ)
    if not secret.is_file():
        raise ConfigError(f"keys.server_secret = {str(secret)!r}: file not found "
                          f"(create it with `stereopath device install` or `stereopath keys generate`)")
    clients = Path(cfg.keys.clients_dir)
    if not clients.is_dir():
        raise ConfigError(f"keys.clients_dir = {str(clients)!r}: directory not found")
    if not any(clients.glob("*.key")):
        raise ConfigError(f"keys.clients_dir = {str(clients)!r} holds no host public key (*.key): "
                          "no host could connect")


def check_config(cfg: DeviceConfig, environ: Mapping[str, str] | None = None) -> None:
    """Checks that need the file system (key files, calibration, recording); ConfigError names the key.

    A path the system cannot look at (a name too long, a loop of links, no permission) is a ConfigError too."""
    try:
        _check_config(cfg, environ)
    except OSError as exc:
        where = f" {_short(str(exc.filename))}" if exc.filename else ""
        raise ConfigError(f"cannot use the path{where}: {exc.strerror or exc}") from None


def _short(path: str, keep: int = 100) -> str:
    """``repr(path)``, its middle cut when it is long (a message stays one readable line)."""
    return repr(path) if len(path) <= keep else f"{path[:keep // 2]!r}...{path[-keep // 2:]!r} ({len(path)} characters)"


def _check_recorder_dir(cfg: DeviceConfig) -> None:
    """``recorder.dir`` (where sessions are made) must be a folder, or not exist yet under a folder."""
    from stereopath.device.formats.fileio import folder_or_parent

    folder_or_parent(cfg.recorder.dir, f"recorder.dir = {cfg.recorder.dir!r}")


def _check_config(cfg: DeviceConfig, environ: Mapping[str, str] | None) -> None:
    if cfg.stream.enabled and not cfg.stream.insecure:
        _check_keys(cfg, environ)
    if cfg.stream.enabled and cfg.stream.insecure:
        from stereopath.device.wire.security import check_loopback_endpoint

        for key in ("pose_endpoint", "keyframe_endpoint"):
            try:
                check_loopback_endpoint(getattr(cfg.stream, key))
            except ConfigError as exc:
                raise ConfigError(f"stream.{key}: {exc}") from None
    check_rig_file(cfg)
    if cfg.recorder.enabled:
        _check_recorder_dir(cfg)
    if cfg.source.backend == "replay" and not cfg.source.replay.path:
        raise ConfigError("source.replay.path is empty: name the recording (session:DIR, euroc:DIR or kitti:DIR)")
    if cfg.imu.backend == "source" and cfg.source.backend == "picamera2":
        raise ConfigError("imu.backend = 'source' but the picamera2 cameras have no IMU of their own")


def check_rig_file(cfg: DeviceConfig) -> None:
    """``source.rig_file``, when set, names a file the system can look at (ConfigError names the key)."""
    if cfg.source.rig_file:
        try:
            found = Path(cfg.source.rig_file).is_file()
        except OSError as exc:  # a name too long, a loop of links
            raise ConfigError(f"source.rig_file = {_short(cfg.source.rig_file)}: {exc.strerror or exc}") from None
        if not found:
            raise ConfigError(f"source.rig_file = {_short(cfg.source.rig_file)}: file not found")


def flat(mapping: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"a": {"b": 1}}`` -> ``{"a.b": 1}``."""
    out: dict[str, Any] = {}
    for k, v in mapping.items():
        key = f"{prefix}{k}"
        if isinstance(v, Mapping):
            out.update(flat(v, key + "."))
        else:
            out[key] = v
    return out


LIVE_KEYS = ("timealign.", "recorder.reserve_mb", "service.status_interval_s", "service.max_data_age_s",
             "service.stop_timeout_s", "service.ready_timeout_s", "stream.drain_s", "selftest.")


def split_changes(old: DeviceConfig, new: DeviceConfig) -> tuple[list[str], list[str]]:
    """Changed keys that can be applied live, and those that need a restart."""
    a, b = flat(as_dict(old)), flat(as_dict(new))
    changed = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
    live = [k for k in changed if k.startswith(LIVE_KEYS)]
    return live, [k for k in changed if k not in live]


def apply_live(old: DeviceConfig, new: DeviceConfig) -> DeviceConfig:
    """``old`` with the settings that can change while running taken from ``new``."""
    return dataclasses.replace(
        old, timealign=new.timealign, selftest=new.selftest,
        service=dataclasses.replace(new.service, status_file=old.service.status_file),
        recorder=dataclasses.replace(old.recorder, reserve_mb=new.recorder.reserve_mb),
        stream=dataclasses.replace(old.stream, drain_s=new.stream.drain_s))
