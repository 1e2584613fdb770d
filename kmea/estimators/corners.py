"""``corner-pnp``: the camera pose from the corners of all reference markers, then ray-plane.

KMEA aligns the *centres* of per-marker PnP poses; the depth of one small marker is its
noisiest coordinate and leaks sideways off the optical axis. Here instead:

1. **Robust start**: :class:`kmea.estimators.robust.KMEARobust` on the per-marker poses
   gives a consensus of references and a rough camera pose (its similarity's rotation,
   and the camera centre where the similarity puts the camera origin).
2. **Levenberg-Marquardt** on the reprojection error of every corner of every consensus
   reference (map corners projected with K and the OpenCV distortion model, numpy), with
   a Huber loss (``huber_px``) so one bad corner cannot dominate.
3. **Rejection**, scaled by the corner noise the frame shows (:mod:`kmea.estimators.
   corner_noise`): ``sigma_px``, the median-based level of the consensus references'
   reprojection residuals (floored at 0.01 px). A corner whose residual ``|e|^2 /
   sigma_px^2`` exceeds the chi-square (2 dof) ``corner_level`` quantile is dropped (one of
   a reference's 4 at most: an outline drawn across it, a glare); a reference is rejected
   as displaced when two or more of its corners are, or when its kept corners' sum of
   ``|e|^2 / sigma_px^2`` exceeds the chi-square (2 x corners) ``reference_level``
   quantile; then LM again, until the consensus is stable. In metres the threshold is
   ``sigma_px sqrt(q / corners)`` times the marker's footprint (its side in metres over its
   side in pixels): a far, small marker gets a larger one than a near, big marker, in
   proportion (``info["thresholds"]``, RMS corner distance). ``threshold`` (metres) gives
   the former fixed rule instead (RMS corner distance on the map plane). Rejected
   references are reported in ``Estimate.rejected`` (id -> how far their centre moved in
   their map plane, m) and ``info["displaced"]``.
4. **Every marker from its corners**: the rays of its 4 corners (pixel -> undistorted
   normalized ray) intersect its plane: ``z = plane_heights[id]`` when the caller gives a
   height (a robot's top plate), else its map plane for a map marker (what leave-one-out
   evaluates); centre = mean of the 4 points, in-plane rotation from a 2D Procrustes fit of
   the square. A corner the marker's own square contradicts (leave-one-corner-out test at
   ``corner_level`` against ``sigma_px``) is left out of that fit. A marker with no known
   plane (not in the map, no height given) is put on a plane of the map when its corners
   are consistent with it (the same corner test first), else estimated free with its
   depth corrected by the references (:mod:`kmea.estimators.unknown_plane`, option
   ``unknown_plane``); a marker without corners gets its own PnP pose moved by the fitted
   camera pose.

Optional intrinsics refinement (``refine_intrinsics``): a common multiplier of fx and fy
and k1 join the LM, with a weak Gaussian prior at the calibrated values (``f`` 5 %, k1
0.1: real calibrations are a few percent off, and the prior keeps a fronto-parallel
view, where focal length and camera height are not separable, well-posed). ``"auto"`` (the
default) refines only when the data call for it: a likelihood-ratio test of the refined
model against the calibrated one (``_select``; 2 extra parameters, chi-square level
``refine_level`` 0.999). Refining an exact calibration anyway moves the focal length by a
few tenths of a percent (it trades against the camera height in a near fronto-parallel
view): harmless on the floor, but it biases markers at another height (a robot's top plate)
by about 1e-3 of their distance from the nadir. With a calibration 1-3 % off, or the
tutorial photo's rough one, the test passes by orders of magnitude.

Warm start (``warm_start``, off by default; the daemon's tracking mode for a fixed live
camera turns it on): the fit of the previous call is kept; when the references and their
corners are the same (a tracked fixed floor), that fit is the answer (a fresh solve would
compute the same numbers); when they changed (a marker hidden, one more found), the
Levenberg-Marquardt starts from the previous pose and intrinsics with the previous
consensus instead of a robust start: a few iterations, not a fresh solve. Calls with
``exclude`` (leave-one-out by exclusion) never use nor change it. With the same fit only
the markers with new observations (the robots) are placed again, and what their placement
needs from the fit alone (its covariance, the perturbed poses of the uncertainty's
derivatives, the camera centre: ``_FitConsts``) is computed once per fit; the numbers are
those of a computation from scratch (``tests/test_corner_fast.py``).

Uncertainty (``MarkerEstimate.sigma``, m): the RMS position error predicted by first-order
propagation of (a) the pose (and intrinsics) covariance ``sigma_px^2 (J^T J)^-1`` of the LM
and (b) the marker's own corner noise ``sigma_px``, through the ray-plane intersection;
``sigma_px^2`` is the residual variance of the fit (sum of squared pixel residuals over
their degrees of freedom). ``sigma = sqrt(trace(Cov))``. Markers placed by their own PnP
pose get ``None``.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from kmea.chi2 import chi2_quantile
from kmea.estimators import unknown_plane as unknown_plane_mod
from kmea.estimators.base import (
    CameraIntrinsics,
    CheckedObservations,
    Estimate,
    EstimateWithLoo,
    EstimatorBase,
    MarkerEstimate,
    MarkerObservation,
    check_observations,
    loo_by_exclusion,
    loo_candidates,
)
from kmea.estimators.common import reference_problem
from kmea.estimators.corner_noise import (
    SIGMA_FLOOR_PX,
    corner_outliers,
    robust_sigma,
    square_pose,
)
from kmea.estimators.robust import KMEARobust, describe_rejected, footprints
from kmea.estimators.robust_lm import huber_cost, huber_weights, robust_lm
from kmea.geometry import (
    check_distortion,
    distort,
    distort_jacobian,
    distort_jacobian_entries,
    intersect_rays_planes,
    make_transform,
    marker_corners_local,
    project,
    rotation_increment_jacobian,
    rotvec_to_matrix,
    rotvecs_to_matrices,
    undistort,
    yaw_of,
)
from kmea.map_model import MarkerMap

__all__ = ["CornerPnP"]


# The score test's screen before fitting the refined model: the chi-square (2 dof) 0.9
# quantile, -2 ln 0.1.
_SCORE_SCREEN = 4.605


@dataclass
class _Fit:
    """State of one LM fit: world2cam pose, intrinsics, and what the covariance needs."""

    R: np.ndarray  # (3, 3) world2cam
    t: np.ndarray  # (3,)
    K: np.ndarray  # (3, 3) current (refined) camera matrix
    K0: np.ndarray  # (3, 3) calibrated camera matrix (the multiplier's reference)
    d: np.ndarray  # (14,) current distortion
    d0: np.ndarray  # (14,) calibrated distortion
    H: np.ndarray  # (p, p) Gauss-Newton matrix at the solution (weighted + prior)
    sigma_px: float  # residual standard deviation per pixel coordinate
    rms_px: float
    iterations: int
    refine: bool
    cost: float = math.nan  # Huber cost of the data (px^2), without the prior
    dof: int = 1  # residuals minus parameters
    refine_test: float = math.nan  # the model-selection statistic ("auto" only)
    corner_sigma: float = math.nan  # robust corner noise (px) of the consensus (corner_noise)
    ref_sigma: float = math.nan  # robust level (px) of the references' centre disagreements
    keep: dict | None = None  # inlier id -> (4,) bool: its corners used by the fit
    thresholds: dict | None = None  # reference id -> its rejection threshold, m (RMS corner)
    consts: _FitConsts | None = field(default=None, repr=False, compare=False)  # _consts()


@dataclass(frozen=True)
class _FitConsts:
    """What placing markers with one fit needs and does not depend on the markers: computed
    once per fit (:meth:`CornerPnP._consts`), not once per frame (a fixed camera keeps its
    fit for many frames while the robots are placed again in each).

    of: the fit's (R, t, H, sigma_px) it was computed from (the same objects: a fit whose
    fields were replaced gets new constants); C (3,): the camera centre, world; cov (p, p):
    ``sigma_px^2 H^-1`` (None: H singular); Rs (6, 3, 3), Cs (6, 3): the world2cam
    rotations and camera centres of the six pose perturbations of :meth:`CornerPnP._sigmas`.
    """

    of: tuple
    C: np.ndarray
    cov: np.ndarray | None
    Rs: np.ndarray
    Cs: np.ndarray


# The step of the numerical derivatives of the ray-plane points (normalized coordinates and
# pose parameters).
_H_STEP = 1e-7


@dataclass(frozen=True)
class _Warm:
    """The last fit kept for the warm start (a fixed camera, :mod:`kmea.incremental`).

    key: (id of the map, camera matrix bytes, distortion bytes) it was solved for; refs, uv:
    its references and their stacked corners (4 rows each, px); inliers, dis: its consensus
    and each reference's disagreement (m); ref_obs, camera: the observation objects and the
    intrinsics object of the last call that returned it (same objects: nothing to check).
    """

    key: tuple
    refs: list[int]
    uv: np.ndarray
    fit: _Fit
    inliers: tuple[int, ...]
    dis: dict[int, float]
    ref_obs: tuple = ()
    camera: object = None


_EYE3 = np.eye(3)
_EYE3.flags.writeable = False  # shared: a horizontal plane's frame


# Placeholders of place_on_planes' observations: markers of known plane are placed from
# their corners; their PnP pose is never read.
_NO_POSE_R = np.eye(3)
_NO_POSE_T = np.array([0.0, 0.0, 1.0])


def _same_square(a: MarkerObservation, b: MarkerObservation) -> bool:
    """The same corners and side: a marker of given plane height is placed from these alone
    (its PnP pose is not read), so either observation gives the same placement."""
    return (a.length == b.length and a.corners is not None and b.corners is not None
            and np.array_equal(a.corners, b.corners))


def _plane_frames(ids: Sequence[int], world_map: MarkerMap, plane_heights: Mapping[int, float]
                  ) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """id -> (frame (3, 3) with columns e1, e2, normal; origin (3,)) for markers with a plane.

    An explicit height wins over the map (the caller knows the marker was lifted, e.g. a
    map marker put on a robot); otherwise a map marker lies in its surveyed plane.
    """
    out = {}
    for i in ids:
        if i in plane_heights:
            out[i] = (_EYE3, np.array([0.0, 0.0, float(plane_heights[i])]))
        elif i in world_map:
            m = world_map[i]
            out[i] = (m.rotation, m.position)
    return out


def _plane_hits(C: np.ndarray, rays: np.ndarray, normals: np.ndarray, num: np.ndarray
                ) -> np.ndarray:
    """:func:`kmea.geometry.intersect_rays_planes` from camera centres C (..., 3) along rays
    (..., N, 3) with the planes' part ``num = sum(normals * (points - C))`` (..., N) given:
    the same operations, so the same numbers (the numerical derivatives difference them)."""
    den = np.add.reduce(normals * rays, axis=-1)
    lam = num / den  # the caller ignores division and overflow warnings (NaN marks misses)
    P = C + lam[..., None] * rays
    bad = ~((lam > 0) & (lam < np.inf))
    if bad.any():
        P[bad] = np.nan
    return P


class CornerPnP(EstimatorBase):
    """All-corner camera pose + ray-plane marker estimator (see the module docstring).

    Options:
        threshold: None (default): references are rejected by the chi-square test on the
            measured corner noise (see the module docstring); a number (m): the RMS corner
            disagreement on its map plane beyond which a reference is rejected instead.
        start_threshold: consensus threshold (m) of the robust KMEA start; None (default):
            scaled by the references' own residual level (:class:`KMEARobust`).
        corner_level, reference_level: levels of the corner and reference tests.
        huber_px: Huber loss knee, pixels.
        refine_intrinsics: False, True or "auto".
        refine_level: "auto" refines when the likelihood-ratio test of the refined model
            against the calibrated one passes at this level (see ``_select``).
        unknown_plane: "auto", "floor" or "free": markers without a known plane
            (:mod:`kmea.estimators.unknown_plane`); plane_level: that test's level.
        max_iterations: LM iterations per fit.
        min_references: fewer consensus references give "not estimated" (>= 3).
        prior_f, prior_k1: 1-sigma of the intrinsics prior (relative focal length, k1).
        prior_px: corner noise (px) the prior is weighed against.
        warm_start: start from the previous call's fit (see the module docstring).
    """

    name = "corner-pnp"
    # The fit reads the references' corners, not their poses (a pose only seeds a cold
    # fit and the depth scale of markers off the map's planes).
    fits_corners = True

    def __init__(self, threshold: float | None = None, start_threshold: float | None = None,
                 huber_px: float = 1.0, refine_intrinsics: bool | str = "auto",
                 max_iterations: int = 50,
                 min_references: int = 3, prior_f: float = 0.05, prior_k1: float = 0.1,
                 prior_px: float = 0.5, unknown_plane: str = "auto",
                 plane_level: float = 0.999, refine_level: float = 0.999,
                 corner_level: float = 0.99999, reference_level: float = 0.9999,
                 warm_start: bool = False) -> None:
        if unknown_plane not in unknown_plane_mod.MODES:
            raise ValueError(f"corner-pnp: unknown_plane must be one of "
                             f"{', '.join(unknown_plane_mod.MODES)}, got {unknown_plane!r}")
        self.unknown_plane = unknown_plane
        self.plane_level = float(plane_level)
        self.refine_level = float(refine_level)
        self._refine_threshold = chi2_quantile(self.refine_level, 2)
        if refine_intrinsics not in (True, False, "auto"):
            raise ValueError(f"corner-pnp: refine_intrinsics must be true, false or 'auto', "
                             f"got {refine_intrinsics!r}")
        if not (all(v is None or v > 0 for v in (threshold, start_threshold))
                and huber_px > 0):
            raise ValueError("corner-pnp: threshold, start_threshold and huber_px must be > 0")
        self.threshold = None if threshold is None else float(threshold)
        self.corner_level = float(corner_level)
        self.reference_level = float(reference_level)
        self._corner_q = chi2_quantile(self.corner_level, 2)
        self._ref_q = chi2_quantile(self.reference_level, 2)
        self.huber_px = float(huber_px)
        self.refine_intrinsics = refine_intrinsics
        self.max_iterations = int(max_iterations)
        self.min_references = max(3, int(min_references))
        self.prior = (float(prior_f), float(prior_k1), float(prior_px))
        # The start only has to find a consensus; the corner stage re-checks every reference.
        self._start = KMEARobust(threshold=start_threshold, trials=50,
                                 min_references=self.min_references)
        self.warm_start = bool(warm_start)
        self._warm: _Warm | None = None
        # Placements of the last fit: (fit, world_map, id -> (observation, plane height,
        # MarkerEstimate, PlaneChoice or None)). A marker's placement depends only on the
        # fit, its own observation and its plane, so while the warm start returns the same
        # fit object, a fixed marker reported with the same observation object is not
        # placed again (only the robots are).
        self._placed: tuple | None = None
        self._last_report: tuple | None = None  # see _report
        self._check = CheckedObservations()
        self._camera_raw: tuple | None = None  # see _same_camera
        self._planes: tuple | None = None  # see _corner_planes

    def reset_warm(self) -> None:
        """Forget the previous fit (the view changed: the next call solves afresh)."""
        self._warm = None
        self._placed = None
        self._last_report = None
        self._check.reset()

    # ------------------------------------------------------------------ LM
    def _residuals(self, X: np.ndarray, uv: np.ndarray, R: np.ndarray, t: np.ndarray,
                   K: np.ndarray, d: np.ndarray, refine: bool, jac: bool,
                   K0: np.ndarray | None = None):
        """Pixel residuals (2N,) and, with ``jac``, their Jacobian (2N, 6 or 8) in the
        parameters (rotation increment, translation[, focal multiplier of K0, k1])."""
        Pc = X @ R.T + t
        if np.any(Pc[:, 2] <= 1e-9):
            return (None, None) if jac else None
        if not jac:
            return (project(Pc, K, d) - uv).reshape(-1)
        proj, J_pc, J_f, J_k1 = project(Pc, K, d, jac=True)
        J_w = rotation_increment_jacobian(J_pc, Pc - t)  # left increment exp(w) R
        cols = [J_w, J_pc]
        if refine:
            # project() differentiates a multiplier of the current K; the parameter multiplies K0.
            cols += [J_f[:, :, None] * (K0[0, 0] / K[0, 0]), J_k1[:, :, None]]
        J = np.concatenate(cols, axis=2).reshape(2 * len(X), -1)
        return (proj - uv).reshape(-1), J

    def _prior_rows(self, K: np.ndarray, d: np.ndarray, K0: np.ndarray, d0: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
        pf, pk, ppx = self.prior
        r = np.array([(K[0, 0] / K0[0, 0] - 1.0) / pf * ppx, (d[0] - d0[0]) / pk * ppx])
        J = np.zeros((2, 8))
        J[0, 6] = ppx / pf
        J[1, 7] = ppx / pk
        return r, J

    @staticmethod
    def _update(R, t, K, d, delta, refine, K0):
        R2 = rotvec_to_matrix(delta[:3]) @ R
        t2 = t + delta[3:6]
        if not refine:
            return R2, t2, K, d
        m = K[0, 0] / K0[0, 0] + delta[6]
        K2 = K0.copy()
        K2[0, 0] *= m
        K2[1, 1] *= m
        d2 = d.copy()
        d2[0] += delta[7]
        return R2, t2, K2, d2

    def _lm(self, X: np.ndarray, uv: np.ndarray, R: np.ndarray, t: np.ndarray,
            K0: np.ndarray, d0: np.ndarray, refine: bool,
            start: tuple[np.ndarray, np.ndarray] | None = None) -> _Fit | None:
        """Minimize the Huber reprojection cost (plus the intrinsics prior, centred on the
        calibration K0, d0) from the pose (R, t) and the intrinsics ``start`` (default K0, d0)
        with :func:`kmea.estimators.robust_lm.robust_lm`; the state is (R, t, K, d)."""
        K, d = (K0.copy(), d0.copy()) if start is None or not refine else start
        res = robust_lm(
            lambda st, jac: self._residuals(X, uv, st[0], st[1], st[2], st[3], refine, jac, K0),
            lambda st, delta: self._update(*st, delta, refine, K0),
            (R, t, K, d),
            weights=lambda r: huber_weights(r, self.huber_px),
            cost=lambda r: huber_cost(r, self.huber_px),
            prior=(lambda st: self._prior_rows(st[2], st[3], K0, d0)) if refine else None,
            max_iterations=self.max_iterations)
        if res is None:
            return None
        R, t, K, d = res.state
        r = res.r
        dof = max(r.size - res.H.shape[0], 1)
        sigma = math.sqrt(float(r @ r) / dof)
        rms = math.sqrt(float(r @ r) / r.size)
        return _Fit(R, t, K, K0, d, d0, res.H, sigma, rms, res.iterations, refine,
                    huber_cost(r, self.huber_px), dof)

    def _select(self, X, uv, R, t, K0, d0) -> tuple[_Fit | None, float]:
        """Model selection between the calibrated intrinsics (M0) and M0 plus a refined
        focal multiplier and k1 (M1): a likelihood-ratio (F) test. With Gaussian corner noise
        and M0 true, ``(cost0 - cost1) / sigma1^2`` follows a chi-square with 2 degrees of
        freedom (sigma1^2 = cost1 / dof1, M1's residual variance); M1 is kept only above the
        ``refine_level`` quantile. Returns (fit, statistic).

        M1 is fitted only when the score (Lagrange multiplier) statistic at M0's solution,
        the same chi-square asymptotically and one Jacobian instead of a second fit, exceeds
        its 0.9 quantile (4.6): a loose screen, so that the likelihood ratio still decides
        every borderline case (score and ratio differ with few references and model errors
        other than f and k1). With a good calibration (the usual case) M1 is then fitted in
        about one frame in ten, which halves the cost.
        """
        fit0 = self._lm(X, uv, R, t, K0, d0, False)
        if fit0 is None:
            return None, math.nan
        score = self._score(X, uv, fit0, K0, d0)
        if not score > _SCORE_SCREEN:
            return fit0, score
        fit1 = self._lm(X, uv, fit0.R, fit0.t, K0, d0, True)
        if fit1 is None:
            return fit0, math.nan
        var1 = fit1.cost / max(fit1.dof, 1)
        stat = (fit0.cost - fit1.cost) / max(var1, 1e-30)
        return (fit1 if stat > self._refine_threshold else fit0), float(stat)

    def _score(self, X, uv, fit0: _Fit, K0, d0) -> float:
        """Score statistic g^T H^-1 g / sigma0^2 of the intrinsics parameters at M0's
        solution (g: the gradient of M1's cost there, zero in the pose parameters)."""
        r, J = self._residuals(X, uv, fit0.R, fit0.t, K0, d0, True, True, K0)
        if r is None:
            return math.nan
        Jw = J * huber_weights(r, self.huber_px)[:, None]
        Jp = self._prior_rows(K0, d0, K0, d0)[1]
        H = J.T @ Jw + Jp.T @ Jp
        g = Jw.T @ r
        try:
            q = float(g @ np.linalg.solve(H, g))
        except np.linalg.LinAlgError:
            return math.nan
        var0 = fit0.cost / max(fit0.dof, 1)
        return q / max(var0, 1e-30)

    # ------------------------------------------------------------------ geometry
    @staticmethod
    def _intersect(R: np.ndarray, t: np.ndarray, xy: np.ndarray, frames: np.ndarray,
                   origins: np.ndarray) -> np.ndarray:
        """World points (N, 3) where the rays of normalized image points xy (N, 2) of the
        world2cam pose (R, t) meet the planes with normals frames[:, :, 2] through origins
        (N, 3); NaN where the plane is behind the camera or parallel to the ray."""
        ray = np.concatenate([xy, np.ones((len(xy), 1))], axis=1) @ R  # R^T ray, world
        return intersect_rays_planes(-R.T @ t, ray, origins, frames[:, :, 2])

    @staticmethod
    def _stack_corners(ids, obs) -> np.ndarray:
        return np.concatenate([np.asarray(obs[i].corners, float).reshape(4, 2) for i in ids])

    def _disagreement(self, fit: _Fit, ref_ids, xy: np.ndarray, world_map) -> dict[int, float]:
        """id -> RMS distance (m) between a reference's corners intersected with its map
        plane (normalized corners xy, 4 rows per id) and its map corners."""
        frames = np.repeat(np.array([world_map[i].rotation for i in ref_ids]), 4, axis=0)
        origins = np.repeat(world_map.positions(list(ref_ids)), 4, axis=0)
        P = self._intersect(fit.R, fit.t, xy, frames, origins).reshape(-1, 4, 3)
        M = np.array([world_map[i].corners_world() for i in ref_ids])
        e = np.sqrt(np.mean(np.sum((P - M) ** 2, axis=2), axis=1))
        return {i: (float(v) if np.isfinite(v) else math.inf)
                for i, v in zip(ref_ids, e, strict=True)}

    def _consensus(self, fit: _Fit, refs, inliers, X_refs: np.ndarray, uv_refs: np.ndarray,
                   xy: np.ndarray, dis: Mapping[int, float], world_map: MarkerMap,
                   obs: Mapping[int, MarkerObservation]
                   ) -> tuple[list[int], dict[int, np.ndarray]]:
        """The references that agree with the fit, and each one's corners to use (see the
        module docstring, step 3). Sets ``fit.corner_sigma`` and ``fit.thresholds``.

        Two noise levels, both measured: the corners' own (each reference's square fitted
        in its map plane, 3 parameters: what a corrupted corner stands out from) and the
        fit's (the map corners reprojected: corner noise plus what the camera model and
        the survey leave, what a displaced reference stands out from)."""
        n = len(refs)
        uv4 = uv_refs.reshape(n, 4, 2)
        frames = np.array([world_map[i].rotation for i in refs])
        origins = world_map.positions(list(refs))
        P = self._intersect(fit.R, fit.t, xy, np.repeat(frames, 4, axis=0),
                            np.repeat(origins, 4, axis=0)).reshape(n, 4, 3)
        lengths = np.array([world_map[i].length for i in refs])
        good = np.all(np.isfinite(P), axis=(1, 2))
        pos = {i: k for k, i in enumerate(refs)}
        inl = np.array([pos[i] for i in inliers])
        drop = np.full(n, -1, dtype=int)
        # The corner noise: the median level of the consensus's reprojection residuals (a
        # fit of many references: one bad corner does not spread to the others).
        r = self._residuals(X_refs, uv_refs, fit.R, fit.t, fit.K, fit.d, False, False)
        e2 = (np.full(8 * n, np.inf) if r is None else r ** 2).reshape(n, 4, 2).sum(axis=2)
        sigma_c = robust_sigma(e2[inl].reshape(-1), fit.H.shape[0])
        if np.any(good):
            g = np.flatnonzero(good)
            centres, Rw = square_pose(P[g], frames[g], lengths[g])
            drop[g], _, _ = corner_outliers(fit.R, fit.t, fit.K, fit.d, uv4[g], centres, Rw,
                                            lengths[g], sigma_c, self._corner_q)
            # The fit leaves a corner out only when the map says so too: a corrupted corner
            # disagrees with its own square and with its map corner; one that a slight
            # model error (a grazing view, the lens) moves stays consistent with one of them.
            k = np.flatnonzero(drop >= 0)
            far = e2[k, drop[k]] / sigma_c ** 2 > self._corner_q
            drop[k[~far]] = -1
        fit.corner_sigma = sigma_c
        keep = {i: np.arange(4) != drop[k] for k, i in enumerate(refs)}
        kept = np.array([keep[i] for i in refs])
        # Each reference's corners against its map corners, in units of its own predicted
        # (centre) uncertainty (the fit's pose covariance and its corner
        # noise through its ray-plane intersection: larger for far, small or grazing
        # markers), times the factor by which the references show more spread than
        # predicted (the median; at least 1: the prediction is the floor).
        # RMS over its kept corners: a shift moves all of them, a turn in place too.
        M = X_refs.reshape(n, 4, 3)
        with np.errstate(invalid="ignore"):
            d = np.sqrt(np.sum(kept * np.sum((P - M) ** 2, axis=2), axis=1) / kept.sum(axis=1))
        d = np.where(good, d, np.inf)
        pred = self._sigmas(fit, xy, np.repeat(frames, 4, axis=0), np.repeat(origins, 4, axis=0))[0]
        pred = np.where(np.isfinite(pred) & (pred > 0), pred, np.inf) / math.sqrt(2.0)
        u2 = (d / pred) ** 2  # chi-square (2 dof) for a reference in place
        factor = max(robust_sigma(u2[inl], 0, 0.0), 1.0)
        fit.ref_sigma = factor
        q = self._ref_q
        new, thr = [], {}
        for k, i in enumerate(refs):
            thr[i] = float(math.sqrt(q) * factor * pred[k])
            ok = (dis[i] <= self.threshold if self.threshold is not None
                  else bool(good[k]) and u2[k] <= q * factor ** 2)
            if ok:
                new.append(i)
        fit.thresholds = thr
        return new, keep

    # ------------------------------------------------------------------ estimate
    def _solve(self, observations, world_map, exclude, camera):
        """The camera fit: (fit, refs, inliers, disagreement, obs), or an ``Estimate.failed``."""
        if camera is None:
            return Estimate.failed(self.name, "corner-pnp needs the camera intrinsics "
                                              "(camera matrix and distortion)")
        excl = set(exclude)
        obs = {o.id: o for o in (self._check(observations) if self.warm_start
                                 else check_observations(observations))}
        in_map = world_map.markers  # (MarkerMap's membership, without a method call each)
        refs = sorted(i for i, o in obs.items()
                      if i in in_map and i not in excl and o.corners is not None
                      and not o.suspect)
        if len(refs) < self.min_references:
            return Estimate.failed(self.name, f"{len(refs)} reference marker(s) with corners "
                                              f"visible, need {self.min_references}")
        ref_obs = tuple(obs[i] for i in refs)
        w = self._warm
        # Excluded markers new to the last fit (a floor marker waiting for the next paced
        # refit, kmea.pipeline) do not change it; excluding one of its references does
        # (leave-one-out), so that is solved afresh.
        reuse = self.warm_start and w is not None and not (excl and excl & set(w.refs))
        if (reuse and w.key[0] == id(world_map) and len(w.ref_obs) == len(ref_obs)
                and all(a is b for a, b in zip(w.ref_obs, ref_obs, strict=True))
                and self._same_camera(w, camera)):
            # The very observations of the last fit (a fixed camera's floor, reused by
            # kmea.incremental): the same fit, nothing to check or stack again.
            return w.fit, refs, list(w.inliers), w.dis, obs
        for i in refs:
            c = np.asarray(obs[i].corners, dtype=float)
            if c.size != 8 or not np.all(np.isfinite(c)):
                raise ValueError(f"observation id {i}: corners must be 4 finite (x, y) pixels")
        try:
            K0 = np.asarray(camera.camera_matrix, dtype=float)
            d0 = check_distortion(camera.dist_coeffs)
        except ValueError as e:
            return Estimate.failed(self.name, f"camera: {e}")
        uv_refs = self._stack_corners(refs, obs)
        warm = None
        # A fit is kept for the next call only when nothing was excluded.
        here = (id(world_map), K0.tobytes(), d0.tobytes())
        key = here if self.warm_start and not excl else None
        if reuse and w.key == here:
            if w.refs == refs and np.array_equal(w.uv, uv_refs):
                if key is not None:
                    self._warm = replace(w, ref_obs=ref_obs, camera=camera)
                return w.fit, refs, list(w.inliers), w.dis, obs  # the same fit
            same = self._warm_subset(w, refs, uv_refs)
            if same is not None:
                return w.fit, refs, same, {i: w.dis[i] for i in refs}, obs
            if key is not None:
                warm = w  # a few iterations from it
        keep_model = False
        if warm is not None:
            # A few iterations from the previous fit; references new to the fit are tried.
            R, t = warm.fit.R, warm.fit.t
            # The intrinsics model (refined or not) is the camera's: a reference set that
            # differs by a few markers (found, uncovered, hidden) keeps the previous choice
            # (its likelihood-ratio test costs a second fit); a larger change tests again.
            changed = len(set(warm.refs) ^ set(refs))
            keep_model = changed <= max(2, len(warm.refs) // 10)
            inliers = [i for i in refs if i in warm.inliers or i not in warm.refs]
            if len(inliers) < self.min_references:
                warm = None
        if warm is None:
            P = np.array([obs[i].marker2cam_t for i in refs], dtype=float)
            Q = world_map.positions(refs)
            problem = reference_problem(Q, P, self.min_references)
            if problem:
                return Estimate.failed(self.name, f"robust start: {problem}")
            try:
                start_inl, (_, Rc2w, C), _ = self._start.consensus(
                    P, Q, refs, world_map.origin_id,
                    np.array([world_map[i].normal for i in refs]),
                    footprints(list(obs.values()), world_map, refs))
            except ValueError as e:
                return Estimate.failed(self.name, f"robust start: {e}")
            # The similarity maps the camera origin to C; its rotation is the camera's.
            R, t = Rc2w.T, -Rc2w.T @ C
            inliers = [i for i, k in zip(refs, start_inl, strict=True) if k]
        row = {i: k for k, i in enumerate(refs)}
        X_refs = np.concatenate([world_map[i].corners_world() for i in refs])
        xy_refs = None
        fit = None
        keep = {i: np.ones(4, bool) for i in refs}
        if warm is not None and warm.fit.keep is not None:
            keep.update({i: k.copy() for i, k in warm.fit.keep.items() if i in keep})
        for _ in range(8):
            sel = np.concatenate([4 * row[i] + np.flatnonzero(keep[i]) for i in inliers])
            prev = (fit.K, fit.d) if fit is not None else (
                (warm.fit.K, warm.fit.d) if warm is not None and warm.fit.refine else None)
            if self.refine_intrinsics == "auto" and keep_model:
                # The same references, their corners moved a little (a reference's corners
                # averaged over one more look): the previous model choice stands; a few LM
                # iterations from the previous fit, no second model.
                fit = self._lm(X_refs[sel], uv_refs[sel], R, t, K0, d0, warm.fit.refine,
                               prev)
                if fit is not None:
                    fit.refine_test = warm.fit.refine_test
            elif self.refine_intrinsics == "auto":
                fit, test = self._select(X_refs[sel], uv_refs[sel], R, t, K0, d0)
                if fit is not None:
                    fit.refine_test = test
            else:
                fit = self._lm(X_refs[sel], uv_refs[sel], R, t, K0, d0,
                               bool(self.refine_intrinsics),
                               prev)
            if fit is None:
                return Estimate.failed(self.name, "reprojection fit failed (camera behind markers)")
            refine = fit.refine
            R, t = fit.R, fit.t
            if refine:
                xy = undistort(uv_refs, fit.K, fit.d)
            else:
                xy = xy_refs = undistort(uv_refs, K0, d0) if xy_refs is None else xy_refs
            dis = self._disagreement(fit, refs, xy, world_map)
            new, new_keep = self._consensus(fit, refs, inliers, X_refs, uv_refs, xy, dis,
                                            world_map, obs)
            if new == inliers and all(np.array_equal(new_keep[i], keep[i]) for i in new):
                break
            keep = new_keep
            if len(new) < self.min_references:
                rule = (f"within {self.threshold * 1e3:.0f} mm" if self.threshold is not None
                        else f"within their corner noise ({fit.corner_sigma:.2f} px)")
                return Estimate.failed(
                    self.name, f"no consensus: {len(new)} of {len(refs)} references agree "
                               f"{rule}")
            inliers = new
        fit.keep = {i: keep[i] for i in inliers}
        if key is not None:
            self._warm = _Warm(key, refs, uv_refs, fit, tuple(inliers), dis, ref_obs, camera)
        return fit, refs, inliers, dis, obs

    def _same_camera(self, w: _Warm, camera: CameraIntrinsics) -> bool:
        """Is ``camera`` the one of the warm fit: the same object, or the same numbers (a
        camera model hands out a new intrinsics object per call)? The last camera's arrays
        as given (bytes, dtype, shape) are kept with their checked form, so the usual call
        only compares bytes."""
        if w.camera is camera:
            return True
        K, d = np.asarray(camera.camera_matrix), np.asarray(camera.dist_coeffs)
        raw = (K.dtype.str, K.shape, K.tobytes(), d.dtype.str, d.shape, d.tobytes())
        last = self._camera_raw
        if last is None or last[0] != raw:
            try:
                key = (np.asarray(K, dtype=float).tobytes(), check_distortion(d).tobytes())
            except (ValueError, TypeError):
                return False
            self._camera_raw = last = (raw, key)
        return last[1] == w.key[1:]

    def _warm_subset(self, warm: _Warm, refs: list[int], uv_refs: np.ndarray
                     ) -> list[int] | None:
        """The previous fit's inliers among ``refs`` when ``refs`` are some of the previous
        fit's references with bit-identical corners (markers hidden, e.g. by a passing
        robot, and nothing else changed: the fit of the larger set stands; None otherwise."""
        old = {i: k for k, i in enumerate(warm.refs)}
        if len(refs) >= len(old) or any(i not in old for i in refs):
            return None
        prev = warm.uv.reshape(-1, 4, 2)
        rows = [old[i] for i in refs]
        if not np.array_equal(prev[rows], uv_refs.reshape(-1, 4, 2)):
            return None
        inl = [i for i in refs if i in warm.inliers]
        return inl if len(inl) >= self.min_references else None

    def estimate(
        self,
        observations: Sequence[MarkerObservation],
        world_map: MarkerMap,
        exclude: Collection[int] = (),
        camera: CameraIntrinsics | None = None,
        plane_heights: Mapping[int, float] | None = None,
    ) -> Estimate:
        """World pose of every observed marker; see the module docstring.

        camera is required; plane_heights: id -> height (m) of horizontal non-map markers.
        """
        return self._estimate_from(self._solve(observations, world_map, exclude, camera),
                                   world_map, plane_heights)

    def _estimate_from(self, res, world_map: MarkerMap,
                       plane_heights: Mapping[int, float] | None) -> Estimate:
        """The Estimate of a camera fit (:meth:`_solve`'s result)."""
        if isinstance(res, Estimate):
            return res
        fit, refs, inliers, dis, obs = res
        planes: dict[int, unknown_plane_mod.PlaneChoice] = {}
        heights = dict(plane_heights or {})
        dropped: dict[int, int] = {}
        markers = self._placed_markers(fit, obs, world_map, heights, inliers, planes, dropped,
                                       refs)
        rejected, turned, displaced, threshold, cam2world = self._report(fit, refs, inliers,
                                                                          markers, world_map)
        info = {"displaced": displaced, "turned": turned,
                "reprojection_rms_px": fit.rms_px,
                "sigma_px": fit.sigma_px, "corner_sigma_px": fit.corner_sigma,
                "iterations": fit.iterations, "threshold": threshold,
                "thresholds": dict(fit.thresholds or {}), "corners_dropped": dropped,
                "intrinsics_refined": fit.refine}
        if math.isfinite(fit.refine_test):
            info["intrinsics_test"] = fit.refine_test
        if planes:
            info["unknown_planes"] = {i: c.kind for i, c in planes.items()}
            info["plane_statistics"] = {i: c.statistic for i, c in planes.items()}
            info["plane_geometry"] = {i: c.plane for i, c in planes.items()}
        if fit.refine:
            info.update(fx=float(fit.K[0, 0]), fy=float(fit.K[1, 1]), k1=float(fit.d[0]))
        return Estimate(
            algorithm=self.name, ok=True, markers=markers, references=tuple(inliers),
            cam2world=cam2world, scale=1.0,
            residuals={i: dis[i] for i in inliers}, rejected=rejected, info=info)

    def _report(self, fit: _Fit, refs: Sequence[int], inliers: Sequence[int],
                markers: Mapping[int, MarkerEstimate], world_map: MarkerMap) -> tuple:
        """(rejected, turned, displaced, threshold, cam2world) of an Estimate: a rejected
        reference is reported by how far its centre moved in its map plane and how much it
        turned there (it was rejected on its corners' RMS disagreement). With the warm start
        the last report is reused (copied) while the fit, the map and the rejected
        references' placements are the same objects."""
        inl = set(inliers)
        out_ids = tuple(i for i in refs if i not in inl)
        placed = tuple(markers[i] for i in out_ids)
        last = self._last_report
        if (self.warm_start and last is not None and last[0] is fit and last[1] is world_map
                and last[2] == out_ids and all(a is b for a, b in zip(last[3], placed,
                                                                     strict=True))):
            rejected, turned, displaced, threshold, cam2world = last[4]
            return dict(rejected), dict(turned), list(displaced), threshold, cam2world.copy()
        rejected, turned = {}, {}
        for i, me in zip(out_ids, placed, strict=True):
            mk = world_map[i]
            rejected[i] = float(np.linalg.norm(me.position - mk.position))
            M = mk.rotation.T @ me.rotation
            turned[i] = math.atan2(M[1, 0], M[0, 0])
        threshold = (self.threshold if self.threshold is not None
                     else float(np.median(list(fit.thresholds.values()))))
        Rc2w = fit.R.T
        report = (rejected, turned, describe_rejected(rejected, turned), threshold,
                  make_transform(Rc2w, -Rc2w @ fit.t))
        if self.warm_start:
            self._last_report = (fit, world_map, out_ids, placed, report)
            rejected, turned, displaced, threshold, cam2world = report
            return dict(rejected), dict(turned), list(displaced), threshold, cam2world.copy()
        return report

    def place_on_planes(self, ids: Sequence[int], corners: np.ndarray,
                        lengths: Sequence[float], world_map: MarkerMap,
                        plane_heights: Mapping[int, float]) -> dict[int, MarkerEstimate] | None:
        """With the warm start's last camera fit: world poses and sigmas of markers of known
        plane height (``plane_heights``; a fixed camera's robots) from their corners alone,
        as :meth:`estimate` places them with that fit (ray-plane points, corner test, square
        fit; no IPPE pose needed). ids (n,); corners (n, 4, 2) px; lengths (n,) m. None
        without a last fit, or when a marker is in the map or has no known height."""
        w = self._warm
        if (not self.warm_start or w is None or not len(ids)
                or any(i in world_map or i not in plane_heights for i in ids)):
            return None
        obs = {i: MarkerObservation(i, _NO_POSE_R, _NO_POSE_T,
                                    np.asarray(c, dtype=float).reshape(4, 2), float(L))
               for i, c, L in zip(ids, corners, lengths, strict=True)}
        dropped: dict[int, int] = {}
        out = self._markers(w.fit, obs, world_map, plane_heights, dropped=dropped)
        # Entered as placements of this fit: the frame's estimate, placing the same markers
        # with the same corners from the same fit, takes them (see _placed_markers).
        old = self._placements(w.fit, world_map)
        for i, me in out.items():
            old[i] = (obs[i], plane_heights.get(i), me, None, dropped.get(i, -1))
        return out

    def placed_observations(self, placed: Mapping[int, MarkerEstimate], ids: Sequence[int],
                            corners: np.ndarray, lengths: Sequence[float]
                            ) -> dict[int, MarkerObservation]:
        """Camera-frame observations of markers :meth:`place_on_planes` placed (``placed``,
        for its ``ids`` (n,), ``corners`` (n, 4, 2) px, ``lengths`` (n,) m), from those
        placements and the last camera fit instead of an IPPE pose per marker: marker2cam =
        world2cam of the fit after the placement's marker2world, the reprojection error of the
        placed square against the corners (px, RMS), one solution, not ambiguous (the plane
        is known). Markers not placed are left out; {} without a last fit."""
        w = self._warm
        sel = [k for k, i in enumerate(ids) if i in placed]
        if w is None or not sel:
            return {}
        fit = w.fit
        R = np.stack([fit.R @ placed[ids[k]].rotation for k in sel])            # (m, 3, 3)
        t = np.stack([fit.R @ placed[ids[k]].position + fit.t for k in sel])    # (m, 3)
        local = np.stack([marker_corners_local(float(lengths[k])) for k in sel])  # (m, 4, 3)
        cam = np.einsum("mij,mkj->mki", R, local) + t[:, None, :]
        uv = project(cam.reshape(-1, 3), fit.K, fit.d).reshape(-1, 4, 2)
        c = np.asarray(corners, dtype=float)[sel].reshape(-1, 4, 2)
        err = np.sqrt(((uv - c) ** 2).sum(axis=2).mean(axis=1))
        return {ids[k]: MarkerObservation(ids[k], R[j], t[j], c[j], float(lengths[k]),
                                          float(err[j]))
                for j, k in enumerate(sel)}

    def _placements(self, fit: _Fit, world_map: MarkerMap) -> dict:
        """The placements entered for ``fit`` and ``world_map`` (a new, empty table when the
        fit or the map changed)."""
        if self._placed is None or self._placed[0] is not fit or self._placed[1] is not world_map:
            self._placed = (fit, world_map, {})
        return self._placed[2]

    def _placed_markers(self, fit: _Fit, obs: Mapping[int, MarkerObservation],
                        world_map: MarkerMap, plane_heights: Mapping[int, float],
                        inliers: Sequence[int],
                        planes: dict[int, unknown_plane_mod.PlaneChoice],
                        dropped: dict[int, int], scale_refs: Sequence[int]
                        ) -> dict[int, MarkerEstimate]:
        """:meth:`_markers`, reusing the placements of the same fit for markers whose
        observation is the same object (warm start only; see ``_placed``)."""
        if not self.warm_start or self._warm is None or self._warm.fit is not fit:
            return self._markers(fit, obs, world_map, plane_heights, inliers, planes,
                                 dropped=dropped, scale_refs=scale_refs)
        old = self._placements(fit, world_map)
        out: dict[int, MarkerEstimate] = {}
        todo: set[int] = set()
        for i, o in obs.items():
            hit = old.get(i)
            if hit is not None and hit[1] == plane_heights.get(i) and (
                    hit[0] is o or (hit[1] is not None and _same_square(hit[0], o))):
                out[i] = hit[2]
                if hit[3] is not None:
                    planes[i] = hit[3]
                if hit[4] >= 0:
                    dropped[i] = hit[4]
            else:
                todo.add(i)
        if todo:
            out.update(self._markers(fit, obs, world_map, plane_heights, inliers, planes,
                                     only=todo, dropped=dropped, scale_refs=scale_refs))
        # Only the new placements are entered (the others are there already); an entry of
        # a marker out of view stays: it is reused only for the very same observation object
        # (or, of a marker of given height, the same corners and side).
        for i in todo:
            if i in out:
                old[i] = (obs[i], plane_heights.get(i), out[i], planes.get(i),
                          dropped.get(i, -1))
        return {i: out[i] for i in obs if i in out}

    def _markers(self, fit: _Fit, obs: Mapping[int, MarkerObservation], world_map: MarkerMap,
                 plane_heights: Mapping[int, float], inliers: Sequence[int] = (),
                 planes: dict[int, unknown_plane_mod.PlaneChoice] | None = None,
                 only: Collection[int] | None = None,
                 dropped: dict[int, int] | None = None,
                 scale_refs: Sequence[int] | None = None) -> dict[int, MarkerEstimate]:
        """World pose and sigma of every observed marker (of ``only`` if given; the others
        still inform the depth scale); ``planes`` receives id -> the choice made for each
        marker without a known plane, ``dropped`` id -> the index of a corner its own square
        contradicts (left out of its pose); ``scale_refs``: the references whose distance
        ratios give the free markers' depth scale (default ``inliers``)."""
        all_obs = obs
        if only is not None:
            obs = {i: o for i, o in obs.items() if i in only}
        Rc2w = fit.R.T
        C = -Rc2w @ fit.t

        def by_pnp(o: MarkerObservation) -> MarkerEstimate:
            Rw = Rc2w @ np.asarray(o.marker2cam_R, dtype=float)
            return MarkerEstimate(o.id, Rc2w @ np.asarray(o.marker2cam_t, float) + C, Rw,
                                  yaw_of(Rw))

        frames = _plane_frames([i for i in obs if obs[i].corners is not None], world_map,
                               plane_heights)
        out = {i: by_pnp(o) for i, o in obs.items() if i not in frames}
        unknown = [i for i in out if obs[i].corners is not None and i not in world_map]
        if unknown and inliers:
            # Every reference in view: a displaced one barely changes its distance ratio
            # (centimetres over metres), and the median takes care of the rest.
            scale = self._depth_scale(fit, all_obs, world_map,
                                      inliers if scale_refs is None else scale_refs)
            cands = unknown_plane_mod.map_planes(world_map)
            for i in unknown:
                o = obs[i]
                ch = unknown_plane_mod.infer(
                    fit.R, fit.t, fit.K, fit.d, np.asarray(o.corners, float), o.length, cands,
                    fit.sigma_px, o.marker2cam_R, o.marker2cam_t, scale, self.unknown_plane,
                    self.plane_level, corner_sigma=self._corner_sigma(fit),
                    corner_threshold=self._corner_q)
                if ch.dropped >= 0 and dropped is not None:
                    dropped[i] = ch.dropped
                out[i] = MarkerEstimate(i, ch.position, ch.rotation, yaw_of(ch.rotation))
                if planes is not None:
                    planes[i] = ch
        if not frames:
            return out
        ids = list(frames)
        uv = self._stack_corners(ids, obs)
        xy = undistort(uv, fit.K, fit.d)
        F, O = self._corner_planes(ids, frames)
        sig, P = self._sigmas(fit, xy, F, O)
        P = P.reshape(-1, 4, 3)
        Fm = F[::4]
        lengths = np.array([world_map[i].length if i in world_map else obs[i].length
                            for i in ids])
        good = np.isfinite(P).all(axis=(1, 2))
        centres, Rw, drop = self._square_poses(fit, P, Fm, lengths, uv.reshape(-1, 4, 2), good)
        if dropped is not None:
            dropped.update({i: int(drop[k]) for k, i in enumerate(ids) if drop[k] >= 0})
        for k, i in enumerate(ids):
            if not good[k]:  # plane behind the camera or parallel to the rays: PnP pose
                out[i] = by_pnp(obs[i])
            else:
                out[i] = MarkerEstimate(i, centres[k], Rw[k], yaw_of(Rw[k]), float(sig[k]))
        return out

    def _corner_planes(self, ids: Sequence[int], frames: Mapping[int, tuple]
                       ) -> tuple[np.ndarray, np.ndarray]:
        """Each corner's plane frame (4n, 3, 3) and origin (4n, 3) of the markers ``ids``
        (4 rows each); the last set is kept (read-only), as the robots' planes are the same
        frame after frame."""
        key = tuple((i, frames[i][0].tobytes(), frames[i][1].tobytes()) for i in ids)
        last = self._planes
        if last is not None and last[0] == key:
            return last[1], last[2]
        F = np.repeat(np.array([frames[i][0] for i in ids]), 4, axis=0)
        O = np.repeat(np.array([frames[i][1] for i in ids]), 4, axis=0)
        F.flags.writeable = False
        O.flags.writeable = False
        self._planes = (key, F, O)
        return F, O

    def _corner_sigma(self, fit: _Fit) -> float:
        """The corner noise (px) the per-marker corner tests use: the consensus's robust
        level, or the fit's residual level for a fit that did not measure it."""
        s = fit.corner_sigma
        return s if math.isfinite(s) else max(fit.sigma_px, SIGMA_FLOOR_PX)

    def _square_poses(self, fit: _Fit, P: np.ndarray, frames: np.ndarray, lengths: np.ndarray,
                      uv: np.ndarray, good: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Centres (n, 3), rotations (n, 3, 3) and dropped corner (n,) (-1: none) of n squares
        from their corners' ray-plane points P (n, 4, 3): the 4-corner fit, then the
        leave-one-corner-out test (:func:`corner_outliers`) and the 3-corner fit where a
        corner is dropped. Rows not ``good`` (non-finite P) are left as they come."""
        centres, Rw = square_pose(P, frames, lengths)
        if good.all():
            drop, _, _ = corner_outliers(fit.R, fit.t, fit.K, fit.d, uv, centres, Rw, lengths,
                                         self._corner_sigma(fit), self._corner_q)
        else:
            drop = np.full(len(P), -1, dtype=int)
            if not np.any(good):
                return centres, Rw, drop
            g = np.flatnonzero(good)
            d_g, _, _ = corner_outliers(fit.R, fit.t, fit.K, fit.d, uv[g], centres[g], Rw[g],
                                        lengths[g], self._corner_sigma(fit), self._corner_q)
            drop[g] = d_g
        sel = np.flatnonzero(drop >= 0)
        if sel.size:
            keep = np.ones((sel.size, 4), bool)
            keep[np.arange(sel.size), drop[sel]] = False
            centres[sel], Rw[sel] = square_pose(P[sel], frames[sel], lengths[sel], keep)
        return centres, Rw, drop

    @staticmethod
    def _depth_scale(fit: _Fit, obs: Mapping[int, MarkerObservation], world_map: MarkerMap,
                     inliers: Sequence[int]) -> float:
        """Median ratio of the inliers' fitted camera distances to their own PnP distances
        (1 when they agree): what the references show about single-marker depth."""
        X = world_map.positions(list(inliers))
        fitted = np.linalg.norm(X @ fit.R.T + fit.t, axis=1)
        own = np.linalg.norm(np.array([obs[i].marker2cam_t for i in inliers], float), axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            s = float(np.median(fitted / own))
        return s if math.isfinite(s) and s > 0 else 1.0

    @staticmethod
    def _consts(fit: _Fit) -> _FitConsts:
        """The fit's per-fit constants (:class:`_FitConsts`), computed on first use."""
        c = fit.consts
        if (c is not None and c.of[0] is fit.R and c.of[1] is fit.t and c.of[2] is fit.H
                and c.of[3] == fit.sigma_px):
            return c
        try:
            cov = fit.sigma_px ** 2 * np.linalg.inv(fit.H)
        except np.linalg.LinAlgError:
            cov = None
        # The six perturbed poses of _update: three rotation increments, three translations.
        h = _H_STEP
        Rs = np.repeat(fit.R[None], 6, axis=0)
        ts = np.repeat(fit.t[None], 6, axis=0)
        for k in range(3):
            Rs[k] = rotvec_to_matrix(h * np.eye(3)[k]) @ fit.R
            ts[3 + k, k] += h
        c = _FitConsts((fit.R, fit.t, fit.H, fit.sigma_px), -fit.R.T @ fit.t, cov, Rs,
                       -np.einsum("kji,kj->ki", Rs, ts))
        fit.consts = c
        return c

    def _sigmas(self, fit: _Fit, xy: np.ndarray, F: np.ndarray, O: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
        """1-sigma (RMS) centre error (m) per marker (n,), and the ray-plane points (4n, 3)
        (:meth:`_intersect`'s); xy (4n, 2) holds 4 normalized corners per marker, F (4n, 3,
        3) and O (4n, 3) their planes.

        First order: Cov = Jp Cov_params Jp^T + sigma_px^2 sum_k Ju_k Ju_k^T / 16 with Jp the
        centre's derivative in the fitted parameters and Ju_k in corner k's pixel; only its
        trace is formed. The derivatives are numerical (the plane intersection is cheap)
        with the step _H_STEP, the points and their xy steps in one product.
        """
        N = len(xy)
        n = N // 4
        c = self._consts(fit)
        h = _H_STEP
        X = np.empty((3, N, 3))  # the rays (x, y, 1), then with x + h, then with y + h
        X[:, :, :2] = xy
        X[:, :, 2] = 1.0
        X[1, :, 0] += h
        X[2, :, 1] += h
        normals = F[:, :, 2]
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            num = np.add.reduce(normals * (O - c.C), axis=-1)
            hits = _plane_hits(c.C, (X.reshape(-1, 3) @ fit.R).reshape(3, N, 3), normals, num)
            P = hits[0]
            if c.cov is None:
                return np.full(n, np.nan), P
            dP = (hits[1:] - P) / h  # (2, N, 3): d P / d x, d P / d y per corner
            # Pose: the rays stay, the camera moves; the six perturbed poses of _update.
            rays = np.einsum("nj,kji->kni", X[0], c.Rs)                 # (6, N, 3) world
            Cs = c.Cs[:, None, :]
            Pk = _plane_hits(Cs, rays, normals, np.add.reduce(normals * (O - Cs), axis=-1))
            Jc = (np.add.reduce(((Pk - P) / h).reshape(6, n, 4, 3), axis=2) / 4.0
                  ).reshape(6, -1)
        if fit.refine:
            # Intrinsics move the rays: distort(xy) = (uv - c) / (K0 m) at fixed pixels, so
            # d xy / d m = -Jd^-1 xd / m and d xy / d k1 = -Jd^-1 d distort / d k1.
            xd, Jd, dk1 = distort(xy, fit.d, jac=True)
            Jd_inv = np.linalg.inv(Jd)
            m = fit.K[0, 0] / fit.K0[0, 0]
            dP_dxy = dP.transpose(1, 2, 0)
            Jc = np.concatenate([Jc, np.empty((2, Jc.shape[1]))])
            for k, rhs in ((6, -xd / m), (7, -dk1)):
                dxy = np.einsum("nij,nj->ni", Jd_inv, rhs)
                Jc[k] = np.einsum("nij,nj->ni", dP_dxy, dxy).reshape(n, 4, 3).mean(axis=1
                                                                                 ).reshape(-1)
            j00, j01, j10, j11 = Jd[:, 0, 0], Jd[:, 0, 1], Jd[:, 1, 0], Jd[:, 1, 1]
        else:
            j00, j01, j10, j11 = distort_jacobian_entries(xy[:, 0], xy[:, 1], fit.d)
        # Jc (p, 3n): column (marker, axis); the trace of Jc^T cov Jc per marker.
        var = np.add.reduce((np.add.reduce((c.cov @ Jc) * Jc, axis=0)).reshape(n, 3), axis=1)
        # Own corner noise: d P / d uv = d P / d xy (d uv / d xy)^-1, per corner, with
        # d uv / d xy = diag(fx, fy) Jd and Jd^-1 in closed form.
        det = j00 * j11 - j01 * j10
        if not (det != 0.0).all():
            np.linalg.inv(distort_jacobian(xy, fit.d))  # singular: the error inv() gives
        sx, sy = det * fit.K[0, 0], det * fit.K[1, 1]
        u0 = dP[0] * (j11 / sx)[:, None] - dP[1] * (j10 / sx)[:, None]
        u1 = dP[1] * (j00 / sy)[:, None] - dP[0] * (j01 / sy)[:, None]
        own = np.add.reduce((u0 * u0 + u1 * u1).reshape(n, 12), axis=1)
        return np.sqrt(var + fit.sigma_px ** 2 / 16.0 * own), P

    # ------------------------------------------------------------------ leave-one-out
    def _loo_steps(self, fit: _Fit, refs, inliers, J, Jw, r, g, uv_refs, xy_full, frames,
                   origins, lengths, drop) -> dict[int, np.ndarray]:
        """One Gauss-Newton step per left-out consensus reference, all at once."""
        n, p = len(inliers), J.shape[1]
        Jk, Jwk, rk = J.reshape(n, 8, p), Jw.reshape(n, 8, p), r.reshape(n, 8)
        Hs = fit.H[None] - np.swapaxes(Jwk, 1, 2) @ Jk
        gs = g[None] - np.einsum("nkp,nk->np", Jwk, rk)
        try:
            deltas = -np.linalg.solve(Hs, gs[:, :, None])[:, :, 0]
        except np.linalg.LinAlgError:
            return {}
        R = rotvecs_to_matrices(deltas[:, :3]) @ fit.R
        t = fit.t[None] + deltas[:, 3:6]
        pos = {i: k for k, i in enumerate(refs)}
        rows = np.array([np.arange(4 * pos[i], 4 * pos[i] + 4) for i in inliers])  # (n, 4)
        xy0 = xy_full[rows]
        xy = xy0.copy()
        if fit.refine:
            # The intrinsics move by ~1e-4 relative: first order in (f, k1) is exact enough.
            h = 1e-6
            uv = uv_refs[rows].reshape(-1, 2)
            for col, (dK, dd) in ((6, (h, 0.0)), (7, (0.0, h))):
                K2, d2 = fit.K.copy(), fit.d.copy()
                K2[0, 0] *= 1.0 + dK * fit.K0[0, 0] / fit.K[0, 0]
                K2[1, 1] *= 1.0 + dK * fit.K0[0, 0] / fit.K[0, 0]
                d2[0] += dd
                dxy = (undistort(uv, K2, d2).reshape(n, 4, 2) - xy0) / h
                xy = xy + dxy * deltas[:, col, None, None]
        P = _batched_plane_points(R, t, xy, frames[rows[:, 0]], origins[rows[:, 0]])
        ok = np.all(np.isfinite(P), axis=(1, 2))
        k_ref = np.array([pos[i] for i in inliers])
        keep = np.ones((n, 4), bool)
        d = drop[k_ref]
        keep[np.flatnonzero(d >= 0), d[d >= 0]] = False
        centres, _ = square_pose(np.where(ok[:, None, None], P, 0.0), frames[rows[:, 0]],
                                 lengths[k_ref], keep)
        return {i: centres[k] for k, i in enumerate(inliers) if ok[k]}

    def estimate_with_loo(
        self,
        observations: Sequence[MarkerObservation],
        world_map: MarkerMap,
        exclude: Collection[int] = (),
        camera: CameraIntrinsics | None = None,
        plane_heights: Mapping[int, float] | None = None,
        loo_ids: Collection[int] | None = None,
    ) -> EstimateWithLoo:
        """The estimate and its leave-one-out (:mod:`kmea.estimators.base`) from ONE camera
        fit, held by the returned object (no cache in the estimator).

        Leave-one-out of a reference j of the fit, by the definition ``estimate(exclude={j})``
        computed fast: one Gauss-Newton step from the full solution with j's rows removed
        (H - J_j^T W_j J_j, g - J_j^T W_j r_j), a 6x6 (8x8) solve for all references at once,
        instead of a robust start and an LM per marker. Removing one of many references
        moves the optimum little, so one step lands on it to second order (under 1e-6 m on
        the simulated floor with 0.2 px of corner noise; the tests compare with
        ``estimate(exclude={j})``). A rejected reference is not in the fit, so its position
        is the full fit's. Every other marker (no corners, a known plane height, too few
        references left, a failed fit) goes through ``estimate(exclude={j})`` itself.
        """
        res = self._solve(observations, world_map, exclude, camera)
        est = self._estimate_from(res, world_map, plane_heights)

        def loo() -> tuple[dict[int, np.ndarray], dict[int, str]]:
            # Computed when asked for (a tracked frame whose floor did not change never is).
            ids = (loo_candidates(observations, world_map, exclude) if loo_ids is None
                   else sorted(set(loo_ids)))
            fast = {} if isinstance(res, Estimate) else self._fast_loo(res, world_map)
            heights = plane_heights or {}
            fast = {i: p for i, p in fast.items() if i in set(ids) and i not in heights}
            pos, fail = loo_by_exclusion(self, observations, world_map,
                                         [i for i in ids if i not in fast], exclude, camera,
                                         plane_heights)
            pos.update(fast)
            return pos, fail

        return EstimateWithLoo(est, world_map, loo)

    def _fast_loo(self, res, world_map: MarkerMap) -> dict[int, np.ndarray]:
        """id -> leave-one-out position of the fit's references (see
        :meth:`estimate_with_loo`); references the one-step update cannot give are omitted."""
        fit, refs, inliers, _, obs = res
        X = np.concatenate([world_map[i].corners_world() for i in inliers])
        uv = self._stack_corners(inliers, obs)
        r, J = self._residuals(X, uv, fit.R, fit.t, fit.K, fit.d, fit.refine, True, fit.K0)
        w = huber_weights(r, self.huber_px)
        if fit.keep is not None:  # the corners the fit left out weigh nothing
            w = w * np.repeat(np.concatenate([fit.keep[i] for i in inliers]), 2)
        Jw = J * w[:, None]
        g = Jw.T @ r
        if fit.refine:
            rp, Jp = self._prior_rows(fit.K, fit.d, fit.K0, fit.d0)
            g = g + Jp.T @ rp
        out: dict[int, np.ndarray] = {}
        frames = np.repeat(np.array([world_map[i].rotation for i in refs]), 4, axis=0)
        origins = np.repeat(world_map.positions(refs), 4, axis=0)
        uv_refs = self._stack_corners(refs, obs)
        xy_full = undistort(uv_refs, fit.K, fit.d)
        full = self._intersect(fit.R, fit.t, xy_full, frames, origins).reshape(-1, 4, 3)
        lengths = np.array([world_map[i].length for i in refs])
        good = np.all(np.isfinite(full), axis=(1, 2))
        # Each reference's own corner test, decided once at the full fit (a left-out
        # reference is tested the same way by estimate(exclude={j})).
        centres, _, drop = self._square_poses(fit, full, frames[::4], lengths,
                                              uv_refs.reshape(-1, 4, 2), good)
        for k, i in enumerate(refs):
            if i not in inliers and good[k]:
                out[i] = centres[k]
        if len(inliers) - 1 >= self.min_references:
            out.update(self._loo_steps(fit, refs, inliers, J, Jw, r, g, uv_refs, xy_full,
                                       frames, origins, lengths, drop))
        return out


def _batched_plane_points(R: np.ndarray, t: np.ndarray, xy: np.ndarray, frames: np.ndarray,
                          origins: np.ndarray) -> np.ndarray:
    """Ray-plane points (M, 4, 3) of M poses (R (M, 3, 3) world2cam, t (M, 3)) for each one's
    4 normalized corners xy (M, 4, 2) and plane (frames (M, 3, 3), origins (M, 3))."""
    rays = np.concatenate([xy, np.ones((*xy.shape[:2], 1))], axis=2) @ R  # R^T ray, world
    C = -np.einsum("mji,mj->mi", R, t)
    return intersect_rays_planes(C[:, None, :], rays, origins[:, None, :],
                                 frames[:, None, :, 2])
