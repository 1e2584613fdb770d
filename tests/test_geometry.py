"""The geometry kernel: known transforms recovered (seeded), OpenCV agreement, validators."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from kmea.geometry import (
    check_camera_matrix,
    check_distortion,
    check_rotation,
    check_rotvecs,
    check_transform,
    distort,
    intersect_ray_height,
    intersect_rays_planes,
    invert_transform,
    kabsch,
    make_transform,
    matrices_to_rotvecs,
    project,
    project_to_so3,
    project_world,
    ray_plane_parameter,
    rotvec_to_matrix,
    rotvecs_to_matrices,
    skew,
    undistort,
    unit_rays_plane_depth,
    wrap_angle,
    yaw_of,
)
from kmea.vision.cvcompat import undistort_points

K = np.array([[1357.0, 0.0, 819.5], [0.0, 1351.0, 615.5], [0.0, 0.0, 1.0]])
DISTORTIONS = {
    "none": np.zeros(5),
    "pi-v2": np.array([0.12, -0.25, 0.0, 0.0, 0.10]),
    "tangential": np.array([0.05, -0.1, 0.001, -0.002, 0.02]),
    "rational": np.array([0.1, -0.2, 0.0005, 0.001, 0.05, 0.01, -0.02, 0.005]),
    "thin-prism": np.array([0.12, -0.25, 0.001, -0.002, 0.10, 0.01, 0.0, 0.0,
                            0.001, 0.0, -0.001, 0.0]),
}


def _random_rotvecs(rng: np.random.Generator, n: int, max_angle: float = 3.0) -> np.ndarray:
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    return axis * rng.uniform(0.0, max_angle, size=(n, 1))


# ----------------------------------------------------------------- rotations

@pytest.mark.parametrize("seed", [0, 1])
def test_rodrigues_matches_opencv_both_ways(seed: int) -> None:
    rv = _random_rotvecs(np.random.default_rng(seed), 50)
    R = rotvecs_to_matrices(rv)
    for r, M in zip(rv, R, strict=True):
        assert np.array_equal(M, cv2.Rodrigues(r)[0])  # the same formula, bit for bit
        check_rotation(M, tol=1e-12)
    back = matrices_to_rotvecs(R)
    assert np.allclose(back, rv, atol=1e-9)
    assert np.allclose(rotvec_to_matrix(rv[0]), R[0], atol=0)


def test_rodrigues_small_angles_and_identity() -> None:
    assert np.array_equal(rotvec_to_matrix(np.zeros(3)), np.eye(3))
    assert np.array_equal(matrices_to_rotvecs(np.eye(3)[None]), np.zeros((1, 3)))
    w = np.array([1e-9, -2e-9, 3e-9])
    assert np.allclose(rotvec_to_matrix(w), np.eye(3) + skew(w), atol=1e-17)


def test_skew_is_the_cross_product() -> None:
    rng = np.random.default_rng(2)
    v, w = rng.normal(size=(2, 7, 3))
    assert np.allclose(np.einsum("nij,nj->ni", skew(v), w), np.cross(v, w))


@pytest.mark.parametrize("seed", [3, 4])
def test_project_to_so3_recovers_a_perturbed_rotation_and_never_reflects(seed: int) -> None:
    rng = np.random.default_rng(seed)
    R = rotvecs_to_matrices(_random_rotvecs(rng, 20))
    noisy = R + rng.normal(scale=1e-4, size=R.shape)
    P = project_to_so3(noisy)
    assert np.allclose(P, R, atol=1e-3)
    assert np.allclose(np.linalg.det(P), 1.0)
    # The chordal mean of rotations near R is near R; a reflection projects to a rotation.
    assert np.allclose(project_to_so3(noisy.sum(axis=0) * 0 + noisy[:5].sum(axis=0)),
                       project_to_so3(R[:5].sum(axis=0)), atol=1e-3)
    mirror = np.diag([1.0, 1.0, -1.0])
    assert np.linalg.det(project_to_so3(mirror)) == pytest.approx(1.0)


@pytest.mark.parametrize("seed", [5, 6, 7])
def test_kabsch_recovers_a_known_rotation(seed: int) -> None:
    rng = np.random.default_rng(seed)
    R = rotvec_to_matrix(_random_rotvecs(rng, 1)[0])
    src = rng.normal(size=(12, 3))
    src -= src.mean(axis=0)
    dst = src @ R.T
    assert np.allclose(kabsch(src.T @ dst), R, atol=1e-12)
    # Batched: a stack of problems at once; a planar set still gives a proper rotation.
    planar = src.copy()
    planar[:, 2] = 0.0
    H = np.stack([src.T @ dst, planar.T @ (planar @ R.T)])
    Rb = kabsch(H)
    assert np.allclose(Rb, R[None], atol=1e-10)
    assert np.allclose(kabsch(src.T @ dst), project_to_so3((src.T @ dst).T), atol=1e-12)


def test_yaw_and_wrap() -> None:
    rng = np.random.default_rng(8)
    a = rng.uniform(-math.pi, math.pi, 10)
    Rs = np.array([rotvec_to_matrix([0.0, 0.0, x]) for x in a])
    assert np.allclose(yaw_of(Rs), a)
    assert yaw_of(Rs[0]) == pytest.approx(a[0])
    assert isinstance(wrap_angle(3 * math.pi), float)
    assert wrap_angle(3 * math.pi) == pytest.approx(-math.pi)
    assert np.allclose(wrap_angle(a + 4 * math.pi), a)


def test_transforms_compose_and_invert() -> None:
    rng = np.random.default_rng(9)
    R = rotvec_to_matrix(_random_rotvecs(rng, 1)[0])
    t = rng.normal(size=3)
    T = check_transform(make_transform(R, t))
    assert np.allclose(invert_transform(T) @ T, np.eye(4), atol=1e-12)
    assert np.allclose(make_transform(R, t, 2.0)[:3, :3], 2.0 * R)


def test_validators_name_the_problem() -> None:
    with pytest.raises(ValueError, match="R: expected shape"):
        check_rotation(np.eye(2))
    with pytest.raises(ValueError, match="not a proper rotation"):
        check_rotation(np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(ValueError, match="non-finite"):
        check_rotvecs([0.0, np.nan, 0.0])
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        check_rotvecs(np.zeros((2, 2)))
    assert check_rotvecs([0.1, 0.2, 0.3]).shape == (1, 3)
    with pytest.raises(ValueError, match="tilted"):
        check_distortion(np.r_[np.zeros(12), 0.01, 0.0])
    with pytest.raises(ValueError, match="at most 14"):
        check_distortion(np.zeros(15))
    with pytest.raises(ValueError, match="non-finite"):
        check_distortion([0.1, np.inf, 0, 0])
    with pytest.raises(ValueError, match="fx, fy must be > 0"):
        check_camera_matrix(np.diag([0.0, 1.0, 1.0]))
    with pytest.raises(ValueError, match="not a camera matrix"):
        check_camera_matrix([[1000.0, 0, 320], [5.0, 1000, 240], [0, 0, 1]])
    with pytest.raises(ValueError, match="non-finite"):
        check_camera_matrix([[np.nan, 0, 320], [0, 1000, 240], [0, 0, 1]])
    K = check_camera_matrix([1000.0, 0, 320, 0, 1000, 240, 0, 0, 1])  # row by row
    assert K.shape == (3, 3) and K[1, 2] == 240
    with pytest.raises(ValueError, match="rigid"):
        check_transform(np.diag([2.0, 1.0, 1.0, 1.0]))


# ----------------------------------------------------------------- camera model

@pytest.mark.parametrize("name", list(DISTORTIONS))
def test_projection_equals_cv2_project_points(name: str) -> None:
    rng = np.random.default_rng(10)
    D = DISTORTIONS[name]
    X = np.column_stack([rng.uniform(-0.8, 0.8, 200), rng.uniform(-0.6, 0.6, 200),
                         rng.uniform(1.0, 2.5, 200)])
    rv = np.array([0.05, -0.1, 0.02])
    tv = np.array([0.01, -0.02, 0.05])
    want = cv2.projectPoints(X, rv, tv, K, D)[0].reshape(-1, 2)
    R = rotvec_to_matrix(rv)
    got = project(X @ R.T + tv, K, check_distortion(D))
    assert np.abs(got - want).max() < 1e-9
    uv, z = project_world(X, make_transform(R, tv), K, check_distortion(D))
    assert np.abs(uv - want).max() < 1e-9
    assert np.allclose(z, (X @ R.T + tv)[:, 2])


@pytest.mark.parametrize("name", list(DISTORTIONS))
def test_undistort_inverts_distort_and_agrees_with_opencv(name: str) -> None:
    rng = np.random.default_rng(11)
    d = check_distortion(DISTORTIONS[name])
    uv = np.column_stack([rng.uniform(50, 1590, 100), rng.uniform(50, 1180, 100)])
    xy = undistort(uv, K, d)
    back = distort(xy, d) * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
    assert np.abs(back - uv).max() < 1e-9
    ref = undistort_points(uv.reshape(-1, 1, 2), K, DISTORTIONS[name],
                           criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100,
                                     1e-15)).reshape(-1, 2)
    assert np.abs(xy - ref).max() < 1e-6


def test_distortion_jacobian_matches_finite_differences() -> None:
    rng = np.random.default_rng(12)
    d = check_distortion(DISTORTIONS["thin-prism"])
    xy = rng.uniform(-0.5, 0.5, size=(30, 2))
    _, J, dk1 = distort(xy, d, jac=True)
    h = 1e-7
    for a in range(2):
        xy2 = xy.copy()
        xy2[:, a] += h
        assert np.allclose((distort(xy2, d) - distort(xy, d)) / h, J[:, :, a], atol=1e-5)
    d2 = d.copy()
    d2[0] += h
    assert np.allclose((distort(xy, d2) - distort(xy, d)) / h, dk1, atol=1e-5)


# ----------------------------------------------------------------- ray-plane

@pytest.mark.parametrize("seed", [13, 14])
def test_ray_plane_intersection_recovers_known_points(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = rng.normal(size=(40, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    q = rng.normal(size=(40, 3))
    # Known points on the planes: q plus an in-plane offset.
    off = rng.normal(size=(40, 3))
    target = q + off - np.sum(off * n, axis=1, keepdims=True) * n
    origin = rng.normal(size=(40, 3)) * 3.0
    direction = (target - origin) * rng.uniform(0.2, 5.0, size=(40, 1))
    P = intersect_rays_planes(origin, direction, q, n)
    assert np.allclose(P, target, atol=1e-9)
    # Behind the origin (reversed ray) or parallel to the plane: NaN, no warning.
    assert np.isnan(intersect_rays_planes(origin, -direction, q, n)).all()
    flat = np.array([0.0, 0.0, 1.0])  # exactly parallel: a horizontal ray, a floor plane
    par = np.column_stack([rng.normal(size=(40, 2)), np.zeros(40)])
    assert np.isnan(intersect_rays_planes(origin, par, q, flat)).all()
    lam = ray_plane_parameter(origin, direction, q, n)
    assert np.allclose(origin + lam[:, None] * direction, target, atol=1e-9)


def test_one_ray_at_a_height_is_the_batched_intersection_to_the_bit() -> None:
    rng = np.random.default_rng(16)
    origin = rng.normal(size=(200, 3)) + np.array([0.0, 0.0, 2.0])
    direction = rng.normal(size=(200, 3))
    height = rng.uniform(-0.2, 0.5, 200)
    direction[:5, 2] = 0.0  # parallel to the plane
    P = intersect_rays_planes(origin, direction, np.column_stack(
        [np.zeros((200, 2)), height]), np.array([0.0, 0.0, 1.0]))
    assert np.isnan(P).any(axis=1).sum() > 50  # planes behind some origins
    for o, d, h, p in zip(origin.tolist(), direction.tolist(), height.tolist(), P,
                          strict=True):
        got = intersect_ray_height(o, d, h)
        if np.isnan(p).any():
            assert got is None
        else:
            assert got is not None and np.array_equal(np.array(got), p)


def test_unit_rays_depth_is_the_ray_plane_intersection_from_the_camera() -> None:
    rng = np.random.default_rng(15)
    x, y = rng.uniform(-0.6, 0.6, size=(2, 8, 9))
    normal = np.array([0.1, -0.2, -1.0])
    normal /= np.linalg.norm(normal)
    point = np.array([0.0, 0.0, 1.4])
    t, ok = unit_rays_plane_depth(x, y, normal, float(normal @ point))
    rays = np.stack([x, y, np.ones_like(x)], axis=-1)
    P = intersect_rays_planes(np.zeros(3), rays, point, normal)
    assert ok.all()
    assert np.allclose(t[..., None] * rays, P, atol=1e-12)
    # Seen from the other side of the plane: masked, depth inf.
    t2, ok2 = unit_rays_plane_depth(x, y, -normal, float(-normal @ point))
    assert not ok2.any() and np.isinf(t2).all()
