"""kmea.vision.cvcompat: the OpenCV 4.x / 5.x differences, on whichever OpenCV is installed
(``make test`` runs the suite on OpenCV 5 and on the Bookworm stack's OpenCV 4.11)."""

from __future__ import annotations

import cv2
import numpy as np

from kmea.geometry import check_distortion as dist14
from kmea.geometry import project
from kmea.vision import cvcompat


def test_version_parsing() -> None:
    assert cvcompat.cv_version("4.11.0") == (4, 11, 0)
    assert cvcompat.cv_version("5.0.0-pre") == (5, 0, 0)
    assert cvcompat.cv_version("4.8") == (4, 8, 0)
    assert cvcompat.cv_version(cv2.__version__) == cvcompat.CV_VERSION
    assert cvcompat.CV_VERSION >= cvcompat.MIN_CV_VERSION


def test_undistort_points_with_criteria_converges_where_the_default_does_not() -> None:
    """Strong distortion: OpenCV's default 5 iterations stop short; the criteria (20
    iterations, 1e-12) reach the true normalised points on both OpenCV versions."""
    K = np.array([[800.0, 0.0, 320.0], [0.0, 800.0, 240.0], [0.0, 0.0, 1.0]])
    d = np.array([-0.35, 0.12, 0.001, -0.002, -0.02])
    rng = np.random.default_rng(3)
    xy = rng.uniform(-0.45, 0.45, (40, 2))
    P = np.column_stack([xy, np.ones(40)])
    uv = project(P, K, dist14(d)).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-12)
    exact = cvcompat.undistort_points(uv, K, d, criteria=crit).reshape(-1, 2)
    default = cvcompat.undistort_points(uv, K, d).reshape(-1, 2)
    assert np.abs(exact - xy).max() < 1e-8
    assert np.abs(default - xy).max() > 1e-6
    np.testing.assert_array_equal(default, cv2.undistortPoints(uv, K, d).reshape(-1, 2))
