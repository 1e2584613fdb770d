"""Thresholds that scale with the measured corner noise, and corrupted corners left out
(kmea.estimators.corner_noise, corner-pnp, kmea-robust), on frames made with
cv2.projectPoints."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from synth_corners import observe, scenario1

from kmea.estimators.corner_noise import (
    SIGMA_FLOOR_PX,
    corner_outliers,
    robust_sigma,
    square_pose,
)
from kmea.estimators.corner_pnp import CornerPnP
from kmea.estimators.robust import KMEARobust
from kmea.estimators.unknown_plane import chi2_quantile
from kmea.geometry import marker_corners_local


def test_robust_sigma_is_the_gaussian_level_despite_outliers() -> None:
    rng = np.random.default_rng(0)
    e = rng.normal(0.0, 0.3, (4000, 2))
    e[::5] += 6.0  # a fifth of the corners 6 px off: the median moves a little
    s = robust_sigma(np.sum(e ** 2, axis=1))
    assert s == pytest.approx(0.3, rel=0.2)
    assert np.sqrt(np.mean(e ** 2)) > 4 * s  # the RMS would be 5x too large
    assert robust_sigma(np.zeros(10)) == SIGMA_FLOOR_PX  # exact corners: the floor


def _obs_by_id(sc, noise: float, seed: int) -> dict:
    return {o.id: o for o in observe(sc, noise_px=noise, seed=seed)}


def test_square_pose_from_three_corners_is_exact() -> None:
    frames = np.eye(3)[None]
    c = np.array([0.3, -0.2, 0.0])
    ang = 0.4
    R = np.array([[np.cos(ang), -np.sin(ang), 0], [np.sin(ang), np.cos(ang), 0], [0, 0, 1]])
    P = (c + marker_corners_local(0.06) @ R.T)[None]
    keep = np.array([[True, False, True, True]])
    P_bad = P.copy()
    P_bad[0, 1] += [0.01, 0.02, 0.0]  # the dropped corner is wrong: it must not matter
    centre, Rw = square_pose(P_bad, frames, np.array([0.06]), keep)
    assert centre[0] == pytest.approx(c, abs=1e-12)
    assert Rw[0] == pytest.approx(R, abs=1e-12)


def test_one_corrupted_corner_is_found_and_clean_squares_are_left_alone() -> None:
    sc = scenario1()
    rng = np.random.default_rng(3)
    obs = _obs_by_id(sc, 0.2, 3)
    ids = sorted(i for i in obs if sc.map[i].on_floor)
    uv = np.array([obs[i].corners for i in ids], float)
    bad = {ids[k]: int(rng.integers(4)) for k in range(0, len(ids), 4)}
    for i, k in bad.items():
        uv[ids.index(i), k] += rng.choice([-1.0, 1.0], 2) * 3.0  # 4.2 px off, 21 sigma
    cam = sc.camera
    K = np.asarray(cam.camera_matrix, float)
    d = np.zeros(14)
    d[:5] = np.asarray(cam.dist_coeffs, float).ravel()[:5]
    centres = np.array([sc.map[i].position for i in ids])
    rots = np.array([sc.map[i].rotation for i in ids])
    drop, _, _ = corner_outliers(sc.R, sc.t, K, d, uv, centres, rots,
                                 np.array([sc.map[i].length for i in ids]), 0.2,
                                 chi2_quantile(0.99999, 2))
    found = {i: int(k) for i, k in zip(ids, drop, strict=True) if k >= 0}
    assert found == bad


def test_corner_pnp_leaves_a_drawn_over_corner_out() -> None:
    # Every reference's first corner 4 px off (a square drawn over it, as in OpenCV's
    # occluded GridBoard photo): the fit leaves those corners out and the markers off the
    # map are placed as well as with clean corners.
    sc = scenario1()
    clean = observe(sc, noise_px=0.1, seed=5)
    corrupt = []
    for o in clean:
        c = np.array(o.corners, float)
        c[0] += [2.8, -2.8]
        corrupt.append(replace(o, corners=c))
    off = [7, 11, 20, 24]
    emap = replace(sc.map, markers={i: m for i, m in sc.map.markers.items() if i not in off},
                   extra=dict(sc.map.extra))
    cam = sc.camera.intrinsics
    est = CornerPnP().estimate(corrupt, emap, camera=cam)
    ref = CornerPnP().estimate(clean, emap, camera=cam)
    assert est.ok and ref.ok
    assert est.info["corner_sigma_px"] < 0.3  # the clean corners' level, not the drawn ones'
    assert set(est.info["corners_dropped"]) >= set(off)
    assert set(est.info["corners_dropped"].values()) == {0}
    assert ref.info["corners_dropped"] == {}

    def err(e):
        return np.array([np.hypot(*(e.markers[i].position[:2] - sc.true[i].position[:2]))
                         for i in off])

    assert err(est).max() < 0.15e-3
    assert err(est).mean() < 2.0 * err(ref).mean() + 0.02e-3


def test_corner_pnp_threshold_scales_with_noise_and_with_each_marker() -> None:
    sc = scenario1(tilt_deg=20.0)
    cam = sc.camera.intrinsics
    lo = CornerPnP().estimate(observe(sc, noise_px=0.05, seed=1), sc.map, camera=cam)
    hi = CornerPnP().estimate(observe(sc, noise_px=0.5, seed=1), sc.map, camera=cam)
    assert lo.ok and hi.ok and lo.rejected == {} and hi.rejected == {}
    ratio = hi.info["threshold"] / lo.info["threshold"]
    assert 4.0 < ratio < 25.0  # 10x the noise
    # Tilted 20 degrees: the far side of the floor is farther and smaller in the image.
    th = hi.info["thresholds"]
    C = sc.cam2world[:3, 3]
    dist = {i: np.linalg.norm(sc.map[i].position - C) for i in th if sc.map[i].on_floor}
    near, far = min(dist, key=dist.get), max(dist, key=dist.get)
    assert th[far] > 1.1 * th[near]


def test_corner_pnp_still_rejects_a_small_displacement_at_low_noise() -> None:
    # 3 mm is many times the noise at 0.1 px (about 0.1 mm): rejected; the former fixed
    # 10 mm threshold kept it (and let it pull the camera).
    sc = scenario1(displaced={9: (0.003, 0.0)})
    cam = sc.camera.intrinsics
    obs = observe(sc, noise_px=0.1, seed=2)
    assert set(CornerPnP().estimate(obs, sc.map, camera=cam).rejected) == {9}
    assert CornerPnP(threshold=0.01).estimate(obs, sc.map, camera=cam).rejected == {}


def test_kmea_robust_threshold_scales_with_noise() -> None:
    sc = scenario1(displaced={9: (0.03, -0.02)})
    lo = KMEARobust().estimate(observe(sc, noise_px=0.05, seed=1), sc.map)
    hi = KMEARobust().estimate(observe(sc, noise_px=0.5, seed=1), sc.map)
    assert set(lo.rejected) == set(hi.rejected) == {9}
    assert hi.info["threshold"] > 3.0 * lo.info["threshold"]
    assert KMEARobust(threshold=0.02).estimate(observe(sc, noise_px=0.5, seed=1),
                                               sc.map).info["threshold"] == 0.02
