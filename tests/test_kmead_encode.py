"""Telemetry bodies encode to the same JSON on the fast path as through the cleaning walk."""

from __future__ import annotations

import json
import math

import numpy as np
from kmead.protocol import PROTOCOL_VERSION, _clean, decode_body, encode_body


def slow(body: dict) -> bytes:
    return json.dumps({"v": PROTOCOL_VERSION, **_clean(body)}, separators=(",", ":"),
                      allow_nan=False).encode()


def test_fast_path_bytes_equal_the_cleaned_encoding() -> None:
    rng = np.random.default_rng(3)
    p = rng.normal(size=3)
    bodies = [
        {"t": 1.5, "frame": 7, "markers": [{"id": 4, "x": p[0], "y": float(p[1]),
                                            "in_map": np.bool_(True), "n": np.int64(3),
                                            "pos": p, "none": None}]},
        {"ids": (1, 2), "by_id": {5: 2, 7: np.int32(1)}, "R": np.eye(3), "s": "é"},
        {"x": math.nan, "arr": np.array([1.0, np.inf]), "ok": np.bool_(False)},  # cleaned
        {"nested": {"deeper": [np.float32(0.25), -0.0, 1e-300]}},
    ]
    for body in bodies:
        assert encode_body(body) == slow(body)
    assert decode_body(encode_body(bodies[2]))["x"] is None


def test_unencodable_body_still_raises() -> None:
    class Thing:
        pass

    try:
        encode_body({"x": Thing()})
    except TypeError:
        return
    raise AssertionError("an object JSON cannot hold must not be sent")
