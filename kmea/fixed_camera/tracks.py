"""What the fixed-camera detector knows of each marker (:class:`Track`) and its settings
(:class:`FixedCameraConfig`), with the averaging of a fixed marker's reference corners
(:func:`averaged`). Pixels and frames throughout.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["FixedCameraConfig", "Track", "averaged"]


@dataclass
class FixedCameraConfig:
    """Tracking settings (pixels, frames).

    full_every: a background full detection every this many frames (new markers), at half
    resolution except every ``full_res_every``-th (small, far markers) and after a loss.
    move_px: a static marker whose corners drift more than this moved.
    drift_every: each static marker's drift is measured every this many frames (a
    rotating share of them a frame, at least ``drift_min``; all of them when there are no
    more); its code is checked every frame.
    bump_fraction: this share of the static markers moved or missing (at least
    ``bump_min`` of them) = the camera was bumped; counted among the markers whose drift
    was measured in the frame, and among all of them for the code check.
    min_score: a static marker is seen when its code correlates at least this much with
    the image at its reference corners (:func:`kmea.fixed_camera.codes.code_scores`);
    add_score: a static marker found by a background detection is taken (or replaces its
    reference) from this score.
    margin: search region around a moving marker's prediction, in marker sides.
    follow: a moving marker seen in the last two frames is first refined from its predicted
    corners (``cornerSubPix`` as the detector refines) and kept when its code reads at
    least ``follow_score`` there and its size held; otherwise, or with ``follow`` off, it
    is detected in a region around the prediction.
    average: a fixed marker's reference corners are the mean of up to this many
    full-resolution detections.
    """

    full_every: int = 6
    full_res_every: int = 10
    average: int = 8
    move_px: float = 1.0
    drift_every: int = 3
    drift_min: int = 8
    bump_fraction: float = 0.5
    bump_min: int = 3
    min_score: float = 0.6
    add_score: float = 0.75
    margin: float = 0.4
    follow: bool = True
    follow_score: float = 0.75
    static_ids: frozenset[int] = field(default_factory=frozenset)


@dataclass(eq=False)
class Track:
    """One marker as last seen: a fixed one's reference corners, a moving one's corners
    and image velocity. Compared by identity: a changed reference is a new track."""

    corners: np.ndarray                     # (4, 2) last seen
    velocity: np.ndarray                    # (4, 2) px per frame
    static: bool
    seen: int                               # frame number last seen
    looks: int = 1                          # full-resolution detections averaged (static)
    steady: bool = False                    # velocity from two consecutive frames (moving)


def averaged(t: Track, c: np.ndarray, frame: int, settings: FixedCameraConfig) -> Track:
    """A fixed marker's reference with one more full-resolution look ``c`` (4, 2) px in
    ``frame``: the mean of up to ``settings.average`` looks within ``move_px`` of it (single
    detections of a 30-60 px marker scatter by up to ~1 px), else ``c`` (it moved); ``t``
    itself when ``c`` is its corners."""
    if np.abs(c - t.corners).max() > 1.5 * settings.move_px:
        return Track(c.copy(), np.zeros((4, 2)), True, frame)
    if np.abs(c - t.corners).max() < 1e-9:
        return t
    n = min(t.looks + 1, settings.average)
    new = Track(t.corners + (c - t.corners) / n, np.zeros((4, 2)), True, frame)
    new.looks = n
    return new
