"""The step bound: no accepted measurement moves the output position by more than ``step_k``
sigmas of the position covariance after it.

An outlier inside the gate would otherwise pull the track by its whole Kalman correction.
The correction is weighted by the largest w in [0, 1] for which the combined position moves
from the prediction by at most ``step_k`` sigmas of its own covariance after the update;
the covariance is that of the weighted gain (Joseph form, :meth:`ModeSet.correct`), so it
stays honest and the next measurements correct more.
"""

from __future__ import annotations

import numpy as np

from kmea.robots.tracking.imm import Gains, Modes

__all__ = ["step_weight"]

BISECTIONS = 12  # weight resolution 1/4096


def step_weight(m: Modes, g: Gains, ky: np.ndarray, pred_xy: tuple[float, float],
                step_k: float) -> float:
    """The largest weight w in [0, 1] of the modes' corrections ``ky`` (M, n: gain times
    innovation) that moves the combined position from ``pred_xy`` (the prediction's, m) by
    at most ``step_k`` sigmas of the combined position covariance after the update.

    The combined mean and covariance are polynomials in w: the mean is a0 + w a1, each
    mode's spread d_j + w e_j, so the covariance is K0 + w K1 + w^2 K2 (2 x 2). Their
    coefficients are computed once, in floats; each weight of the bisection then costs a
    few float operations.
    """
    ss, Ps, _ = m
    _, Ks, mu = g
    g2 = ky[:, :2].tolist()
    # B = Kp P[:3, :2] (Kp: the gain's position rows); the quadratic coefficient
    # C = Kp S Kp^T equals it (K = P H^T S^-1), so B stands for both below.
    Bs = (Ks[:, :2, :] @ Ps[:, :3, :2]).tolist()
    P0s = Ps[:, :2, :2].tolist()
    mul = mu.tolist()
    sl = ss[:, :2].tolist()
    p0 = q0 = p1 = q1 = 0.0
    for w, (sx, sy), (gx, gy) in zip(mul, sl, g2, strict=True):
        p0, q0, p1, q1 = p0 + w * sx, q0 + w * sy, p1 + w * gx, q1 + w * gy
    a_0 = a_1 = a_2 = b_0 = b_1 = b_2 = d_0 = d_1 = d_2 = 0.0
    for w, (sx, sy), (gx, gy), P, B in zip(mul, sl, g2, P0s, Bs, strict=True):
        dx, dy, ex, ey = sx - p0, sy - q0, gx - p1, gy - q1
        a_0 += w * (P[0][0] + dx * dx)
        a_1 += w * (2.0 * (dx * ex - B[0][0]))
        a_2 += w * (B[0][0] + ex * ex)
        b_0 += w * (0.5 * (P[0][1] + P[1][0]) + dx * dy)
        b_1 += w * (dx * ey + ex * dy - (B[0][1] + B[1][0]))
        b_2 += w * (0.5 * (B[0][1] + B[1][0]) + ex * ey)
        d_0 += w * (P[1][1] + dy * dy)
        d_1 += w * (2.0 * (dy * ey - B[1][1]))
        d_2 += w * (B[1][1] + ey * ey)
    rx, ry = float(pred_xy[0]), float(pred_xy[1])
    k2 = step_k ** 2

    def within(w: float) -> bool:
        """The step at weight w, squared Mahalanobis against the covariance after it."""
        x, y = p0 + w * p1 - rx, q0 + w * q1 - ry
        ww = w * w
        a = a_0 + w * a_1 + ww * a_2
        b = b_0 + w * b_1 + ww * b_2
        d = d_0 + w * d_1 + ww * d_2
        det = a * d - b * b
        if not det > 0.0:  # no covariance to measure the step by (or not finite): refused
            return False
        return (d * x * x - 2.0 * b * x * y + a * y * y) / det <= k2

    if within(1.0):
        return 1.0
    lo, hi = 0.0, 1.0
    for _ in range(BISECTIONS):
        mid = (lo + hi) / 2.0
        if within(mid):
            lo = mid
        else:
            hi = mid
    return lo
