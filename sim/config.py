"""Typed, locked configs: dataclasses loaded from TOML or a flat dict, validated field by field.

Every config in sudd is a frozen dataclass whose fields carry their allowed range in `metadata`:

    speed: float = field(default=0.25, metadata=spec(0.0, 1.0, "m/s"))
    mode: str = field(default="fast", metadata=spec(choices=("full", "fast")))

`load_config(cls, data)` rejects unknown keys (a typo'd key raises, naming the close matches), converts
lists to tuples, recurses into nested dataclasses, and checks each value against its range. Errors name the
field path, the value received and what is allowed.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import tomllib
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

T = TypeVar("T")


class ConfigError(ValueError):
    """A config value or key that is not allowed; the message names the field and the allowed values."""


def spec(lo: float | None = None, hi: float | None = None, unit: str = "", choices: tuple | None = None,
         doc: str = "") -> dict:
    """Field metadata: numeric range [lo, hi] (inclusive, applied to every element of a tuple) or choices."""
    return {"lo": lo, "hi": hi, "unit": unit, "choices": choices, "doc": doc}


def read_toml(path: str | Path) -> dict:
    """A TOML file as a dict; a missing file or bad syntax is a ConfigError naming the file."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"config file {path} does not exist; pass the path of a TOML file")
    try:
        return tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path} is not valid TOML: {exc}") from exc


def load_toml(cls: type[T], path: str | Path, overrides: dict[str, Any] | None = None) -> T:
    data = read_toml(path)
    if overrides:
        data = merge_flat(data, overrides)
    return load_config(cls, data, where=str(path))


def merge_flat(data: dict, overrides: dict[str, Any]) -> dict:
    """Apply overrides given as a flat dict of dotted keys ("physics.friction": [0.5, 1.0])."""
    out = _deep_copy(data)
    for dotted, value in overrides.items():
        node = out
        *parents, leaf = dotted.split(".")
        for key in parents:
            node = node.setdefault(key, {})
            if not isinstance(node, dict):
                raise ConfigError(f"override {dotted!r}: {key!r} is a value, not a section")
        node[leaf] = value
    return out


def load_config(cls: type[T], data: dict[str, Any] | None = None, where: str = "", base: T | None = None) -> T:
    """Build `cls` from `data`, starting from `base` (or the defaults) for missing keys."""
    data = data or {}
    prefix = f"{where}: " if where else ""
    return _build(cls, data, base, path="", prefix=prefix)


def _build(cls, data: dict, base, path: str, prefix: str):
    if not isinstance(data, dict):
        raise ConfigError(f"{prefix}{path or cls.__name__} must be a table/section, got {data!r}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    for key in data:
        if key not in fields:
            close = difflib.get_close_matches(key, fields, n=3)
            hint = f"; did you mean {' or '.join(map(repr, close))}?" if close else ""
            raise ConfigError(f"{prefix}unknown field {_join(path, key)!r} in {cls.__name__}{hint} "
                              f"Allowed fields: {', '.join(sorted(fields))}")
    hints = typing.get_type_hints(cls)
    values = {}
    for name, f in fields.items():
        field_path = _join(path, name)
        current = getattr(base, name) if base is not None else _default(f)
        if name not in data:
            values[name] = current
            continue
        ftype = hints[name]
        if dataclasses.is_dataclass(ftype):
            values[name] = _build(ftype, data[name], current, field_path, prefix)
        else:
            values[name] = _check(field_path, _coerce(field_path, ftype, data[name], prefix), f.metadata, prefix)
    obj = cls(**values)
    validate = getattr(obj, "validate", None)
    if validate is not None:
        try:
            validate()
        except ConfigError as exc:
            raise ConfigError(f"{prefix}{exc}") from None
    return obj


def validate(obj) -> None:
    """Check an already-built config against its field ranges (for configs made in code)."""
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            validate(value)
        else:
            _check(f.name, value, f.metadata, "")


def _default(f: dataclasses.Field):
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    raise ConfigError(f"field {f.name!r} has no default and must be given")


def _coerce(path: str, ftype, value, prefix: str):
    origin = typing.get_origin(ftype)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(ftype) if a is not type(None)]
        if value is None:
            return None
        return _coerce(path, args[0], value, prefix)
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{prefix}{path} must be a list, got {value!r}")
        args = typing.get_args(ftype)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(f"{path}[{i}]", args[0], v, prefix) for i, v in enumerate(value))
        if len(args) != len(value):
            raise ConfigError(f"{prefix}{path} must have {len(args)} elements, got {len(value)}: {value!r}")
        return tuple(_coerce(f"{path}[{i}]", a, v, prefix) for i, (a, v) in enumerate(zip(args, value)))
    if ftype is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{prefix}{path} must be a number, got {value!r}")
        return float(value)
    if ftype is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{prefix}{path} must be a whole number, got {value!r}")
        return value
    if ftype is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{prefix}{path} must be true or false, got {value!r}")
        return value
    if ftype is str:
        if not isinstance(value, str):
            raise ConfigError(f"{prefix}{path} must be a string, got {value!r}")
        return value
    return value


def _check(path: str, value, meta, prefix: str):
    if not meta:
        return value
    choices = meta.get("choices")
    if choices is not None:
        items = value if isinstance(value, tuple) else (value,)
        for item in items:
            if item not in choices:
                raise ConfigError(f"{prefix}{path} = {item!r} is not allowed; expected one of {list(choices)}")
    lo, hi, unit = meta.get("lo"), meta.get("hi"), meta.get("unit", "")
    if lo is None and hi is None:
        return value
    items = value if isinstance(value, tuple) else (value,)
    for item in items:
        if item is None:
            continue
        bad = isinstance(item, float) and not math.isfinite(item)
        bad = bad or (lo is not None and item < lo) or (hi is not None and item > hi)
        if bad:
            rng = f"[{'-inf' if lo is None else lo}, {'inf' if hi is None else hi}]" + (f" {unit}" if unit else "")
            raise ConfigError(f"{prefix}{path} = {value!r} is out of range; allowed: each value in {rng}")
    return value


def _join(path: str, key: str) -> str:
    return f"{path}.{key}" if path else key


def _deep_copy(data):
    if isinstance(data, dict):
        return {k: _deep_copy(v) for k, v in data.items()}
    return data


def as_dict(obj) -> dict:
    """The resolved config as plain data, for logs and episode records."""
    return dataclasses.asdict(obj)
