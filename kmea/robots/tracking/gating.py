"""The gate: a measurement's innovation against a prediction, its Mahalanobis distance, and
the words for a rejection.

A measurement (x, y, theta) is gated out when its squared Mahalanobis distance d^2 to the
prediction exceeds the chi-square quantile of 3 degrees of freedom at the gate probability.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from kmea.geometry.rotations import wrap_angle

try:
    # The gufuncs behind np.linalg.inv and np.linalg.det: the same LAPACK calls, without
    # the public functions' per-call argument checks and error-state switch (most of the
    # cost of a 3x3 inverse). Private to numpy; without them, the public functions.
    from numpy.linalg import _umath_linalg as _gufuncs
except ImportError:  # pragma: no cover
    _gufuncs = None

__all__ = ["Innovation", "det3", "innovation", "inv3", "mahalanobis", "rejection_reason"]


def inv3(S: np.ndarray) -> np.ndarray:
    """np.linalg.inv of float64 ``S`` (..., 3, 3), bit for bit. A singular S gives NaN
    here (numpy warns): callers check their result and call :func:`np.linalg.inv` itself
    when it is not finite (it raises LinAlgError as before)."""
    if _gufuncs is None:  # pragma: no cover
        return np.linalg.inv(S)
    return _gufuncs.inv(S, signature="d->d")


def det3(S: np.ndarray) -> np.ndarray:
    """np.linalg.det of float64 ``S`` (..., 3, 3), bit for bit (the same gufunc call)."""
    if _gufuncs is None:  # pragma: no cover
        return np.linalg.det(S)
    return _gufuncs.det(S, signature="d->d")


def mahalanobis(y: list, Si: list) -> float:
    """y^T Si y of 3 floats and a 3x3 nested list: (y Si) y, summed in order (as numpy's
    y @ Si @ y does, bit for bit)."""
    y0, y1, y2 = y
    (a, b, c), (d, e, f), (g, h, i) = Si
    return (y0 * a + y1 * d + y2 * g) * y0 + (y0 * b + y1 * e + y2 * h) * y1 \
        + (y0 * c + y1 * f + y2 * i) * y2


class Innovation(NamedTuple):
    """A measurement against a prediction: y (3 floats: m, m, rad wrapped), its covariance
    S (3, 3) and the squared Mahalanobis distance d2."""

    y: list
    S: np.ndarray
    d2: float


def innovation(s: np.ndarray, P: np.ndarray, z: np.ndarray, R: np.ndarray
               ) -> Innovation | None:
    """Innovation of measurement ``z`` (x, y, theta) with covariance ``R`` (3, 3) against
    the predicted state ``s`` and covariance ``P``; None when S is singular."""
    s0, s1, s2 = s[:3].tolist()
    z0, z1, z2 = z.tolist()
    y = [z0 - s0, z1 - s1, wrap_angle(z2 - s2)]
    S = P[:3, :3] + R
    Si = inv3(S)
    d2 = mahalanobis(y, Si.tolist())
    if not math.isfinite(d2):
        # Singular (or overflowing) S: np.linalg.inv's own answer.
        try:
            Si = np.linalg.inv(S)
        except np.linalg.LinAlgError:
            return None
        d2 = mahalanobis(y, Si.tolist())
    return Innovation(y, S, d2)


def rejection_reason(inn: Innovation, gate: float) -> str:
    """What a rejected measurement was: a heading flip, a position or a heading jump, with
    its distance against the gate."""
    y, S, d2 = inn
    dpos = math.hypot(y[0], y[1])
    dth = abs(y[2])
    sp = math.sqrt(max(S[0, 0], S[1, 1]))
    st = math.sqrt(S[2, 2])
    if dth > math.pi / 2:
        what = f"heading flip {math.degrees(dth):.0f} deg"
    elif dpos / sp >= dth / st:
        what = f"position jump {dpos * 100:.1f} cm"
    else:
        what = f"heading jump {math.degrees(dth):.1f} deg"
    return f"{what} (d2 {d2:.1f} > gate {gate:.1f})"
