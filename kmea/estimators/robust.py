"""``kmea-robust``: the KMEA alignment inside a robust loop (numpy only).

The paper's KMEA aligns every visible reference marker, so one reference that was kicked
or re-taped pulls the whole frame. Here the alignment is wrapped in:

1. **RANSAC (MSAC scoring) over minimal sets of 3 references.** Each triple gives a closed
   form similarity (Umeyama); every reference's residual (metres) is scored with the
   truncated square ``min(r^2, threshold^2)``. All triples are tried when there are at most
   ``trials`` of them, otherwise ``trials`` random ones from a seeded generator
   (deterministic). The residual is measured in the reference's map plane: its aligned
   position slid along its camera ray onto the plane, minus its map position
   (:func:`plane_residuals`), because a single marker's PnP depth is its noisiest
   coordinate while its direction is good.
2. **Iteratively reweighted Umeyama** with Tukey biweights ``(1 - (r/c)^2)^2`` whose cut-off
   ``c`` is the consensus threshold, so a reference beyond the threshold has weight 0.
   It refines the rough 3-point model until the consensus set stops changing.
3. **The paper's KMEA on the consensus set** (scale step from distances to the origin marker,
   Kabsch rotation), repeated while the consensus set changes. With no outlier the result
   is exactly plain KMEA's.

References outside the consensus are reported in ``Estimate.rejected`` (id -> that in-plane
distance in metres: how far they look displaced) and, for people, in
``Estimate.info["displaced"]``.

Threshold: automatic by default (``threshold=None``), scaled by what each residual
measures. A reference's residual is divided by its footprint (metres per pixel: its side
over its mean side in pixels; without corners, its camera distance over a nominal 1000 px
focal length) and by ``sqrt(1 + rho^2 / mean rho^2)`` (``rho`` its distance from the
references' centre: an alignment's rotation and scale errors grow with it). The RANSAC
picks the model by least median of squares of these normalised residuals (no threshold
needed), whose order statistic gives the noise level; the consensus keeps a reference
when its normalised residual is below ``sqrt(chi2_2(level))`` (``level`` 0.9999: 4.3)
times the level, re-measured (median, :func:`kmea.estimators.corner_noise.robust_sigma`,
at least 0.01 px) on each model's residuals. So a far, small marker gets a larger threshold
than a near, big one, and a noisier camera a larger one than a clean one. A number (m)
gives the former fixed threshold (0.02 m was the default: in-plane residuals of undisturbed
references reach 0.8, 2.5, 4.3 and 9 mm with 0.1, 0.3, 0.5 and 1 px of corner noise on
the simulated floor). When every reference disagrees with every other by decimetres, the
automatic level is that large and the estimate says so (``info["threshold"]``).
"""

from __future__ import annotations

import math
from collections.abc import Collection, Mapping, Sequence
from itertools import combinations

import numpy as np

from kmea.estimators.base import Estimate, EstimatorBase, MarkerObservation, check_observations
from kmea.estimators.common import (
    References,
    finish_estimate,
    reference_problem,
    select_references,
)
from kmea.estimators.corner_noise import SIGMA_FLOOR_PX, robust_sigma
from kmea.estimators.kmea import kmea_align
from kmea.estimators.umeyama import umeyama_batch
from kmea.estimators.unknown_plane import check_mode
from kmea.geometry import ray_plane_parameter
from kmea.geometry.camera import CameraIntrinsics
from kmea.maps.model import MarkerMap
from kmea.stats.chi2 import chi2_quantile

__all__ = ["KMEARobust", "describe_rejected", "footprints", "kmea_align", "plane_residuals",
           "umeyama_batch"]

# Relative size below which 3 points count as collinear (area / longest side^2).
_COLLINEAR = 1e-6
# Without corners a reference's footprint (m per px) is its distance over this focal
# length (px): only the noise floor (SIGMA_FLOOR_PX) depends on it.
_NOMINAL_FOCAL_PX = 1000.0


class KMEARobust(EstimatorBase):
    """KMEA with RANSAC consensus, Tukey-reweighted refinement and displaced-marker reports.

    Options:
        threshold: None (automatic, see the module docstring) or the consensus residual (m)
            between an aligned reference and its map position.
        level: the automatic threshold's chi-square (2 dof) level.
        trials: RANSAC budget; all 3-subsets are enumerated when there are at most this many.
            100 random triples all contain an outlier with probability 0.875^100 = 2e-6
            even when half the references are displaced.
        seed: seed of the sampling generator (deterministic results).
        irls_iterations: maximum Tukey-reweighting iterations.
        min_references: fewer consensus references give "not estimated" (>= 3).
        in_plane: measure residuals in each reference's map plane, along its camera ray
            (:func:`plane_residuals`); False: plain 3-D distances.
    """

    name = "kmea-robust"

    def __init__(self, threshold: float | None = None, trials: int = 100, seed: int = 0,
                 irls_iterations: int = 20, min_references: int = 3,
                 in_plane: bool = True, unknown_plane: str = "free",
                 plane_level: float = 0.999, level: float = 0.9999) -> None:
        self.unknown_plane = check_mode(self.name, unknown_plane)
        self.plane_level = float(plane_level)
        if threshold is not None and not threshold > 0:
            raise ValueError(f"kmea-robust: threshold must be > 0 m, got {threshold}")
        if min_references < 3:
            raise ValueError("kmea-robust: min_references must be >= 3")
        self.threshold = None if threshold is None else float(threshold)
        self.level = float(level)
        # k-sigma of a 2-D residual at ``level``: sqrt of the chi-square (2 dof) quantile.
        self._q = math.sqrt(chi2_quantile(self.level, 2))
        self.last_thresholds: np.ndarray = np.zeros(0)
        self.trials = int(trials)
        self.seed = int(seed)
        self.irls_iterations = int(irls_iterations)
        self.min_references = int(min_references)
        self.in_plane = bool(in_plane)

    # ------------------------------------------------------------------ consensus
    def _triples(self, n: int) -> np.ndarray:
        if math.comb(n, 3) <= self.trials:
            return np.array(list(combinations(range(n), 3)), dtype=int)
        rng = np.random.default_rng(self.seed)
        # Three distinct indices per trial: argsort of uniform keys, first three columns.
        return np.argsort(rng.random((self.trials, n)), axis=1)[:, :3]

    def consensus(self, P: np.ndarray, Q: np.ndarray, ids: Sequence[int], origin_id: int,
                  normals: np.ndarray | None = None, footprint: np.ndarray | None = None
                  ) -> tuple[np.ndarray, tuple[float, np.ndarray, np.ndarray], int]:
        """Robust fit of map = s R cam + t. Returns (inlier mask (N,), (s, R, t), trials).

        normals: (N, 3) map normals of the references; with them the residuals are measured
        in each reference's plane (see :func:`plane_residuals`). footprint: (N,) metres per
        pixel of each reference (its side over its side in pixels) for the automatic
        threshold; None: its camera distance over a nominal 1000 px focal length. Raises
        ``ValueError`` with the reason when no non-degenerate consensus of
        ``min_references`` exists. Sets ``self.last_thresholds`` ((N,) m).
        """
        n = len(P)
        # An alignment's rotation and scale errors grow with the distance from the
        # references' centre: its residuals spread as sqrt(1 + rho^2 / mean rho^2) there.
        rho2 = np.sum((Q - Q.mean(axis=0)) ** 2, axis=1)
        spread = np.sqrt(1.0 + rho2 / max(float(rho2.mean()), 1e-300))

        def residuals(s: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
            pred = s[:, None, None] * (P @ np.swapaxes(R, 1, 2)) + t[:, None, :]
            return plane_residuals(pred, t, Q, normals)

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
        r_all = residuals(s, R, t)
        if self.threshold is not None:
            th = np.full(n, self.threshold)
            score = np.minimum(r_all ** 2, self.threshold ** 2).sum(axis=1)
            best = int(np.argmin(score))
        else:
            # Residuals in pixels at each reference (metres over its footprint): least
            # median of squares picks the model (no threshold needed), its order statistic
            # gives a first noise level.
            if footprint is None:
                dist = np.linalg.norm(P, axis=1)
                g = np.maximum(s[:, None] * dist[None, :] / _NOMINAL_FOCAL_PX, 1e-300)
            else:
                g = np.broadcast_to(np.asarray(footprint, float), r_all.shape)
            g = g * spread[None, :]
            u2 = (r_all / g) ** 2
            h = min(n, n // 2 + 2)
            kth = np.partition(u2, h - 1, axis=1)[:, h - 1]
            best = int(np.argmin(kth))
            q = -2.0 * math.log(1.0 - (h - 0.5) / n)  # chi-square (2 dof) quantile at h/n
            sigma = max(math.sqrt(float(kth[best]) / q), SIGMA_FLOOR_PX)
            th = self._q * sigma * g[best]
        r = r_all[best]
        model = (float(s[best]), R[best], t[best])

        def rescale(r: np.ndarray, sm: float) -> np.ndarray:
            """Per-reference thresholds (m) from the model's residuals r, scale sm."""
            if self.threshold is not None:
                return th
            gg = (sm * np.linalg.norm(P, axis=1) / _NOMINAL_FOCAL_PX if footprint is None
                  else np.asarray(footprint, float))
            gg = np.maximum(gg * spread, 1e-300)
            return self._q * robust_sigma((r / gg) ** 2, 7) * gg

        # Tukey-reweighted Umeyama from the best minimal model.
        inl = r < th
        for _ in range(self.irls_iterations):
            if inl.sum() < 3:
                break
            w = np.where(inl, (1.0 - (r / th) ** 2) ** 2, 0.0)
            # Exact fits give weight 1 everywhere; tiny floor keeps near-threshold ones alive.
            w = np.maximum(w, 1e-6) * inl
            sb, Rb, tb = umeyama_batch(P[None], Q[None], w[None])
            model = (float(sb[0]), Rb[0], tb[0])
            r = residuals(sb, Rb, tb)[0]
            new = r < th
            if np.array_equal(new, inl):
                break
            inl = new

        # The paper's KMEA on the consensus, repeated while the consensus changes; the
        # automatic threshold is re-measured on each model's residuals.
        th = rescale(r, model[0])
        inl = r < th
        for _ in range(5):
            problem = reference_problem(Q[inl], P[inl], self.min_references)
            if problem:
                rule = (f"within {self.threshold * 1e3:.0f} mm" if self.threshold is not None
                        else "within their noise level")
                raise ValueError(f"no consensus: {int(inl.sum())} of {n} references agree "
                                 f"{rule} ({problem})")
            sel = [ids[i] for i in np.flatnonzero(inl).tolist()]
            model = kmea_align(P[inl], Q[inl], sel, origin_id)
            r = residuals(np.array([model[0]]), model[1][None], model[2][None])[0]
            th = rescale(r, model[0])
            new = r < th
            if np.array_equal(new, inl):
                break
            inl = new
        self.last_thresholds = th
        return inl, model, len(tri)

    def _normals(self, world_map: MarkerMap, ids: Sequence[int]) -> np.ndarray | None:
        if not self.in_plane:
            return None
        return np.array([world_map[i].normal for i in ids]).reshape(-1, 3)

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

        camera is accepted for the common interface and not used (this estimator works on
        the markers' camera-frame poses only); plane_heights moves markers of known height
        along their camera rays, as for KMEA.
        """
        obs = check_observations(observations)
        refs = select_references(obs, world_map, exclude)
        problem = reference_problem(refs.world, refs.cam, self.min_references)
        if problem:
            return Estimate.failed(self.name, problem)
        try:
            inl, (s, R, t), trials = self.consensus(refs.cam, refs.world, refs.ids,
                                                    world_map.origin_id,
                                                    self._normals(world_map, refs.ids),
                                                    footprints(obs, world_map, refs.ids))
        except ValueError as e:
            return Estimate.failed(self.name, str(e))
        r = plane_residuals((s * refs.cam @ R.T + t)[None], t[None], refs.world,
                            self._normals(world_map, refs.ids))[0]
        rejected = {i: float(ri) for i, ri, k in zip(refs.ids, r, inl, strict=True) if not k}
        used = References(tuple(i for i, k in zip(refs.ids, inl, strict=True) if k),
                          refs.cam[inl], refs.world[inl])
        est = finish_estimate(self.name, obs, used, s, R, t, plane_heights, info={
            "displaced": describe_rejected(rejected), "ransac_trials": trials,
            "threshold": (self.threshold if self.threshold is not None
                          else float(np.median(self.last_thresholds))),
            "thresholds": {i: float(v) for i, v in zip(refs.ids, self.last_thresholds,
                                                        strict=True)},
            "origin_in_consensus": world_map.origin_id in used.ids},
            unknown=(world_map, camera, self.unknown_plane, self.plane_level))
        est.rejected = rejected
        return est


def footprints(observations: Sequence[MarkerObservation], world_map: MarkerMap,
               ids: Sequence[int]) -> np.ndarray | None:
    """(N,) metres per pixel of the markers ``ids`` (the map's side length over the mean side
    of their detected corners, px), or None unless every one has corners."""
    by_id = {o.id: o for o in observations}
    cs = [by_id[i].corners if i in by_id else None for i in ids]
    if not cs or any(c is None for c in cs):
        return None
    c = np.asarray(cs, dtype=float).reshape(-1, 4, 2)
    side = np.sqrt(np.sum((c - c[:, [3, 0, 1, 2]]) ** 2, axis=2)).mean(axis=1)
    if not np.all(side > 0):
        return None
    return np.array([world_map[i].length for i in ids]) / side


def plane_residuals(pred: np.ndarray, C: np.ndarray, Q: np.ndarray,
                    normals: np.ndarray | None, min_cos: float = 0.3) -> np.ndarray:
    """Disagreement (m) of aligned references with the map, measured in their map planes.

    pred: (M, N, 3) aligned positions under M candidate alignments; C: (M, 3) where each
    puts the camera centre; Q: (N, 3) map positions; normals: (N, 3) map normals or None.
    A single marker's PnP depth is its noisiest coordinate (tens of millimetres for a small
    or distant marker) while its direction from the camera is good to a fraction of that.
    So each aligned reference is slid along its camera ray onto its map plane and compared
    there: depth noise drops out, and a marker that really moved shows its in-plane
    displacement. Where the ray meets the plane at a grazing angle (|cos| < min_cos, wall
    markers seen from above) the distance perpendicular to the ray is used instead.
    Returns (M, N).
    """
    diff = pred - Q[None]
    if normals is None:
        return np.linalg.norm(diff, axis=2)
    ray = pred - C[:, None, :]
    u = ray / np.maximum(np.linalg.norm(ray, axis=2, keepdims=True), 1e-300)
    raw = np.linalg.norm(diff - np.sum(diff * u, axis=2, keepdims=True) * u, axis=2)
    den = np.einsum("mni,ni->mn", ray, normals)
    cos = np.abs(den) / np.maximum(np.linalg.norm(ray, axis=2), 1e-300)
    ok = cos >= min_cos
    lam = ray_plane_parameter(C[:, None, :], ray, Q[None], normals[None])
    on_plane = C[:, None, :] + lam[:, :, None] * ray
    return np.where(ok & (lam > 0), np.linalg.norm(on_plane - Q[None], axis=2), raw)


def describe_rejected(rejected: Mapping[int, float],
                      turned: Mapping[int, float] | None = None) -> list[str]:
    """Human-readable lines, largest disagreement first: "marker 16 looks displaced by 28 mm"
    (rejected: id -> metres), with ", turned 5 deg" when ``turned`` (id -> radians) says it
    turned by at least a degree."""
    out = []
    for i, d in sorted(rejected.items(), key=lambda kv: -kv[1]):
        line = f"marker {i} looks displaced by {d * 1e3:.0f} mm"
        a = (turned or {}).get(i)
        if a is not None and abs(math.degrees(a)) >= 1.0:
            line += f", turned {math.degrees(a):+.0f} deg"
        out.append(line)
    return out
