"""Typed configs from YAML: nested plain mappings -> frozen dataclasses, unknown keys refused.

Every package keeps its numbers as dataclass defaults (citing the paper or the RL spec); a
YAML file under ``configs/`` mirrors them and may override any field.
"""

from __future__ import annotations

import dataclasses
import typing
from pathlib import Path

import yaml


def load_yaml_mapping(path: str | Path | None, default: Path, what: str) -> dict:
    """The mapping in ``path`` (or in ``default`` when ``path`` is None and that file exists;
    ``{}`` otherwise). A missing explicit file or a non-mapping top level raises naming the file."""
    if path is None and not default.is_file():
        return {}
    path = Path(path) if path is not None else default
    if not path.is_file():
        raise FileNotFoundError(f"{path}: {what} config not found")
    data = yaml.safe_load(path.read_text()) or {}
    if not isinstance(data, dict):
        raise ValueError(f"{path}: top level must be a mapping, got {type(data).__name__}")
    return data


def merge(base: dict, extra: dict | None) -> dict:
    """``base`` with ``extra`` laid over it, nested mappings merged key by key."""
    out = dict(base)
    for key, value in (extra or {}).items():
        out[key] = merge(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out


def parse_sets(items: list[str], flag: str = "--set") -> dict:
    """["a.b=1", "a.c=x"] -> {"a": {"b": 1, "c": "x"}} (values parsed as YAML); errors name
    ``flag`` and the item."""
    out: dict = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"{flag} {item!r}: expected KEY=VALUE with a dotted KEY")
        *parents, leaf = key.strip().split(".")
        node = out
        for part in parents:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ValueError(f"{flag} {item!r}: '{part}' is already set to a value")
        node[leaf] = yaml.safe_load(value)
    return out


def from_dict(cls, data: dict, where: str):
    """Instantiate dataclass ``cls`` from a plain mapping, converting nested dataclasses,
    tuples, lists/dicts of dataclasses and numbers; unknown keys raise naming ``where``."""
    if not isinstance(data, dict):
        raise ValueError(f"config '{where}' must be a mapping, got {data!r}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ValueError(f"config '{where}': unknown keys {unknown} (expected some of {sorted(names)})")
    return cls(**{k: _convert(hints[k], v, f"{where}.{k}") for k, v in data.items()})


def _convert(tp, value, where: str):
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if dataclasses.is_dataclass(tp):
        return from_dict(tp, value, where)
    if origin is tuple:
        return tuple(value)
    if origin is list and args and dataclasses.is_dataclass(args[0]):
        return [from_dict(args[0], v, f"{where}[{i}]") for i, v in enumerate(value)]
    if origin is dict and len(args) == 2 and dataclasses.is_dataclass(args[1]):
        return {k: from_dict(args[1], v, f"{where}.{k}") for k, v in value.items()}
    if tp is float:
        return float(value)
    if tp is int and not isinstance(value, bool):
        return int(value)
    return value
