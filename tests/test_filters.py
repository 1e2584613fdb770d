"""The first-order IIR pose filter: values by hand, angle wrapping, track resets."""

from __future__ import annotations

import math

import numpy as np
import pytest

from kmea.robots.iir import PoseFilter


def test_alpha_one_passes_samples_through() -> None:
    f = PoseFilter(alpha=1.0)
    for t, x in enumerate((0.0, 1.0, -3.0)):
        p, yaw = f.update("m", t * 0.1, [x, 2 * x, 0.5], 3.0 * x)
        assert p.tolist() == [x, 2 * x, 0.5]
        assert yaw == pytest.approx(math.remainder(3.0 * x, 2 * math.pi))


def test_alpha_half_by_hand() -> None:
    f = PoseFilter(alpha=0.5, reset_after_s=1.0)
    p, yaw = f.update(13, 0.0, [0.0, 0.0, 0.0], 0.0)  # first sample: taken as is
    assert p.tolist() == [0.0, 0.0, 0.0] and yaw == 0.0
    p, yaw = f.update(13, 0.1, [1.0, 2.0, 4.0], 0.4)  # 0.5 * x + 0.5 * 0
    assert p.tolist() == [0.5, 1.0, 2.0] and yaw == pytest.approx(0.2)
    p, yaw = f.update(13, 0.2, [1.0, 2.0, 4.0], 0.4)  # 0.5 * 1 + 0.5 * 0.5 = 0.75
    assert p.tolist() == [0.75, 1.5, 3.0] and yaw == pytest.approx(0.3)


def test_yaw_is_filtered_across_the_wrap() -> None:
    f = PoseFilter(alpha=0.5)
    f.update("r", 0.0, np.zeros(3), math.radians(179))
    _, yaw = f.update("r", 0.1, np.zeros(3), math.radians(-179))
    # Half way from 179 deg to -179 deg the short way is 180 deg, not 0.
    assert abs(abs(yaw) - math.pi) < 1e-12
    _, yaw = f.update("r", 0.2, np.zeros(3), math.radians(-179))
    # 180 + 0.5 * 2 = 181 deg = -179 deg
    assert yaw == pytest.approx(math.radians(-179.5))


def test_track_resets_after_the_timeout_or_when_time_goes_back() -> None:
    f = PoseFilter(alpha=0.2, reset_after_s=0.5)
    f.update(1, 0.0, [0.0, 0.0, 0.0], 0.0)
    p, _ = f.update(1, 0.5, [1.0, 0.0, 0.0], 0.0)  # 0.5 s: still the same track
    assert p[0] == pytest.approx(0.2)
    p, yaw = f.update(1, 1.01, [5.0, 0.0, 0.0], 1.0)  # 0.51 s gap: lost, restart
    assert p[0] == 5.0 and yaw == 1.0
    p, _ = f.update(1, 0.9, [0.0, 0.0, 0.0], 0.0)  # time ran backwards: restart
    assert p[0] == 0.0


def test_keys_are_independent_and_reset() -> None:
    f = PoseFilter(alpha=0.5)
    f.update("a", 0.0, [0.0, 0.0, 0.0], 0.0)
    f.update("b", 0.0, [10.0, 0.0, 0.0], 0.0)
    assert f.update("a", 0.1, [2.0, 0.0, 0.0], 0.0)[0][0] == 1.0
    assert f.update("b", 0.1, [12.0, 0.0, 0.0], 0.0)[0][0] == 11.0
    f.reset("a")
    assert f.keys() == ["b"]
    assert f.update("a", 0.2, [2.0, 0.0, 0.0], 0.0)[0][0] == 2.0
    f.reset()
    assert f.keys() == []
    # The returned array is a copy: changing it does not change the state.
    p, _ = f.update("c", 0.0, [1.0, 1.0, 1.0], 0.0)
    p[:] = 100.0
    assert f.update("c", 0.1, [1.0, 1.0, 1.0], 0.0)[0].tolist() == [1.0, 1.0, 1.0]


@pytest.mark.parametrize("alpha", [0.0, -0.1, 1.5, math.nan, True, "0.5"])
def test_bad_alpha(alpha: object) -> None:
    with pytest.raises(ValueError, match=r"alpha must be in \(0, 1\]"):
        PoseFilter(alpha=alpha)  # type: ignore[arg-type]


def test_bad_samples_and_timeout() -> None:
    with pytest.raises(ValueError, match="reset_after_s"):
        PoseFilter(0.5, reset_after_s=0.0)
    f = PoseFilter(0.5)
    with pytest.raises(ValueError, match="position must be 3 finite numbers"):
        f.update(1, 0.0, [0.0, math.inf, 0.0], 0.0)
    with pytest.raises(ValueError, match="position must be 3 finite numbers"):
        f.update(1, 0.0, [0.0, 0.0], 0.0)
    with pytest.raises(ValueError, match="yaw and t must be finite"):
        f.update(1, 0.0, [0.0, 0.0, 0.0], math.nan)
