"""Typed configuration: dataclasses filled from `configs/*.yaml`; unknown keys, values of the
wrong type and non-finite numbers are rejected naming the key, and a dataclass with a
`check()` method checks its ranges there (raising ValueError)."""

from __future__ import annotations

import dataclasses
import math
import os
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

from rgbd_gt.errors import InputError, read_yaml, require_file, yaml_number

T = TypeVar("T")
CONFIG_DIR = Path(__file__).resolve().parent.parent / "configs"


def from_dict(cls: type[T], data: dict[str, Any], where: str = "") -> T:
    """Build dataclass `cls` from a mapping, recursing into nested dataclass fields.

    Missing keys keep the dataclass defaults; unknown keys raise InputError naming `where`.
    """
    at = f"{where}: " if where else ""  # the file's top level: the caller names the file
    if not isinstance(data, dict):
        raise InputError(f"{at}expected a mapping of keys to values, got {_name(data)}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise InputError(f"{at}unknown key(s) {', '.join(unknown)} (known: {', '.join(sorted(names))})")
    values = {}
    for key, value in data.items():
        hint = hints[key]
        sub = f"{where}.{key}" if where else key
        if dataclasses.is_dataclass(hint):
            values[key] = from_dict(hint, {} if value is None else value, sub)
        elif typing.get_origin(hint) is dict and dataclasses.is_dataclass(typing.get_args(hint)[1]):
            if not isinstance(value, dict):
                raise InputError(f"{sub}: expected a mapping, got {_name(value)}")
            values[key] = {str(k): from_dict(typing.get_args(hint)[1], {} if v is None else v, f"{sub}.{k}")
                           for k, v in value.items()}
        else:
            values[key] = _typed(value, hint, sub)
    return cls(**values)


def require(ok: bool, key: str, rule: str, value: Any) -> None:
    """A config's range check: ValueError naming the one key that breaks its rule, and its value."""
    if not ok:
        raise ValueError(f"{key} must be {rule}, got {value}")


_KINDS = {int: "a whole number", float: "a number", str: "a string", bool: "true or false"}


def _name(value: Any) -> str:
    return "null" if value is None else f"{type(value).__name__} {value!r}"[:60]


def _typed(value: Any, hint: Any, where: str) -> Any:
    """`value` as type `hint` (str, int, float, bool, a dataclass, X | None, list[X]); InputError
    otherwise."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if dataclasses.is_dataclass(hint):
        return from_dict(hint, {} if value is None else value, where)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        inner = [a for a in args if a is not type(None)]
        if len(inner) == 1:
            return _typed(value, inner[0], where)
        for alt in inner:  # e.g. `int | str`: a number, or a word such as "auto"
            try:
                return _typed(value, alt, where)
            except InputError:
                pass
        # named after all of them: the last one's own message ("expected a string") would hide the others
        raise InputError(f"{where}: expected {' or '.join(_KINDS.get(a, str(a)) for a in inner)}, got {_name(value)}")
    if origin is list:
        if not isinstance(value, list):
            raise InputError(f"{where}: expected a list, got {_name(value)}")
        return [_typed(v, args[0], f"{where}[{k}]") for k, v in enumerate(value)]
    if hint is bool:
        if not isinstance(value, bool):
            raise InputError(f"{where}: expected true or false, got {_name(value)}")
        return value
    if hint in (int, float):
        value = yaml_number(value)
    if hint is int:
        if isinstance(value, bool) or not (isinstance(value, int) or (isinstance(value, float) and value.is_integer())):
            raise InputError(f"{where}: expected a whole number, got {_name(value)}")
        return int(value)
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise InputError(f"{where}: expected a number, got {_name(value)}")
        if not math.isfinite(value):
            raise InputError(f"{where}: must be a finite number, got {value}")
        return float(value)
    if hint is str:
        if not isinstance(value, str):
            raise InputError(f"{where}: expected a string, got {_name(value)}")
        return value
    return value


def load_config(cls: type[T], path: str | os.PathLike | None, default_name: str | None = None) -> T:
    """Load `path` into dataclass `cls`; when `path` is None, `configs/<default_name>`, or the
    dataclass defaults when that file is not installed."""
    if path is None:
        path = CONFIG_DIR / default_name
        if not path.is_file():  # installed without the configs folder: built-in defaults
            return cls()
    path = require_file(path, "config file")
    data = read_yaml(path)
    try:
        cfg = from_dict(cls, {} if data is None else data)
        if hasattr(cfg, "check"):
            cfg.check()
        return cfg
    except InputError as exc:
        raise InputError(str(exc), path) from None
    except ValueError as exc:
        raise InputError(str(exc), path) from None
