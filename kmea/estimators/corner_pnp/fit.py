"""The camera fit of ``corner-pnp``: Levenberg-Marquardt on the reprojection error of the
references' corners, with optional intrinsics refinement and its model selection.

State ``(R, t, K, d)``: world2cam rotation (3, 3) and translation (3,) m, camera matrix
(3, 3) px and distortion (14,) (OpenCV's model). Residuals are pixels, 2 per corner.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from kmea.estimators.robust_lm import huber_cost, huber_weights, robust_lm
from kmea.geometry import project, rotation_increment_jacobian, rotvec_to_matrix

# The score test's screen before fitting the refined model: the chi-square (2 dof) 0.9
# quantile, -2 ln 0.1.
SCORE_SCREEN = 4.605

State = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]  # (R, t, K, d)


@dataclass(frozen=True)
class FitSettings:
    """What the fit reads of the estimator's options (see :class:`CornerPnP`)."""

    huber_px: float  # Huber loss knee, px
    prior_f: float  # 1-sigma of the relative focal length's prior
    prior_k1: float  # 1-sigma of k1's prior
    prior_px: float  # corner noise (px) the prior is weighed against
    max_iterations: int
    refine_threshold: float  # chi-square (2 dof) quantile of the likelihood-ratio test


@dataclass(frozen=True)
class FitConsts:
    """What placing markers with one fit needs and does not depend on the markers: computed
    once per fit (:func:`kmea.estimators.corner_pnp.uncertainty.fit_consts`), not once per
    frame (a fixed camera keeps its fit for many frames while the robots are placed again).

    version: the fit's version it was computed for; C (3,): the camera centre, world; cov
    (p, p): ``sigma_px^2 H^-1`` (None: H singular); Rs (6, 3, 3), Cs (6, 3): the world2cam
    rotations and camera centres of the six pose perturbations of the uncertainty.
    """

    version: int
    C: np.ndarray
    cov: np.ndarray | None
    Rs: np.ndarray
    Cs: np.ndarray


_versions = iter(range(1, 1 << 62))


@dataclass
class CameraFit:
    """State of one LM fit: world2cam pose, intrinsics, and what the covariance needs.

    ``version`` is unique per fit: caches of what follows from a fit are keyed on it. The
    solution (R, t, K, d, H, sigma_px) is never assigned after construction;
    ``dataclasses.replace`` makes a changed fit, with a new version.
    """

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
    ref_sigma: float = math.nan  # robust level of the references' disagreements
    keep: dict[int, np.ndarray] | None = None  # inlier id -> (4,) bool: corners the fit used
    thresholds: dict[int, float] | None = None  # reference id -> rejection threshold, m (RMS)
    consts: FitConsts | None = field(default=None, repr=False, compare=False)
    version: int = field(init=False, default_factory=lambda: next(_versions), compare=False)


def residuals(X: np.ndarray, uv: np.ndarray, R: np.ndarray, t: np.ndarray, K: np.ndarray,
              d: np.ndarray) -> np.ndarray | None:
    """Pixel residuals (2N,) of the world points X (N, 3) projected against uv (N, 2); None
    when a point is behind the camera."""
    Pc = X @ R.T + t
    if np.any(Pc[:, 2] <= 1e-9):
        return None
    return (project(Pc, K, d) - uv).reshape(-1)


def residuals_jacobian(X: np.ndarray, uv: np.ndarray, R: np.ndarray, t: np.ndarray,
                       K: np.ndarray, d: np.ndarray, refine: bool, K0: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray] | None:
    """:func:`residuals` and their Jacobian (2N, 6 or 8) in the parameters (rotation
    increment, translation[, focal multiplier of K0, k1]); None when a point is behind."""
    Pc = X @ R.T + t
    if np.any(Pc[:, 2] <= 1e-9):
        return None
    proj, J_pc, J_f, J_k1 = project(Pc, K, d, jac=True)
    J_w = rotation_increment_jacobian(J_pc, Pc - t)  # left increment exp(w) R
    cols = [J_w, J_pc]
    if refine:
        # project() differentiates a multiplier of the current K; the parameter multiplies K0.
        cols += [J_f[:, :, None] * (K0[0, 0] / K[0, 0]), J_k1[:, :, None]]
    J = np.concatenate(cols, axis=2).reshape(2 * len(X), -1)
    return (proj - uv).reshape(-1), J


def prior_rows(s: FitSettings, K: np.ndarray, d: np.ndarray, K0: np.ndarray, d0: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """The intrinsics prior as 2 residual rows (px) and their Jacobian (2, 8)."""
    pf, pk, ppx = s.prior_f, s.prior_k1, s.prior_px
    r = np.array([(K[0, 0] / K0[0, 0] - 1.0) / pf * ppx, (d[0] - d0[0]) / pk * ppx])
    J = np.zeros((2, 8))
    J[0, 6] = ppx / pf
    J[1, 7] = ppx / pk
    return r, J


def update_state(state: State, delta: np.ndarray, refine: bool, K0: np.ndarray) -> State:
    """The state moved by the parameter step ``delta`` (6,) or (8,)."""
    R, t, K, d = state
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


def fit_lm(s: FitSettings, X: np.ndarray, uv: np.ndarray, R: np.ndarray, t: np.ndarray,
           K0: np.ndarray, d0: np.ndarray, refine: bool,
           start: tuple[np.ndarray, np.ndarray] | None = None) -> CameraFit | None:
    """Minimize the Huber reprojection cost (plus the intrinsics prior, centred on the
    calibration K0, d0) from the pose (R, t) and the intrinsics ``start`` (default K0, d0)
    with :func:`kmea.estimators.robust_lm.robust_lm`."""
    K, d = (K0.copy(), d0.copy()) if start is None or not refine else start

    def evaluate(st: State, jac: bool) -> object:
        if jac:
            return residuals_jacobian(X, uv, *st, refine, K0) or (None, None)
        return residuals(X, uv, *st)

    res = robust_lm(
        evaluate,
        lambda st, delta: update_state(st, delta, refine, K0),
        (R, t, K, d),
        weights=lambda r: huber_weights(r, s.huber_px),
        cost=lambda r: huber_cost(r, s.huber_px),
        prior=(lambda st: prior_rows(s, st[2], st[3], K0, d0)) if refine else None,
        max_iterations=s.max_iterations)
    if res is None:
        return None
    R, t, K, d = res.state
    r = res.r
    dof = max(r.size - res.H.shape[0], 1)
    sigma = math.sqrt(float(r @ r) / dof)
    rms = math.sqrt(float(r @ r) / r.size)
    return CameraFit(R, t, K, K0, d, d0, res.H, sigma, rms, res.iterations, refine,
                     huber_cost(r, s.huber_px), dof)


def select_model(s: FitSettings, X: np.ndarray, uv: np.ndarray, R: np.ndarray, t: np.ndarray,
                 K0: np.ndarray, d0: np.ndarray) -> tuple[CameraFit | None, float]:
    """Model selection between the calibrated intrinsics (M0) and M0 plus a refined focal
    multiplier and k1 (M1): a likelihood-ratio (F) test. With Gaussian corner noise and M0
    true, ``(cost0 - cost1) / sigma1^2`` follows a chi-square with 2 degrees of freedom
    (sigma1^2 = cost1 / dof1, M1's residual variance); M1 is kept only above the
    ``refine_threshold`` quantile. Returns (fit, statistic).

    M1 is fitted only when the score (Lagrange multiplier) statistic at M0's solution, the
    same chi-square asymptotically and one Jacobian instead of a second fit, exceeds its 0.9
    quantile (4.6): a loose screen, so that the likelihood ratio still decides every
    borderline case (score and ratio differ with few references and model errors other than
    f and k1). With a good calibration (the usual case) M1 is then fitted in about one frame
    in ten, which halves the cost.
    """
    fit0 = fit_lm(s, X, uv, R, t, K0, d0, False)
    if fit0 is None:
        return None, math.nan
    score = score_statistic(s, X, uv, fit0, K0, d0)
    if not score > SCORE_SCREEN:
        return fit0, score
    fit1 = fit_lm(s, X, uv, fit0.R, fit0.t, K0, d0, True)
    if fit1 is None:
        return fit0, math.nan
    var1 = fit1.cost / max(fit1.dof, 1)
    stat = (fit0.cost - fit1.cost) / max(var1, 1e-30)
    return (fit1 if stat > s.refine_threshold else fit0), float(stat)


def score_statistic(s: FitSettings, X: np.ndarray, uv: np.ndarray, fit0: CameraFit,
                    K0: np.ndarray, d0: np.ndarray) -> float:
    """Score statistic g^T H^-1 g / sigma0^2 of the intrinsics parameters at M0's solution
    (g: the gradient of M1's cost there, zero in the pose parameters)."""
    rj = residuals_jacobian(X, uv, fit0.R, fit0.t, K0, d0, True, K0)
    if rj is None:
        return math.nan
    r, J = rj
    Jw = J * huber_weights(r, s.huber_px)[:, None]
    Jp = prior_rows(s, K0, d0, K0, d0)[1]
    H = J.T @ Jw + Jp.T @ Jp
    g = Jw.T @ r
    try:
        q = float(g @ np.linalg.solve(H, g))
    except np.linalg.LinAlgError:
        return math.nan
    var0 = fit0.cost / max(fit0.dof, 1)
    return q / max(var0, 1e-30)
