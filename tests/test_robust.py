"""kmea-robust: RANSAC + Tukey IRLS + the paper's KMEA on the consensus."""

from __future__ import annotations

import math

import numpy as np
import pytest
from synth_corners import observe, scenario1

from kmea.estimators import get
from kmea.estimators.base import MarkerObservation
from kmea.estimators.loo import loo_errors
from kmea.estimators.robust import KMEARobust, umeyama_batch
from kmea.geometry import rotvec_to_matrix
from kmea.maps.files import default_map

DISPLACED = {4: (0.02, -0.03), 13: (-0.03, 0.02), 16: (0.025, 0.025)}


def _similarity_obs(world_map, ids, s, R, t, moved=None):
    """Observations whose camera positions map exactly onto the map by world = s R cam + t,
    except ``moved`` ids (id -> world offset), which sit elsewhere in the world."""
    moved = moved or {}
    out = []
    for i in ids:
        p = world_map[i].position + np.asarray(moved.get(i, (0.0, 0.0, 0.0)))
        cam = R.T @ (p - t) / s
        out.append(MarkerObservation(i, R.T @ world_map[i].rotation, cam))
    return out


@pytest.mark.parametrize("seed", range(5))
def test_exact_similarity_with_displaced_references(seed):
    rng = np.random.default_rng(seed)
    m = default_map()
    ids = [i for i in m.ids if m[i].on_floor]
    s = rng.uniform(0.5, 2.0)
    R = rotvec_to_matrix(rng.normal(size=3))
    # The camera origin maps to t: somewhere above the floor, as a real camera is.
    t = np.array([*rng.uniform(-0.5, 0.5, 2), rng.uniform(1.0, 2.5)])
    bad = [int(i) for i in rng.choice(ids, size=4, replace=False)]
    moved = {}
    for i in bad:
        ang = rng.uniform(0, 2 * math.pi)
        d = rng.uniform(0.03, 0.2)
        moved[i] = (d * math.cos(ang), d * math.sin(ang), 0.0)
    obs = _similarity_obs(m, ids, s, R, t, moved)
    est = KMEARobust().estimate(obs, m)
    assert est.ok, est.reason
    assert set(est.rejected) == set(bad)
    for i in bad:
        assert est.rejected[i] == pytest.approx(math.hypot(*moved[i][:2]), abs=1e-9)
        assert est.markers[i].position == pytest.approx(m[i].position + moved[i], abs=1e-9)
    assert est.scale == pytest.approx(s, rel=1e-9)
    for i in ids:
        if i not in bad:
            assert np.linalg.norm(est.markers[i].position - m[i].position) < 1e-9
    # Plain KMEA is pulled by the displaced references.
    plain = get("kmea").estimate(obs, m)
    worst = max(np.linalg.norm(plain.markers[i].position - m[i].position)
                for i in ids if i not in bad)
    assert worst > 1e-3


def test_equals_plain_kmea_without_outliers():
    sc = scenario1()
    obs = observe(sc, noise_px=0.1, seed=4)
    robust = KMEARobust().estimate(obs, sc.map)
    plain = get("kmea").estimate(obs, sc.map)
    assert robust.ok and plain.ok
    assert robust.rejected == {} and robust.info["displaced"] == []
    assert robust.references == plain.references
    assert robust.scale == pytest.approx(plain.scale, rel=1e-12)
    for i, me in plain.markers.items():
        assert np.allclose(robust.markers[i].position, me.position, atol=1e-12)


def test_displaced_anchors_are_rejected_and_reported():
    sc = scenario1(displaced=DISPLACED)
    obs = observe(sc, noise_px=0.1, seed=5)
    est = get("kmea-robust").estimate(obs, sc.map)
    assert est.ok, est.reason
    assert set(est.rejected) == set(DISPLACED)
    for i, (dx, dy) in DISPLACED.items():
        # Measured in the floor plane, along the marker's ray: PnP depth noise drops out.
        assert est.rejected[i] == pytest.approx(math.hypot(dx, dy), abs=0.002)
    assert len(est.info["displaced"]) == 3
    assert all(line.startswith("marker ") and line.endswith(" mm")
               for line in est.info["displaced"])
    assert set(DISPLACED).isdisjoint(est.references)

    # Leave-one-out errors of the other floor markers: small for kmea-robust, pulled for KMEA.
    others = [i for i in sc.map.ids if sc.map[i].on_floor and i not in DISPLACED]
    robust = loo_errors(KMEARobust(), obs, sc.map)
    plain = loo_errors(get("kmea"), obs, sc.map)
    r_mean = np.mean([robust[i] for i in others if i in robust])
    p_mean = np.mean([plain[i] for i in others if i in plain])
    assert r_mean < 0.0015
    # About 1.7 to 2.6 times over seeds; the 3 displaced anchors pull every KMEA alignment.
    assert p_mean > 1.5 * r_mean and p_mean - r_mean > 0.4e-3


def test_leave_one_out_is_estimate_with_the_marker_excluded():
    sc = scenario1(displaced={4: (0.03, 0.0)})
    obs = observe(sc, noise_px=0.15, seed=6)
    kr = KMEARobust()
    res = kr.estimate_with_loo(obs, sc.map)
    assert set(res.loo_positions) == {o.id for o in obs if o.id in sc.map}
    assert set(res.estimate.rejected) == {4}
    for i, p in res.loo_positions.items():
        est = kr.estimate(obs, sc.map, exclude={i})
        assert np.array_equal(est.markers[i].position, p), i
    assert res.loo_errors[4] == pytest.approx(0.03, abs=2e-3)


def test_deterministic_with_sampling():
    sc = scenario1(displaced=DISPLACED)
    obs = observe(sc, noise_px=0.2, seed=7)
    kr = KMEARobust(trials=50, seed=3)  # 37 references: C(37, 3) > 50, so it samples
    a, b = kr.estimate(obs, sc.map), kr.estimate(obs, sc.map)
    assert a.info["ransac_trials"] <= 50
    assert a.rejected == b.rejected and a.references == b.references
    assert np.array_equal(a.cam2world, b.cam2world)


def test_degenerate_inputs_are_not_estimated():
    m = default_map()
    kr = KMEARobust()
    R, t = np.eye(3), np.zeros(3)
    two = _similarity_obs(m, [13, 16], 1.0, R, t)
    est = kr.estimate(two, m)
    assert not est.ok and "2 reference" in est.reason and est.markers == {}
    collinear = _similarity_obs(m, [13, 14, 15, 16], 1.0, R, t)  # all on y = 0
    est = kr.estimate(collinear, m)
    assert not est.ok and "collinear" in est.reason
    # Every reference disagrees with every other: no three agree within a fixed threshold.
    rng = np.random.default_rng(0)
    ids = [0, 5, 13, 22, 30]
    scattered = _similarity_obs(m, ids, 1.0, R, t,
                                {i: (*rng.uniform(-0.3, 0.3, 2), 0.0) for i in ids})
    est = KMEARobust(threshold=0.02).estimate(scattered, m)
    assert not est.ok and "consensus" in est.reason
    # The automatic threshold measures the noise level on the references themselves: when
    # they all disagree by decimetres, that is the level, and the report says so.
    est = kr.estimate(scattered, m)
    assert est.ok and est.info["threshold"] > 0.05
    res = kr.estimate_with_loo(two, m)
    assert res.loo_positions == {} and set(res.loo_failures) == {13, 16}
    with pytest.raises(ValueError, match="threshold"):
        KMEARobust(threshold=0.0)


def test_umeyama_batch_recovers_similarities():
    rng = np.random.default_rng(1)
    P = rng.normal(size=(4, 6, 3))
    s = rng.uniform(0.5, 2.0, 4)
    R = np.array([rotvec_to_matrix(rng.normal(size=3)) for _ in range(4)])
    t = rng.normal(size=(4, 3))
    Q = s[:, None, None] * np.einsum("mij,mnj->mni", R, P) + t[:, None, :]
    s2, R2, t2 = umeyama_batch(P, Q)
    assert np.allclose(s2, s) and np.allclose(R2, R) and np.allclose(t2, t)


def test_depth_noise_is_not_taken_for_displacement():
    # 0.5 px of corner noise puts single-marker PnP depths tens of millimetres off; measured
    # in the floor plane along each marker's ray, no undisturbed reference looks displaced.
    sc = scenario1()
    in_plane, raw = KMEARobust(), KMEARobust(in_plane=False)
    false_raw = 0
    for seed in range(4):
        obs = observe(sc, noise_px=0.5, seed=seed)
        assert in_plane.estimate(obs, sc.map).rejected == {}
        false_raw += len(raw.estimate(obs, sc.map).rejected)
    assert false_raw > 0  # the plain 3-D residual would have cried wolf
