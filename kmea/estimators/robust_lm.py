"""A generic robust Levenberg-Marquardt solver (numpy only).

Minimises ``cost(r(x)) + |r_prior(x)|^2`` over a state ``x`` that the caller updates on a
manifold (rotations, multipliers, ...): the caller gives the residuals and their Jacobian
in the local increment, the update ``x (+) delta``, the IRLS weights of the robust loss and
its cost. Marquardt's damping scales the diagonal of the Gauss-Newton matrix. Used by
``corner-pnp`` (:mod:`kmea.estimators.corner_pnp`) for the camera pose and intrinsics.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["LMResult", "huber_cost", "huber_weights", "robust_lm"]


@dataclass
class LMResult:
    """The solution: state, residuals r (m,), Jacobian J (m, p), the weighted Gauss-Newton
    matrix H (p, p) at the solution (prior included) and the iterations run."""

    state: Any
    r: np.ndarray
    J: np.ndarray
    H: np.ndarray
    iterations: int


def huber_weights(r: np.ndarray, knee: float, dim: int = 2) -> np.ndarray:
    """IRLS weights (m,) of Huber's loss on the norms of consecutive ``dim``-vectors of r
    (one weight per point, repeated for its ``dim`` rows); ``knee`` in r's units."""
    e = np.linalg.norm(r.reshape(-1, dim), axis=1)
    w = np.where(e <= knee, 1.0, knee / np.maximum(e, 1e-300))
    return np.repeat(w, dim)


def huber_cost(r: np.ndarray, knee: float, dim: int = 2) -> float:
    """Huber's cost: sum of e^2 below the knee, 2 knee e - knee^2 above, per point norm e."""
    e = np.linalg.norm(r.reshape(-1, dim), axis=1)
    return float(np.sum(np.where(e <= knee, e * e, 2.0 * knee * e - knee * knee)))


Residuals = Callable[[Any, bool], Any]


def robust_lm(evaluate: Residuals, update: Callable[[Any, np.ndarray], Any], state: Any,
              weights: Callable[[np.ndarray], np.ndarray], cost: Callable[[np.ndarray], float],
              prior: Callable[[Any], tuple[np.ndarray, np.ndarray]] | None = None,
              max_iterations: int = 50) -> LMResult | None:
    """Levenberg-Marquardt with IRLS weights from ``state``.

    evaluate(state, jac): residuals (m,) (None if the state is invalid), with ``jac`` the
    pair (r, J (m, p)) ((None, None) if invalid). update(state, delta (p,)): the new state.
    weights(r): IRLS weights (m,); cost(r): the robust cost. prior(state): extra residual
    rows (k,) and their Jacobian (k, p), added to the cost unweighted.
    Stops when a step is below 1e-10, the cost drops by less than 1e-14 relative, the cost
    is below 1e-26, the damping exceeds 1e8 or after ``max_iterations``. None when the
    start is invalid or a damped system is singular.
    """

    def total(r: np.ndarray, st: Any) -> float:
        c = cost(r)
        if prior is not None:
            c += float(np.sum(prior(st)[0] ** 2))
        return c

    r, J = evaluate(state, True)
    if r is None:
        return None
    c = total(r, state)
    lam = 1e-6
    iterations = 0
    for it in range(1, max_iterations + 1):
        iterations = it
        w = weights(r)
        H = J.T @ (J * w[:, None])
        g = J.T @ (w * r)
        if prior is not None:
            rp, Jp = prior(state)
            H = H + Jp.T @ Jp
            g = g + Jp.T @ rp
        done = False
        while True:
            A = H + lam * np.diag(np.diag(H) + 1e-12)
            try:
                delta = -np.linalg.solve(A, g)
            except np.linalg.LinAlgError:
                return None
            state2 = update(state, delta)
            r2 = evaluate(state2, False)
            c2 = math.inf if r2 is None else total(r2, state2)
            if c2 <= c:
                state = state2
                # Steps of 1e-10 (rad, m, relative focal) leave errors of ~1e-20 behind.
                small = float(np.max(np.abs(delta))) < 1e-10 or c - c2 <= 1e-14 * c
                c = c2
                lam = max(lam / 10.0, 1e-12)
                done = small
                break
            lam *= 10.0
            if lam > 1e8:
                done = True
                break
        r, J = evaluate(state, True)
        if done or c < 1e-26:
            break
    w = weights(r)
    H = J.T @ (J * w[:, None])
    if prior is not None:
        Jp = prior(state)[1]
        H = H + Jp.T @ Jp
    return LMResult(state, r, J, H, iterations)
