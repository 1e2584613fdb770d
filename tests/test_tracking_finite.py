"""The tracking filter never holds a non-finite or singular state: measurements of absurd
size (finite, but far beyond any floor) are refused and the track reset, never raised."""

from __future__ import annotations

import math

import numpy as np
import pytest

from kmea.robots.tracking import Tracker


def _finite(tr: Tracker) -> bool:
    t = tr.tracks["a"]
    return t.s is None or bool(np.isfinite(t.s).all() and np.isfinite(t.P).all())


@pytest.mark.parametrize("big", [1e300, 1e100, 1e12])
def test_absurd_measurements_after_a_track_are_refused(big: float) -> None:
    tr = Tracker()
    for k in range(3):
        assert tr.update("a", 1 + 0.033 * k, 1.0, 1.0, 0.0, 0.002).accepted
    for k in range(6):  # more than reacquire_n: a chain of them must not take the track
        out = tr.update("a", 1.1 + 0.033 * k, big, 1.0, 0.0, 0.002)
        assert not out.accepted and _finite(tr)
    st = tr.tracks["a"].state()
    assert st is not None and math.hypot(st.x - 1.0, st.y - 1.0) < 0.01
    assert tr.counts["reacquired"] == 0


@pytest.mark.parametrize("big", [1e300, 1e100])
def test_a_track_started_by_absurd_measurements_is_refused_and_reset(big: float) -> None:
    tr = Tracker()
    kinds = [tr.update("a", 1.0 + 0.033 * k, big, 1.0, 0.0, 0.002).kind for k in range(6)]
    assert set(kinds) == {"failed"} and tr.counts["failed"] == 6
    assert tr.tracks["a"].state() is None and _finite(tr)
    assert len(tr.rejections) == 6 and "reset" in tr.rejections[-1].reason
    # The next sane measurement starts the track again.
    assert tr.update("a", 2.0, 1.0, 1.0, 0.0, 0.002).kind == "init"
    assert tr.update("a", 2.033, 1.0, 1.0, 0.0, 0.002).kind == "update"
