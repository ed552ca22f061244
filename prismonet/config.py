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
        elif isinstance(value, list):
            value = tuple(value)
        kwargs[f.name] = value
    return cls(**kwargs)


def to_dict(cfg) -> dict:
    return dataclasses.asdict(cfg)


def load_config(cls, path: str | Path | None = None, overrides: list[str] | None = None):
    """Build ``cls`` from defaults, then a JSON file (``"-"`` for none), then ``key=value`` overrides."""
    data: dict = {}
    if path is not None and str(path) != "-":  # "-": defaults only
        try:
            data = json.loads(Path(path).read_text())
        except FileNotFoundError:
            raise ConfigError(f"{path}: no such config file") from None
        except json.JSONDecodeError as e:
            raise ConfigError(f"{path}: not valid JSON ({e})") from None
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
