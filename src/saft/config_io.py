"""Typed config dataclasses ⇄ TOML, with `key.sub=value` overrides and strict checking.

Unknown keys and values of the wrong type are rejected with a message naming the key (and the file).
"""

from __future__ import annotations

import dataclasses
import tomllib
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

from saft.errors import SaftInputError

T = TypeVar("T")


def to_dict(cfg) -> dict:
    """Nested plain dict of a config dataclass (None values are left out: TOML has no null)."""
    out = {}
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if dataclasses.is_dataclass(value):
            out[f.name] = to_dict(value)
        elif value is not None:
            out[f.name] = list(value) if isinstance(value, tuple) else value
    return out


def to_toml(cfg) -> str:
    import tomli_w

    return tomli_w.dumps(to_dict(cfg))


def from_dict(cls: type[T], data: dict, where: str = "config", prefix: str = "", base=None) -> T:
    """Build `cls` from a (partial) nested dict; missing keys keep the values of `base` (default: cls())."""
    if not isinstance(data, dict):
        raise SaftInputError(where, f"section {prefix.rstrip('.') or '<top>'} must be a table")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        key = prefix + unknown[0]
        raise SaftInputError(where, f"unknown config key {key!r} (known here: {', '.join(sorted(fields))})")
    base = cls() if base is None else base
    kwargs = {}
    for name, value in data.items():
        if dataclasses.is_dataclass(hints[name]):
            # a nested section starts from the parent's default for it, not from its class defaults
            kwargs[name] = from_dict(hints[name], value, where, prefix + name + ".", getattr(base, name))
        else:
            kwargs[name] = _convert(hints[name], value, where, prefix + name)
    return dataclasses.replace(base, **kwargs)


def _convert(tp, value, where: str, key: str):
    origin = typing.get_origin(tp)
    if dataclasses.is_dataclass(tp):
        return from_dict(tp, value, where, key + ".")
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(tp)
        if value is None and type(None) in args:
            return None
        errors = []
        for a in args:
            if a is type(None):
                continue
            try:
                return _convert(a, value, where, key)
            except SaftInputError as exc:
                errors.append(exc)
        raise errors[0]
    if origin is typing.Literal:
        allowed = typing.get_args(tp)
        if value not in allowed:
            raise SaftInputError(where, f"{key} must be one of {', '.join(map(repr, allowed))}, got {value!r}")
        return value
    if origin in (tuple, list):
        if not isinstance(value, (list, tuple)):
            raise SaftInputError(where, f"{key} must be a list, got {type(value).__name__}")
        args = typing.get_args(tp)
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(value) != len(args):
                raise SaftInputError(where, f"{key} must have {len(args)} elements, got {len(value)}")
            return tuple(_convert(a, v, where, f"{key}[{i}]") for i, (a, v) in enumerate(zip(args, value)))
        inner = args[0] if args else Any
        items = [_convert(inner, v, where, f"{key}[{i}]") for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    if tp is bool:
        if not isinstance(value, bool):
            raise SaftInputError(where, f"{key} must be true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise SaftInputError(where, f"{key} must be an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise SaftInputError(where, f"{key} must be a number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise SaftInputError(where, f"{key} must be a string, got {value!r}")
        return value
    return value


def load_toml(path: str | Path) -> dict:
    path = Path(path)
    if not path.is_file():
        raise SaftInputError(path, "config file not found")
    try:
        return tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise SaftInputError(path, f"not valid TOML ({exc})") from None


def parse_override(text: str) -> tuple[list[str], Any]:
    """'shape.lambda_sil=0.2' → (['shape', 'lambda_sil'], 0.2); values parsed as TOML, else as strings."""
    if "=" not in text:
        raise SaftInputError("--set", f"expected key=value, got {text!r}")
    key, raw = text.split("=", 1)
    key = key.strip()
    if not key:
        raise SaftInputError("--set", f"empty key in {text!r}")
    try:
        value = tomllib.loads(f"v = {raw.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw.strip()
    return key.split("."), value


def merge_overrides(data: dict, overrides: list[str]) -> dict:
    """Apply `--set` overrides onto a nested dict (new dict returned)."""
    import copy

    out = copy.deepcopy(data)
    for text in overrides:
        path, value = parse_override(text)
        node = out
        for p in path[:-1]:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                raise SaftInputError("--set", f"{'.'.join(path)}: {p} is not a section")
        node[path[-1]] = value
    return out


def load_config(cls: type[T], path: str | Path | None = None, overrides: list[str] | None = None) -> T:
    """Defaults ← TOML file ← `--set` overrides, checked strictly against `cls`."""
    data = load_toml(path) if path else {}
    where = str(path) if path else "config"
    if overrides:
        data = merge_overrides(data, overrides)
        where = f"{path} + --set" if path else "--set"
    return from_dict(cls, data, where)
