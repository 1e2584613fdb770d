"""Which detected markers are suspect: a quadrilateral that is not a square seen by this
camera (see ``docs/vision.md`` and :mod:`kmea.vision.marker_pose`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kmea.geometry.camera import CameraIntrinsics
from kmea.vision.camera import CameraModel

__all__ = ["QualitySettings", "suspect_mask"]


@dataclass(frozen=True)
class QualitySettings:
    """When a detected quadrilateral is ``suspect`` (pixels).

    floor_px: a chosen-pose RMS reprojection error above this may be suspect (an unoccluded
        marker's stays below ~0.3 px on rendered 1640x1232 frames; a corner hidden by a
        robot gives 0.6-2.3 px).
    ratio: ... and it must also exceed ``ratio`` times the frame's median error, so a
        noisier camera (a higher median) raises the bar with its noise.
    border_px: a corner closer than this to the image border (truncated marker).
    """

    floor_px: float = 0.3
    ratio: float = 5.0
    border_px: float = 2.0


def suspect_mask(err: np.ndarray, corners: np.ndarray,
                  camera: CameraModel | CameraIntrinsics, q: QualitySettings) -> np.ndarray:
    """(N,) bool: the quadrilateral is not trustworthy (module docstring). err: (N,) RMS px
    of the chosen poses; corners: (N, 4, 2) px."""
    if not len(err):
        return np.zeros(0, bool)
    bar = max(q.floor_px, q.ratio * float(np.median(err)))
    bad = ~(err <= bar)  # NaN is suspect too
    w, h = getattr(camera, "width", 0), getattr(camera, "height", 0)
    if w and h and q.border_px > 0:
        c = corners.reshape(-1, 4, 2)
        b = q.border_px
        # Pixel centres at integer coordinates: the image spans -0.5 .. w - 0.5.
        near = ((c[..., 0] < b - 0.5) | (c[..., 0] > w - 0.5 - b)
                | (c[..., 1] < b - 0.5) | (c[..., 1] > h - 0.5 - b)).any(axis=1)
        bad |= near
    return bad
