"""corner-pnp's per-frame path on a fixed camera (issue 14): the robots placed again with the
warm fit, from constants cached per fit and leaner numerics, give what the straightforward
formulation gives (to 1e-9), frame after frame and across a refit of the camera.

The references below are the formulation corner-pnp had before it was made fast (the same
formulas, one numpy call per step, nothing cached); the library's versions must agree with
them, and a cache that outlives its fit must be caught.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from synth_corners import observe, robot_marker, scenario1

from kmea.estimators.base import check_observations
from kmea.estimators.corner_noise import corner_outliers, square_pose
from kmea.estimators.corner_pnp import CornerPnP, uncertainty
from kmea.estimators.corner_pnp.placement import corner_sigma
from kmea.geometry import (
    distort,
    distort_jacobian,
    intersect_rays_planes,
    marker_corners_local,
    project,
    project_jac_pc,
    rotvec_to_matrix,
    undistort,
)
from kmea.geometry.camera import CameraIntrinsics

ROBOTS = (40, 41, 42)
HEIGHT = 0.2


# ----------------------------------------------------------------- the references
def ref_undistort(uv, K, d, iterations=20):
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    target = (uv - np.array([K[0, 2], K[1, 2]])) / np.array([K[0, 0], K[1, 1]])
    if not np.any(d[:12]):
        return target
    xy = target.copy()
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = d[:12]
    for _ in range(3):
        x, y = xy[:, 0], xy[:, 1]
        r2 = x * x + y * y
        r4 = r2 * r2
        icd = (1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))) / (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3)))
        dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) + s1 * r2 + s2 * r4
        dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y + s3 * r2 + s4 * r4
        xy = np.stack([(target[:, 0] - dx) * icd, (target[:, 1] - dy) * icd], axis=1)
    for _ in range(iterations):
        f, J = distort(xy, d, jac=True)[:2]
        F = f - target
        if np.max(np.abs(F)) < 1e-15:
            break
        det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
        step_x = (J[:, 1, 1] * F[:, 0] - J[:, 0, 1] * F[:, 1]) / det
        step_y = (-J[:, 1, 0] * F[:, 0] + J[:, 0, 0] * F[:, 1]) / det
        xy = xy - np.stack([step_x, step_y], axis=1)
    return xy


def ref_intersect(R, t, xy, frames, origins):
    ray = np.concatenate([xy, np.ones((len(xy), 1))], axis=1) @ R
    return intersect_rays_planes(-R.T @ t, ray, origins, frames[:, :, 2])


def ref_sigmas(fit, xy, F, O):
    p = fit.H.shape[0]
    n = len(xy) // 4
    cov = fit.sigma_px ** 2 * np.linalg.inv(fit.H)
    base = ref_intersect(fit.R, fit.t, xy, F, O)
    h = 1e-7
    dP_dxy = np.empty((len(xy), 3, 2))
    for axis in range(2):
        xy2 = xy.copy()
        xy2[:, axis] += h
        dP_dxy[:, :, axis] = (ref_intersect(fit.R, fit.t, xy2, F, O) - base) / h
    xd, Jd, dk1 = distort(xy, fit.d, jac=True)
    Jd_inv = np.linalg.inv(Jd)
    Jc = np.empty((n, 3, p))
    Rs = np.repeat(fit.R[None], 6, axis=0)
    ts = np.repeat(fit.t[None], 6, axis=0)
    for k in range(3):
        Rs[k] = rotvec_to_matrix(h * np.eye(3)[k]) @ fit.R
        ts[3 + k, k] += h
    xy1 = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
    rays = np.einsum("nj,kji->kni", xy1, Rs)
    Pk = intersect_rays_planes(-np.einsum("kji,kj->ki", Rs, ts)[:, None, :], rays,
                               O[None], F[None, :, :, 2])
    Jc[:, :, :6] = np.moveaxis(((Pk - base[None]) / h).reshape(6, n, 4, 3).mean(axis=2), 0, 2)
    if fit.refine:
        m = fit.K[0, 0] / fit.K0[0, 0]
        for k, rhs in ((6, -xd / m), (7, -dk1)):
            dxy = np.einsum("nij,nj->ni", Jd_inv, rhs)
            Jc[:, :, k] = np.einsum("nij,nj->ni", dP_dxy, dxy).reshape(n, 4, 3).mean(axis=1)
    cov_c = np.einsum("nik,kl,njl->nij", Jc, cov, Jc)
    A_inv = np.diag([1.0 / fit.K[0, 0], 1.0 / fit.K[1, 1]])
    dP_duv = np.einsum("nij,njk,kl->nil", dP_dxy, Jd_inv, A_inv).reshape(n, 4, 3, 2)
    cov_c += fit.sigma_px ** 2 / 16.0 * np.einsum("nkia,nkja->nij", dP_duv, dP_duv)
    return np.sqrt(np.trace(cov_c, axis1=1, axis2=2))


def ref_square_pose(P, frames, lengths, keep=None):
    """The general (weighted) square fit, with all 4 corners kept unless told otherwise: the
    reference of square_pose's all-corner shortcut."""
    return square_pose(P, frames, lengths, np.ones((len(P), 4), bool) if keep is None else keep)


def ref_corner_outliers(R, t, K, d, uv, centres, rotations, lengths, sigma_px, threshold):
    n = len(uv)
    sq = marker_corners_local(1.0)[None] * np.asarray(lengths, float)[:, None, None]
    X = centres[:, None, :] + np.einsum("nij,nkj->nki", rotations, sq)
    Pc = X.reshape(-1, 3) @ R.T + t
    proj, J_pc, _, _ = project(Pc, K, d, jac=True)
    e0 = (proj - uv.reshape(-1, 2)).reshape(n, 8)
    dX = np.empty((n, 4, 3, 3))
    dX[:, :, :, 0] = rotations[:, None, :, 0]
    dX[:, :, :, 1] = rotations[:, None, :, 1]
    dX[:, :, :, 2] = np.cross(rotations[:, None, :, 2], X - centres[:, None, :])
    J = np.einsum("nkab,bc,nkcp->nkap", J_pc.reshape(n, 4, 2, 3), R, dX).reshape(n, 8, 3)
    inv = np.linalg.inv(np.einsum("nap,naq->npq", J, J))
    H = np.einsum("nap,npq,nbq->nab", J, inv, J)
    e = e0 - np.einsum("nab,nb->na", H, e0)
    stats = np.empty((n, 4))
    for k in range(4):
        s = slice(2 * k, 2 * k + 2)
        ek = e[:, s]
        A = np.eye(2)[None] - H[:, s, s]
        stats[:, k] = np.einsum("na,na->n", ek, np.linalg.solve(A, ek[:, :, None])[:, :, 0])
    stats /= max(sigma_px, 1e-12) ** 2
    worst = np.argmax(stats, axis=1)
    top = stats[np.arange(n), worst]
    return np.where(top > threshold, worst, -1), top, np.sum(e.reshape(n, 4, 2) ** 2, axis=2)


def ref_place(est: CornerPnP, fit, obs: dict, ids, heights):
    """Robot markers on their height planes from a fit, the former way: id -> (centre,
    rotation, sigma, dropped corner or -1)."""
    uv = np.concatenate([np.asarray(obs[i].corners, float).reshape(4, 2) for i in ids])
    xy = ref_undistort(uv, fit.K, fit.d)
    F = np.repeat(np.eye(3)[None], 4 * len(ids), axis=0)
    O = np.repeat(np.array([[0.0, 0.0, heights[i]] for i in ids]), 4, axis=0)
    P = ref_intersect(fit.R, fit.t, xy, F, O).reshape(-1, 4, 3)
    sig = ref_sigmas(fit, xy, F, O)
    lengths = np.array([obs[i].length for i in ids])
    centres, Rw = ref_square_pose(P, F[::4], lengths)
    drop, _, _ = ref_corner_outliers(fit.R, fit.t, fit.K, fit.d, uv.reshape(-1, 4, 2), centres,
                                     Rw, lengths, corner_sigma(fit), est._placing.corner_q)
    sel = np.flatnonzero(drop >= 0)
    if sel.size:
        keep = np.ones((sel.size, 4), bool)
        keep[np.arange(sel.size), drop[sel]] = False
        centres[sel], Rw[sel] = ref_square_pose(P[sel], F[::4][sel], lengths[sel], keep)
    return {i: (centres[k], Rw[k], float(sig[k]), int(drop[k])) for k, i in enumerate(ids)}


# ----------------------------------------------------------------- the scene
def _robots(k: int) -> dict:
    """The robot markers of frame k: driving and turning (a few cm and degrees a frame)."""
    return {i: robot_marker(i, -0.45 + 0.3 * j + 0.02 * k, -0.15 + 0.1 * j + 0.01 * k * (j - 1),
                            HEIGHT, 0.4 * j + 0.07 * k)
            for j, i in enumerate(ROBOTS)}


def _camera(sc) -> CameraIntrinsics:
    """A new intrinsics object with the same numbers every call, as a camera model gives."""
    return CameraIntrinsics(sc.camera.camera_matrix, sc.camera.dist_coeffs, sc.camera.width,
                            sc.camera.height)


def _frames(n: int = 8, refit_at: int = 4, seed: int = 3):
    """(scene, [observations per frame]): the floor's observation objects are the same
    frame after frame (a tracked fixed floor) except from ``refit_at`` on, where the floor
    is observed again with other noise (new corners: the camera is refitted)."""
    sc = scenario1(tilt_deg=10.0)
    floor_ids = [i for i in sc.map.markers if i not in ROBOTS]
    floor = observe(sc, noise_px=0.3, seed=seed, ids=floor_ids)
    frames = []
    for k in range(n):
        if k == refit_at:
            floor = observe(sc, noise_px=0.3, seed=seed + 100, ids=floor_ids)
        sck = scenario1(tilt_deg=10.0, extra=_robots(k))
        robots = observe(sck, noise_px=0.3, seed=seed + k, ids=list(ROBOTS))
        if k == 2:  # one robot corner pulled off its square: dropped
            o = robots[1]
            c = np.array(o.corners, float)
            c[2] += (4.0, -3.0)
            robots[1] = type(o)(o.id, o.marker2cam_R, o.marker2cam_t, corners=c, length=o.length)
        frames.append(floor + robots)
    return sc, frames


def _compare(got: dict, want: dict) -> list[str]:
    """The differences beyond 1e-9 (positions relative to their size, rotations absolute,
    sigmas relative), as lines; empty when equal."""
    bad = []
    for i, (c, Rw, s, drop) in want.items():
        g = got[i]
        if np.max(np.abs(g[0] - c)) > 1e-9 * max(np.linalg.norm(c), 1.0):
            bad.append(f"{i} position {g[0]} != {c}")
        if np.max(np.abs(g[1] - Rw)) > 1e-9:
            bad.append(f"{i} rotation")
        if not abs(g[2] - s) <= 1e-9 * s:
            bad.append(f"{i} sigma {g[2]!r} != {s!r} ({abs(g[2] / s - 1):.1e})")
        if g[3] != drop:
            bad.append(f"{i} dropped corner {g[3]} != {drop}")
    return bad


def _run(est: CornerPnP, sc, frames) -> tuple[list[list[str]], list, list]:
    """Per frame: the differences from ref_place, the fit used, the robots' placements."""
    heights = dict.fromkeys(ROBOTS, HEIGHT)
    mismatches, fits, placed = [], [], []
    for obs in frames:
        res = est.estimate_with_loo(obs, sc.map, camera=_camera(sc), plane_heights=heights)
        e = res.estimate
        assert e.ok, e.reason
        fit = est._warm.fit
        fits.append(fit)
        dropped = e.info["corners_dropped"]
        got = {i: (e.markers[i].position, e.markers[i].rotation, e.markers[i].sigma,
                   dropped.get(i, -1)) for i in ROBOTS}
        want = ref_place(est, fit, {o.id: o for o in obs}, ROBOTS, heights)
        mismatches.append(_compare(got, want))
        placed.append(got)
    return mismatches, fits, placed


def test_warm_robot_placements_equal_the_straightforward_computation():
    sc, frames = _frames()
    est = CornerPnP(warm_start=True)
    mismatches, fits, placed = _run(est, sc, frames)
    assert all(not m for m in mismatches), mismatches
    # The path under test ran: the same fit reused while the floor stayed, one refit.
    assert fits[1] is fits[0] and fits[3] is fits[0] and fits[5] is fits[4]
    assert fits[4] is not fits[3]
    assert not np.allclose(fits[4].t, fits[3].t, rtol=0, atol=1e-9)
    # Frame 2's pulled corner was dropped (the corner test ran on the robots), no other.
    assert [[p[i][3] for i in ROBOTS] for p in placed] == [
        [-1, 2, -1] if k == 2 else [-1, -1, -1] for k in range(len(frames))]
    # The robots moved: every frame placed them anew.
    assert all(not np.allclose(placed[k][40][0], placed[k + 1][40][0], atol=1e-3)
               for k in range(len(frames) - 1))


def test_a_cache_that_outlives_its_fit_is_caught(monkeypatch):
    """The comparison above fails when the per-fit constants are not renewed with the fit:
    the constants of the first fit reused for every later one."""
    stale: list = []
    real = uncertainty.fit_consts

    def never_renewed(fit):
        if not stale:
            stale.append(real(fit))
        return stale[0]

    monkeypatch.setattr(uncertainty, "fit_consts", never_renewed)
    sc, frames = _frames()
    mismatches, _, _ = _run(CornerPnP(warm_start=True), sc, frames)
    assert all(not m for m in mismatches[:4])  # the first fit: its own constants
    assert all(m for m in mismatches[4:]), mismatches  # after the refit: caught


def test_fit_constants_are_renewed_when_the_fit_changes():
    sc, frames = _frames(n=1)
    est = CornerPnP(warm_start=True)
    est.estimate(frames[0], sc.map, camera=_camera(sc),
                 plane_heights=dict.fromkeys(ROBOTS, HEIGHT))
    fit = est._warm.fit
    c = uncertainty.fit_consts(fit)
    assert uncertainty.fit_consts(fit) is c  # cached
    fit = replace(fit, R=rotvec_to_matrix(np.array([0.0, 0.0, 1e-3])) @ fit.R)  # a new fit
    c2 = uncertainty.fit_consts(fit)
    assert c2 is not c and c2.version == fit.version != c.version
    np.testing.assert_allclose(c2.C, -fit.R.T @ fit.t, rtol=0, atol=1e-15)
    obs = {o.id: o for o in frames[0]}
    uv = np.concatenate([np.asarray(obs[i].corners, float).reshape(4, 2) for i in ROBOTS])
    xy = undistort(uv, fit.K, fit.d)
    F = np.repeat(np.eye(3)[None], 12, axis=0)
    O = np.repeat(np.array([[0.0, 0.0, HEIGHT]]), 12, axis=0)
    sig, P = uncertainty.marker_sigmas(fit, xy, F, O)
    np.testing.assert_allclose(sig, ref_sigmas(fit, xy, F, O), rtol=1e-9, atol=0)
    np.testing.assert_allclose(P, ref_intersect(fit.R, fit.t, xy, F, O), rtol=0, atol=1e-12)


def test_refined_intrinsics_sigmas_equal_the_straightforward_computation():
    """A calibration 3 % off: the fit refines f and k1 (8 parameters), whose columns enter the
    sigmas too."""
    sc, frames = _frames(n=3, refit_at=99)
    est = CornerPnP(warm_start=True)
    K = sc.camera.camera_matrix.copy()
    K[0, 0] *= 1.03
    K[1, 1] *= 1.03
    cam = CameraIntrinsics(K, sc.camera.dist_coeffs, sc.camera.width, sc.camera.height)
    heights = dict.fromkeys(ROBOTS, HEIGHT)
    for obs in frames:
        e = est.estimate(obs, sc.map, camera=cam, plane_heights=heights)
        fit = est._warm.fit
        assert fit.refine and fit.H.shape == (8, 8)
        got = {i: (e.markers[i].position, e.markers[i].rotation, e.markers[i].sigma,
                   e.info["corners_dropped"].get(i, -1)) for i in ROBOTS}
        assert not _compare(got, ref_place(est, fit, {o.id: o for o in obs}, ROBOTS, heights))


def test_cold_floor_placements_and_sigmas_equal_the_straightforward_computation():
    """Every floor marker of a cold (non-warm) estimate: the same formulas on 30-odd markers
    at once, map planes instead of a height."""
    sc, frames = _frames(n=1)
    obs = {o.id: o for o in frames[0]}
    est = CornerPnP()
    e = est.estimate(frames[0], sc.map, camera=_camera(sc),
                     plane_heights=dict.fromkeys(ROBOTS, HEIGHT))
    fit, *_ = est._solve(frames[0], sc.map, (), _camera(sc))
    ids = [i for i in obs if i in sc.map.markers and i not in ROBOTS]
    uv = np.concatenate([np.asarray(obs[i].corners, float).reshape(4, 2) for i in ids])
    xy = ref_undistort(uv, fit.K, fit.d)
    F = np.repeat(np.array([sc.map[i].rotation for i in ids]), 4, axis=0)
    O = np.repeat(sc.map.positions(ids), 4, axis=0)
    sig = ref_sigmas(fit, xy, F, O)
    P = ref_intersect(fit.R, fit.t, xy, F, O).reshape(-1, 4, 3)
    centres, _ = ref_square_pose(P, F[::4], np.array([sc.map[i].length for i in ids]))
    for k, i in enumerate(ids):
        assert abs(e.markers[i].sigma / sig[k] - 1) <= 1e-9
        if i not in e.info["corners_dropped"]:
            np.testing.assert_allclose(e.markers[i].position, centres[k], rtol=0, atol=1e-9)


# ----------------------------------------------------------------- the pieces
@pytest.mark.parametrize("pattern", range(8))
def test_lean_camera_model_is_bit_identical(pattern):
    """undistort, distort_jacobian and project_jac_pc: the very bits of the formulation above
    and of distort/project (the numerical derivatives of the sigmas difference these)."""
    rng = np.random.default_rng(pattern)
    for _ in range(40):
        d = np.zeros(14)
        d[[0, 1, 4]] = rng.normal(0.0, [0.2, 0.2, 0.1])
        if pattern & 1:
            d[2:4] = rng.normal(0.0, 0.01, 2)
        if pattern & 2:
            d[5:8] = rng.normal(0.0, 0.05, 3)
        if pattern & 4:
            d[8:12] = rng.normal(0.0, 0.01, 4)
        K = np.array([[1357.0 * rng.uniform(0.8, 1.2), 0, 819.5], [0, 1357.0, 615.5], [0, 0, 1]])
        n = int(rng.integers(1, 40))
        uv = rng.uniform([0, 0], [1640, 1232], size=(n, 2))
        assert np.array_equal(undistort(uv, K, d), ref_undistort(uv, K, d))
        xy = rng.normal(0.0, 0.4, (n, 2))
        assert np.array_equal(distort_jacobian(xy, d), distort(xy, d, jac=True)[1])
        Pc = np.column_stack([xy, rng.uniform(0.5, 3.0, n)])
        uv0, J0, _, _ = project(Pc, K, d, jac=True)
        uv1, J1 = project_jac_pc(Pc, K, d)
        assert np.array_equal(uv0, uv1) and np.array_equal(J0, J1)


def test_square_pose_and_corner_outliers_match_the_straightforward_computation():
    rng = np.random.default_rng(7)
    sc = scenario1(tilt_deg=15.0)
    K, d = sc.camera.camera_matrix, sc.camera.dist_coeffs.reshape(-1)
    d14 = np.zeros(14)
    d14[: d.size] = d
    dropped = 0
    for trial in range(60):
        n = int(rng.integers(1, 6))
        frames = np.array([rotvec_to_matrix(rng.normal(0.0, 0.3, 3)) for _ in range(n)])
        lengths = rng.uniform(0.04, 0.1, n)
        centres = np.column_stack([rng.uniform(-0.6, 0.6, n), rng.uniform(-0.3, 0.3, n),
                                   rng.uniform(0.0, 0.3, n)])
        turn = np.array([rotvec_to_matrix(np.array([0.0, 0.0, a]))
                         for a in rng.uniform(-math.pi, math.pi, n)])
        Rw = frames @ turn
        X = centres[:, None] + np.einsum("nij,nkj->nki", Rw,
                                         marker_corners_local(1.0)[None] * lengths[:, None, None])
        P = X + rng.normal(0.0, 2e-4, X.shape)
        c0, R0 = ref_square_pose(P, frames, lengths)
        c1, R1 = square_pose(P, frames, lengths)
        np.testing.assert_allclose(c1, c0, rtol=0, atol=1e-12)
        np.testing.assert_allclose(R1, R0, rtol=0, atol=1e-12)
        uv = project(X.reshape(-1, 3) @ sc.R.T + sc.t, K, d14).reshape(n, 4, 2)
        uv = uv + rng.normal(0.0, 0.2, uv.shape)
        if trial % 2:
            uv[0, rng.integers(4)] += rng.normal(0.0, 3.0, 2)
        want = ref_corner_outliers(sc.R, sc.t, K, d14, uv, c0, R0, lengths, 0.2, 23.0)
        got = corner_outliers(sc.R, sc.t, K, d14, uv, c0, R0, lengths, 0.2, 23.0)
        assert np.array_equal(got[0], want[0])
        np.testing.assert_allclose(got[1], want[1], rtol=1e-9)
        np.testing.assert_allclose(got[2], want[2], rtol=1e-6, atol=1e-12)
        dropped += int(np.sum(want[0] >= 0))
    assert dropped >= 10  # the test saw corners dropped, not only clean squares


# ----------------------------------------------------------------- the warm path's checks
def test_warm_path_reuses_the_fit_for_equal_camera_numbers_and_refits_for_others():
    sc, frames = _frames(n=2, refit_at=99)
    est = CornerPnP(warm_start=True)
    heights = dict.fromkeys(ROBOTS, HEIGHT)
    est.estimate(frames[0], sc.map, camera=_camera(sc), plane_heights=heights)
    fit = est._warm.fit
    est.estimate(frames[1], sc.map, camera=_camera(sc), plane_heights=heights)
    assert est._warm.fit is fit  # a new intrinsics object, the same numbers
    K = sc.camera.camera_matrix.copy()
    K[0, 2] += 2.0
    cam = CameraIntrinsics(K, sc.camera.dist_coeffs, sc.camera.width, sc.camera.height)
    e = est.estimate(frames[1], sc.map, camera=cam, plane_heights=heights)
    assert e.ok and est._warm.fit is not fit and est._warm.camera[0] == K.tobytes()


def test_warm_path_still_refuses_bad_observations_with_the_same_error():
    sc, frames = _frames(n=2, refit_at=99)
    est = CornerPnP(warm_start=True)
    cam = _camera(sc)
    est.estimate(frames[0], sc.map, camera=cam)
    o = frames[1][-1]
    bad = type(o)(o.id, o.marker2cam_R, np.array([0.0, np.nan, 1.0]), corners=o.corners,
                  length=o.length)
    for obs in ([*frames[1][:-1], bad], [*frames[1], frames[1][0]]):
        with pytest.raises(ValueError) as full:
            check_observations(obs)
        with pytest.raises(ValueError) as warm:
            est.estimate(obs, sc.map, camera=cam)
        assert str(warm.value) == str(full.value)
