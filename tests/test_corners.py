"""corner-pnp and its numpy camera model, on frames made with cv2.projectPoints."""

from __future__ import annotations

import ast
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from synth_corners import observe, robot_marker, scenario1

from kmea.estimators import get
from kmea.estimators.corner_pnp import CornerPnP
from kmea.estimators.loo import loo_errors
from kmea.geometry import check_distortion as dist14
from kmea.geometry import project, rotvec_to_matrix, undistort, wrap_angle
from kmea.vision.cvcompat import undistort_points

DISPLACED = {4: (0.02, -0.03), 13: (-0.03, 0.02), 16: (0.025, 0.025)}
ROOT = Path(__file__).resolve().parent.parent


def _floor_ids(sc):
    return [i for i in sc.map.ids if sc.map[i].on_floor]


# ---------------------------------------------------------------- camera model vs OpenCV

@pytest.mark.parametrize("dist", [
    [0.12, -0.25, 0.0, 0.0, 0.10],
    [0.1905, -0.3910, 0.00638, 0.00939, 0.1568],
    [0.2, -0.1, 0.003, -0.002, 0.05, 0.01, 0.02, -0.01],
    [-0.05, 0.02, 0.001, 0.002, 0.0, 0.01, 0.0, 0.003, 0.001, -0.002, 0.0015, 0.001],
])
def test_projection_and_undistortion_match_opencv(dist):
    rng = np.random.default_rng(0)
    K = np.array([[1357.0, 0.4, 819.5], [0.0, 1350.0, 615.5], [0.0, 0.0, 1.0]])
    d = np.array(dist)
    P = np.column_stack([rng.uniform(-0.5, 0.5, (50, 2)), rng.uniform(1.0, 2.0, 50)])
    uv_cv, _ = cv2.projectPoints(P, np.zeros(3), np.zeros(3), K, d)
    uv = project(P, K, dist14(d))
    assert np.abs(uv - uv_cv.reshape(-1, 2)).max() < 1e-9
    xy = undistort(uv, K, dist14(d))
    assert np.abs(xy - P[:, :2] / P[:, 2:]).max() < 1e-12
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-15)
    xy_cv = undistort_points(uv.reshape(-1, 1, 2), K, d, criteria=crit)
    assert np.abs(xy - xy_cv.reshape(-1, 2)).max() < 1e-9


def test_projection_jacobians_match_finite_differences():
    rng = np.random.default_rng(1)
    K = np.array([[1357.0, 0.0, 819.5], [0.0, 1357.0, 615.5], [0.0, 0.0, 1.0]])
    d = dist14([0.12, -0.25, 0.001, -0.002, 0.10, 0.01, 0.0, 0.0, 0.001, 0.0, -0.001, 0.0])
    P = np.column_stack([rng.uniform(-0.5, 0.5, (20, 2)), rng.uniform(1.0, 2.0, 20)])
    uv, J_pc, J_f, J_k1 = project(P, K, d, jac=True)
    h = 1e-7
    for a in range(3):
        P2 = P.copy()
        P2[:, a] += h
        assert np.allclose((project(P2, K, d) - uv) / h, J_pc[:, :, a], atol=1e-3)
    K2 = K.copy()
    K2[:2, :2] *= 1 + h
    assert np.allclose((project(P, K2, d) - uv) / h, J_f, atol=1e-4)
    d2 = d.copy()
    d2[0] += h
    assert np.allclose((project(P, K, d2) - uv) / h, J_k1, atol=1e-3)


def test_algorithm_modules_are_numpy_only():
    est = ROOT / "kmea" / "estimators"
    files = [*sorted((est / "corner_pnp").glob("*.py")), est / "robust.py"]
    assert len(files) >= 8
    for path in files:
        name = path.name
        tree = ast.parse(path.read_text())
        mods = set()
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                mods |= {a.name.split(".")[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom):
                mods.add((node.module or "").split(".")[0])
        assert mods <= {"numpy", "kmea", "math", "collections", "dataclasses", "itertools",
                        "__future__", "typing"}, (name, mods)


# ---------------------------------------------------------------- the estimator

def test_exact_corners_recover_camera_and_markers():
    robot = robot_marker(42, 0.31, 0.22, 0.20, 0.7)
    sc = scenario1(extra={42: robot})
    obs = observe(sc)
    est = get("corner-pnp").estimate(obs, sc.map, camera=sc.camera.intrinsics,
                                     plane_heights={42: 0.20})
    assert est.ok, est.reason
    assert est.rejected == {} and est.scale == 1.0
    assert np.abs(est.cam2world - sc.cam2world).max() < 1e-9
    assert len(est.markers) == len(obs)
    for i, me in est.markers.items():
        assert np.linalg.norm(me.position - sc.true[i].position) < 1e-6, i  # micrometres
        assert abs(wrap_angle(me.yaw - math.atan2(sc.true[i].rotation[1, 0],
                                                  sc.true[i].rotation[0, 0]))) < 1e-6
    assert est.markers[42].position == pytest.approx([0.31, 0.22, 0.20], abs=1e-9)
    assert est.markers[42].yaw == pytest.approx(0.7, abs=1e-9)
    assert est.info["reprojection_rms_px"] < 1e-9


def test_robot_height_matters_and_unknown_height_uses_its_pnp_pose():
    robot = robot_marker(42, -0.4, 0.3, 0.20, -2.0)
    sc = scenario1(extra={42: robot})
    obs = observe(sc, noise_px=0.1, seed=2)
    cp = CornerPnP()
    on_plane = cp.estimate(obs, sc.map, camera=sc.camera.intrinsics, plane_heights={42: 0.2})
    assert np.linalg.norm(on_plane.markers[42].position - robot.position) < 0.5e-3
    assert on_plane.markers[42].yaw == pytest.approx(-2.0, abs=0.01)
    wrong = cp.estimate(obs, sc.map, camera=sc.camera.intrinsics, plane_heights={42: 0.0})
    assert np.linalg.norm(wrong.markers[42].position[:2] - robot.position[:2]) > 0.03
    pnp = cp.estimate(obs, sc.map, camera=sc.camera.intrinsics)
    assert pnp.markers[42].sigma is None  # no plane: its own PnP pose
    assert np.linalg.norm(pnp.markers[42].position - robot.position) < 0.02


def test_loo_with_corner_noise_beats_kmea():
    sc = scenario1()
    cam = sc.camera.intrinsics
    floor = _floor_ids(sc)
    for seed, noise in ((10, 0.1), (11, 0.2)):
        obs = observe(sc, noise_px=noise, seed=seed)
        cp = loo_errors(CornerPnP(), obs, sc.map, camera=cam)
        km = loo_errors(get("kmea"), obs, sc.map, camera=cam)
        cp_mean = np.mean([cp[i] for i in floor])
        km_mean = np.mean([km[i] for i in floor])
        assert cp_mean < km_mean / 4, (noise, cp_mean, km_mean)
        assert cp_mean < 0.25e-3


def test_estimate_with_loo_is_the_estimate_and_the_leave_one_out_by_exclusion():
    sc = scenario1(displaced={4: (0.03, 0.0)})
    cam = sc.camera.intrinsics
    obs = observe(sc, noise_px=0.2, seed=12)
    for cp in (CornerPnP(refine_intrinsics=False), CornerPnP()):
        res = cp.estimate_with_loo(obs, sc.map, camera=cam)
        full = cp.estimate(obs, sc.map, camera=cam)
        assert res.estimate.ok and set(res.estimate.rejected) == set(full.rejected) == {4}
        assert np.array_equal(res.estimate.cam2world, full.cam2world)
        assert set(res.loo_positions) == {o.id for o in obs if o.id in sc.map}
        assert res.loo_failures == {}
        # The one-step fast path against the definition, estimate(exclude={j}).
        for i in [4, *list(res.loo_positions)[::5]]:
            one = cp.estimate(obs, sc.map, exclude={i}, camera=cam)
            assert np.linalg.norm(one.markers[i].position - res.loo_positions[i]) < 2e-6, i
        assert res.loo_errors[4] == pytest.approx(0.03, abs=2e-3)  # the displaced one shows it


def test_leave_one_out_of_chosen_markers_with_exclusions():
    """loo_ids and exclude as the experiments use them: markers outside the fast path (a
    known plane height, an excluded reference) come from estimate(exclude=...) exactly."""
    sc = scenario1()
    cam = sc.camera.intrinsics
    obs = observe(sc, noise_px=0.2, seed=19)
    cp = CornerPnP()
    res = cp.estimate_with_loo(obs, sc.map, exclude={16}, camera=cam, loo_ids=[0, 5, 16],
                               plane_heights={5: 0.0})
    assert set(res.loo_positions) == {0, 5, 16}
    for i in (5, 16):
        one = cp.estimate(obs, sc.map, exclude={i, 16}, camera=cam, plane_heights={5: 0.0})
        assert np.array_equal(one.markers[i].position, res.loo_positions[i])
    assert res.loo_seconds > 0


def test_displaced_anchors_rejected_with_their_displacement():
    sc = scenario1(displaced=DISPLACED)
    cam = sc.camera.intrinsics
    obs = observe(sc, noise_px=0.15, seed=13)
    est = CornerPnP().estimate(obs, sc.map, camera=cam)
    assert est.ok, est.reason
    assert set(est.rejected) == set(DISPLACED)
    for i, (dx, dy) in DISPLACED.items():
        assert est.rejected[i] == pytest.approx(math.hypot(dx, dy), abs=0.002)
        # The displaced marker itself is located where it really is.
        assert np.linalg.norm(est.markers[i].position - sc.true[i].position) < 0.5e-3
    assert est.info["displaced"][0].startswith("marker ")
    others = [i for i in _floor_ids(sc) if i not in DISPLACED]
    cp = loo_errors(CornerPnP(), obs, sc.map, camera=cam)
    km = loo_errors(get("kmea"), obs, sc.map, camera=cam)
    assert np.mean([cp[i] for i in others]) < 0.25e-3
    assert np.mean([km[i] for i in others]) > 1e-3


def test_sigma_is_finite_grows_with_noise_and_is_calibrated():
    sc = scenario1()
    cam = sc.camera.intrinsics
    floor = _floor_ids(sc)
    means = []
    for noise in (0.05, 0.2, 0.8):
        sig, err2 = [], []
        for seed in range(4):
            est = CornerPnP().estimate(observe(sc, noise_px=noise, seed=100 + seed), sc.map,
                                       camera=cam)
            for i in floor:
                me = est.markers[i]
                assert me.sigma is not None and math.isfinite(me.sigma)
                sig.append(me.sigma)
                err2.append(np.sum((me.position - sc.true[i].position) ** 2))
        rms = math.sqrt(np.mean(err2))
        means.append(np.mean(sig))
        # sigma predicts the RMS error (first order), within a factor of 1.5.
        assert rms / 1.5 < np.mean(sig) < rms * 1.5, (noise, rms, np.mean(sig))
    assert means[0] < means[1] < means[2]


def test_intrinsics_refinement_recovers_focal_length_and_k1():
    # A pitched camera makes focal length and distance separable.
    sc = scenario1(height=1.6, tilt_deg=20.0)
    true = sc.camera
    given = true.intrinsics
    K = given.camera_matrix.copy()
    K[:2, :2] *= 1.03
    dist = given.dist_coeffs.copy()
    dist[0] += 0.04
    wrong = type(given)(K, dist, given.width, given.height)
    obs = observe(sc, noise_px=0.1, seed=14)
    floor = [i for i in _floor_ids(sc) if i in {o.id for o in obs}]
    plain = CornerPnP(refine_intrinsics=False).estimate(obs, sc.map, camera=wrong)
    refined = CornerPnP(refine_intrinsics=True).estimate(obs, sc.map, camera=wrong)
    assert refined.info["intrinsics_refined"] and not plain.info["intrinsics_refined"]
    assert refined.info["fx"] == pytest.approx(true.fx, rel=0.003)
    assert refined.info["k1"] == pytest.approx(true.dist_coeffs[0], abs=0.01)

    def mean_err(est):
        return np.mean([np.linalg.norm(est.markers[i].position - sc.true[i].position)
                        for i in floor])

    assert mean_err(refined) < mean_err(plain) / 3
    # "auto": the likelihood-ratio test calls for refinement with the wrong calibration,
    # not with the exact one.
    auto = CornerPnP(refine_intrinsics="auto")
    assert auto.estimate(obs, sc.map, camera=wrong).info["intrinsics_refined"]
    assert not auto.estimate(obs, sc.map, camera=given).info["intrinsics_refined"]


def test_random_camera_poses_exact():
    rng = np.random.default_rng(5)
    sc = scenario1()
    for _ in range(3):
        sc.R = rotvec_to_matrix(rng.normal(scale=0.15, size=3)) @ np.diag([1.0, -1.0, -1.0])
        centre = np.array([rng.uniform(-0.1, 0.3), rng.uniform(0.0, 0.3), rng.uniform(1.2, 1.8)])
        sc.t = -sc.R @ centre
        obs = observe(sc)
        est = CornerPnP().estimate(obs, sc.map, camera=sc.camera.intrinsics)
        assert est.ok, est.reason
        assert np.abs(est.cam2world - sc.cam2world).max() < 1e-9


def test_degenerate_inputs_are_not_estimated():
    sc = scenario1()
    cam = sc.camera.intrinsics
    obs = observe(sc, noise_px=0.1, seed=15)
    cp = CornerPnP()
    est = cp.estimate(obs, sc.map)
    assert not est.ok and "intrinsics" in est.reason and est.markers == {}
    two = [o for o in obs if o.id in (13, 16)]
    est = cp.estimate(two, sc.map, camera=cam)
    assert not est.ok and "2 reference" in est.reason
    no_corners = [type(o)(o.id, o.marker2cam_R, o.marker2cam_t) for o in obs]
    est = cp.estimate(no_corners, sc.map, camera=cam)
    assert not est.ok and "corners" in est.reason
    res = cp.estimate_with_loo(obs, sc.map)
    assert res.loo_positions == {} and not res.estimate.ok
    assert all("intrinsics" in r for r in res.loo_failures.values())
    with pytest.raises(ValueError, match="refine_intrinsics"):
        CornerPnP(refine_intrinsics="sometimes")


def test_turned_reference_is_rejected_and_described():
    from kmea.geometry import rot_z
    from kmea.maps.files import Marker

    sc = scenario1()
    mk = sc.map[16]
    # Corners move by 2 sin(10 deg) x 42 mm = 15 mm RMS, beyond the 10 mm threshold.
    sc.true[16] = Marker(16, mk.position, rot_z(math.radians(20.0)), mk.length)  # turned in place
    est = CornerPnP().estimate(observe(sc, noise_px=0.1, seed=16), sc.map,
                               camera=sc.camera.intrinsics)
    assert set(est.rejected) == {16}
    assert est.rejected[16] < 1e-3  # its centre did not move
    assert math.degrees(est.info["turned"][16]) == pytest.approx(20.0, abs=0.2)
    assert est.info["displaced"] == ["marker 16 looks displaced by 0 mm, turned +20 deg"]


@pytest.mark.parametrize("seed", range(3))
def test_random_displacements_exact_corners(seed):
    rng = np.random.default_rng(seed)
    floor = [i for i in scenario1().map.ids if scenario1().map[i].on_floor]
    bad = [int(i) for i in rng.choice(floor, size=4, replace=False)]
    moves = {}
    for i in bad:
        a, d = rng.uniform(0, 2 * math.pi), rng.uniform(0.015, 0.1)
        moves[i] = (d * math.cos(a), d * math.sin(a))
    sc = scenario1(displaced=moves)
    obs = observe(sc)
    est = CornerPnP().estimate(obs, sc.map, camera=sc.camera.intrinsics)
    seen = {o.id for o in obs}
    assert set(est.rejected) == {i for i in bad if i in seen}
    for i in est.rejected:
        assert est.rejected[i] == pytest.approx(math.hypot(*moves[i]), abs=1e-9)
        assert np.linalg.norm(est.markers[i].position - sc.true[i].position) < 1e-9
    assert np.abs(est.cam2world - sc.cam2world).max() < 1e-9
