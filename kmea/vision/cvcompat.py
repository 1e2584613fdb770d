"""The OpenCV calls whose Python signature differs between OpenCV 4.8+ and 5.x, in one place.

KMEA supports both for real: 4.x is what goes with numpy 1.x (Raspberry Pi OS Bookworm's apt
numpy 1.24 pins ``opencv-python-headless`` to 4.11, see ``constraints/bookworm.txt``), 5.x is
what pip picks with numpy 2. Every other OpenCV call the project makes is the same in both
(the test suite runs on both stacks). Call sites use these functions instead of ``cv2.X``
where they differ; the choice is made once, from the OpenCV that is imported.

Differences handled here:

- ``cv2.undistortPoints(..., criteria=...)``: 5.x takes the iteration criteria as a keyword;
  4.x rejects it (``'criteria' is an invalid keyword argument``) and has the separate
  ``cv2.undistortPointsIter(src, K, D, R, P, criteria)`` instead (removed in 5.x).

Checked against the binding's signatures of 4.11 and 5.0 for every ``cv2`` function and
constant and every ``cv2.aruco`` class method the project calls: the others differ only by
optional arguments or overloads added in 5.x (``putText``, ``getTextSize``,
``warpPerspective``, ``Dictionary.getBitsFromByteList``) and by the numeric values of the
``SOLVEPNP_*`` flags, which the code uses by name only (never store them as numbers).
"""

from __future__ import annotations

import re

import cv2
import numpy as np

__all__ = ["CV_VERSION", "MIN_CV_VERSION", "cv_version", "undistort_points"]

MIN_CV_VERSION = (4, 8, 0)


def cv_version(text: str | None = None) -> tuple[int, int, int]:
    """(major, minor, patch) of ``cv2.__version__`` or of ``text`` (``4.11.0-dev``: (4, 11, 0))."""
    nums = [int(n) for n in re.findall(r"\d+", text if text is not None else cv2.__version__)[:3]]
    while len(nums) < 3:
        nums.append(0)
    return nums[0], nums[1], nums[2]


CV_VERSION = cv_version()

# Decided by what the binding offers rather than by the number alone, so a 4.x build that
# gained the keyword (or a 5.x one that kept the old function) still takes a working path.
_ITER_FN = getattr(cv2, "undistortPointsIter", None)
_CRITERIA_KW = CV_VERSION >= (5, 0, 0) or _ITER_FN is None


def undistort_points(src: np.ndarray, camera_matrix: np.ndarray, dist_coeffs: np.ndarray,
                     criteria: tuple[int, int, float] | None = None) -> np.ndarray:
    """``cv2.undistortPoints`` with optional iteration ``criteria`` on OpenCV 4.x and 5.x.

    src: (N, 1, 2) float pixel coordinates; camera_matrix: (3, 3); dist_coeffs: OpenCV's
    4, 5, 8, 12 or 14 coefficients. criteria: ``(type, max_count, epsilon)`` as for
    ``cv2.TermCriteria`` or None for OpenCV's default (5 iterations). Returns (N, 1, 2)
    normalised image coordinates (no R, no P), identical on both versions.
    """
    if criteria is None:
        return cv2.undistortPoints(src, camera_matrix, dist_coeffs)
    if _CRITERIA_KW or _ITER_FN is None:  # (the second test only narrows _ITER_FN)
        return cv2.undistortPoints(src, camera_matrix, dist_coeffs, criteria=criteria)
    # 4.x: R and P empty = identity rotation and normalised output, as undistortPoints.
    return _ITER_FN(src, camera_matrix, dist_coeffs, None, None, criteria)
