"""The paper's error metrics on the floor plane, numpy only.

For N estimates of one marker against its true position, the error of sample i is the
Euclidean floor-plane distance e_i = |(x_i, y_i) - (x*, y*)| in metres. Then

- RMSE  = sqrt(mean(e_i^2))
- STD   = sample standard deviation (ddof = 1) of the magnitudes e_i (NaN when N = 1)
- MAE   = mean(e_i)
- MaxAE = max(e_i)
- MRE   = MAE / reference_length * 100 (percent; the paper's reference length is the floor
  diagonal, 2.081 m)

so RMSE^2 = MAE^2 + (N - 1) / N * STD^2. STD is the paper's figure, and it depends on a
constant bias: for isotropic Gaussian noise of sigma per axis it is 0.66 sigma without bias
(Rayleigh) and tends to sigma when the bias is much larger than sigma. Two figures separate
precision from accuracy (from the estimates themselves, so only :func:`marker_metrics`
has them):

- Scatter = sqrt(var(x_i) + var(y_i)) (ddof = 1): the 2-D spread of the estimates about
  their own mean; a constant bias does not change it;
- Bias    = |(mean x_i, mean y_i) - (x*, y*)|: the constant part of the error.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass, fields, replace

import numpy as np
from numpy.typing import ArrayLike

__all__ = [
    "MarkerMetrics",
    "WindowStats",
    "marker_metrics",
    "mean_metrics",
    "metrics_from_errors",
    "percent_change",
    "planar_errors",
]


@dataclass(frozen=True)
class MarkerMetrics:
    """Error metrics of one marker (or their average over markers).

    n: number of samples (for an average: the total over markers); rmse, std, mae, maxae in
    metres; mre in percent of the reference length; scatter and bias in metres (NaN when
    computed from error magnitudes only).
    """

    n: int
    rmse: float
    std: float
    mae: float
    maxae: float
    mre: float
    scatter: float = math.nan
    bias: float = math.nan

    def as_dict(self) -> dict[str, float]:
        """Every field; scatter and bias only when known (not NaN)."""
        return {f.name: getattr(self, f.name) for f in fields(self)
                if f.name not in ("scatter", "bias") or math.isfinite(getattr(self, f.name))}


def _check_ref(reference_length: float) -> float:
    r = float(reference_length)
    if not (math.isfinite(r) and r > 0.0):
        raise ValueError(f"reference_length must be a finite length > 0 m, "
                         f"got {reference_length!r}")
    return r


def planar_errors(estimates: ArrayLike, truth: ArrayLike) -> np.ndarray:
    """(N,) floor-plane distances (m) of estimates (N, 2) or (N, 3) to truth (2,) or (3,);
    only x and y are used."""
    est = np.asarray(estimates, dtype=float)
    if est.ndim == 1:
        est = est[None, :]
    tru = np.asarray(truth, dtype=float).reshape(-1)
    if est.ndim != 2 or est.shape[1] not in (2, 3) or tru.shape[0] not in (2, 3):
        raise ValueError(f"estimates must be (N, 2) or (N, 3) and truth (2,) or (3,), got "
                         f"{est.shape} and {tru.shape}")
    if not (np.all(np.isfinite(est)) and np.all(np.isfinite(tru))):
        raise ValueError("estimates and truth must be finite")
    return np.hypot(est[:, 0] - tru[0], est[:, 1] - tru[1])


def metrics_from_errors(errors: Iterable[float] | np.ndarray,
                        reference_length: float) -> MarkerMetrics:
    """Metrics of error magnitudes e_i >= 0 (m); see the module docstring."""
    ref = _check_ref(reference_length)
    e = np.asarray(list(errors) if not isinstance(errors, np.ndarray) else errors,
                   dtype=float).reshape(-1)
    if e.size == 0:
        raise ValueError("no samples")
    if not np.all(np.isfinite(e)) or np.any(e < 0):
        raise ValueError("errors must be finite distances >= 0 m")
    mae = float(e.mean())
    return MarkerMetrics(
        n=int(e.size),
        rmse=float(np.sqrt(np.mean(e**2))),
        std=float(e.std(ddof=1)) if e.size > 1 else math.nan,
        mae=mae,
        maxae=float(e.max()),
        mre=mae / ref * 100.0,
    )


def marker_metrics(estimates: np.ndarray, truth: np.ndarray,
                   reference_length: float) -> MarkerMetrics:
    """Metrics of N estimates (N, 2) or (N, 3) of one marker against its truth (2,) or (3,),
    scatter and bias included."""
    m = metrics_from_errors(planar_errors(estimates, truth), reference_length)
    xy = np.asarray(estimates, dtype=float).reshape(m.n, -1)[:, :2]
    tru = np.asarray(truth, dtype=float).reshape(-1)[:2]
    scatter = (float(np.sqrt(np.sum(xy.var(axis=0, ddof=1)))) if m.n > 1 else math.nan)
    bias = float(np.hypot(*(xy.mean(axis=0) - tru)))
    return replace(m, scatter=scatter, bias=bias)


def mean_metrics(items: Iterable[MarkerMetrics]) -> MarkerMetrics:
    """Average of each metric over markers (the paper's "average over all markers").

    n is the total number of samples. A metric that is NaN for some markers (STD of a single
    sample) is averaged over the others; it is NaN only when NaN for all.
    """
    items = list(items)
    if not items:
        raise ValueError("no markers to average")

    def avg(name: str) -> float:
        v = np.array([getattr(m, name) for m in items], dtype=float)
        v = v[np.isfinite(v)]
        return float(v.mean()) if v.size else math.nan

    return MarkerMetrics(n=sum(m.n for m in items), rmse=avg("rmse"), std=avg("std"),
                         mae=avg("mae"), maxae=avg("maxae"), mre=avg("mre"),
                         scatter=avg("scatter"), bias=avg("bias"))


def percent_change(value: float, baseline: float) -> float:
    """The paper's "% change" of ``value`` relative to ``baseline``: (value - baseline) /
    baseline * 100; negative means smaller (better, for an error) than the baseline."""
    if baseline == 0.0:
        return math.nan
    return (value - baseline) / baseline * 100.0


class WindowStats:
    """Rolling per-marker error statistics over the last ``window`` samples of each marker.

    reference_length: metres, for the MRE.
    """

    def __init__(self, window: int, reference_length: float) -> None:
        if isinstance(window, bool) or int(window) != window or window < 1:
            raise ValueError(f"window must be an integer >= 1, got {window!r}")
        self.window = int(window)
        self.reference_length = _check_ref(reference_length)
        self._errors: dict[int, deque[float]] = {}

    def add(self, marker_id: int, error_or_estimate: float | np.ndarray,
            truth: np.ndarray | None = None) -> float:
        """Add one sample: an error magnitude (m), or an estimate (2,)/(3,) with its ``truth``
        (2,)/(3,) (floor-plane distance). Returns the error added."""
        if truth is None:
            arr = np.asarray(error_or_estimate, dtype=float)
            if arr.ndim != 0:
                raise ValueError("pass truth with a position estimate, or a scalar error")
            e = float(arr)
            if not (math.isfinite(e) and e >= 0.0):
                raise ValueError(f"error must be a finite distance >= 0 m, got {e!r}")
        else:
            e = float(planar_errors(error_or_estimate, truth)[0])
        q = self._errors.get(marker_id)
        if q is None:
            q = self._errors[marker_id] = deque(maxlen=self.window)
        q.append(e)
        return e

    def per_marker(self) -> dict[int, MarkerMetrics]:
        """id -> metrics over that marker's window, sorted by id."""
        return {mid: metrics_from_errors(np.fromiter(q, float), self.reference_length)
                for mid, q in sorted(self._errors.items()) if q}

    def _all(self) -> np.ndarray:
        return np.fromiter((e for q in self._errors.values() for e in q), float)

    @property
    def n(self) -> int:
        """Samples held, all markers."""
        return sum(len(q) for q in self._errors.values())

    @property
    def mean_error(self) -> float:
        """Mean error (m) over every sample held; NaN when empty."""
        a = self._all()
        return float(a.mean()) if a.size else math.nan

    @property
    def max_error(self) -> float:
        """Largest error (m) held; NaN when empty."""
        a = self._all()
        return float(a.max()) if a.size else math.nan

    def mean(self) -> MarkerMetrics | None:
        """Average of the per-marker metrics, or None when empty."""
        pm = self.per_marker()
        return mean_metrics(pm.values()) if pm else None

    def reset(self) -> None:
        """Forget every sample."""
        self._errors.clear()
