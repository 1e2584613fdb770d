"""The simulator's images against its truth, checked with real OpenCV detection."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from kmea.geometry import marker_corners_local, rot_z
from kmea.maps.files import Marker
from kmea.sim import (
    Effects,
    Occluder,
    Renderer,
    Scene,
    SimRobot,
    Stationary,
    get_scene,
    scenario1_camera,
)
from kmea.vision.camera import pi_camera_v2


def _detector(**params: float) -> cv2.aruco.ArucoDetector:
    p = cv2.aruco.DetectorParameters()
    p.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    p.cornerRefinementMaxIterations = 50
    p.cornerRefinementMinAccuracy = 0.01
    for k, v in params.items():
        setattr(p, k, v)
    return cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_5X5_100), p)


def _detect(image: np.ndarray, **params: float) -> dict[int, np.ndarray]:
    """ArUco detection with sub-pixel refinement; at 640x480 the markers are ~27 px wide, so
    small images use a refinement window of 0.7 module (OpenCV's 0.3 is ~1 px there)."""
    if image.shape[1] <= 800:
        params.setdefault("relativeCornerRefinmentWinSize", 0.7)
    corners, ids, _ = _detector(**params).detectMarkers(image)
    if ids is None:
        return {}
    return {int(i): c.reshape(4, 2) for i, c in zip(ids.ravel(), corners, strict=True)}


def _min_side(c: np.ndarray) -> float:
    return float(np.linalg.norm(c - np.roll(c, 1, axis=0), axis=1).min())


def _expected(truth, shape: tuple[int, int], margin: float, min_side: float) -> set[int]:
    """Visible markers whose corners lie ``margin`` px inside the image, big enough to read."""
    H, W = shape
    out = set()
    for mid in truth.visible:
        c = truth.corners[mid]
        if (c.min() >= margin and c[:, 0].max() <= W - 1 - margin
                and c[:, 1].max() <= H - 1 - margin and _min_side(c) >= min_side):
            out.add(mid)
    return out


@pytest.fixture(scope="module")
def default_frame():
    """Frame 0 of the default scene at the default 1640x1232 (both robots in view)."""
    r = Renderer(get_scene("default"))
    return r, r.render(0)


def test_default_frame_corner_fidelity(default_frame):
    _, f = default_frame
    assert f.image.shape == (1232, 1640) and f.image.dtype == np.uint8
    found = _detect(f.image)
    truth = f.truth
    expect = _expected(truth, f.image.shape, margin=30, min_side=20)
    # every floor marker in view, both robots' markers
    assert {13, 16, 4, 40, 41, 42} <= expect
    assert len(expect) >= 30
    assert expect <= set(found), f"missed {sorted(expect - set(found))}"
    assert set(found) <= set(truth.markers), "a detected id is not in the scene"
    err = np.concatenate([found[m] - truth.corners[m] for m in sorted(expect)])
    rms = math.sqrt(float((err ** 2).sum(axis=1).mean()))
    mean = err.mean(axis=0)
    assert rms < 0.25, rms
    assert abs(mean[0]) < 0.05 and abs(mean[1]) < 0.05, mean


def test_truth_corners_match_cv2_project_points(default_frame):
    r, f = default_frame
    _check_truth_against_cv2(r, f.truth)
    assert {40, 41, 42} <= set(f.truth.corners)


def _check_truth_against_cv2(r: Renderer, truth) -> None:
    cam = r.scene.camera
    w2c = np.linalg.inv(truth.cam2world)
    rvec, _ = cv2.Rodrigues(w2c[:3, :3])
    assert truth.corners
    for mid, c in truth.corners.items():
        T = truth.markers[mid]
        pts = marker_corners_local(truth.lengths[mid]) @ T[:3, :3].T + T[:3, 3]
        ref, _ = cv2.projectPoints(pts, rvec, w2c[:3, 3], cam.camera_matrix, cam.dist_coeffs)
        assert np.abs(ref.reshape(4, 2) - c).max() < 1e-6, mid


def test_truth_corners_oblique_camera_and_misplaced_marker():
    sc = get_scene("scenario2-robots", width=640, height=480,
                   misplaced={13: ((0.01, -0.02, 0.0), (0.0, 0.0, 15.0))})
    r = Renderer(sc)
    truth = r.truth(50)
    _check_truth_against_cv2(r, truth)
    # wall markers are seen in this view
    assert any(m >= 50 for m in truth.corners)


def _plain(**kw) -> Effects:
    return Effects(noise_sigma=0.0, blur_sigma=0.0, vignetting=0.0, **kw)


def test_robot_marker_above_the_floor_drawn_where_projected_and_hides_floor():
    cam = pi_camera_v2(640, 480)
    world = get_scene("scenario1").world_map
    # Robot parked over floor marker 15 (0.468, 0), far enough from the optical axis that
    # its 0.2 m height moves its marker tens of pixels from where it would be on the floor.
    robot = SimRobot("solo", (42,), height=0.20, length=0.06, path=Stationary(0.468, 0.0, 0.3))
    base = Scene(world, cam, scenario1_camera(1.35), [], _plain())
    with_robot = Scene(world, cam, scenario1_camera(1.35), [robot], _plain())
    f0 = Renderer(base).render(0)
    f1 = Renderer(with_robot).render(0)
    d0, d1 = _detect(f0.image), _detect(f1.image)
    assert 15 in d0 and 15 not in d1
    assert 15 in f0.truth.visible and 15 not in f1.truth.visible
    c = f1.truth.corners[42]
    assert np.abs(d1[42] - c).max() < 0.6
    # every cell of the marker has the dictionary's colour where projection puts its centre
    tex = cv2.aruco.generateImageMarker(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_5X5_100),
                                        42, 7, borderBits=1)
    T = f1.truth.markers[42]
    k = (np.arange(7) + 0.5) / 7 * 0.06 - 0.03
    gx, gy = np.meshgrid(k, -k)  # row 0 is the top (+y) of the marker
    cells = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(49)]) @ T[:3, :3].T + T[:3, 3]
    from kmea.sim.lens import project

    uv, _ = project(cells, np.linalg.inv(f1.truth.cam2world), cam)
    px = f1.image[np.round(uv[:, 1]).astype(int), np.round(uv[:, 0]).astype(int)]
    assert np.array_equal(px > 128, tex.ravel() > 128)
    # the same marker on the floor would be elsewhere: the height matters
    assert abs(T[2, 3] - 0.20) < 1e-12
    floor_T = T.copy()
    floor_T[2, 3] = 0.0
    on_floor, _ = project(marker_corners_local(0.06) @ floor_T[:3, :3].T + floor_T[:3, 3],
                          np.linalg.inv(f1.truth.cam2world), cam)
    assert np.linalg.norm(on_floor - c, axis=1).min() > 10
    # the floor marker's pixels now show the robot's plate (uniform grey), not the marker
    fc = f0.truth.corners[15]
    inside = np.round(fc.mean(axis=0)).astype(int)
    x0, y0 = np.floor(fc.min(axis=0)).astype(int) + 2
    x1, y1 = np.ceil(fc.max(axis=0)).astype(int) - 2
    patch0 = f0.image[y0:y1, x0:x1].astype(int)
    patch1 = f1.image[y0:y1, x0:x1].astype(int)
    assert patch0.max() - patch0.min() > 150  # black and white cells
    assert f1.image[inside[1], inside[0]] != f0.image[inside[1], inside[0]] or \
        patch1.std() < patch0.std() / 2


def test_misplaced_marker_appears_displaced_map_keeps_nominal():
    sc = get_scene("scenario1", width=640, height=480, noise=0,
                   misplaced={13: (0.03, 0.0, 0.0), 14: ((0.0, 0.0, 0.0), (0.0, 0.0, 20.0))})
    r = Renderer(sc)
    f = r.render(0)
    found = _detect(f.image)
    T13 = f.truth.markers[13]
    assert np.allclose(T13[:3, 3], [0.03, 0.0, 0.0])
    assert np.allclose(sc.effective_map()[13].position, [0.0, 0.0, 0.0])
    nominal = Renderer(get_scene("scenario1", width=640, height=480, noise=0)).truth(0)
    shift = np.linalg.norm(f.truth.corners[13] - nominal.corners[13], axis=1)
    assert shift.min() > 8  # 3 cm at 1.35 m with f = 530 px: ~12 px
    assert np.abs(found[13] - f.truth.corners[13]).max() < 0.6
    assert np.linalg.norm(found[13] - nominal.corners[13], axis=1).min() > 8
    # the rotated one: detected corners follow the 20 degree turn
    yaw = math.degrees(math.atan2(*(found[14][1] - found[14][0])[::-1]))
    yaw0 = math.degrees(math.atan2(*(nominal.corners[14][1] - nominal.corners[14][0])[::-1]))
    assert abs(abs(yaw - yaw0) - 20) < 1.5


def test_raised_markers_on_supports_and_effective_map():
    sc = get_scene("scenario1", width=640, height=480, noise=0, raised=[13, 7])
    assert sc.effective_map()[13].position[2] == pytest.approx(0.20)
    assert sc.world_map[13].position[2] == 0.0
    f = Renderer(sc).render(0)
    found = _detect(f.image)
    for mid in (13, 7):
        assert f.truth.markers[mid][2, 3] == pytest.approx(0.20)
        assert np.abs(found[mid] - f.truth.corners[mid]).max() < 0.6


def test_occluders_hide_markers():
    sc = get_scene("scenario1", width=640, height=480, covered=[13, 16])
    f = Renderer(sc).render(0)
    found = _detect(f.image)
    assert {13, 16}.isdisjoint(f.truth.visible)
    assert {13, 16}.isdisjoint(found)
    assert {4, 14, 15} <= set(found)
    # an arm crossing at t = 1..3 s along y = 0 hides the middle row while it passes
    arm = Occluder.arm(y=0.0, z=0.5, t0=1.0, duration=2.0)
    r = Renderer(get_scene("scenario1", width=640, height=480, occluders=[arm]))
    before, during = r.render(0), r.render(60)  # t = 0 s and t = 2 s (arm at x = 0)
    assert 13 in before.truth.visible and 13 not in during.truth.visible
    assert 13 in _detect(before.image) and 13 not in _detect(during.image)


def test_deterministic_for_a_seed():
    sc = get_scene("default", width=320, height=240, seed=7)
    a, b = Renderer(sc), Renderer(sc)
    fa, fb = a.render(12), b.render(12)
    assert np.array_equal(fa.image, fb.image)
    assert np.array_equal(a.render(12).image, fa.image)  # order does not matter
    other = Renderer(get_scene("default", width=320, height=240, seed=8)).render(12)
    assert not np.array_equal(other.image, fa.image)
    assert np.abs(other.image.astype(int) - fa.image.astype(int)).mean() < 4  # noise only
    assert not np.array_equal(a.render(13).image, fa.image)


def test_noise_level_and_frames_differ():
    sc = get_scene("scenario1", width=320, height=240, noise=3.0)
    r = Renderer(sc)
    d = r.render(0).image.astype(float) - r.render(1).image.astype(float)
    # two independent noise draws: std of the difference is sigma * sqrt(2)
    assert 3.0 * math.sqrt(2) * 0.85 < d.std() < 3.0 * math.sqrt(2) * 1.15


def test_wall_markers_found_in_oblique_view():
    f = Renderer(get_scene("scenario2", noise=1.0)).render(0)
    found = _detect(f.image, minDistanceToBorder=1)
    expect = _expected(f.truth, f.image.shape, margin=20, min_side=24)
    walls = {m for m in expect if m >= 50}
    assert len(walls) >= 4
    assert expect <= set(found)
    err = np.concatenate([found[m] - f.truth.corners[m] for m in sorted(expect)])
    assert np.abs(err).max() < 1.5
    assert math.sqrt(float((err ** 2).sum(axis=1).mean())) < 0.5


def test_extra_marker_and_robot_truth_conventions():
    extra = Marker(77, np.array([0.1, -0.25, 0.0]), rot_z(0.4), 0.06)
    sc = get_scene("default", width=320, height=240, extra_markers=[extra],
                   misplaced={41: (0.0, 0.01, 0.0)})
    tr = Renderer(sc).truth(30)
    assert np.allclose(tr.markers[77][:3, 3], extra.position)
    x, y, th = tr.robots["amr1"]
    left, right = tr.markers[40][:3, 3], tr.markers[41][:3, 3]
    # pair: left at +d, right at -d (robot frame), the right one misplaced +1 cm to the left
    fwd, lft = np.array([math.cos(th), math.sin(th)]), np.array([-math.sin(th), math.cos(th)])
    assert np.allclose(left[:2], [x, y] + 0.05 * lft)
    assert np.allclose(right[:2], [x, y] - 0.04 * lft)
    assert abs(np.dot(tr.markers[40][:2, 0], fwd) - 1) < 1e-12  # x axis forward
    # the robots' own pose rule (kmea.robots.poses) recovers the true pose from the true markers
    from kmea.estimators.base import MarkerEstimate
    from kmea.robots.poses import robot_pose

    spec = {s.name: s for s in sc.robot_specs()}["amr1"]
    R40 = tr.markers[40][:3, :3]
    est = {40: MarkerEstimate(40, tr.markers[40][:3, 3], R40, math.atan2(R40[1, 0], R40[0, 0]))}
    rp = robot_pose(spec, est)
    assert np.allclose((rp.x, rp.y, rp.theta), (x, y, th), atol=1e-9)
    T = tr.marker2cam(42)
    assert np.allclose(tr.cam2world @ T, tr.markers[42])
    x2, y2, th2 = tr.robots["amr2"]
    assert np.allclose(tr.markers[42][:3, 3], [x2, y2, 0.20])
    assert abs(math.atan2(tr.markers[42][1, 0], tr.markers[42][0, 0]) - th2) < 1e-12


def test_moving_robot_rendered_like_the_same_geometry_in_the_static_pass():
    """Robots are re-rendered every frame with their own sampling; the static pass renders a
    box with the same top and a marker at the same pose: their pixels must agree."""
    from kmea.sim.scene import PALETTE

    cam = pi_camera_v2(640, 480)
    world = get_scene("scenario1").world_map
    pose = (0.30, -0.12, 0.7)
    robot = SimRobot("solo", (42,), path=Stationary(*pose))
    dyn = Renderer(Scene(world, cam, scenario1_camera(1.35), [robot], _plain())).render(0)
    box = Occluder((robot.plate, robot.plate), (0.0, 0.20), Stationary(*pose),
                   shade=PALETTE["plate"])
    marker = Marker(42, np.array([pose[0], pose[1], 0.20]), rot_z(pose[2]), 0.06)
    sta = Renderer(Scene(world, cam, scenario1_camera(1.35), [], _plain(occluders=[box]),
                         extra_markers=[marker])).render(0)
    c = dyn.truth.corners[42]
    assert np.allclose(c, sta.truth.corners[42])
    # the marker, its quiet zone and a pixel of the plate around it
    centre = c.mean(axis=0)
    zone = centre + (c - centre) * 9 / 7
    zone += np.sign(zone - centre) * 1.0
    mask = np.zeros(dyn.image.shape, np.uint8)
    cv2.fillConvexPoly(mask, np.round(zone).astype(np.int32), 1)
    a = dyn.image[mask > 0].astype(int)
    b = sta.image[mask > 0].astype(int)
    assert a.size > 600 and a.max() - a.min() > 150  # the marker is there
    # 34 rays per edge pixel against 89: coverage differs by up to ~1.5 / 34 of the contrast
    # (identical with 89 rays); a pixel sampled wrongly would differ by up to ~200
    diff = np.abs(a - b)
    assert diff.max() <= 16 and diff.mean() < 1.0, (diff.max(), diff.mean())


def test_any_map_any_dictionary():
    from kmea.maps.files import MarkerMap

    markers = {i: Marker(i, np.array([x, y, 0.0]), rot_z(yaw), 0.08)
               for i, (x, y, yaw) in enumerate([(-0.3, 0.1, 0.0), (0.2, -0.1, 0.6),
                                                (0.1, 0.25, -2.0)])}
    m = MarkerMap(markers, dictionary="DICT_4X4_50", default_length=0.08, origin_id=0,
                  x_id=1, y_id=2, name="three")
    sc = Scene(m, pi_camera_v2(640, 480), scenario1_camera(1.0), [], _plain())
    assert sc.floor_rect() == pytest.approx((-0.45, 0.35, -0.25, 0.4))
    f = Renderer(sc).render(0)
    p = cv2.aruco.DetectorParameters()
    p.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    p.relativeCornerRefinmentWinSize = 0.7
    det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50), p)
    corners, ids, _ = det.detectMarkers(f.image)
    found = {int(i): c.reshape(4, 2) for i, c in zip(ids.ravel(), corners, strict=True)}
    assert set(found) == {0, 1, 2}
    for i in found:
        assert np.abs(found[i] - f.truth.corners[i]).max() < 0.5
