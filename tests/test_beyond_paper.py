"""Beyond the paper, in ``kmea experiment`` on the simulated floor (rendered, detected):
corner-pnp against KMEA in Parts I, III and IV, kmea-robust's and corner-pnp's reports of
the displaced anchors. Few frames, but the margins are wide (see the comments)."""

from __future__ import annotations

import math

import pytest

from kmea.experiments.parts import get_part
from kmea.experiments.run import ExperimentConfig, run_simulation
from kmea.experiments.tables import rejected_summary, score

pytestmark = pytest.mark.slow

ALGS = ("kmea", "kmea-robust", "corner-pnp")
SAMPLES = 5


def _run(part: str, **kw):
    result = run_simulation(ExperimentConfig(part=get_part(part), algorithms=ALGS,
                                             baseline="kmea", samples=SAMPLES, **kw))
    return result, score(result)


@pytest.fixture(scope="module")
def part1():
    return _run("I")


def _mae(scores, alg: str) -> float:
    assert scores.complete[alg], alg
    return scores.average[alg].mae


def test_part1_corner_pnp_at_most_a_third_of_kmea(part1):
    _, sc = part1
    # Measured with 8 frames: 0.05 mm against 0.38 mm.
    assert _mae(sc, "corner-pnp") <= _mae(sc, "kmea") / 3


def test_part3_displaced_anchors_reported_and_corner_pnp_unharmed(part1):
    result, sc = _run("III")
    # Measured: 0.06 mm against 0.05 mm in Part I.
    assert _mae(sc, "corner-pnp") <= 1.5 * _mae(part1[1], "corner-pnp")
    assert _mae(sc, "kmea-robust") < _mae(sc, "kmea")
    displaced = get_part("III").displaced
    summary = rejected_summary(result)
    for alg in ("kmea-robust", "corner-pnp"):
        got = {i: (median, share) for i, median, share in summary[alg]}
        assert set(got) >= set(displaced), (alg, got)
        # Thresholds scale with the measured corner noise (issue 13): a reference whose
        # corners disagree with the map by about a millimetre, many times that noise (a
        # wall marker seen at a grazing angle), may be left out too; never by anything near
        # a displacement (36-39 mm here).
        assert all(got[i][0] < 0.003 for i in set(got) - set(displaced)), (alg, got)
        for i, d in displaced.items():
            median, share = got[i]
            assert share == 1.0
            assert median == pytest.approx(math.hypot(d.dx, d.dy), abs=0.003), (alg, i)


@pytest.mark.parametrize("miscalibrate", [False, True])
def test_part4_corner_pnp_at_most_half_of_kmea(miscalibrate):
    kw = {"focal_error": 0.02, "k1_error": 0.02} if miscalibrate else {}
    result, sc = _run("IV", **kw)
    # Measured with 8 frames: 0.26 mm against 20 mm (both calibrations).
    assert _mae(sc, "corner-pnp") <= _mae(sc, "kmea") / 2
    summary = {i: median for i, median, _ in rejected_summary(result)["corner-pnp"]}
    displaced = set(get_part("IV").displaced)
    assert set(summary) >= displaced
    # Besides the displaced anchors (92-106 mm), only references off by a millimetre or
    # less than the corner noise allows (see Part III above).
    assert all(summary[i] < 0.003 for i in set(summary) - displaced), summary
