"""kmea.wire.jsonsafe: the one JSON cleaner."""

import json
import math
from dataclasses import dataclass

import numpy as np

from kmea.wire.jsonsafe import to_jsonable


@dataclass
class _Pose:
    xy: np.ndarray
    name: str


def test_nan_inf_numpy_keys_dataclasses():
    obj = {1: np.array([1.0, np.nan, np.inf]), "s": np.float32(2.5), "i": np.int64(7),
           "n": -math.inf, "t": (1, 2), "set": {3, 1}, "pose": _Pose(np.eye(2), "r1"),
           "ok": True, "none": None}
    out = to_jsonable(obj)
    assert out == {"1": [1.0, None, None], "s": 2.5, "i": 7, "n": None, "t": [1, 2],
                   "set": [1, 3], "pose": {"xy": [[1.0, 0.0], [0.0, 1.0]], "name": "r1"},
                   "ok": True, "none": None}
    assert type(out["i"]) is int and type(out["s"]) is float
    json.dumps(out, allow_nan=False)  # raises if anything non-JSON is left


def test_unknown_objects_become_text():
    assert to_jsonable({"p": object}) == {"p": str(object)}
