"""Typed configuration: frozen dataclasses filled from mappings that reject unknown keys.

One precedence rule everywhere: dataclass defaults < configuration file <
command line.  :func:`from_mapping` builds a (possibly nested) frozen
dataclass from a plain mapping (a parsed TOML/YAML table), checking every key
and type and naming the offending key in the :class:`ConfigError`.
A field's range is declared once, with the field (:func:`ranged`), and
checked by :func:`check_ranges` from the dataclass's ``__post_init__``; checks
that relate several fields stay in ``__post_init__`` and raise through
:func:`check_range`.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import tomllib
import types
import typing
from pathlib import Path
from typing import Any, Mapping, TypeVar

from stereopath.device.errors import ConfigError

log = logging.getLogger(__name__)

T = TypeVar("T")


def check_range(key: str, value: float, lo: float | None = None, hi: float | None = None) -> None:
    """Raise :class:`ConfigError` naming ``key`` unless ``lo <= value <= hi`` (NaN never is)."""
    if value != value:
        raise ConfigError(f"{key} = {value!r} is not a number")
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        raise ConfigError(f"{key} = {value!r} is out of range [{lo}, {hi}]")


def ranged(default: T, lo: float | None = None, hi: float | None = None) -> T:
    """A dataclass field whose value (or each element of a tuple value) must lie in ``[lo, hi]``; None is
    always allowed (it means "off" or "automatic" where a field's type admits it)."""
    return dataclasses.field(default=default, metadata={"range": (lo, hi)})


def field_range(cls: type, name: str) -> tuple[float | None, float | None] | None:
    """The ``(lo, hi)`` declared for ``cls.name`` by :func:`ranged`, or None."""
    for f in dataclasses.fields(cls):
        if f.name == name:
            return f.metadata.get("range")
    raise KeyError(name)


def check_ranges(obj: object, prefix: str = "") -> None:
    """Check every field of ``obj`` declared with :func:`ranged`; errors name ``prefix + field``."""
    for f in dataclasses.fields(obj):
        bounds = f.metadata.get("range")
        if bounds is None:
            continue
        value = getattr(obj, f.name)
        if value is None:
            continue
        key = f"{prefix}{f.name}"
        if isinstance(value, (tuple, list)):
            for i, v in enumerate(value):
                check_range(f"{key}[{i}]", v, *bounds)
        else:
            check_range(key, value, *bounds)


def _convert(key: str, tp: object, value: object) -> object:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if tp is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _convert(key, arg, value)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(f"{key}: {value!r} matches none of {tp}")
    if origin is typing.Literal:
        if value not in args:
            raise ConfigError(f"{key} = {value!r} must be one of {list(args)}")
        return value
    if dataclasses.is_dataclass(tp):
        if isinstance(value, tp):
            return value
        if not isinstance(value, Mapping):
            raise ConfigError(f"{key} must be a table, got {type(value).__name__}")
        return from_mapping(tp, value, prefix=key)
    if origin in (tuple, list):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{key} must be a list, got {type(value).__name__}")
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(args) != len(value):
                raise ConfigError(f"{key} must have {len(args)} elements, got {len(value)}")
            items = [_convert(f"{key}[{i}]", a, v) for i, (a, v) in enumerate(zip(args, value))]
        else:
            inner = args[0] if args else Any
            items = [_convert(f"{key}[{i}]", inner, v) for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{key} must be a number, got {value!r}")
        try:
            number = float(value)
        except OverflowError:  # an integer too large for a float
            number = math.inf
        if not math.isfinite(number):
            raise ConfigError(f"{key} must be a finite number, got {value!r}")
        return number
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{key} must be an integer, got {value!r}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{key} must be true or false, got {value!r}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{key} must be a string, got {value!r}")
        return value
    if isinstance(tp, type) and isinstance(value, tp):
        return value
    raise ConfigError(f"{key}: cannot use {value!r} as {tp}")


def from_mapping(cls: type[T], data: Mapping[str, Any], prefix: str = "") -> T:
    """Build the frozen dataclass ``cls`` from ``data``; unknown keys raise ConfigError."""
    if not isinstance(data, Mapping):
        raise ConfigError(f"{prefix or cls.__name__} must be a table, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        where = f" in [{prefix}]" if prefix else ""
        raise ConfigError(f"unknown configuration key(s){where}: {', '.join(map(str, unknown))}; known: {', '.join(sorted(fields))}")
    kwargs = {}
    for name, value in data.items():
        key = f"{prefix}.{name}" if prefix else name
        kwargs[name] = _convert(key, hints[name], value)
    try:
        return cls(**kwargs)
    except TypeError as exc:  # a required field is missing
        raise ConfigError(f"{prefix or cls.__name__}: {exc}") from None


def replace(obj: T, **changes: object) -> T:
    """``dataclasses.replace`` that validates the new values like :func:`from_mapping`."""
    current = {f.name: getattr(obj, f.name) for f in dataclasses.fields(obj) if f.init}
    unknown = sorted(set(changes) - set(current))
    if unknown:
        raise ConfigError(f"unknown configuration key(s): {', '.join(unknown)}")
    current.update(changes)
    hints = typing.get_type_hints(type(obj))
    return type(obj)(**{k: (_convert(k, hints[k], v) if k in changes else v) for k, v in current.items()})


def load_toml(path: str | Path) -> dict[str, Any]:
    """Parse a TOML file, turning syntax errors and unreadable or missing files into ConfigError."""
    p = Path(path)
    try:
        if p.exists() and not p.is_dir() and not p.is_file():  # a FIFO or a device would block or never end
            raise ConfigError(f"configuration file {p} is not a regular file")
        with p.open("rb") as fh:
            return tomllib.load(fh)
    except RecursionError:  # tomllib parses nested arrays and inline tables recursively
        raise ConfigError(f"{p}: invalid TOML: arrays or inline tables nested too deeply") from None
    except FileNotFoundError:
        raise ConfigError(f"configuration file not found: {p}") from None
    except IsADirectoryError:
        raise ConfigError(f"configuration file {p} is a folder, not a TOML file") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{p}: not a UTF-8 text (TOML) file: {exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: invalid TOML: {exc}") from None
    except OSError as exc:
        raise ConfigError(f"cannot read configuration file {p}: {exc.strerror or exc}") from None


def as_dict(obj: object) -> dict[str, Any]:
    """Plain-dict view of a configuration dataclass (for logging and manifests)."""
    return dataclasses.asdict(obj)
