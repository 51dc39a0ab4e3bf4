"""Records are strict JSON: a number that is not finite is null, numpy's numbers are numbers."""

import json

import numpy as np

from rgbd_gt.io.json_text import json_text


def _strict(constant):
    raise AssertionError(f"not strict JSON: {constant}")


def test_json_text_is_strict_json():
    record = {"p50": float("nan"), "sigma": np.array([0.5, np.inf, -np.inf]), "n": np.int64(3), "ok": np.bool_(True),
              "ratio": np.float32(1.25), "nested": [{"x": (1.0, np.nan)}], "name": "a"}
    assert json.loads(json_text(record), parse_constant=_strict) == {
        "p50": None, "sigma": [0.5, None, None], "n": 3, "ok": True, "ratio": 1.25, "nested": [{"x": [1.0, None]}], "name": "a"}
    assert json.dumps({"x": float("nan")}) == '{"x": NaN}'  # what json_text exists to avoid
