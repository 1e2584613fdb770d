"""``kmea-robust``: the KMEA alignment inside a robust loop (numpy only).

The paper's KMEA aligns every visible reference marker, so one reference that was kicked
or re-taped pulls the whole frame. Here the alignment is wrapped in:

1. **RANSAC (MSAC scoring) over minimal sets of 3 references.** Each triple gives a closed
   form similarity (Umeyama); every reference's residual ``|s R p + t - q|`` (metres, map
   frame) is scored with the truncated square ``min(r^2, threshold^2)``. All triples are
   tried when there are at most ``trials`` of them, otherwise ``trials`` random ones from a
   seeded generator (deterministic).
2. **Iteratively reweighted Umeyama** with Tukey biweights ``(1 - (r/c)^2)^2`` whose cut-off
   ``c`` is the consensus threshold, so a reference beyond the threshold has weight 0.
   It refines the rough 3-point model until the consensus set stops changing.
3. **The paper's KMEA on the consensus set** (scale step from distances to the origin marker,
   Kabsch rotation), repeated while the consensus set changes. With no outlier the result
   is exactly plain KMEA's.

References outside the consensus are reported in ``Estimate.rejected`` (id -> distance in
metres between where the alignment puts them and their map position, i.e. how far they
look displaced) and, for people, in ``Estimate.info["displaced"]``.

Threshold default, 0.02 m: KMEA's reference residuals come from single-marker PnP depth
noise, a few millimetres for 60 mm markers seen from 1.3-2 m (depth error of a marker
``w`` pixels wide is about ``Z * sigma_px / w``, 60 px wide and 0.2-0.5 px of corner noise
give 4-10 mm once it leaks sideways off the optical axis). 20 mm stays clear of that noise
while catching the centimetre displacements that matter on a 1.7 x 1.2 m floor.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Mapping, Sequence
from itertools import combinations

import numpy as np

from kmea.estimators.base import (
    CameraIntrinsics,
    Estimate,
    MarkerObservation,
    check_observations,
)
from kmea.estimators.common import (
    References,
    finish_estimate,
    kabsch,
    reference_problem,
    select_references,
)
from kmea.maps import MarkerMap

__all__ = ["KMEARobust", "describe_rejected", "kmea_align", "umeyama_batch"]

# Relative size below which 3 points count as collinear (area / longest side^2).
_COLLINEAR = 1e-6


def umeyama_batch(P: np.ndarray, Q: np.ndarray, w: np.ndarray | None = None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weighted least-squares similarities ``Q ~ s R P + t`` for a batch of point sets.

    P, Q: (M, K, 3); w: (M, K) non-negative weights or None. Returns s (M,), R (M, 3, 3),
    t (M, 3). Degenerate sets give whatever the SVD gives; callers check collinearity.
    """
    P = np.asarray(P, dtype=float)
    Q = np.asarray(Q, dtype=float)
    if w is None:
        w = np.ones(P.shape[:2])
    w = w / np.maximum(w.sum(axis=1, keepdims=True), 1e-300)
    wc = w[:, :, None]
    mp = (wc * P).sum(axis=1)
    mq = (wc * Q).sum(axis=1)
    Pc = P - mp[:, None, :]
    Qc = Q - mq[:, None, :]
    C = np.swapaxes(wc * Qc, 1, 2) @ Pc  # (M, 3, 3) cross-covariance, map x camera
    U, S, Vt = np.linalg.svd(C)
    d = np.sign(np.linalg.det(U @ Vt))
    d[d == 0] = 1.0
    U[:, :, 2] *= d[:, None]
    R = U @ Vt
    var_p = (wc * Pc * Pc).sum(axis=(1, 2))
    s = (S[:, 0] + S[:, 1] + d * S[:, 2]) / np.maximum(var_p, 1e-300)
    t = mq - s[:, None] * (R @ mp[:, :, None])[:, :, 0]
    return s, R, t


def kmea_align(P: np.ndarray, Q: np.ndarray, ids: Sequence[int], origin_id: int
               ) -> tuple[float, np.ndarray, np.ndarray]:
    """The paper's KMEA alignment of camera positions P (N, 3) onto map positions Q (N, 3).

    The same steps as :class:`kmea.estimators.kmea.KMEA`: scale = mean distance of the
    references to the origin marker in the map over the same mean in the camera frame (the
    reference centroid when the origin is not among ``ids``), then Kabsch on the scaled
    camera positions. Returns (s, R, t) with ``map = s R cam + t``.
    """
    ids = list(ids)
    if origin_id in ids:
        k = ids.index(origin_id)
        p0, q0 = P[k], Q[k]
    else:
        p0, q0 = P.mean(axis=0), Q.mean(axis=0)
    s = float(np.linalg.norm(Q - q0, axis=1).mean() / np.linalg.norm(P - p0, axis=1).mean())
    cs, cq = s * P.mean(axis=0), Q.mean(axis=0)
    R = kabsch(s * P - cs, Q - cq)
    return s, R, cq - R @ cs


class KMEARobust:
    """KMEA with RANSAC consensus, Tukey-reweighted refinement and displaced-marker reports.

    Options:
        threshold: consensus residual (m) between an aligned reference and its map position.
        trials: RANSAC budget; all 3-subsets are enumerated when there are at most this many.
            100 random triples all contain an outlier with probability 0.875^100 = 2e-6
            even when half the references are displaced.
        seed: seed of the sampling generator (deterministic results).
        irls_iterations: maximum Tukey-reweighting iterations.
        min_references: fewer consensus references give "not estimated" (>= 3).
    """

    name = "kmea-robust"

    def __init__(self, threshold: float = 0.02, trials: int = 100, seed: int = 0,
                 irls_iterations: int = 20, min_references: int = 3) -> None:
        if not threshold > 0:
            raise ValueError(f"kmea-robust: threshold must be > 0 m, got {threshold}")
        if min_references < 3:
            raise ValueError("kmea-robust: min_references must be >= 3")
        self.threshold = float(threshold)
        self.trials = int(trials)
        self.seed = int(seed)
        self.irls_iterations = int(irls_iterations)
        self.min_references = int(min_references)

    # ------------------------------------------------------------------ consensus
    def _triples(self, n: int) -> np.ndarray:
        if math.comb(n, 3) <= self.trials:
            return np.array(list(combinations(range(n), 3)), dtype=int)
        rng = np.random.default_rng(self.seed)
        # Three distinct indices per trial: argsort of uniform keys, first three columns.
        return np.argsort(rng.random((self.trials, n)), axis=1)[:, :3]

    def consensus(self, P: np.ndarray, Q: np.ndarray, ids: Sequence[int], origin_id: int
                  ) -> tuple[np.ndarray, tuple[float, np.ndarray, np.ndarray], int]:
        """Robust fit of map = s R cam + t. Returns (inlier mask (N,), (s, R, t), trials).

        Raises ``ValueError`` with the reason when no non-degenerate consensus of
        ``min_references`` exists.
        """
        n = len(P)
        th2 = self.threshold ** 2
        tri = self._triples(n)
        Pt, Qt = P[tri], Q[tri]
        # Reject collinear triples (in the map or in the camera) before fitting.
        def area(X: np.ndarray) -> np.ndarray:
            c = np.cross(X[:, 1] - X[:, 0], X[:, 2] - X[:, 0])
            side = np.max(np.linalg.norm(X - np.roll(X, 1, axis=1), axis=2), axis=1)
            return np.linalg.norm(c, axis=1) / np.maximum(side ** 2, 1e-300)
        good = (area(Pt) > _COLLINEAR) & (area(Qt) > _COLLINEAR)
        if not good.any():
            raise ValueError("references are collinear")
        tri, Pt, Qt = tri[good], Pt[good], Qt[good]
        s, R, t = umeyama_batch(Pt, Qt)
        pred = s[:, None, None] * (P @ np.swapaxes(R, 1, 2)) + t[:, None, :]
        r2 = np.sum((pred - Q[None]) ** 2, axis=2)
        score = np.minimum(r2, th2).sum(axis=1)
        best = int(np.argmin(score))
        r = np.sqrt(r2[best])
        model = (float(s[best]), R[best], t[best])

        # Tukey-reweighted Umeyama from the best minimal model.
        inl = r < self.threshold
        for _ in range(self.irls_iterations):
            if inl.sum() < 3:
                break
            w = np.where(inl, (1.0 - (r / self.threshold) ** 2) ** 2, 0.0)
            # Exact fits give weight 1 everywhere; tiny floor keeps near-threshold ones alive.
            w = np.maximum(w, 1e-6) * inl
            sb, Rb, tb = umeyama_batch(P[None], Q[None], w[None])
            model = (float(sb[0]), Rb[0], tb[0])
            r = np.linalg.norm(model[0] * P @ model[1].T + model[2] - Q, axis=1)
            new = r < self.threshold
            if np.array_equal(new, inl):
                break
            inl = new

        # The paper's KMEA on the consensus, repeated while the consensus changes.
        for _ in range(5):
            problem = reference_problem(Q[inl], P[inl], self.min_references)
            if problem:
                raise ValueError(f"no consensus: {int(inl.sum())} of {n} references agree "
                                 f"within {self.threshold * 1e3:.0f} mm ({problem})")
            sel = [ids[i] for i in np.flatnonzero(inl)]
            model = kmea_align(P[inl], Q[inl], sel, origin_id)
            r = np.linalg.norm(model[0] * P @ model[1].T + model[2] - Q, axis=1)
            new = r < self.threshold
            if np.array_equal(new, inl):
                break
            inl = new
        return inl, model, len(tri)

    # ------------------------------------------------------------------ estimate
    def estimate(
        self,
        observations: Sequence[MarkerObservation],
        world_map: MarkerMap,
        exclude: Collection[int] = (),
        camera: CameraIntrinsics | None = None,
        plane_heights: Mapping[int, float] | None = None,
    ) -> Estimate:
        """World pose of every observed marker; see the module docstring.

        camera and plane_heights are accepted for the common interface and not used: this
        estimator works on the markers' camera-frame poses only.
        """
        obs = check_observations(observations)
        refs = select_references(obs, world_map, exclude)
        problem = reference_problem(refs.world, refs.cam, self.min_references)
        if problem:
            return Estimate.failed(self.name, problem)
        try:
            inl, (s, R, t), trials = self.consensus(refs.cam, refs.world, refs.ids,
                                                    world_map.origin_id)
        except ValueError as e:
            return Estimate.failed(self.name, str(e))
        r = np.linalg.norm(s * refs.cam @ R.T + t - refs.world, axis=1)
        rejected = {i: float(ri) for i, ri, k in zip(refs.ids, r, inl, strict=True) if not k}
        used = References(tuple(i for i, k in zip(refs.ids, inl, strict=True) if k),
                          refs.cam[inl], refs.world[inl])
        est = finish_estimate(self.name, obs, used, s, R, t, plane_heights, info={
            "displaced": describe_rejected(rejected), "ransac_trials": trials,
            "threshold": self.threshold, "origin_in_consensus": world_map.origin_id in used.ids})
        est.rejected = rejected
        return est

    def estimate_loo(
        self,
        observations: Sequence[MarkerObservation],
        world_map: MarkerMap,
        camera: CameraIntrinsics | None = None,
        plane_heights: Mapping[int, float] | None = None,
    ) -> dict[int, np.ndarray]:
        """Leave-one-out: id -> (3,) world position (m) of each observed map marker estimated
        without itself (the convention of :func:`kmea.estimators.loo.loo_positions`).

        One consensus for the frame, then for each consensus member the closed-form KMEA on
        the consensus without it; a rejected reference is not in the consensus, so its
        position is the full alignment's. N Kabsch solves instead of N robust loops; it
        differs from ``estimate(exclude={j})`` only if removing j would change which other
        references agree.
        """
        obs = check_observations(observations)
        refs = select_references(obs, world_map)
        out: dict[int, np.ndarray] = {}
        if reference_problem(refs.world, refs.cam, self.min_references + 1):
            return out
        P, Q, ids = refs.cam, refs.world, refs.ids
        try:
            inl, (s, R, t), _ = self.consensus(P, Q, ids, world_map.origin_id)
        except ValueError:
            return out
        for j, mid in enumerate(ids):
            if not inl[j]:
                out[mid] = s * R @ P[j] + t
                continue
            keep = inl.copy()
            keep[j] = False
            if reference_problem(Q[keep], P[keep], self.min_references):
                continue
            sel = [ids[i] for i in np.flatnonzero(keep)]
            sj, Rj, tj = kmea_align(P[keep], Q[keep], sel, world_map.origin_id)
            out[mid] = sj * Rj @ P[j] + tj
        return out


def describe_rejected(rejected: Mapping[int, float]) -> list[str]:
    """Human-readable lines, largest disagreement first: "marker 16 looks displaced by 28 mm"."""
    return [f"marker {i} looks displaced by {d * 1e3:.0f} mm"
            for i, d in sorted(rejected.items(), key=lambda kv: -kv[1])]
