"""What the simulator knows about a frame: the exact marker poses and corners, robots."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from kmea.frame import Frame
from kmea.timing import FrameTiming

__all__ = ["FrameTruth", "SimFrame"]


@dataclass
class FrameTruth:
    """Ground truth of one frame.

    cam2world: (4, 4). markers: id -> (4, 4) true marker2world of every marker in the scene
    (map markers as placed, i.e. displaced when misplaced; extra markers; robot markers).
    lengths: id -> marker side, m. corners: id -> (4, 2) exact pixel corners (TL, TR, BR, BL,
    lens distortion included) of the markers in front of the camera, facing it, whose four
    corners lie inside the image. visible: ids of ``corners`` that nothing hides (corners and
    centre unoccluded). robots: name -> true (x, y, theta), m and rad, at ``t``. t: seconds
    (the frame's timestamp: the instant row 0 is read out). timing: when each row was
    exposed (:class:`kmea.timing.FrameTiming`, exact). paths: robot name -> its path, so
    :meth:`robot_at` gives the truth at any instant (a pose's own time). With exposure or a
    rolling shutter the ``corners`` of robot markers are where each corner was at its own
    row's mid-exposure (what a perfect detector of the smeared image would find).
    """

    cam2world: np.ndarray
    markers: dict[int, np.ndarray]
    lengths: dict[int, float]
    corners: dict[int, np.ndarray]
    visible: set[int]
    robots: dict[str, tuple[float, float, float]]
    t: float = 0.0
    timing: FrameTiming | None = None
    paths: Mapping[str, object] = field(default_factory=dict, repr=False)

    def robot_at(self, name: str, t: float) -> tuple[float, float, float]:
        """True (x, y, theta) of robot ``name`` at ``t`` seconds (m, rad)."""
        p = self.paths[name].pose(t)  # type: ignore[attr-defined]
        if p is None:
            raise ValueError(f"robot {name!r}: absent at t = {t} s")
        return (float(p[0]), float(p[1]), float(p[2]))

    def marker2cam(self, mid: int) -> np.ndarray:
        """(4, 4) true marker2cam of marker ``mid`` (what a perfect PnP would give)."""
        return np.linalg.inv(self.cam2world) @ self.markers[mid]


@dataclass
class SimFrame(Frame):
    """A rendered frame: a :class:`kmea.frame.Frame` with its truth.

    index; timestamp = index / fps seconds (also ``t``); image: (H, W) uint8 greyscale
    (never None: :attr:`pixels` is the same array, typed so); truth: :class:`FrameTruth`
    (also in ``meta["truth"]``), a required keyword.
    """

    truth: FrameTruth = field(kw_only=True)

    @property
    def t(self) -> float:
        return self.timestamp

    @property
    def pixels(self) -> np.ndarray:
        """``image``, which a rendered frame always has."""
        if self.image is None:
            raise ValueError(f"simulated frame {self.index} has no image")
        return self.image
