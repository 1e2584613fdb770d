"""The chi-square distribution: CDF and quantile (numpy-free, no scipy): the one
implementation behind every gate and significance level (tracking, estimators, survey)."""

from __future__ import annotations

import functools
import math

__all__ = ["chi2_cdf", "chi2_quantile"]


def chi2_cdf(x: float, dof: int) -> float:
    """Chi-square CDF: the regularized lower incomplete gamma P(dof/2, x/2) by its series."""
    if x <= 0:
        return 0.0
    a, z = dof / 2.0, x / 2.0
    term = 1.0 / a
    total = term
    n = 0
    while term > 1e-17 * total and n < 1000:
        n += 1
        term *= z / (a + n)
        total += term
    return min(1.0, math.exp(a * math.log(z) - z - math.lgamma(a)) * total)


@functools.lru_cache(maxsize=256)
def chi2_quantile(level: float, dof: int = 3) -> float:
    """Quantile of the chi-square distribution with ``dof`` degrees of freedom (bisection
    on the exact CDF; numpy only, no scipy)."""
    p = float(level)
    if not 0.0 < p < 1.0:
        raise ValueError(f"chi2_quantile: level must be in (0, 1), got {level!r}")
    if dof == 2:  # exact: the chi-square with 2 dof is an exponential
        return -2.0 * math.log(1.0 - p)
    lo, hi = 0.0, max(1.0, 4.0 * dof)
    while chi2_cdf(hi, dof) < p:
        hi *= 2.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if chi2_cdf(mid, dof) < p:
            lo = mid
        else:
            hi = mid
        if hi - lo < 1e-10 * hi:
            break
    return 0.5 * (lo + hi)
