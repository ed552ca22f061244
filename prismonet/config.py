"""Frozen-dataclass configs: loaded from a JSON file, overridden with ``key=value`` strings.

Nested dataclasses are addressed with dots (``decoder.width=128``). Values are parsed as JSON
when they parse (numbers, booleans, lists, null) and taken as strings otherwise. Unknown keys
are errors: a typo never silently does nothing.
"""

from __future__ import annotations

import dataclasses
import json
import typing
from pathlib import Path


class ConfigError(ValueError):
    """A config file or override that does not fit the config's fields."""


def _build(cls, data: dict, where: str):
    if not isinstance(data, dict):
        raise ConfigError(f"{where or 'config'}: expected an object, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = set(data) - names
    if unknown:
        raise ConfigError(f"{where or 'config'}: unknown field(s) {sorted(unknown)}; known: {sorted(names)}")
    kwargs = {}
    for f in dataclasses.fields(cls):
        if f.name not in data:
            continue
        value = data[f.name]
        typ = hints[f.name]
        if dataclasses.is_dataclass(typ):
            value = _build(typ, value, f"{where}{f.name}.")
        else:
            _check_type(f"{where}{f.name}", value, typ)
            if isinstance(value, list):
                value = tuple(value)
        kwargs[f.name] = value
    return cls(**kwargs)


def _check_type(name: str, value, typ) -> None:
    """Raise ``ConfigError`` unless ``value`` (parsed JSON) fits the field's annotation: numbers
    for ``float`` (finite), integers for ``int``, lists for tuples, ``null`` for optional fields."""
    import math
    import types

    def fits(v, t) -> bool:
        origin = typing.get_origin(t)
        if origin in (typing.Union, types.UnionType):
            return any(fits(v, a) for a in typing.get_args(t))
        if t is type(None):
            return v is None
        if t is bool:
            return isinstance(v, bool)
        if t is int:
            return isinstance(v, int) and not isinstance(v, bool)
        if t is float:
            return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
        if t is str:
            return isinstance(v, str)
        if origin is tuple:
            args = typing.get_args(t)
            if not isinstance(v, (list, tuple)):
                return False
            if len(args) == 2 and args[1] is Ellipsis:
                return all(fits(x, args[0]) for x in v)
            return len(v) == len(args) and all(fits(x, a) for x, a in zip(v, args))
        return True  # anything else is checked by the config's own validation

    if not fits(value, typ):
        want = str(typ).replace("typing.", "").replace("<class '", "").replace("'>", "")
        raise ConfigError(f"{name}: expected {want}, got {value!r}")


def to_dict(cfg) -> dict:
    return dataclasses.asdict(cfg)


def load_config(cls, path: str | Path | None = None, overrides: list[str] | None = None):
    """Build ``cls`` from defaults, then a JSON file (``"-"`` for none), then ``key=value`` overrides."""
    data: dict = {}
    if path is not None and str(path) != "-":  # "-": defaults only
        from prismonet.files import InputError, read_json

        try:
            data = read_json(path)
        except InputError as e:
            raise ConfigError(str(e).replace("no such file", "no such config file")) from None
    for item in overrides or []:
        if "=" not in item:
            raise ConfigError(f"override {item!r}: expected key=value")
        key, raw = item.split("=", 1)
        try:
            value = json.loads(raw)
        except json.JSONDecodeError:
            value = raw
        node = data
        parts = key.split(".")
        for p in parts[:-1]:
            node = node.setdefault(p, {})
        node[parts[-1]] = value
    try:
        return _build(cls, data, "")
    except TypeError as e:
        raise ConfigError(f"config: {e}") from None
