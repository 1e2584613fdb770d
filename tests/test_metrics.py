"""The paper's metrics on hand-made samples, computed by hand in the comments."""

from __future__ import annotations

import math

import numpy as np
import pytest

from kmea.stats.metrics import (
    MarkerMetrics,
    WindowStats,
    marker_metrics,
    mean_metrics,
    metrics_from_errors,
    percent_change,
)

# Truth (1, 2); four estimates whose floor-plane errors are 0, 0.5, 1.0 and 0.5 m:
#   (1.0, 2.0) -> 0; (1.3, 2.4) -> hypot(0.3, 0.4) = 0.5; (0.4, 2.8) -> hypot(0.6, 0.8) = 1;
#   (1.0, 1.5) -> 0.5. The z column must be ignored.
EST = np.array([[1.0, 2.0, 9.0], [1.3, 2.4, -3.0], [0.4, 2.8, 0.0], [1.0, 1.5, 0.1]])
TRUTH = np.array([1.0, 2.0, 0.0])


def test_marker_metrics_by_hand() -> None:
    m = marker_metrics(EST, TRUTH, reference_length=2.0)
    assert m.n == 4
    # MAE = (0 + 0.5 + 1 + 0.5) / 4 = 0.5
    assert m.mae == pytest.approx(0.5, abs=1e-15)
    # RMSE = sqrt((0 + 0.25 + 1 + 0.25) / 4) = sqrt(0.375)
    assert m.rmse == pytest.approx(math.sqrt(0.375), abs=1e-15)
    # STD (ddof 1): deviations from 0.5 are -0.5, 0, 0.5, 0 -> 0.5 / 3 -> sqrt(1/6)
    assert m.std == pytest.approx(math.sqrt(1 / 6), abs=1e-15)
    assert m.maxae == pytest.approx(1.0, abs=1e-15)
    # MRE = 0.5 / 2.0 * 100 = 25 %
    assert m.mre == pytest.approx(25.0, abs=1e-12)
    # RMSE^2 = MAE^2 + (n - 1) / n STD^2: 0.375 = 0.25 + 3/4 * 1/6
    assert m.rmse**2 == pytest.approx(m.mae**2 + 0.75 * m.std**2)
    # 2-D input gives the same.
    assert marker_metrics(EST[:, :2], TRUTH[:2], 2.0) == m


def test_single_sample_has_no_sample_std() -> None:
    m = marker_metrics([[0.3, 0.4]], [0.0, 0.0], 1.0)
    assert (m.n, m.rmse, m.mae, m.maxae) == (1, 0.5, 0.5, 0.5)
    assert math.isnan(m.std)


def test_mean_metrics_and_percent_change() -> None:
    a = MarkerMetrics(n=4, rmse=0.2, std=0.1, mae=0.15, maxae=0.3, mre=1.0)
    b = MarkerMetrics(n=1, rmse=0.4, std=math.nan, mae=0.25, maxae=0.5, mre=3.0)
    m = mean_metrics([a, b])
    assert m.n == 5
    assert (m.rmse, m.mae, m.maxae, m.mre) == pytest.approx((0.3, 0.2, 0.4, 2.0))
    assert m.std == pytest.approx(0.1)  # the NaN of a single sample is left out
    # KMEA 0.8 mm vs LMEA 1.0 mm: -20 %.
    assert percent_change(0.8, 1.0) == pytest.approx(-20.0)
    assert percent_change(3.0, 2.0) == pytest.approx(50.0)
    assert math.isnan(percent_change(1.0, 0.0))
    with pytest.raises(ValueError, match="no markers"):
        mean_metrics([])


def test_bad_input_is_refused() -> None:
    with pytest.raises(ValueError, match="no samples"):
        metrics_from_errors([], 1.0)
    with pytest.raises(ValueError, match="finite distances"):
        metrics_from_errors([0.1, -0.2], 1.0)
    with pytest.raises(ValueError, match="reference_length must be a finite length > 0 m"):
        marker_metrics(EST, TRUTH, 0.0)
    with pytest.raises(ValueError, match="must be finite"):
        marker_metrics([[np.nan, 0.0]], [0.0, 0.0], 1.0)
    with pytest.raises(ValueError, match=r"\(N, 2\) or \(N, 3\)"):
        marker_metrics(np.zeros((3, 4)), TRUTH, 1.0)


def test_window_stats_keep_the_last_samples_per_marker() -> None:
    w = WindowStats(window=3, reference_length=2.0)
    assert math.isnan(w.mean_error) and w.per_marker() == {} and w.mean() is None
    for e in (5.0, 0.0, 0.5, 1.0):  # 5.0 falls out of the window of 3
        w.add(7, e)
    w.add(7, EST[3], TRUTH)  # -> 0.5, pushing out 0.0
    assert w.add(2, (0.3, 0.4, 1.0), (0.0, 0.0)) == pytest.approx(0.5)
    pm = w.per_marker()
    assert list(pm) == [2, 7]
    # marker 7 holds 0.5, 1.0, 0.5: MAE 2/3, MaxAE 1, RMSE sqrt(1.5 / 3)
    assert pm[7].n == 3 and pm[7].mae == pytest.approx(2 / 3)
    assert pm[7].rmse == pytest.approx(math.sqrt(0.5)) and pm[7].maxae == 1.0
    assert pm[7].mre == pytest.approx(2 / 3 / 2.0 * 100)
    assert w.n == 4
    assert w.mean_error == pytest.approx((0.5 + 1.0 + 0.5 + 0.5) / 4)
    assert w.max_error == 1.0
    assert w.mean().mae == pytest.approx((2 / 3 + 0.5) / 2)
    w.reset()
    assert w.n == 0 and w.per_marker() == {}
    with pytest.raises(ValueError, match="window must be an integer >= 1"):
        WindowStats(0, 1.0)
    with pytest.raises(ValueError, match="error must be a finite distance"):
        w.add(1, math.nan)
    with pytest.raises(ValueError, match="pass truth"):
        w.add(1, (0.1, 0.2))


def test_scatter_and_bias_separate_precision_from_accuracy():
    from kmea.stats.metrics import marker_metrics

    rng = np.random.default_rng(3)
    noise = rng.normal(0.0, 0.001, (4000, 2))
    truth = np.array([0.2, -0.1])
    centred = marker_metrics(truth + noise, truth, 2.0)
    biased = marker_metrics(truth + noise + [0.01, 0.0], truth, 2.0)
    # The paper's STD moves with a constant bias (Rayleigh 0.66 sigma -> sigma) ...
    assert centred.std == pytest.approx(0.655e-3, rel=0.05)
    assert biased.std == pytest.approx(1.0e-3, rel=0.05)
    # ... the scatter does not, and the bias is the constant part.
    assert biased.scatter == pytest.approx(centred.scatter, rel=1e-12)
    assert centred.scatter == pytest.approx(np.sqrt(2) * 1e-3, rel=0.05)
    assert biased.bias == pytest.approx(0.01, abs=1e-4)
    assert centred.bias < 1e-4
    assert "scatter" in biased.as_dict()
    assert "scatter" not in metrics_from_errors([0.1, 0.2], 2.0).as_dict()
