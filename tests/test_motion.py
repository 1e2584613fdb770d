"""Robots on the move (issue 27): the simulator's exposure and rolling shutter against real
OpenCV detection, the time of every pose, and the corrections for a pair seen in two rows
and for a moving square's skew."""

from __future__ import annotations

import math

import numpy as np
import pytest

from kmea.estimators.base import MarkerEstimate
from kmea.geometry import rot_z
from kmea.pipeline import FrameInput, Pipeline, PipelineSettings
from kmea.robots.poses import RobotSpec, robot_pose, skew_yaw
from kmea.sim import CrossingPath, Renderer, SimRobot, get_scene
from kmea.sim.motion import StadiumPath
from kmea.sim.scene import Effects
from kmea.vision.detection import DetectorConfig, MarkerDetector

# A robot crossing the floor along x at 1.5 m/s (single marker 42 on a 0.2 m plate).
ACROSS = CrossingPath((-0.8, 0.10), (0.8, 0.10), 0.0, 1.6 / 1.5)
# ... and along -y (down the image rows).
DOWN = CrossingPath((0.1, 0.6), (0.1, -0.6), 0.0, 1.2 / 1.5, theta=0.0)


def _scene(path, width=640, **opts):
    sc = get_scene("scenario1", width=width, **opts)
    return sc.with_(robots=[SimRobot("r", (42,), 0.20, path=path)])


def _detect(image: np.ndarray, dictionary: str) -> dict[int, np.ndarray]:
    det = MarkerDetector(DetectorConfig(dictionary)).detect(image)
    return {int(i): c for i, c in zip(det.ids, det.corners, strict=True)}


def test_stadium_path_is_exact() -> None:
    """Heading = direction of travel, |v| = speed, turn rate speed / radius on the arcs."""
    p = StadiumPath((0.1, -0.05), 0.9, 0.5, 1.5, axis=math.pi / 2, ccw=False)
    dt = 1e-5
    for t in np.linspace(0.0, p.perimeter / 1.5, 97) + 0.0037:  # off the joins
        a, b = p.pose(t - dt), p.pose(t + dt)
        v = math.hypot(b[0] - a[0], b[1] - a[1]) / (2 * dt)
        assert v == pytest.approx(1.5, abs=1e-6)
        heading = math.atan2(b[1] - a[1], b[0] - a[0])
        assert abs(math.remainder(heading - p.pose(t)[2], math.tau)) < 1e-6
        w = math.remainder(b[2] - a[2], math.tau) / (2 * dt)
        if abs(w) > 1e-3:
            assert w == pytest.approx(p.turn_rate(t), abs=1e-6)
            assert abs(w) == pytest.approx(3.0, abs=1e-6)


def test_noise_grows_with_the_gain_of_a_short_exposure() -> None:
    e = Effects(noise_sigma=2.0, exposure_time_s=0.002, light_exposure_s=0.016)
    assert e.gain == 8.0
    assert e.sensor_noise_sigma == pytest.approx(2.0 * math.sqrt(0.7 * 8 + 0.3 * 64))
    assert Effects(noise_sigma=2.0, exposure_time_s=0.03, light_exposure_s=0.016
                   ).sensor_noise_sigma == 2.0
    sc = get_scene("scenario1", width=320, height=240, exposure_ms=2, light_ms=16)
    r = Renderer(sc)
    d = r.render_image(1).astype(float) - r.render_image(2).astype(float)
    assert np.std(d) / math.sqrt(2) == pytest.approx(e.sensor_noise_sigma, rel=0.1)


def test_exposure_smears_the_moving_robot_not_the_floor() -> None:
    """Same frame, 8 ms against an instant: away from the robot the images are equal; the
    marker's edges across the motion spread over the 12 mm it moves (about 7 px here)."""
    sharp = Renderer(_scene(ACROSS, noise=0)).render(12)
    smear = Renderer(_scene(ACROSS, noise=0, exposure_ms=8)).render(12)
    u, v = sharp.truth.corners[42].mean(axis=0)
    box = (slice(int(v) - 45, int(v) + 45), slice(int(u) - 50, int(u) + 50))  # the plate
    far = np.ones(sharp.image.shape, bool)
    far[box] = False
    assert np.array_equal(sharp.image[far], smear.image[far])
    row = int(v)
    grad = [np.abs(np.diff(im.image[row, box[1]].astype(float))).max() for im in (sharp, smear)]
    assert grad[1] < 0.4 * grad[0]


def test_rolling_shutter_truth_is_where_opencv_finds_the_corners() -> None:
    """A robot driving down an 820x616 image under a slow rolling shutter (100 us a row,
    62 ms a frame: exaggerated so the effect is many pixels): OpenCV finds its corners where
    the truth says each was at its own row's mid-exposure (within its 0.2-0.4 px detection
    error at this size), not where it was at the frame's timestamp."""
    sc = _scene(DOWN, 820, line_us=100, exposure_ms=0.5)
    plain = Renderer(_scene(DOWN, 820)).truth(9)
    f = Renderer(sc).render(9)
    found = _detect(f.image, sc.world_map.dictionary)[42]
    assert np.abs(found - f.truth.corners[42]).max() < 0.45
    assert np.abs(found - plain.corners[42]).max() > 10.0
    # the floor's markers do not move: the same corners either way
    assert np.abs(f.truth.corners[13] - plain.corners[13]).max() < 1e-9


def test_pose_is_stamped_with_its_markers_time() -> None:
    """Through the pipeline with the frame's timing: the robot's time is its marker's
    mid-exposure, and the truth then matches the measurement to a millimetre; stamped with
    the frame's timestamp (no timing), the same pose is over 9 mm off."""
    # driving forwards (ctrv) at 1 m/s down the image, the IMX219's 48.5 us a row at 640x480
    down = CrossingPath((0.1, 0.6), (0.1, -0.6), 0.0, 1.2)
    sc = _scene(down, rolling=1, exposure_ms=1.0)
    r = Renderer(sc)
    specs = tuple(sc.robot_specs())
    p = Pipeline(sc.camera, sc.effective_map(),
                 PipelineSettings(robots=specs, filter_kind="kalman", loo=False))
    for i in range(16, 21):  # the robot in the lower half: read out 11-14 ms after row 0
        f = r.render(i)
        res = p.process(FrameInput(i, f.timestamp, f.image, meta={"timing": f.truth.timing}))
        fix = res.robots["r"]
        rows = res.corners[list(res.ids).index(42)][:, 1].mean()
        assert fix.t == pytest.approx(f.timestamp + rows * sc.effects.line_time_s - 0.5e-3)
        x, y, _ = f.truth.robot_at("r", fix.t)
        assert math.hypot(fix.raw[0] - x, fix.raw[1] - y) < 1e-3
        x0, y0, _ = f.truth.robot_at("r", f.timestamp)
        assert math.hypot(fix.raw[0] - x0, fix.raw[1] - y0) > 0.009
    p.close()


def _estimate(mid: int, xy, yaw: float) -> MarkerEstimate:
    return MarkerEstimate(mid, np.array([xy[0], xy[1], 0.2]), rot_z(yaw), yaw)


def test_pair_seen_in_two_rows_is_brought_to_one_instant() -> None:
    """A pair driving +x at 1.5 m/s, its left marker seen 1.2 ms after its right one: the
    midpoint is the centre at the mean time; the heading is right only once each marker is
    moved to that time with the robot's motion (0.9 deg off without)."""
    spec = RobotSpec("amr1", (40, 41), 0.2)
    v, t_r, t_l = 1.5, 0.0100, 0.0112
    est = {40: _estimate(40, (v * t_l, 0.05), 0.0), 41: _estimate(41, (v * t_r, -0.05), 0.0)}
    times = {40: t_l, 41: t_r}
    pose = robot_pose(spec, est, times, (v, 0.0, 0.0))
    assert pose.t == pytest.approx((t_l + t_r) / 2)
    assert pose.x == pytest.approx(v * pose.t) and pose.y == pytest.approx(0.0)
    assert pose.theta == pytest.approx(0.0, abs=1e-12)
    bare = robot_pose(spec, est, times)
    assert abs(math.degrees(bare.theta)) == pytest.approx(
        math.degrees(math.atan2(v * (t_l - t_r), 0.10)), rel=1e-9)


def test_skew_yaw_is_half_the_shear_of_the_drawn_square() -> None:
    """The best rotation onto a square whose points are seen later by g . p (s/m) while it
    moves at v is off by skew_yaw (the first-order formula, against a Procrustes fit), up
    to 3 % of it."""
    rng = np.random.default_rng(27)
    side = 0.06
    sq = np.array([[-1, 1], [1, 1], [1, -1], [-1, -1]], float) * side / 2
    for _ in range(20):
        yaw = rng.uniform(-math.pi, math.pi)
        v = rng.uniform(-1.5, 1.5, 2)
        g_local = rng.uniform(-0.03, 0.03, 2)  # s/m: ~1 ms across a 6 cm marker
        R = rot_z(yaw)[:2, :2]
        world = sq @ R.T
        g = R @ g_local
        seen = world + np.outer(world @ g, v)
        h = (sq.T @ seen)
        fit = math.atan2(h[0, 1] - h[1, 0], h[0, 0] + h[1, 1])
        err = math.remainder(fit - yaw, math.tau)
        first = skew_yaw(yaw, tuple(g_local), tuple(v))
        # first order: what is left is ~1 % of it (0.01 deg of the 0.9 deg at 1.5 m/s)
        assert abs(err - first) < 0.03 * abs(first) + 1e-6


def test_without_exposure_or_rolling_shutter_poses_keep_the_frame_time() -> None:
    """The default simulated floor (no exposure, no line time): the frame's timing is all
    zeros and every robot's time is the frame's timestamp, bit for bit (outputs as before)."""
    from kmea.sources.sim import SimSource

    src = SimSource("sim:default?width=640&height=480", frames=3)
    p = Pipeline(src.camera, src.world_map,
                 PipelineSettings(robots=tuple(src.scene.robot_specs()), filter_kind="kalman",
                                  loo=False))
    for f in src:
        res = p.process(FrameInput(f.index, 1.7e9 + f.timestamp, f.image, meta=f.meta))
        assert res.robots and all(fix.t == 1.7e9 + f.timestamp for fix in res.robots.values())
    p.close()


def test_rendered_pair_and_square_corrections() -> None:
    """Rendered frames, the IMX219's 48.5 us a row at 640x480, two robots driving +x at
    1 m/s: the pair's markers sit 46 rows apart (2.2 ms: 1.3 deg of heading) and the single
    marker is drawn skewed (0.64 deg). With the frame's timing and the track's motion the
    pair's heading is within 0.45 deg of the truth at the pose's time in every frame and the
    single marker's bias is gone (its yaw scatters by +-0.7 deg at 28 px); the same markers
    without the corrections are off by those figures."""
    pair = SimRobot("pair", (40, 41), 0.20, path=CrossingPath((-0.6, 0.15), (0.6, 0.15), 0, 1.2))
    one = SimRobot("one", (42,), 0.20, path=CrossingPath((-0.6, -0.2), (0.6, -0.2), 0, 1.2))
    sc = get_scene("scenario1", width=640, rolling=1, exposure_ms=1.0).with_(robots=[pair, one])
    r = Renderer(sc)
    specs = {s.name: s for s in sc.robot_specs()}
    p = Pipeline(sc.camera, sc.effective_map(),
                 PipelineSettings(robots=tuple(specs.values()), filter_kind="kalman", loo=False))
    err: dict[str, list[tuple[float, float]]] = {"pair": [], "one": []}
    for i in range(6, 16):
        f = r.render(i)
        res = p.process(FrameInput(i, f.timestamp, f.image, meta={"timing": f.truth.timing}))
        if i < 10:
            continue  # the tracks learn the velocity
        for name, fix in res.robots.items():
            th = f.truth.robot_at(name, fix.t)[2]
            plain = robot_pose(specs[name], res.estimate.markers)  # no times, no motion
            err[name].append((math.degrees(math.remainder(fix.raw[2] - th, math.tau)),
                              math.degrees(math.remainder(plain.theta - th, math.tau))))
    p.close()
    pair_e, one_e = np.array(err["pair"]), np.array(err["one"])
    assert len(pair_e) == len(one_e) == 6
    assert np.abs(pair_e[:, 0]).max() < 0.45 and pair_e[:, 1].mean() > 0.9
    assert abs(one_e[:, 0].mean()) < 0.2 and one_e[:, 1].mean() > 0.5
    assert (one_e[:, 1] - one_e[:, 0]).mean() == pytest.approx(0.64, abs=0.1)
