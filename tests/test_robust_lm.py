"""The generic robust Levenberg-Marquardt solver on a problem with a known answer."""

from __future__ import annotations

import numpy as np
import pytest

from kmea.estimators.robust_lm import huber_cost, huber_weights, robust_lm


def _circle_problem(seed: int, outliers: int):
    """2-D points on a circle (centre (0.3, -0.2), radius 1.5) with 0.01 noise; ``outliers``
    of them pushed 0.5 outwards. Residual: point - (centre + radius * unit direction)."""
    rng = np.random.default_rng(seed)
    a = rng.uniform(0, 2 * np.pi, 60)
    truth = np.array([0.3, -0.2, 1.5])
    P = truth[:2] + truth[2] * np.column_stack([np.cos(a), np.sin(a)])
    P += rng.normal(scale=0.01, size=P.shape)
    P[:outliers] += 0.5 * np.column_stack([np.cos(a[:outliers]), np.sin(a[:outliers])])

    def evaluate(x, jac):
        d = P - x[:2]
        n = np.linalg.norm(d, axis=1, keepdims=True)
        u = d / n
        r = (d - x[2] * u).reshape(-1)
        if not jac:
            return r
        # d r / d centre = -(I - x2 (I - u u^T) / n); d r / d radius = -u.
        eye = np.eye(2)[None]
        uu = u[:, :, None] * u[:, None, :]
        Jc = -(eye - x[2] * (eye - uu) / n[:, :, None])
        J = np.concatenate([Jc, -u[:, :, None]], axis=2).reshape(-1, 3)
        return r, J

    return truth, evaluate


@pytest.mark.parametrize("seed", [0, 1])
def test_recovers_a_known_circle_despite_outliers(seed: int) -> None:
    truth, evaluate = _circle_problem(seed, outliers=6)
    start = np.array([0.0, 0.0, 1.0])

    def solve(knee):
        return robust_lm(evaluate, lambda x, d: x + d, start,
                         weights=lambda r: huber_weights(r, knee),
                         cost=lambda r: huber_cost(r, knee), max_iterations=100)

    robust = solve(0.02)
    plain = solve(1e9)  # a knee beyond every residual: least squares
    assert robust is not None and plain is not None
    assert np.abs(robust.state - truth).max() < 0.01
    assert np.abs(plain.state - truth).max() > 2 * np.abs(robust.state - truth).max()
    assert robust.H.shape == (3, 3) and robust.iterations >= 1


def test_prior_pulls_towards_its_centre_and_invalid_start_gives_none() -> None:
    _, evaluate = _circle_problem(2, outliers=0)
    start = np.array([0.0, 0.0, 1.0])
    # A stiff prior radius = 1.0 wins over the data.
    res = robust_lm(evaluate, lambda x, d: x + d, start, weights=lambda r: np.ones_like(r),
                    cost=lambda r: float(r @ r),
                    prior=lambda x: (np.array([(x[2] - 1.0) * 1e4]),
                                     np.array([[0.0, 0.0, 1e4]])))
    assert res is not None and abs(res.state[2] - 1.0) < 1e-3
    assert robust_lm(lambda x, jac: (None, None) if jac else None, lambda x, d: x + d,
                     start, weights=lambda r: r, cost=lambda r: 0.0) is None


def test_huber_weights_and_cost() -> None:
    r = np.array([0.3, 0.4, 3.0, 4.0])  # point norms 0.5 and 5
    assert np.allclose(huber_weights(r, 1.0), [1.0, 1.0, 0.2, 0.2])
    assert huber_cost(r, 1.0) == pytest.approx(0.25 + 2 * 5 - 1)
