"""Re-acquisition after a hand move, and outliers in a row that must not trigger it: small
scenarios built here, and an excerpt of a tuning drive (never a held-out one)."""

from __future__ import annotations

import math

import numpy as np

from kmea.benchmarks.tracking import TUNE_HARD, make_measurements, trajectory
from kmea.robots.tracking import Track, Tracker, TrackerConfig


def _standing_then(chain: list[tuple[float, float]], cfg: TrackerConfig) -> list[str]:
    tr = Track("r", cfg)
    rng = np.random.default_rng(2)
    for k in range(30):  # standing at the origin, heading 0, 20 frames/s
        tr.update(k / 20, rng.normal(0, 0.004), rng.normal(0, 0.004), 0.0, 0.006)
    return [tr.update((30 + i) / 20, x, y, 0.0, 0.006).kind for i, (x, y) in enumerate(chain)]


def test_outliers_in_a_row_faster_than_a_robot_do_not_reacquire() -> None:
    # Three outliers 5-20 cm around a standing robot that happen to lie on a line, 13 cm
    # apart at 20 frames/s (2.7 m/s): they agree with each other, but no robot drives that
    # fast (max_speed 1.5 m/s), so they do not re-acquire the track.
    chain = [(-0.18, 0.0), (-0.05, 0.03), (0.08, 0.06)]
    assert _standing_then(chain, TrackerConfig()) == ["rejected"] * 3
    assert _standing_then(chain, TrackerConfig(max_speed=10.0))[-1] == "reacquired"
    # A robot moved by hand and standing at its new place is re-acquired as before.
    moved = [(0.30, 0.20)] * 4
    assert _standing_then(moved, TrackerConfig()) == ["rejected", "rejected", "reacquired",
                                                      "update"]


def test_hand_move_is_reacquired_through_the_candidates() -> None:
    # "tune C-like", seed 601: the robot is moved by hand (31 cm) while braking at 20.0 s.
    # Two measurements at the new place are rejected; the third passes the gate of the
    # track's prediction (widened by the manoeuvre mode and the two rejections), but fits
    # it poorly and the two candidates well: it is the third candidate, the track
    # re-acquires there, instead of walking over by bounded steps.
    s = next(m for m in TUNE_HARD if m.name == "tune C-like")
    tr = trajectory(601, s.duration, s.max_speed, s.max_turn, s.max_accel, s.stops)
    ms = make_measurements(tr, 601, s.fps, s.sigma, 0.05)
    trk = Tracker(TrackerConfig())
    kinds = {}
    for k in np.flatnonzero((ms.t >= 17.0) & (ms.t <= 20.4)):
        kinds[round(float(ms.t[k]), 2)] = trk.update("r", float(ms.t[k]), *ms.z[k],
                                                     float(ms.sigma[k])).kind
    assert tr.kidnap_t == 20.0
    assert [kinds[t] for t in (20.0, 20.05, 20.1)] == ["rejected", "rejected", "reacquired"]
    st = trk.track("r").state()
    gx, gy, _ = tr.at(np.array([st.t]))
    assert math.hypot(st.x - gx[0], st.y - gy[0]) < 0.03


def test_an_outlier_among_the_candidates_does_not_delay_reacquisition() -> None:
    # A robot moved by hand to (0.3, 0.2); among the measurements at its new place one
    # outlier (15 cm off) breaks the candidates' chain. The chain it broke is kept: the next
    # measurement continues it, so the track re-acquires after 3 consistent measurements
    # without it.
    place = [(0.3, 0.2), (0.3, 0.2), (0.45, 0.2), (0.3, 0.2), (0.3, 0.2), (0.3, 0.2)]
    assert _standing_then(place, TrackerConfig())[:4] == ["rejected", "rejected", "rejected",
                                                          "reacquired"]
