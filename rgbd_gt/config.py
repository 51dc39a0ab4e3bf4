"""Typed configuration: dataclasses filled from `configs/*.yaml`, unknown keys rejected."""

from __future__ import annotations

import dataclasses
import os
import typing
from pathlib import Path
from typing import Any, TypeVar

import yaml

from rgbd_gt.errors import InputError

T = TypeVar("T")
CONFIG_DIR = Path(__file__).resolve().parent.parent / "configs"


def from_dict(cls: type[T], data: dict[str, Any], where: str = "") -> T:
    """Build dataclass `cls` from a mapping, recursing into nested dataclass fields.

    Missing keys keep the dataclass defaults; unknown keys raise InputError naming `where`.
    """
    if not isinstance(data, dict):
        raise InputError(f"{where or cls.__name__}: expected a mapping, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise InputError(f"{where or cls.__name__}: unknown key(s) {', '.join(unknown)} (known: {', '.join(sorted(names))})")
    values = {}
    for key, value in data.items():
        hint = hints[key]
        sub = f"{where}.{key}" if where else key
        if dataclasses.is_dataclass(hint):
            values[key] = from_dict(hint, value or {}, sub)
        elif typing.get_origin(hint) is dict and dataclasses.is_dataclass(typing.get_args(hint)[1]):
            values[key] = {k: from_dict(typing.get_args(hint)[1], v or {}, f"{sub}.{k}") for k, v in (value or {}).items()}
        else:
            values[key] = value
    return cls(**values)


def load_config(cls: type[T], path: str | os.PathLike | None, default_name: str | None = None) -> T:
    """Load `path` into dataclass `cls`; when `path` is None, `configs/<default_name>`, or the
    dataclass defaults when that file is not installed."""
    if path is None:
        path = CONFIG_DIR / default_name
        if not path.is_file():  # installed without the configs folder: built-in defaults
            return cls()
    path = Path(path)
    if not path.is_file():
        raise InputError("config file not found", path)
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise InputError(f"invalid YAML ({str(exc).splitlines()[0]})", path) from None
    try:
        return from_dict(cls, data)
    except InputError as exc:
        raise InputError(str(exc), path) from None
