"""The outlier mixture: the covariance after an accepted measurement includes the chance
that it was an outlier, as probabilistic data association does (Bar-Shalom, Li,
Kirubarajan, ch. 11.3).

With the measurement's posterior probability q of being an outlier (prior
``outlier_probability``; an outlier's position uniform within ``outlier_radius`` m of the
robot; a good measurement's position Gaussian with the innovation covariance), the
covariance about the output is (1 - q) times that of the update taken (the measurement was
good) plus q times that of the prediction plus the step taken (it was an outlier). The
reported sigma then says how doubtful the measurement was, and the next measurements
correct the more.
"""

from __future__ import annotations

import math

import numpy as np

from kmea.robots.tracking.imm import Modes

__all__ = ["mixed", "outlier_posterior", "prior_density_ratio"]


def prior_density_ratio(outlier_probability: float, outlier_radius: float) -> float:
    """The outliers' prior odds times their position density (1/m^2): p / (1 - p) / (pi r^2)."""
    return outlier_probability / (1.0 - outlier_probability) / (
        math.pi * outlier_radius ** 2)


def outlier_posterior(s: np.ndarray, P: np.ndarray, z: np.ndarray, R: np.ndarray,
                      ratio: float) -> float:
    """The posterior probability that measurement ``z`` (with covariance ``R``) is an
    outlier, against the combined prediction ``s``, ``P``: its position innovation's
    Gaussian density against the outliers' (``ratio``: :func:`prior_density_ratio`)."""
    (p00, p01), (p10, p11) = P[:2, :2].tolist()
    (r00, r01), (_, r11) = R[:2, :2].tolist()
    a = p00 + r00
    b = 0.5 * (p01 + p10) + r01
    d = p11 + r11
    det = a * d - b * b
    if not det > 0.0:
        return 0.0
    x, y = float(z[0] - s[0]), float(z[1] - s[1])
    d2 = (d * x * x - 2.0 * b * x * y + a * y * y) / det
    good = math.exp(-0.5 * d2) / (2.0 * math.pi * math.sqrt(det))
    return ratio / (ratio + good)


def mixed(pred: Modes, updated: Modes, step: np.ndarray, q: float) -> Modes:
    """``updated`` with each mode's covariance (1 - q) P_updated + q (P_pred + step
    step^T); ``step`` (M, n): the correction each mode took."""
    if not q > 1e-9:
        return updated
    out_P = (1.0 - q) * updated.Ps + q * (pred.Ps + step[:, :, None] * step[:, None, :])
    return Modes(updated.ss, out_P, updated.mu)
