"""The tracking filter's third round against outliers (docs/tracking.md): the cumulative step
bound, the look-back over a run of rejected measurements, the candidates' speed check and
the candidates followed inside the gate. Each on a small scenario built here or on an excerpt
of a tuning drive (never a held-out one), and each fails with its mechanism switched off."""

from __future__ import annotations

import math

import numpy as np

from kmea.benchmarks.tracking import (
    TUNE_HARD,
    Measurements,
    make_measurements,
    outlier_effect,
    run_kalman,
    trajectory,
)
from kmea.tracking import Track, Tracker, TrackerConfig

SETS = {s.name: s for s in TUNE_HARD}


def _drive(name: str, seed: int, t_end: float, t_start: float):
    """A tuning drive from ``t_start`` to ``t_end`` s: truth, measurements with outliers, and
    the same measurements without them (the track starts at t_start: a short test)."""
    s = SETS[name]
    tr = trajectory(seed, s.duration, s.max_speed, s.max_turn, s.max_accel, s.stops)
    ms = make_measurements(tr, seed, s.fps, s.sigma, 0.05, burst=s.burst,
                           manoeuvre_outliers=s.manoeuvre_outliers,
                           stop_outliers=s.stop_outliers)
    clean = make_measurements(tr, seed, s.fps, s.sigma, 0.0)
    k = (ms.t >= t_start) & (ms.t <= t_end)

    def cut(m: Measurements) -> Measurements:
        return Measurements(m.t[k], m.z[k], m.sigma[k], m.outlier[k])

    return tr, cut(ms), cut(clean)


def _largest_effect(ms: Measurements, clean: Measurements, cfg: TrackerConfig,
                    t0: float, t1: float) -> float:
    """The largest jump (in the filter's sigma) the outliers between t0 and t1 s cause."""
    out, info = run_kalman(ms, cfg)
    ref, _ = run_kalman(clean, cfg)
    _, eff = outlier_effect(ms, out, info["sigma"], ref, (ms.t >= t0) & (ms.t <= t1 + 0.2))
    return float(np.max(eff, initial=0.0))


def test_two_outliers_in_a_row_cannot_add_their_bounded_steps() -> None:
    # Tuning set "tune stops", seed 623 at 29.45-29.50 s: a robot starting to turn from a
    # near standstill; the first outlier (d 3.6 innovation sigmas) is accepted with a bounded
    # step and switches the filter to its manoeuvre model, whose widened prediction lets the
    # second one in with another bounded step of a larger sigma. Traced with the step bound
    # of the rounds before the eighth (1.5), where the two steps add to above 3 sigma; with
    # today's 1.2 they stay below it either way, and the bound still halves the jump.
    _, ms, clean = _drive("tune stops", 623, 30.0, 26.0)
    assert ms.outlier[(ms.t > 29.4) & (ms.t < 29.55)].sum() == 2
    for cfg in (TrackerConfig(step_k=1.5), TrackerConfig()):
        on = _largest_effect(ms, clean, cfg, 29.4, 29.55)
        off = _largest_effect(ms, clean, cfg.with_(step_cumulative=False), 29.4, 29.55)
        assert on < 0.6 * off
    assert on < 3.0 and _largest_effect(
        ms, clean, TrackerConfig(step_k=1.5, step_cumulative=False), 29.4, 29.55) > 3.0


def test_look_back_over_rejected_measurements_retracts_the_outlier_before_them() -> None:
    # "tune stops", seed 622 at 31.30 s: braking to a stop, an outlier lands where the
    # still-braking prediction expects the robot and is accepted; the good measurements
    # after it are rejected. The first of them alone does not show which one is wrong (the
    # outlier also fits the track through it), the second does: two rejected measurements
    # that fit the track without the accepted one. The outlier is retracted and reported and
    # the track is back at once, instead of after a re-acquisition (main's filter before
    # this round, whose look-back tested the new measurement alone, rejected both and was
    # 52 mm off at 31.40 s). Traced with the step bound of the rounds before the eighth
    # (1.5); with today's 1.2 the track through the outlier is pulled less and recovery
    # (after a rejected run) brings it back at 31.40 s instead.
    tr, ms, _ = _drive("tune stops", 622, 31.45, 27.0)
    k_out = int(np.flatnonzero(np.isclose(ms.t, 31.30))[0])
    assert ms.outlier[k_out] and not ms.outlier[k_out + 1:].any()
    errors, reported = {}, {}
    for look_back in (True, False):
        # Recovery off: with the look-back off it retracts the outlier at 31.40 s instead.
        trk = Tracker(TrackerConfig(look_back=look_back, recover=False, step_k=1.5))
        kinds = []
        for k in range(len(ms.t)):
            kinds.append(trk.update("r", float(ms.t[k]), *ms.z[k], float(ms.sigma[k])).kind)
        st = trk.track("r").state()
        gx, gy, _ = tr.at(np.array([st.t]))
        errors[look_back] = math.hypot(st.x - gx[0], st.y - gy[0])
        reported[look_back] = [r for r in trk.rejections if r.t == ms.t[k_out]]
        assert kinds[k_out] == "update" and kinds[k_out + 1] == "rejected"
    assert len(reported[True]) == 1 and "found by a later measurement" in reported[True][0].reason
    assert not reported[False]
    assert errors[True] < 0.015 < 0.05 < errors[False]
    # The defaults: recovery reports the outlier at 31.40 s and the track is back.
    trk = Tracker(TrackerConfig())
    outs = [trk.update("r", float(ms.t[k]), *ms.z[k], float(ms.sigma[k]))
            for k in range(len(ms.t))]
    assert outs[k_out].kind == "update" and outs[k_out + 1].kind == "rejected"
    assert outs[k_out + 2].reason.startswith("recovered")
    st = trk.track("r").state()
    gx, gy, _ = tr.at(np.array([st.t]))
    assert math.hypot(st.x - gx[0], st.y - gy[0]) < 0.015


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
    # track's prediction (widened by the manoeuvre model and the two rejections), but fits
    # it poorly and the two candidates well: it is the third candidate, the track
    # re-acquires there, instead of walking over by bounded steps.
    tr, ms, _ = _drive("tune C-like", 601, 20.4, 17.0)
    for follow in (True, False):
        trk = Tracker(TrackerConfig(reacquire_follow=follow))
        kinds = {}
        for k in range(len(ms.t)):
            kinds[round(float(ms.t[k]), 2)] = trk.update("r", float(ms.t[k]), *ms.z[k],
                                                         float(ms.sigma[k])).kind
        after = [kinds[t] for t in (20.0, 20.05, 20.1)]
        st = trk.track("r").state()
        gx, gy, _ = tr.at(np.array([st.t]))
        err = math.hypot(st.x - gx[0], st.y - gy[0])
        if follow:
            assert after == ["rejected", "rejected", "reacquired"] and err < 0.03
        else:
            assert "reacquired" not in [v for t, v in kinds.items() if t >= 20.0]
            assert after == ["rejected", "rejected", "update"]
    assert tr.kidnap_t == 20.0


def test_an_outlier_among_the_candidates_does_not_delay_reacquisition() -> None:
    # A robot moved by hand to (0.3, 0.2); among the measurements at its new place one
    # outlier (15 cm off) breaks the candidates' chain. The chain it broke is kept: the next
    # measurement continues it, so the track re-acquires after 3 consistent measurements
    # without it; switched off, the chain starts again and re-acquisition waits.
    place = [(0.3, 0.2), (0.3, 0.2), (0.45, 0.2), (0.3, 0.2), (0.3, 0.2), (0.3, 0.2)]
    on = _standing_then(place, TrackerConfig())
    off = _standing_then(place, TrackerConfig(reacquire_skip_outlier=False))
    assert on[:4] == ["rejected", "rejected", "rejected", "reacquired"]
    assert off[:4] == ["rejected"] * 4 and "reacquired" in off
