"""LMEA as printed (e_z not normalised) against the orthonormalised reading."""

from __future__ import annotations

import numpy as np
import pytest
from synth_corners import observe, scenario1

from kmea.estimators import get
from kmea.estimators.lmea import anchor_basis, printed_basis


def test_printed_basis_is_the_normalised_one_for_orthogonal_anchors_only():
    o, x, y = np.zeros(3), np.array([0.7, 0.0, 0.0]), np.array([0.0, 0.35, 0.0])
    assert np.allclose(printed_basis(o, x, y), anchor_basis(o, x, y))
    skewed = np.array([0.01, 0.35, 0.0])  # 1.6 degrees off
    B = printed_basis(o, x, skewed)
    assert np.linalg.norm(B[:, 2]) < 1.0 - 1e-4  # e_z not a unit vector
    assert not np.allclose(B, anchor_basis(o, x, skewed))


def test_both_readings_agree_on_exact_data_and_differ_with_noise():
    sc = scenario1()
    exact = observe(sc)
    a = get("lmea").estimate(exact, sc.map)
    b = get("lmea-printed").estimate(exact, sc.map)
    assert a.ok and b.ok
    for i in a.markers:
        assert np.linalg.norm(a.markers[i].position - b.markers[i].position) < 1e-6
    noisy = observe(sc, noise_px=0.3, seed=4)
    a = get("lmea").estimate(noisy, sc.map)
    b = get("lmea-printed").estimate(noisy, sc.map)
    diff = max(np.linalg.norm(a.markers[i].position[:2] - b.markers[i].position[:2])
               for i in a.markers if sc.map[i].on_floor) if a.ok else 0.0
    assert diff > 1e-5  # the skew of the noisy anchor axes shows


def test_the_papers_typo_is_no_live_algorithm() -> None:
    """lmea-printed reproduces the paper (kmea experiment); a daemon never runs it."""
    from kmea.estimators import available
    from kmead.config.layers import ConfigError, load_config

    assert "lmea-printed" in available() and "lmea-printed" not in available(live=True)
    with pytest.raises(ConfigError) as e:
        load_config(None, ['estimator.algorithm="lmea-printed"'])
    assert "kmea experiment" in str(e.value) and "\n" not in str(e.value)
