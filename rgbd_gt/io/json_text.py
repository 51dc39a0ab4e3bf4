"""JSON records as strict JSON, whatever numbers they hold."""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np


def json_text(data: Any, indent: int | None = 1) -> str:
    """`data` (dicts, lists, tuples, numbers, numpy scalars and arrays, strings) as JSON text in
    which a number that is not finite is null: Python's json writes NaN and Infinity bare, which
    JSON.parse, jq and most other readers refuse, and a record's NaN or inf means "unknown"."""
    return json.dumps(_plain(data), indent=indent, allow_nan=False)


def _plain(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value
