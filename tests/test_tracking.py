"""The tracking filter: noise reduction, velocity, wrapping, gating, re-acquisition,
prediction, out-of-order measurements, configuration errors; and its evaluation harness."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from kmea.benchmarks.tracking import (
    MotionSet,
    evaluate,
    make_measurements,
    outlier_effect,
    run_iir,
    run_kalman,
    trajectory,
    tuning_sets,
)
from kmea.robots.tracking import Track, Tracker, TrackerConfig
from kmea.stats.chi2 import chi2_quantile

HEADING = math.atan2(-0.2, 0.5)  # of the default line: robots drive along their heading


def _line(n: int = 90, v: tuple[float, float] = (0.5, -0.2), fps: float = 30.0,
          sigma: float = 0.003, seed: int = 0):
    rng = np.random.default_rng(seed)
    t = np.arange(n) / fps
    truth = np.column_stack([0.1 + v[0] * t, -0.3 + v[1] * t])
    meas = truth + rng.normal(0.0, sigma, truth.shape)
    return t, truth, meas


@pytest.mark.parametrize("model", ["cv", "ctrv"])
def test_straight_run_filters_noise_and_finds_the_velocity(model: str) -> None:
    t, truth, meas = _line()
    heading = math.atan2(-0.2, 0.5)
    tr = Track("r", TrackerConfig(model=model, accel_noise=0.01))
    errs_f, errs_m = [], []
    for k in range(len(t)):
        out = tr.update(t[k], meas[k, 0], meas[k, 1], heading, 0.003)
        assert out.accepted
        if k >= 30:
            errs_f.append(math.hypot(out.state.x - truth[k, 0], out.state.y - truth[k, 1]))
            errs_m.append(math.hypot(*(meas[k] - truth[k])))
    assert np.sqrt(np.mean(np.square(errs_f))) < 0.7 * np.sqrt(np.mean(np.square(errs_m)))
    st = tr.state()
    assert st.vx == pytest.approx(0.5, abs=0.1) and st.vy == pytest.approx(-0.2, abs=0.1)
    assert abs(st.speed) == pytest.approx(math.hypot(0.5, 0.2), abs=0.1)
    # Latency compensation: 100 ms ahead is 100 ms further along the line.
    ahead = tr.predict(t[-1] + 0.1)
    assert ahead.x == pytest.approx(0.1 + 0.5 * (t[-1] + 0.1), abs=0.01)
    assert ahead.y == pytest.approx(-0.3 - 0.2 * (t[-1] + 0.1), abs=0.01)
    assert ahead.sigma > st.sigma  # less certain about the future
    assert tr.state() == st  # predicting does not change the track


def test_turn_rate_and_heading_wrap_through_pi() -> None:
    # A robot turning at 2 rad/s on a circle of 0.3 m: theta passes +-pi many times.
    w, r, fps = 2.0, 0.3, 30.0
    rng = np.random.default_rng(3)
    tr = Track("r", TrackerConfig(model="ctrv"))
    worst = 0.0
    for k in range(150):
        t = k / fps
        th = math.pi / 2 + w * t
        x, y = r * math.cos(w * t), r * math.sin(w * t)
        meas_th = math.remainder(th + rng.normal(0, 0.02), 2 * math.pi)
        out = tr.update(t, x + rng.normal(0, 0.002), y + rng.normal(0, 0.002), meas_th, 0.002)
        assert out.accepted, out.reason
        assert -math.pi <= out.state.theta < math.pi
        if k > 30:
            worst = max(worst, abs(math.remainder(out.state.theta - th, 2 * math.pi)))
    assert worst < 0.08
    assert tr.state().omega == pytest.approx(w, abs=0.25)
    assert tr.state().speed == pytest.approx(w * r, abs=0.05)


def test_outlier_is_rejected_and_reported_not_followed() -> None:
    t, _truth, meas = _line(60)
    trk = Tracker(TrackerConfig())
    for k in range(40):
        trk.update("amr1", t[k], meas[k, 0], meas[k, 1], HEADING, 0.003,
                   source="cam0")
    before = trk.predict("amr1", t[40])
    out = trk.update("amr1", t[40], meas[40, 0] + 0.08, meas[40, 1], HEADING, 0.003,
                     source="cam1")
    assert out.kind == "rejected" and "position jump 8." in out.reason
    assert math.hypot(out.state.x - before.x, out.state.y - before.y) < 1e-9
    flip = trk.update("amr1", t[41], meas[41, 0], meas[41, 1], HEADING + math.pi, 0.003)
    assert flip.kind == "rejected" and "heading flip 17" in flip.reason
    assert [r.source for r in trk.rejections] == ["cam1", ""]
    assert trk.rejections[0].name == "amr1" and trk.rejections[0].t == t[40]
    assert trk.counts["rejected"] == 2
    # The next good measurement is accepted: two unrelated outliers never re-acquire.
    assert trk.update("amr1", t[42], meas[42, 0], meas[42, 1], HEADING, 0.003).kind == "update"


def test_robot_moved_by_hand_is_reacquired_after_n_consistent_measurements() -> None:
    tr = Track("r", TrackerConfig(reacquire_n=3))
    for k in range(30):
        tr.update(k / 30, 0.0, 0.0, 0.0, 0.002)
    kinds = [tr.update((30 + k) / 30, 0.4, 0.1, 1.0, 0.002).kind for k in range(4)]
    assert kinds == ["rejected", "rejected", "reacquired", "update"]
    st = tr.state()
    assert st.x == pytest.approx(0.4, abs=0.005) and st.theta == pytest.approx(1.0, abs=0.05)


def test_out_of_order_and_too_old_measurements() -> None:
    t, truth, meas = _line(60)
    tr = Track("r")
    for k in range(0, 60, 2):  # even frames on time
        tr.update(t[k], meas[k, 0], meas[k, 1], HEADING, 0.003)
    last_t = tr.t
    late = tr.update(t[57], meas[57, 0], meas[57, 1], HEADING, 0.003)  # older than the last
    assert late.kind == "update" and tr.t == last_t
    assert math.hypot(tr.state().x - truth[58, 0], tr.state().y - truth[58, 1]) < 0.01
    old = tr.update(t[58] - 5.0, 0.0, 0.0, 0.0, 0.003)
    assert old.kind == "rejected" and "too old" in old.reason and old.state is None
    assert tr.update(math.nan, 0, 0, 0).kind == "rejected"


def test_gap_longer_than_reset_restarts_the_track() -> None:
    tr = Track("r", TrackerConfig(reset_after_s=0.5))
    assert tr.update(0.0, 0.0, 0.0, 0.0).kind == "init"
    assert tr.update(0.1, 0.001, 0.0, 0.0).kind == "update"
    out = tr.update(1.0, 1.0, 1.0, 0.0)
    assert out.kind == "reset" and out.state.x == 1.0


def test_sigma_drives_the_weight_of_a_measurement() -> None:
    a, b = Track("a"), Track("b")
    for tr in (a, b):
        tr.update(0.0, 0.0, 0.0, 0.0, 0.002)
        tr.update(1 / 30, 0.0, 0.0, 0.0, 0.002)
    a.update(2 / 30, 0.004, 0.0, 0.0, 0.002)   # a precise measurement moves it more
    b.update(2 / 30, 0.004, 0.0, 0.0, 0.02)
    assert a.state().x > 2 * b.state().x > 0


def test_heading_sigma_is_the_measurements_own_not_the_floored_positions() -> None:
    # Position sigma floored at min_sigma (2 mm); the heading's sigma / heading_lever comes
    # from the measurement's own sigma, floored at min_sigma_theta (0.0125 rad) only.
    tr = Track("r")
    R = tr.noise(0.0002)
    assert R[0, 0] == pytest.approx(0.002 ** 2) and R[2, 2] == pytest.approx(0.0125 ** 2)
    assert tr.noise(0.001)[2, 2] == pytest.approx((0.001 / 0.05) ** 2)
    assert tr.noise(0.004)[2, 2] == pytest.approx((0.004 / 0.05) ** 2)
    assert tr.noise(0.0002, 0.02)[2, 2] == pytest.approx(0.02 ** 2)


@pytest.mark.parametrize("model", ["cv", "ctrv"])
def test_new_track_takes_its_velocity_from_its_first_two_measurements(model: str) -> None:
    # A robot entering the view at 1.5 m/s: the track starts at rest (velocity unknown);
    # its first update is not step-bounded, so from the second measurement on it follows.
    tr = Track("r", TrackerConfig(model=model))
    rng = np.random.default_rng(3)
    errs = []
    for k in range(6):
        t = k / 30
        out = tr.update(t, 1.5 * t + rng.normal(0, 0.0005), rng.normal(0, 0.0005), 0.0,
                        0.0005)
        assert out.accepted
        errs.append(math.hypot(out.state.x - 1.5 * t, out.state.y))
        if k == 1:
            assert out.state.speed == pytest.approx(1.5, abs=0.1)
    assert max(errs) < 0.003  # bounded, the first update gave 22 mm


def test_bad_configuration_names_the_key() -> None:
    with pytest.raises(ValueError, match="model"):
        TrackerConfig(model="ukf")
    with pytest.raises(ValueError, match="accel_noise"):
        TrackerConfig(accel_noise=-1.0)
    with pytest.raises(ValueError, match="gate_probability"):
        TrackerConfig(gate_probability=1.0)
    with pytest.raises(ValueError, match="reacquire_n"):
        TrackerConfig(reacquire_n=2.5)


def test_chi_square_quantiles() -> None:
    assert chi2_quantile(0.99, 3) == pytest.approx(11.345, abs=0.01)
    assert chi2_quantile(0.999, 3) == pytest.approx(16.266, abs=0.01)
    assert chi2_quantile(0.95, 2) == pytest.approx(5.991, abs=0.001)
    with pytest.raises(ValueError):
        chi2_quantile(1.0, 3)


def test_simulated_drive_respects_its_limits_and_outlier_rate() -> None:
    tr = trajectory(5, duration=20.0, max_speed=1.5, max_turn=3.0)
    assert np.max(np.abs(tr.v)) <= 1.5 + 1e-9 and np.max(np.abs(tr.omega)) <= 3.0 + 1e-9
    assert np.max(np.abs(tr.v)) > 0.5  # it does drive
    ms = make_measurements(tr, 5, fps=30.0, sigma=0.003, outliers=0.05)
    assert 0.02 < ms.outlier.mean() < 0.09
    jump = np.hypot(*(ms.z[ms.outlier, :2] - np.column_stack(tr.at(ms.t)[:2])[ms.outlier]).T)
    assert np.all((jump > 0.04) & (jump < 0.23))


def test_kalman_beats_raw_measurements_on_a_drive() -> None:
    s = MotionSet("t", (11,), 1.5, 3.0, 0.003, 30.0, 15.0)
    raw = evaluate(s, "iir", 1.0)
    kal = evaluate(s, "kalman", TrackerConfig(model="ctrv"))
    assert kal["pos"] < raw["pos"] and kal["head"] < raw["head"]
    assert kal["caught"] >= 0.9 * kal["outliers"] > 0 and raw["caught"] == 0
    assert kal["jumps_outlier"] < raw["jumps_outlier"]


def test_pipeline_robot_filter_kind_kalman_reports_rejections() -> None:
    from kmea.estimators.base import Estimate, MarkerEstimate
    from kmea.maps.files import default_map
    from kmea.pipeline import Pipeline, PipelineSettings
    from kmea.robots.poses import RobotSpec
    from kmea.vision.camera import pi_camera_v2

    spec = RobotSpec("amr2", (42,), height=0.2)
    settings = PipelineSettings(filter_kind="kalman", robots=(spec,))
    pipe = Pipeline(pi_camera_v2(), default_map(), settings)

    def est(x: float, y: float) -> Estimate:
        me = MarkerEstimate(42, np.array([x, y, 0.2]), np.eye(3), 0.0, 0.003)
        return Estimate("kmea", True, {42: me})

    for k in range(30):  # driving along +x at 0.3 m/s
        fixes = pipe.robot_fixes(est(0.01 * k, 0.0), k / 30)
    fix = fixes["amr2"]
    assert fix.vx == pytest.approx(0.3, abs=0.1) and fix.omega is not None
    assert fix.raw == pytest.approx((0.29, 0.0, 0.0, 0.003))
    rejections: dict[str, str] = {}
    assert pipe.robot_fixes(est(0.45, 0.0), 1.0, rejections) == {}
    assert "position jump 15." in rejections["amr2"]
    # The paper's filter (the library's default kind): every measurement, no velocity.
    iir = Pipeline(pi_camera_v2(), default_map(), PipelineSettings(robots=(spec,)))
    fix = iir.robot_fixes(est(0.45, 0.0), 1.0)["amr2"]
    assert (fix.x, fix.vx, fix.raw) == (pytest.approx(0.45), None, None)


def test_outlier_caused_jump_stays_below_3_sigma_and_rejections_are_reported() -> None:
    # A held-out-style drive (seed 12, not a tuning seed; 1.5 m/s, 3 rad/s, 2 m/s^2, 3 mm,
    # 30 fps) with 5 % outliers of 5-20 cm, run again with the same noise without them.
    s = MotionSet("t", (12,), 1.5, 3.0, 0.003, 30.0, 15.0)
    kal = evaluate(s, "kalman", TrackerConfig())
    assert kal["outliers"] > 10
    assert kal["caused_big"] == 0 and 0.0 < kal["caused_max_sig"] < 3.0
    assert kal["caught"] >= 0.9 * kal["outliers"]
    assert kal["reported"] == kal["caught"]  # every rejected outlier is in the report
    # Against the run with the outlier measurements left out (the outliers' own doing):
    # every outlier of this drive is rejected, and a rejected measurement leaves no trace.
    assert kal["caught"] == kal["outliers"]
    assert kal["own_big"] == 0 and kal["own_max_sig"] == 0.0
    # So the filter is its own oracle (the same filter told which measurements are outliers).
    assert (kal["oracle_big"], kal["oracle_max_sig"]) == (kal["caused_big"],
                                                          kal["caused_max_sig"])
    # The metrics can fail: the raw measurements (IIR alpha 1) follow every outlier.
    raw = evaluate(s, "iir", 1.0)
    assert raw["caused_big"] >= 0.9 * raw["outliers"] and raw["caused_max_sig"] > 10.0
    assert raw["own_big"] >= 0.9 * raw["outliers"] and raw["own_max_sig"] > 10.0


def test_the_oracle_tells_an_outlier_taken_in_from_the_good_measurement_lost() -> None:
    # Tuning drive 622 ("tune stops"): braking to a stop, an outlier that lands on the
    # prediction is taken in and the next good measurement is rejected (7.3 sigma). The same
    # filter told which measurements are outliers stays below 3 sigma: the jump is the
    # outlier's, not the good measurement's it replaced.
    s = replace(next(m for m in tuning_sets() if m.name == "tune stops"), seeds=(622,))
    kal = evaluate(s, "kalman", TrackerConfig())
    assert kal["caused_big"] >= 1 and kal["caused_max_sig"] > 5.0
    assert kal["oracle_big"] == 0 and 0.0 < kal["oracle_max_sig"] < 3.0


def test_left_out_measurements_give_the_prediction_of_the_filter_without_them() -> None:
    tr = trajectory(7, duration=6.0)
    ms = make_measurements(tr, 7, outliers=0.05)
    skip = ms.outlier
    assert 3 <= int(skip.sum()) < len(ms.t) // 5
    out, info = run_kalman(ms, TrackerConfig(), skip)
    # The same filter fed only the other measurements, asked for its state at each time.
    trk = Tracker(TrackerConfig())
    for k in range(len(ms.t)):
        t = float(ms.t[k])
        if not skip[k]:
            trk.update("r", t, *ms.z[k], float(ms.sigma[k]))
        st = trk.predict("r", t)
        assert (out[k, 0], out[k, 1], info["sigma"][k]) == (st.x, st.y, st.sigma)
    assert not info["rejected"][skip].any()
    # The IIR filter holds its previous output there.
    iir, _ = run_iir(ms, 1.0, skip)
    k = int(np.flatnonzero(skip)[0])
    assert np.array_equal(iir[k], iir[k - 1]) and np.array_equal(iir[k - 1], ms.z[k - 1])


def test_outlier_effect_is_the_difference_to_the_clean_run() -> None:
    tr = trajectory(7, duration=5.0)
    ms = make_measurements(tr, 7, outliers=0.05)
    clean = np.zeros_like(ms.z)
    out = clean.copy()
    k = int(np.flatnonzero(ms.outlier)[0])
    out[k + 1, 0] = 0.012  # the outlier moves the next output by 12 mm
    sigma = np.full(len(ms.t), 0.003)
    keep = np.ones(len(ms.t), bool)
    eff_m, eff_s = outlier_effect(ms, out, sigma, clean, keep)
    assert eff_m[0] == pytest.approx(0.012) and eff_s[0] == pytest.approx(4.0)


def _brake(cfg: TrackerConfig, seed: int = 4) -> tuple[float, int, list[float]]:
    """A robot cruising at 1.2 m/s along x brakes at 4 m/s^2 to a stop at t = 2 s (20
    frames/s, 4 mm noise); returns the position RMSE during the brake, the measurements
    rejected, and the manoeuvre model's probability at each frame."""
    rng = np.random.default_rng(seed)
    tr = Track("r", cfg)
    errs, mu, rejected = [], [], 0
    for k in range(80):
        t = k / 20
        tau = min(max(t - 2.0, 0.0), 0.3)
        x = 1.2 * min(t, 2.0) + 1.2 * tau - 2.0 * tau * tau
        out = tr.update(t, x + rng.normal(0, 0.004), rng.normal(0, 0.004), 0.0, 0.004)
        rejected += not out.accepted
        mu.append(float(tr.modes.mu[-1]))
        if 2.0 <= t <= 2.4:
            errs.append(tr.predict(t).x - x)
    return float(np.sqrt(np.mean(np.square(errs)))), rejected, mu


def test_two_models_follow_a_hard_brake_that_one_cruise_model_lags() -> None:
    # With the shipped step bound: one cruise model lags the brake, bounded step by step.
    cruise = TrackerConfig(accel_noise=0.06, manoeuvre_scale=1.0)
    one, rej_one, _ = _brake(cruise)
    two, rej_two, mu = _brake(cruise.with_(manoeuvre_scale=40.0))
    assert rej_two == 0 and rej_one > 0  # the cruise model alone gates the brake out
    assert two < 0.5 * one
    # The manoeuvre model takes over during the brake (frames 40-46), and hands back after.
    assert max(mu[41:47]) > 0.5 and max(mu[30:40]) < 0.1 and mu[-1] < 0.1


def test_step_bound_keeps_an_outlier_inside_the_gate_within_k_sigma() -> None:
    # After a 0.4 s gap the prediction is wide: a 4 cm outlier passes the gate. Its step is
    # bounded to step_k of the reported sigma after it; without the bound it moves further.
    def run(step_k: float) -> tuple[float, float]:
        # The outlier mixture all but off (a prior of 1e-6): the bound is on the covariance
        # of the update it bounds (the mixture widens the reported one further).
        tr = Track("r", TrackerConfig(step_k=step_k, outlier_probability=1e-6))
        rng = np.random.default_rng(1)
        for k in range(30):
            tr.update(k / 30, 0.5 * k / 30 + rng.normal(0, 0.003), rng.normal(0, 0.003),
                      0.0, 0.003)
        t = 29 / 30 + 0.4
        before = tr.predict(t)
        out = tr.update(t, 0.5 * t, 0.04, 0.0, 0.003)
        assert out.kind == "update"
        d = np.array([out.state.x - before.x, out.state.y - before.y])
        return float(np.sqrt(d @ np.linalg.solve(out.state.cov[:2, :2], d))), out.state.y

    bounded, y_bounded = run(1.5)
    free, y_free = run(1e9)
    assert bounded == pytest.approx(1.5, abs=0.05) and free > 3.0
    assert 0.0 < y_bounded < y_free
