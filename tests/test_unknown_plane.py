"""Markers with no known plane: the plane test, its modes, and the free estimate's depth
correction, on frames made with cv2.projectPoints (exact geometry, controlled noise)."""

from __future__ import annotations

import numpy as np
import pytest
from synth_corners import observe, robot_marker, scenario1

from kmea.estimators import get
from kmea.estimators.corner_pnp import CornerPnP
from kmea.estimators.unknown_plane import chi2_quantile, map_planes
from kmea.maps.files import Marker, default_map


def test_chi2_quantile_matches_tables():
    # Reference values from any chi-square table.
    assert chi2_quantile(0.999, 2) == pytest.approx(13.816, rel=1e-4)
    assert chi2_quantile(0.999, 3) == pytest.approx(16.266, rel=1e-4)
    assert chi2_quantile(0.99, 3) == pytest.approx(11.345, rel=1e-4)
    assert chi2_quantile(0.95, 1) == pytest.approx(3.841, rel=1e-3)
    assert chi2_quantile(0.9999, 2) == pytest.approx(18.421, rel=1e-4)
    with pytest.raises(ValueError, match="level"):
        chi2_quantile(1.0)


def test_map_planes_are_the_floor_and_the_walls():
    m = default_map()
    planes = map_planes(m)
    assert planes[0].label == "floor"
    walls = {i for i in m.ids if not m[i].on_floor}
    # Every wall marker lies on exactly one of the other planes.
    for i in walls:
        n, p = m[i].normal, m[i].position
        on = [q for q in planes[1:] if abs(q.frame[:, 2] @ n) > 0.999
              and abs(q.frame[:, 2] @ (p - q.origin)) < 1e-3]
        assert len(on) == 1, i
    assert 1 < len(planes) <= 1 + len(walls)


def _new_floor_marker(mid, x, y, yaw):
    from kmea.geometry import rot_z

    return Marker(mid, np.array([x, y, 0.0]), rot_z(yaw), 0.06)


def test_auto_puts_a_new_floor_marker_on_the_floor_and_a_raised_one_free():
    floor_new = _new_floor_marker(44, 0.41, -0.27, 0.4)
    raised = robot_marker(45, -0.33, 0.12, 0.12, 1.1)
    sc = scenario1(extra={44: floor_new, 45: raised})
    cam = sc.camera.intrinsics
    kmea_err = {44: [], 45: []}
    auto_err = {44: [], 45: []}
    for seed in range(4):
        obs = observe(sc, noise_px=0.15, seed=seed)
        est = CornerPnP().estimate(obs, sc.map, camera=cam)
        assert est.info["unknown_planes"] == {44: "floor", 45: "free"}
        k = get("kmea").estimate(obs, sc.map)
        for i, mk in ((44, floor_new), (45, raised)):
            auto_err[i].append(np.linalg.norm(est.markers[i].position[:2] - mk.position[:2]))
            kmea_err[i].append(np.linalg.norm(k.markers[i].position[:2] - mk.position[:2]))
    # On the floor: a ray-plane estimate, far better than any single-marker depth.
    assert np.mean(auto_err[44]) < 0.3e-3
    assert np.mean(auto_err[44]) < np.mean(kmea_err[44]) / 3
    # Free: no worse than KMEA on the same frames.
    assert np.mean(auto_err[45]) <= np.mean(kmea_err[45]) * 1.05


def test_modes_floor_and_free():
    raised = robot_marker(45, 0.2, 0.2, 0.10, 0.0)
    sc = scenario1(extra={45: raised})
    obs = observe(sc, noise_px=0.1, seed=3)
    cam = sc.camera.intrinsics
    on_floor = CornerPnP(unknown_plane="floor").estimate(obs, sc.map, camera=cam)
    assert on_floor.info["unknown_planes"] == {45: "floor"}
    assert on_floor.markers[45].position[2] == pytest.approx(0.0, abs=1e-12)
    free = CornerPnP(unknown_plane="free").estimate(obs, sc.map, camera=cam)
    assert free.info["unknown_planes"] == {45: "free"}
    assert free.markers[45].position[2] == pytest.approx(0.10, abs=0.01)
    with pytest.raises(ValueError, match="unknown_plane"):
        CornerPnP(unknown_plane="wall")


def test_free_depth_follows_the_references():
    # Every marker printed 2 % small while the map and the PnP assume its map size: each
    # single-marker PnP depth is 2 % short. The camera fit rests on the markers' positions
    # (right), so the references show the ratio and the free estimate corrects it.
    import cv2

    from kmea.estimators.base import MarkerObservation
    from kmea.geometry import marker_corners_local, rotvec_to_matrix

    raised = robot_marker(45, 0.45, 0.3, 0.15, 0.0, length=0.0588)
    sc = scenario1(extra={45: raised})
    sc.true = {i: Marker(i, m.position, m.rotation, m.length * 0.98) if i != 45 else m
               for i, m in sc.true.items()}
    cam = sc.camera
    redo = []
    for o in observe(sc, noise_px=0.05, seed=0):
        believed = sc.map[o.id].length if o.id in sc.map else 0.06
        _, rv, tv = cv2.solvePnP(marker_corners_local(believed), o.corners, cam.camera_matrix,
                                  cam.dist_coeffs, flags=cv2.SOLVEPNP_IPPE_SQUARE)
        redo.append(MarkerObservation(o.id, rotvec_to_matrix(rv.reshape(3)), tv.reshape(3),
                                      o.corners, believed))
    est = CornerPnP(refine_intrinsics=False, unknown_plane="free").estimate(
        redo, sc.map, camera=cam.intrinsics)
    assert est.info["unknown_planes"] == {45: "free"}
    err = np.linalg.norm(est.markers[45].position - raised.position)
    own = redo[[o.id for o in redo].index(45)].marker2cam_t
    uncorrected = np.linalg.norm(est.cam2world[:3, :3] @ own + est.cam2world[:3, 3]
                                 - raised.position)
    assert uncorrected > 0.015  # 2 % of about 1.2 m
    assert err < uncorrected / 5, (err, uncorrected)


@pytest.mark.parametrize("name", ["kmea", "kmea-robust", "umeyama", "lmea"])
def test_kabsch_family_modes(name):
    floor_new = _new_floor_marker(44, -0.37, 0.21, 2.0)
    raised = robot_marker(45, 0.28, -0.15, 0.15, 0.3)
    sc = scenario1(extra={44: floor_new, 45: raised})
    obs = observe(sc, noise_px=0.15, seed=7)
    cam = sc.camera.intrinsics
    paper = get(name).estimate(obs, sc.map, camera=cam)
    assert paper.info["unknown_planes"] == {44: "free", 45: "free"}  # the paper's default
    auto = get(name, unknown_plane="auto").estimate(obs, sc.map, camera=cam)
    assert auto.info["unknown_planes"] == {44: "floor", 45: "free"}
    assert auto.markers[44].position[2] == pytest.approx(0.0, abs=1e-9)
    err = np.linalg.norm(auto.markers[44].position[:2] - floor_new.position[:2])
    if name != "lmea":  # LMEA's 3-anchor camera is too rough for the plane to help always
        assert err < np.linalg.norm(paper.markers[44].position[:2] - floor_new.position[:2])
    assert np.allclose(auto.markers[45].position, paper.markers[45].position)
    # Without intrinsics: "auto" cannot test, "floor" still slides along the ray.
    assert get(name, unknown_plane="auto").estimate(obs, sc.map).info["unknown_planes"] == {
        44: "free", 45: "free"}
    fl = get(name, unknown_plane="floor").estimate(obs, sc.map)
    assert fl.markers[44].position[2] == pytest.approx(0.0, abs=1e-9)
    with pytest.raises(ValueError, match="unknown_plane"):
        get(name, unknown_plane="ceiling")
