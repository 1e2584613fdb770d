"""The fusion's track restarts from a measurement once its prediction is less certain than
the outlier model's radius (kmea.robots.fusion.Fusion): after a fast turn no camera saw, the
fused output is the measurement, not a point between it and the coasted prediction."""

from __future__ import annotations

import math

from kmea.robots.fusion import Fusion, Measurement
from kmea.robots.tracking import TrackerConfig


def _drive(fu: Fusion, t0: float, n: int, x0: float, v: float) -> None:
    for k in range(n):
        t = t0 + k / 15
        fu.add(Measurement("cam1", "amr1", t, x0 + v * (t - t0), 0.2, 0.0, 0.002))


def test_a_track_that_coasted_past_the_outlier_radius_starts_again_from_the_measurement(
        ) -> None:
    fu = Fusion(TrackerConfig(), max_age_s=0.5)
    _drive(fu, 0.0, 20, 0.0, 1.5)  # 1.5 m/s along x
    t_last = 19 / 15
    # 0.9 s later (under reset_after_s) the robot comes back the other way, 0.3 m off the
    # straight-line prediction: it turned where no camera saw it.
    t = t_last + 0.9
    tr = fu.tracker.tracks["amr1"]
    st = tr.predict(t)
    assert st is not None and st.sigma is not None and st.sigma > 0.2
    out = fu.add(Measurement("cam0", "amr1", t, 1.7, 0.5, math.pi, 0.002))
    assert out is not None and out.accepted and fu.restarted == 1
    new = fu.pose("amr1")
    assert new is not None and math.hypot(new.x - 1.7, new.y - 0.5) < 1e-6


def test_a_short_gap_is_an_ordinary_update() -> None:
    fu = Fusion(TrackerConfig(), max_age_s=0.5)
    _drive(fu, 0.0, 20, 0.0, 0.25)
    _drive(fu, 20 / 15 + 0.1, 3, 0.25 * (20 / 15 + 0.1), 0.25)
    assert fu.restarted == 0
