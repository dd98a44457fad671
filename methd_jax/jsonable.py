"""Configuration dataclasses to and from JSON-ready dicts (run configs, policy manifests)."""

from __future__ import annotations

import dataclasses


def jsonable(value):
    """Dataclasses as dicts and tuples as lists, recursively (for JSON)."""
    if dataclasses.is_dataclass(value):
        return {f.name: jsonable(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, tuple | list):
        return [jsonable(v) for v in value]
    return value


def from_jsonable(default, data: dict):
    """The inverse of :func:`jsonable` for a dataclass: ``default`` with the fields in ``data``
    (nested dataclasses and tuples rebuilt from dicts and lists)."""

    def as_tuple(v):
        return tuple(as_tuple(x) for x in v) if isinstance(v, list) else v

    changes = {}
    for f in dataclasses.fields(default):
        if f.name not in data:
            continue
        current, value = getattr(default, f.name), data[f.name]
        if dataclasses.is_dataclass(current):
            value = from_jsonable(current, value)
        elif isinstance(current, tuple):
            value = as_tuple(value)
        changes[f.name] = value
    return dataclasses.replace(default, **changes)
