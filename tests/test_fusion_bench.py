"""``kmea bench fusion-node`` against a real fusion node process: a node that refuses its
configuration is reported with its reason instead of showing as every message lost (the
benchmark's larger loads once exceeded the configuration's robot bound and printed 100 %
lost, 0 % CPU)."""

from __future__ import annotations

import pytest

from kmead.benchmarks.fusion_node import _load
from kmead.config.checks import MAX_ROBOTS


def test_a_node_that_does_not_start_is_reported_with_its_reason() -> None:
    with pytest.raises(RuntimeError, match=f"at most {MAX_ROBOTS} robots"):
        _load(1, MAX_ROBOTS + 1, 30.0, 0.2)


def test_a_small_load_is_fused_and_relayed() -> None:
    a = _load(1, 2, 30.0, 1.0)
    assert a["sent_per_s"] > 40 and a["fused_per_s"] > 0.5 * a["sent_per_s"]
    assert 0.0 < a["p50"] <= a["p99"]  # latencies measured (no timing target here)
