"""The one interface of every estimator.

An estimator takes the camera-frame poses of the markers detected in one frame and the
map, and returns the world pose of every detected marker (in the map or not) plus
diagnostics. Numpy only.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from kmea.maps import MarkerMap

__all__ = [
    "CameraIntrinsics",
    "Estimate",
    "Estimator",
    "MarkerEstimate",
    "MarkerObservation",
    "NotEstimated",
    "check_observations",
]


class NotEstimated(Exception):
    """Raised inside estimators for a degenerate input; turned into ``Estimate.ok = False``."""


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics with OpenCV distortion, as plain arrays (numpy only).

    camera_matrix: (3, 3) K in pixels; dist_coeffs: (n,) OpenCV order (k1, k2, p1, p2, k3, ...).
    width, height: image size in pixels the intrinsics belong to.
    """

    camera_matrix: np.ndarray
    dist_coeffs: np.ndarray
    width: int
    height: int


@dataclass(frozen=True)
class MarkerObservation:
    """One marker detected in one frame, in the camera frame (OpenCV axes, metres).

    Attributes:
        id: ArUco id.
        marker2cam_R: (3, 3) rotation of the chosen PnP solution.
        marker2cam_t: (3,) marker centre in the camera frame, metres.
        corners: (4, 2) detected pixel corners (TL, TR, BR, BL, OpenCV convention: pixel
            centres at integer coordinates), or None when unknown.
        length: side used for the PnP, metres.
        reproj_error: RMS reprojection error of the chosen solution, pixels.
        alt_R, alt_t: the other IPPE solution, if any.
        alt_reproj_error: its RMS reprojection error, pixels.
        ambiguous: the choice between the two solutions is uncertain.
        flipped: the scene-consistent choice differs from the lowest-error one.
        suspect: the detected quadrilateral is not trustworthy (a corner hidden, e.g. by a
            passing robot, or at the image border: see ``docs/vision.md``). The marker is
            still estimated and published, but never used as an alignment reference.
    """

    id: int
    marker2cam_R: np.ndarray
    marker2cam_t: np.ndarray
    corners: np.ndarray | None = None
    length: float = 0.06
    reproj_error: float = math.nan
    alt_R: np.ndarray | None = None
    alt_t: np.ndarray | None = None
    alt_reproj_error: float = math.nan
    ambiguous: bool = False
    flipped: bool = False
    suspect: bool = False


@dataclass
class MarkerEstimate:
    """World pose of one marker.

    position: (3,) world, metres; rotation: (3, 3) marker2world; yaw: radians (heading of
    the marker's x axis, CCW from world x); sigma: 1-sigma position uncertainty (m) or None.
    """

    id: int
    position: np.ndarray
    rotation: np.ndarray
    yaw: float
    sigma: float | None = None


@dataclass
class Estimate:
    """Result of one estimator on one frame.

    ok: False means "not estimated" (``reason`` says why; ``markers`` is then empty).
    references: ids of the map markers the alignment used.
    cam2world: (4, 4) similarity world = scale * R @ cam + t, or None.
    scale: the similarity's scale (1 for rigid estimators).
    residuals: reference id -> distance (m) between its aligned and its map position.
    rejected: reference id -> disagreement with the map (m), for robust estimators.
    info: anything else worth publishing (refined focal length, iterations, ...).
    """

    algorithm: str
    ok: bool
    markers: dict[int, MarkerEstimate] = field(default_factory=dict)
    reason: str = ""
    references: tuple[int, ...] = ()
    cam2world: np.ndarray | None = None
    scale: float = math.nan
    residuals: dict[int, float] = field(default_factory=dict)
    rejected: dict[int, float] = field(default_factory=dict)
    info: dict = field(default_factory=dict)

    @classmethod
    def failed(cls, algorithm: str, reason: str) -> Estimate:
        return cls(algorithm=algorithm, ok=False, reason=reason)


@runtime_checkable
class Estimator(Protocol):
    """What every estimator provides."""

    name: str

    def estimate(
        self,
        observations: Sequence[MarkerObservation],
        world_map: MarkerMap,
        exclude: Collection[int] = (),
        camera: CameraIntrinsics | None = None,
        plane_heights: Mapping[int, float] | None = None,
    ) -> Estimate:
        """Estimate the world pose of every observed marker.

        exclude: map ids not to use as references (leave-one-out); they are still estimated.
        camera: intrinsics, for estimators that work on corners.
        plane_heights: id -> known height (m) of a horizontal marker not in the map (robots).
        """
        ...


def check_observations(observations: Sequence[MarkerObservation]) -> list[MarkerObservation]:
    """Drop nothing silently: raise ``ValueError`` on duplicate ids, non-finite poses or bad
    shapes."""
    seen: set[int] = set()
    out = []
    Rs: list[np.ndarray] = []
    ts: list[np.ndarray] = []
    for o in observations:
        if o.id in seen:
            raise ValueError(f"observation id {o.id}: duplicate id in one frame")
        seen.add(o.id)
        R = np.asarray(o.marker2cam_R, dtype=float)
        t = np.asarray(o.marker2cam_t, dtype=float)
        if R.shape != (3, 3) or t.shape != (3,):
            raise ValueError(f"observation id {o.id}: marker2cam_R must be (3, 3) and "
                             f"marker2cam_t (3,), got {R.shape} and {t.shape}")
        Rs.append(R)
        ts.append(t)
        out.append(o)
    if out:
        # One vectorised finiteness test for the whole frame (this runs every frame).
        ok = np.isfinite(np.stack(Rs)).all(axis=(1, 2)) & np.isfinite(np.stack(ts)).all(axis=1)
        if not ok.all():
            raise ValueError(f"observation id {out[int(np.argmin(ok))].id}: non-finite pose")
    return out
