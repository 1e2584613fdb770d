"""KMEA, LMEA and Umeyama: exact recovery, hand-worked examples, leave-one-out, bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest

from kmea.estimators import Estimator, MarkerObservation, available, get
from kmea.estimators.base import loo_by_exclusion
from kmea.estimators.common import reference_problem
from kmea.estimators.kmea import KMEA
from kmea.estimators.lmea import LMEA
from kmea.estimators.loo import loo_errors, loo_positions
from kmea.estimators.umeyama import Umeyama
from kmea.geometry import kabsch, rot_x, rot_z, rotvec_to_matrix
from kmea.maps.files import Marker, MarkerMap, default_map

# ----------------------------------------------------------------------------- helpers


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """Uniform random rotation (QR of a Gaussian matrix, sign-fixed to det +1)."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1
    return q


def observe(world_map: MarkerMap, ids, s: float, R: np.ndarray, t: np.ndarray,
            extra: dict | None = None) -> list[MarkerObservation]:
    """Exact observations for the similarity cam2world: world = s R cam + t.

    extra: id -> (world position (3,), marker2world rotation) of markers not in the map.
    """
    obs = []
    for mid in ids:
        mk = world_map[mid]
        obs.append(MarkerObservation(mid, R.T @ mk.rotation, R.T @ (mk.position - t) / s))
    for mid, (p, Rw) in (extra or {}).items():
        obs.append(MarkerObservation(mid, R.T @ Rw, R.T @ (np.asarray(p) - t) / s))
    return obs


def random_map(rng: np.random.Generator, n: int, coplanar: bool) -> MarkerMap:
    """n markers with well-spread random positions; anchors are ids 0, 1, 2."""
    while True:
        P = rng.uniform(-1.5, 1.5, size=(n, 3))
        if coplanar:
            P[:, 2] = 0.0
        sv = np.linalg.svd(P - P.mean(0), compute_uv=False)
        if sv[1] > 0.1 * sv[0]:
            break
    markers = {i: Marker(i, P[i], random_rotation(rng) if not coplanar else rot_z(
        rng.uniform(-np.pi, np.pi)), 0.06) for i in range(n)}
    return MarkerMap(markers, origin_id=0, x_id=1, y_id=2)


def pos_err(est, world_map: MarkerMap) -> float:
    return max(float(np.abs(est.markers[i].position - world_map[i].position).max())
               for i in est.markers if i in world_map)


# ------------------------------------------------------------------ exact recovery


@pytest.mark.parametrize("name", ["kmea", "umeyama"])
@pytest.mark.parametrize("coplanar", [False, True])
def test_random_similarities_are_recovered_exactly(name: str, coplanar: bool) -> None:
    rng = np.random.default_rng(1234 + coplanar)
    est = get(name)
    for case in range(150):
        n = int(rng.integers(3, 40))
        m = random_map(rng, n, coplanar)
        s = rng.uniform(0.5, 2.0)
        R = random_rotation(rng)
        t = rng.uniform(-20.0, 20.0, size=3)
        ids = list(rng.permutation(m.ids))  # detection order must not matter
        if case % 3 == 0 and n > 3:  # origin not visible: KMEA's centroid scale step
            ids.remove(0)
        # Robot markers off the reference plane: a reflection would put them on the
        # wrong side, which coplanar references alone cannot reveal.
        extra = {40 + j: (rng.uniform(-1, 1, 3) + np.array([0, 0, 0.3]), random_rotation(rng))
                 for j in range(2)}
        obs = observe(m, ids, s, R, t, extra)
        e = est.estimate(obs, m)
        assert e.ok, e.reason
        assert set(e.markers) == set(ids) | set(extra)
        assert e.references == tuple(sorted(ids))
        assert e.scale == pytest.approx(s, rel=1e-9)
        for mid in ids:
            assert np.allclose(e.markers[mid].position, m[mid].position, rtol=0, atol=1e-9)
            assert np.allclose(e.markers[mid].rotation, m[mid].rotation, rtol=0, atol=1e-9)
        for mid, (p, Rw) in extra.items():
            assert np.allclose(e.markers[mid].position, p, rtol=0, atol=1e-9)
            assert np.allclose(e.markers[mid].rotation, Rw, rtol=0, atol=1e-9)
            assert e.markers[mid].yaw == pytest.approx(math.atan2(Rw[1, 0], Rw[0, 0]),
                                                       abs=1e-9)
        assert max(e.residuals.values()) < 1e-9
        # cam2world is the inverse of the similarity the observations were made with.
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R.T / s, -R.T @ t / s  # world2cam
        assert np.allclose(e.cam2world @ T, np.eye(4), atol=1e-9)


@pytest.mark.parametrize("name", ["kmea", "lmea", "umeyama"])
@pytest.mark.parametrize("R", [np.eye(3), rot_x(np.pi), rot_z(np.pi), rot_x(np.pi) @ rot_z(np.pi),
                               rotvec_to_matrix([0.0, np.pi / 2, 0.0])])
def test_special_rotations_on_the_real_floor(name: str, R: np.ndarray) -> None:
    # Half turns (a camera looking straight down is Rx(180 deg)) make H's singular vectors
    # sign-ambiguous; the coplanar floor leaves one singular value at zero.
    m = default_map()
    floor = [i for i in m.ids if m[i].on_floor]
    extra = {40: (np.array([0.3, 0.2, 0.2]), rot_z(0.5))}
    e = get(name).estimate(observe(m, floor, 1.3, R, np.array([0.1, 0.0, 2.0]), extra), m)
    assert e.ok
    assert pos_err(e, m) < 1e-9
    assert np.allclose(e.markers[40].position, [0.3, 0.2, 0.2], atol=1e-9)
    assert np.allclose(e.markers[40].rotation, rot_z(0.5), atol=1e-9)


def test_lmea_recovers_random_similarities_exactly() -> None:
    rng = np.random.default_rng(77)
    for _ in range(100):
        m = random_map(rng, int(rng.integers(3, 20)), coplanar=bool(rng.integers(2)))
        s, R, t = rng.uniform(0.5, 2.0), random_rotation(rng), rng.uniform(-5, 5, 3)
        e = LMEA().estimate(observe(m, m.ids, s, R, t), m)
        assert e.ok, e.reason
        assert e.references == (0, 1, 2)
        assert pos_err(e, m) < 1e-9


def test_kabsch_returns_a_proper_rotation_for_mirrored_points() -> None:
    # The best orthogonal map from src to its mirror image is the mirror (det -1); Kabsch
    # must flip the last axis and return a rotation instead.
    rng = np.random.default_rng(5)
    src = rng.normal(size=(10, 3))
    src -= src.mean(0)
    dst = src * [1, 1, -1]
    R = kabsch(src.T @ dst)
    assert np.linalg.det(R) == pytest.approx(1.0)
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-12)


# ------------------------------------------------------------- worked by hand

def hand_map() -> MarkerMap:
    # Origin 13 at (0,0,0), +X anchor 16 at (1,0,0), +Y anchor 4 at (0,1,0), marker 7 at (1,1,0).
    P = {13: (0, 0, 0), 16: (1, 0, 0), 4: (0, 1, 0), 7: (1, 1, 0)}
    return MarkerMap({i: Marker(i, np.array(p, float), np.eye(3), 0.06) for i, p in P.items()},
                     origin_id=13, x_id=16, y_id=4)


# The camera frame of the hand examples: world = 2 * Rz(90 deg) @ cam + (1, 2, 0), so
# cam = Rz(-90 deg) @ (world - (1, 2, 0)) / 2, and Rz(-90 deg) maps (x, y) to (y, -x):
#   13: (0,0,0) - t = (-1,-2,0) -> (-2, 1,0) / 2 = (-1.0, 0.5, 0)
#   16: (1,0,0) - t = ( 0,-2,0) -> (-2, 0,0) / 2 = (-1.0, 0.0, 0)
#    4: (0,1,0) - t = (-1,-1,0) -> (-1, 1,0) / 2 = (-0.5, 0.5, 0)
#    7: (1,1,0) - t = ( 0,-1,0) -> (-1, 0,0) / 2 = (-0.5, 0.0, 0)
HAND_CAM = {13: (-1.0, 0.5, 0.0), 16: (-1.0, 0.0, 0.0), 4: (-0.5, 0.5, 0.0), 7: (-0.5, 0.0, 0.0)}


def hand_obs(cam: dict) -> list[MarkerObservation]:
    # Every map marker lies flat with yaw 0, so its camera rotation is Rz(-90 deg).
    return [MarkerObservation(i, rot_z(-np.pi / 2), np.array(p, float)) for i, p in cam.items()]


def test_kmea_hand_worked_example() -> None:
    m = hand_map()
    # A robot marker 40 seen at cam (0.25, 0.25, 0.1), yawed -90 deg in the camera frame:
    # world = 2 * Rz90 (0.25, 0.25, 0.1) + (1, 2, 0) = 2 * (-0.25, 0.25, 0.1) + (1, 2, 0)
    #       = (0.5, 2.5, 0.2); world rotation Rz(90) Rz(-90) = I, so yaw 0.
    obs = [*hand_obs(HAND_CAM), MarkerObservation(40, rot_z(-np.pi / 2),
                                                  np.array([0.25, 0.25, 0.1]))]
    e = KMEA().estimate(obs, m)
    assert e.ok
    # Step 1, scale. Map distances to the origin 13: 0, 1, 1, sqrt2 -> mean (2 + sqrt2)/4.
    # Camera distances to 13: 0, 0.5, 0.5, sqrt(0.5) -> mean (2 + sqrt2)/8. Scale = 2.
    assert e.scale == pytest.approx(2.0, abs=1e-12)
    assert e.info["scale_from"] == "origin"
    # Step 2: scaled camera positions 13 (-2,1), 16 (-2,0), 4 (-1,1), 7 (-1,0), centroid
    # (-1.5, 0.5); map centroid (0.5, 0.5). Step 3, about the centroids:
    #   camera 13 (-.5,.5) 16 (-.5,-.5) 4 (.5,.5) 7 (.5,-.5)
    #   map    13 (-.5,-.5) 16 (.5,-.5) 4 (-.5,.5) 7 (.5,.5)
    # H = sum cam map^T = [[0, 1, 0], [-1, 0, 0], [0, 0, 0]] -> R = Rz(90 deg).
    R = e.cam2world[:3, :3] / e.scale
    assert np.allclose(R, [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    # Step 4: t = (0.5, 0.5, 0) - Rz90 (-1.5, 0.5, 0) = (0.5, 0.5) - (-0.5, -1.5) = (1, 2, 0).
    assert np.allclose(e.cam2world[:3, 3], [1, 2, 0], atol=1e-12)
    assert np.allclose(e.markers[40].position, [0.5, 2.5, 0.2], atol=1e-12)
    assert e.markers[40].yaw == pytest.approx(0.0, abs=1e-12)
    for i in (13, 16, 4, 7):
        assert np.allclose(e.markers[i].position, m[i].position, atol=1e-12)


def test_kmea_scale_without_origin_uses_the_reference_centroid() -> None:
    m = hand_map()
    cam = {k: v for k, v in HAND_CAM.items() if k != 13}
    e = KMEA().estimate(hand_obs(cam), m)
    # Map centroid of 16, 4, 7 = (2/3, 2/3); distances sqrt(1/9 + 4/9) = sqrt5/3 (16 and 4)
    # and sqrt2/3 (7). The camera distances are those halved, so the scale is still 2.
    assert e.info["scale_from"] == "centroid"
    assert e.scale == pytest.approx(2.0, abs=1e-12)
    assert pos_err(e, m) < 1e-12
    # Excluding the origin has the same effect as not seeing it.
    e2 = KMEA().estimate(hand_obs(HAND_CAM), m, exclude={13})
    assert e2.info["scale_from"] == "centroid" and 13 not in e2.references
    assert np.allclose(e2.markers[13].position, [0, 0, 0], atol=1e-12)


def test_lmea_hand_worked_example() -> None:
    m = hand_map()
    # Marker 7 observed 5 cm off: (-0.5, 0.05, 0) instead of (-0.5, 0, 0).
    cam = dict(HAND_CAM)
    cam[7] = (-0.5, 0.05, 0.0)
    e = LMEA().estimate(hand_obs(cam), m)
    assert e.ok and e.references == (13, 16, 4)
    # Scale: |m16 - m13| / |c16 - c13| = 1 / 0.5 = 2.
    assert e.scale == pytest.approx(2.0, abs=1e-12)
    # Basis from the camera anchors: e_x = (c16 - c13)/|.| = (0, -1, 0);
    # e_z = e_x x (c4 - c13) = (0,-1,0) x (0.5,0,0) = (0, 0, 0.5) -> (0, 0, 1);
    # e_y = e_z x e_x = (1, 0, 0). The map basis is I, so R = B_cam^T = Rz(90 deg).
    R = e.cam2world[:3, :3] / e.scale
    assert np.allclose(R, [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    # Marker 7: m13 + 2 Rz90 (c7 - c13) = 2 Rz90 (0.5, -0.45, 0) = 2 (0.45, 0.5, 0) = (0.9, 1, 0).
    assert np.allclose(e.markers[7].position, [0.9, 1.0, 0.0], atol=1e-12)
    # LMEA uses the anchors only, so marker 7's error did not move them.
    for i in (13, 16, 4):
        assert np.allclose(e.markers[i].position, m[i].position, atol=1e-12)


# ---------------------------------------------------------------- leave-one-out

def noisy_frame(seed: int = 3, noise: float = 0.003):
    m = default_map()
    rng = np.random.default_rng(seed)
    floor = [i for i in m.ids if m[i].on_floor]
    R = rot_z(0.4) @ rot_x(np.pi + 0.1)
    t = np.array([0.1, -0.05, 2.2])
    obs = observe(m, floor, 1.0, R, t, {40: ((0.3, 0.2, 0.2), rot_z(0.5))})
    return m, [MarkerObservation(o.id, o.marker2cam_R,
                                 o.marker2cam_t + rng.normal(0, noise, 3)) for o in obs]


@pytest.mark.parametrize("name", ["kmea", "lmea", "umeyama"])
def test_corrupting_the_left_out_marker_changes_nothing_else(name: str) -> None:
    m, obs = noisy_frame()
    est = get(name)
    for k in (0, 20, 35):  # a corner, an inner and the last floor marker (none is an anchor)
        base = est.estimate(obs, m, exclude={k})
        bad = [MarkerObservation(o.id, rotvec_to_matrix([0.3, -1.0, 2.0]),
                                 o.marker2cam_t + np.array([0.4, -0.3, 0.7]))
               if o.id == k else o
               for o in obs]
        other = est.estimate(bad, m, exclude={k})
        assert base.ok and other.ok
        assert k not in base.references
        assert np.array_equal(base.cam2world, other.cam2world)
        for i in base.markers:
            if i != k:
                assert np.array_equal(base.markers[i].position, other.markers[i].position)
                assert np.array_equal(base.markers[i].rotation, other.markers[i].rotation)
        # The corruption did reach marker k itself.
        assert np.linalg.norm(base.markers[k].position - other.markers[k].position) > 0.1


@pytest.mark.parametrize("seed", [3, 4])
def test_kmea_batched_leave_one_out_equals_the_loop(seed: int) -> None:
    m, obs = noisy_frame(seed)
    k = KMEA()
    fast = k.estimate_with_loo(obs, m).loo_positions
    assert set(fast) == {o.id for o in obs if o.id in m}  # origin 13 included
    slow, failed = loo_by_exclusion(k, obs, m, list(fast))
    assert not failed
    for mid, p in fast.items():
        assert np.allclose(p, slow[mid], rtol=0, atol=1e-12)
    errs = loo_errors(k, obs, m)
    for mid, e in errs.items():
        assert e == pytest.approx(float(np.hypot(*(fast[mid][:2] - m[mid].position[:2]))))
    # 3 mm of camera noise on a 2.2 m high view gives mm-level errors, not garbage.
    assert 0 < max(errs.values()) < 0.02


def test_kmea_batched_leave_one_out_on_a_small_and_a_collinear_set() -> None:
    m = hand_map()
    obs = hand_obs(HAND_CAM)
    fast = KMEA().estimate_with_loo(obs, m).loo_positions
    assert set(fast) == {13, 16, 4, 7}
    assert all(np.allclose(fast[i], m[i].position, atol=1e-12) for i in fast)
    # Three visible markers: leaving one out leaves two, never an estimate.
    res = KMEA().estimate_with_loo(hand_obs({i: HAND_CAM[i] for i in (13, 16, 4)}), m)
    assert res.estimate.ok and res.loo_positions == {}
    assert set(res.loo_failures) == {13, 16, 4}
    assert all("2 reference" in r for r in res.loo_failures.values())
    # Four markers, three of them collinear (13, 16 and a new 9 on the x axis) plus 4:
    # leaving out 4 leaves a collinear set, the others can still be estimated.
    m2 = hand_map()
    m2.markers[9] = Marker(9, np.array([2.0, 0, 0]), np.eye(3), 0.06)
    cam = {13: HAND_CAM[13], 16: HAND_CAM[16], 4: HAND_CAM[4], 9: (-1.0, -0.5, 0.0)}
    res = KMEA().estimate_with_loo(hand_obs(cam), m2)
    fast = res.loo_positions
    assert set(fast) == {13, 16, 9}
    assert "collinear" in res.loo_failures[4]
    assert all(np.allclose(fast[i], m2[i].position, atol=1e-12) for i in fast)


def test_lmea_leave_one_out_omits_its_anchors() -> None:
    m, obs = noisy_frame()
    errs = loo_errors(LMEA(), obs, m)
    assert set(errs) == {o.id for o in obs if o.id in m} - {13, 16, 4}
    pos = loo_positions(Umeyama(), obs, m)
    assert 40 not in pos and len(pos) == 33


# ------------------------------------------------------- degenerate and bad input

@pytest.mark.parametrize("name", ["kmea", "umeyama"])
def test_fewer_than_three_references_are_not_estimated(name: str) -> None:
    m = hand_map()
    for ids in ((), (13,), (13, 16)):
        robot = MarkerObservation(40, np.eye(3), np.array([0.0, 0.0, 1.0]))
        obs = [*hand_obs({i: HAND_CAM[i] for i in ids}), robot]
        e = get(name).estimate(obs, m)
        assert not e.ok and e.markers == {} and e.cam2world is None
        assert f"{len(ids)} reference marker(s) visible, need at least 3" in e.reason
    # Excluding enough references has the same effect.
    e = get(name).estimate(hand_obs(HAND_CAM), m, exclude={13, 16})
    assert not e.ok and "2 reference" in e.reason


@pytest.mark.parametrize("name", ["kmea", "umeyama"])
def test_collinear_references_are_not_estimated(name: str) -> None:
    m = default_map()
    R, t = rot_x(np.pi), np.array([0.0, 0.0, 2.0])
    row = [0, 1, 2, 3, 4, 30, 31, 5]  # the top row of the floor, y = 0.355
    e = get(name).estimate(observe(m, row, 1.0, R, t), m)
    assert not e.ok and "collinear (map positions)" in e.reason
    # Coincident camera positions for three non-collinear map markers.
    obs = [MarkerObservation(i, np.eye(3), np.array([0.1, 0.2, 2.0])) for i in (13, 16, 4)]
    e = get(name).estimate(obs, m)
    assert not e.ok and "coincide (camera positions)" in e.reason
    # Camera positions collinear (a broken frame) though the map markers are not.
    obs = [MarkerObservation(i, np.eye(3), np.array([0.1 * j, 0.0, 2.0]))
           for j, i in enumerate((13, 16, 4))]
    e = get(name).estimate(obs, m)
    assert not e.ok and "collinear (camera positions)" in e.reason


def test_nearly_collinear_references_are_refused_by_the_tolerance() -> None:
    P = np.array([[0, 0, 0], [1, 0, 0], [2, 1e-5, 0]], float)
    assert "collinear" in reference_problem(P, P)
    P[2, 1] = 0.05
    assert reference_problem(P, P) is None


@pytest.mark.parametrize("name", ["kmea", "lmea", "umeyama"])
def test_malformed_observations_raise_value_error(name: str) -> None:
    m = hand_map()
    obs = hand_obs(HAND_CAM)
    nan = [*obs[:-1], MarkerObservation(7, np.eye(3), np.array([np.nan, 0, 1]))]
    with pytest.raises(ValueError, match="observation id 7: non-finite pose"):
        get(name).estimate(nan, m)
    inf_R = [*obs[:-1], MarkerObservation(7, np.full((3, 3), np.inf), np.zeros(3))]
    with pytest.raises(ValueError, match="observation id 7: non-finite pose"):
        get(name).estimate(inf_R, m)
    with pytest.raises(ValueError, match="observation id 13: duplicate id"):
        get(name).estimate([*obs, obs[0]], m)
    with pytest.raises(ValueError, match=r"observation id 7: marker2cam_R must be \(3, 3\)"):
        get(name).estimate([*obs[:-1], MarkerObservation(7, np.eye(3), np.zeros(2))], m)


def test_lmea_without_its_anchors_is_not_estimated() -> None:
    m = hand_map()
    for missing, label in ((13, "origin"), (16, "x-axis"), (4, "y-axis")):
        cam = {i: p for i, p in HAND_CAM.items() if i != missing}
        e = LMEA().estimate(hand_obs(cam), m)
        assert not e.ok and e.markers == {}
        assert e.reason == f"{label} anchor {missing} not visible"
        e = LMEA().estimate(hand_obs(HAND_CAM), m, exclude={missing})
        assert not e.ok and e.reason == f"{label} anchor {missing} is excluded"
    # Anchors on one line.
    m.markers[4] = Marker(4, np.array([2.0, 0.0, 0.0]), np.eye(3), 0.06)
    e = LMEA().estimate(hand_obs(HAND_CAM), m)
    assert not e.ok and "collinear" in e.reason
    # A map without the anchor ids at all.
    m2 = MarkerMap({i: mk for i, mk in hand_map().markers.items() if i != 16},
                   origin_id=13, x_id=16, y_id=4)
    e = LMEA().estimate(hand_obs(HAND_CAM), m2)
    assert not e.ok and e.reason == "x-axis anchor 16 is not in the map"


def test_markers_outside_the_map_are_estimated_but_never_references() -> None:
    m = hand_map()
    obs = [*hand_obs(HAND_CAM), MarkerObservation(99, np.eye(3), np.array([5.0, 5.0, 5.0]))]
    for name in available()[:3]:
        e = get(name).estimate(obs, m)
        assert e.ok and 99 in e.markers and 99 not in e.references
        assert 99 not in e.residuals


# ------------------------------------------------------------- options and extras

def test_kmea_z_noise_option_is_seeded_and_small() -> None:
    m, obs = noisy_frame(noise=0.0)
    a = KMEA(z_noise=1e-4, seed=7).estimate(obs, m)
    b = KMEA(z_noise=1e-4, seed=7).estimate(obs, m)
    c = KMEA(z_noise=1e-4, seed=8).estimate(obs, m)
    clean = KMEA().estimate(obs, m)
    assert np.array_equal(a.cam2world, b.cam2world)
    assert not np.array_equal(a.cam2world, c.cam2world)
    assert not np.array_equal(a.cam2world, clean.cam2world)
    # 0.1 mm of map noise moves a 1.7 m floor by well under a millimetre.
    assert pos_err(a, m) < 1e-3
    assert pos_err(clean, m) < 1e-9
    # Leave-one-out with map noise (one draw per estimate) still matches the map closely.
    loo = KMEA(z_noise=1e-4, seed=1).estimate_with_loo(obs, m).loo_positions
    assert max(np.abs(p - m[i].position).max() for i, p in loo.items()) < 1e-3
    with pytest.raises(ValueError, match="z_noise"):
        KMEA(z_noise=-1.0)


@pytest.mark.parametrize("name", ["kmea", "lmea", "umeyama"])
def test_plane_heights_put_a_robot_marker_back_on_its_plane(name: str) -> None:
    m, obs = noisy_frame(noise=0.0)
    # Marker 40 (true world position (0.3, 0.2, 0.2)) seen 4 % too far along its ray, the
    # typical error of a single marker's PnP depth.
    obs = [MarkerObservation(o.id, o.marker2cam_R, o.marker2cam_t * 1.04) if o.id == 40
           else o for o in obs]
    plain = get(name).estimate(obs, m)
    fixed = get(name).estimate(obs, m, plane_heights={40: 0.2, 99: 0.5})
    assert np.linalg.norm(plain.markers[40].position - [0.3, 0.2, 0.2]) > 0.05
    assert np.allclose(fixed.markers[40].position, [0.3, 0.2, 0.2], atol=1e-9)
    assert fixed.info["plane_height_ids"] == [40]
    # References are never moved by plane_heights.
    fixed2 = get(name).estimate(obs, m, plane_heights={13: 0.5})
    assert np.array_equal(fixed2.markers[13].position, plain.markers[13].position)


def test_registry_names_and_protocol() -> None:
    for name, cls in (("kmea", KMEA), ("lmea", LMEA), ("umeyama", Umeyama)):
        e = get(name)
        assert isinstance(e, cls) and e.name == name and isinstance(e, Estimator)
    assert get("kmea", z_noise=1e-4, seed=1).z_noise == 1e-4
    with pytest.raises(ValueError, match="unknown algorithm 'nope'"):
        get("nope")


def test_residuals_are_reference_distances_after_alignment() -> None:
    m, obs = noisy_frame()
    e = KMEA().estimate(obs, m)
    assert set(e.residuals) == set(e.references)
    T = e.cam2world
    for o in obs:
        if o.id in e.residuals:
            p = T[:3, :3] @ o.marker2cam_t + T[:3, 3]
            assert e.residuals[o.id] == pytest.approx(np.linalg.norm(p - m[o.id].position))
    rms = math.sqrt(np.mean(np.square(list(e.residuals.values()))))
    assert e.info["rms_residual"] == pytest.approx(rms)


@pytest.mark.parametrize("n", [3, 12])  # the few new ones of a tracked frame; a whole frame
def test_a_non_finite_pose_is_named_among_few_or_many_observations(n: int) -> None:
    from kmea.estimators.base import check_observations

    obs = [MarkerObservation(i, np.eye(3), np.array([0.0, 0.0, 1.0 + i])) for i in range(n)]
    assert check_observations(obs) == obs
    for bad_R, bad_t in ((np.eye(3), np.array([0.0, np.inf, 1.0])),
                         (np.where(np.eye(3) > 0, np.nan, 0.0), np.ones(3))):
        broken = [*obs[:-1], MarkerObservation(n - 1, bad_R, bad_t)]
        with pytest.raises(ValueError, match=f"observation id {n - 1}: non-finite pose"):
            check_observations(broken)
