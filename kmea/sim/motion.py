"""Paths that move robots and occluders over the floor (numpy only).

A path is anything with ``pose(t: float) -> (x, y, theta) | None``: world metres and radians
at time ``t`` seconds; ``None`` means the object is absent at that time (an arm that has
not entered the scene yet). Robots drive forwards: their heading is the path's tangent.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from kmea.geometry.rotations import wrap_angle

__all__ = ["CrossingPath", "LoopPath", "Path", "StadiumPath", "Stationary", "WallClock"]

Pose2D = tuple[float, float, float]


@runtime_checkable
class Path(Protocol):
    def pose(self, t: float) -> Pose2D | None:
        """(x, y, theta) in metres and radians at ``t`` seconds, or None when absent."""
        ...


@dataclass(frozen=True)
class Stationary:
    """Stands still at (x, y) metres with heading ``theta`` radians."""

    x: float
    y: float
    theta: float = 0.0

    def pose(self, t: float) -> Pose2D:
        return (float(self.x), float(self.y), float(self.theta))


def _catmull_rom_closed(points: np.ndarray, per_segment: int) -> np.ndarray:
    """Dense closed centripetal Catmull-Rom curve through ``points`` (N, 2) -> (M, 2)."""
    n = len(points)
    out = []
    for i in range(n):
        p0, p1, p2, p3 = (points[(i + k - 1) % n] for k in range(4))

        def knot(ti: float, a: np.ndarray, b: np.ndarray) -> float:
            return ti + max(float(np.linalg.norm(b - a)) ** 0.5, 1e-9)

        t0 = 0.0
        t1 = knot(t0, p0, p1)
        t2 = knot(t1, p1, p2)
        t3 = knot(t2, p2, p3)
        ts = np.linspace(t1, t2, per_segment, endpoint=False)[:, None]
        a1 = (t1 - ts) / (t1 - t0) * p0 + (ts - t0) / (t1 - t0) * p1
        a2 = (t2 - ts) / (t2 - t1) * p1 + (ts - t1) / (t2 - t1) * p2
        a3 = (t3 - ts) / (t3 - t2) * p2 + (ts - t2) / (t3 - t2) * p3
        b1 = (t2 - ts) / (t2 - t0) * a1 + (ts - t0) / (t2 - t0) * a2
        b2 = (t3 - ts) / (t3 - t1) * a2 + (ts - t1) / (t3 - t1) * a3
        out.append((t2 - ts) / (t2 - t1) * b1 + (ts - t1) / (t2 - t1) * b2)
    return np.concatenate(out)


@dataclass(frozen=True)
class LoopPath:
    """A closed loop through ``waypoints`` ((N, 2) metres, N >= 2) at ``speed`` m/s.

    ``smooth``: a centripetal Catmull-Rom curve through the waypoints (no sharp turns);
    otherwise the closed polyline (the heading jumps at the corners). ``phase``: metres along
    the loop at t = 0. The heading is the direction of travel (reversed when ``speed`` < 0).
    """

    waypoints: Sequence[Sequence[float]]
    speed: float = 0.12
    phase: float = 0.0
    smooth: bool = True
    _s: np.ndarray = field(init=False, repr=False, compare=False)
    _xy: np.ndarray = field(init=False, repr=False, compare=False)
    _heading: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        pts = np.asarray(self.waypoints, dtype=float)
        if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) < 2 or not np.all(np.isfinite(pts)):
            raise ValueError(f"LoopPath: waypoints must be (N >= 2, 2) finite metres, got "
                             f"{np.shape(self.waypoints)}")
        if not math.isfinite(self.speed):
            raise ValueError(f"LoopPath: speed must be finite, got {self.speed!r}")
        dense = _catmull_rom_closed(pts, 200) if self.smooth and len(pts) > 2 else pts
        closed = np.vstack([dense, dense[:1]])
        seg = np.diff(closed, axis=0)
        seglen = np.hypot(seg[:, 0], seg[:, 1])
        keep = seglen > 1e-12
        if not np.any(keep):
            raise ValueError("LoopPath: waypoints must not all coincide")
        seg, seglen = seg[keep], seglen[keep]
        starts = closed[:-1][keep]
        object.__setattr__(self, "_s", np.concatenate([[0.0], np.cumsum(seglen)]))
        object.__setattr__(self, "_xy", starts)
        object.__setattr__(self, "_heading", np.arctan2(seg[:, 1], seg[:, 0]))

    @property
    def length(self) -> float:
        """Length of one loop, metres."""
        return float(self._s[-1])

    @property
    def period(self) -> float:
        """Seconds per loop (inf when standing still)."""
        return math.inf if self.speed == 0 else self.length / abs(self.speed)

    def pose(self, t: float) -> Pose2D:
        s = (self.phase + self.speed * t) % self.length
        i = int(np.searchsorted(self._s, s, side="right") - 1)
        i = min(max(i, 0), len(self._xy) - 1)
        frac = s - self._s[i]
        h = float(self._heading[i])
        x = self._xy[i, 0] + frac * math.cos(h)
        y = self._xy[i, 1] + frac * math.sin(h)
        if self.speed < 0:
            h += math.pi
        return (float(x), float(y), float(wrap_angle(h)))


@dataclass(frozen=True)
class CrossingPath:
    """Moves in a straight line from ``start`` to ``end`` (metres) between ``t0`` and
    ``t0 + duration`` seconds; absent before and after. ``period`` > 0 repeats the crossing
    every ``period`` seconds. The heading is ``theta`` (radians) or, when None, the direction
    of travel.
    """

    start: Sequence[float]
    end: Sequence[float]
    t0: float = 0.0
    duration: float = 2.0
    period: float = 0.0
    theta: float | None = None

    def __post_init__(self) -> None:
        if not self.duration > 0:
            raise ValueError(f"CrossingPath: duration must be > 0 s, got {self.duration!r}")
        if self.period and self.period < self.duration:
            raise ValueError("CrossingPath: period must be 0 (once) or >= duration")

    def pose(self, t: float) -> Pose2D | None:
        dt = t - self.t0
        if self.period and dt >= 0:
            dt %= self.period
        if dt < 0 or dt > self.duration:
            return None
        a = dt / self.duration
        x0, y0 = float(self.start[0]), float(self.start[1])
        x1, y1 = float(self.end[0]), float(self.end[1])
        th = math.atan2(y1 - y0, x1 - x0) if self.theta is None else float(self.theta)
        return (x0 + a * (x1 - x0), y0 + a * (y1 - y0), th)


@dataclass
class WallAnchor:
    """The Unix time of the frame being rendered minus its frame time (s), set by the paced
    source before each frame (:class:`kmea.sources.sim.SimSource`); None: not paced."""

    offset: float | None = None


@dataclass(frozen=True)
class WallClock:
    """``path`` driven by the Unix time, ``time.time() - epoch`` s, instead of the frame time:
    several simulated cameras rendered by separate processes, started at different moments,
    show the robots where they are at the same instant (a paced source's timestamps are
    Unix times too). Not reproducible from frame indices: for live runs only.

    Paced, the source anchors each frame (``anchor``): its frame time t maps to one Unix
    instant, so every row of the frame (a rolling shutter's) is rendered at the instant the
    frame's timing says, and the frame is stamped with it: the measurements' times are
    exact however long the rendering takes (stamped when the rendering ended, a loaded
    machine's cameras disagreed by centimetres, and by tens of degrees of heading in the
    wide scene's tight turns)."""

    path: Path
    epoch: float = 0.0
    anchor: WallAnchor = field(default_factory=WallAnchor, compare=False)

    def pose(self, t: float) -> Pose2D | None:
        off = self.anchor.offset
        return self.path.pose((time.time() if off is None else t + off) - self.epoch)


@dataclass(frozen=True)
class StadiumPath:
    """A stadium driven at constant ``speed`` m/s: two straights of ``length`` m joined by
    half circles of ``radius`` m (turn rate speed / radius rad/s there), exact in closed
    form (heading and turn rate have no discretisation error: truth for heading RMSE).

    center: (x, y) m; axis: direction of the straights, rad (0: along world x, pi/2: along
    y); phase: metres along the loop at t = 0; ccw: counter-clockwise (else clockwise).
    Starts at the beginning of the first straight (on the right of the axis for ccw).
    """

    center: Sequence[float]
    length: float
    radius: float
    speed: float
    axis: float = 0.0
    phase: float = 0.0
    ccw: bool = True

    def __post_init__(self) -> None:
        if not (self.length >= 0 and self.radius > 0 and math.isfinite(self.speed)):
            raise ValueError(f"StadiumPath: need length >= 0 m, radius > 0 m, finite speed; "
                             f"got {self.length!r}, {self.radius!r}, {self.speed!r}")

    @property
    def perimeter(self) -> float:
        return 2.0 * self.length + 2.0 * math.pi * self.radius

    def turn_rate(self, t: float) -> float:
        """rad/s at ``t``: 0 on the straights, +-speed / radius on the half circles."""
        s = (self.phase + self.speed * t) % self.perimeter
        L, arc = self.length, math.pi * self.radius
        on_arc = L <= s < L + arc or s >= 2 * L + arc
        w = self.speed / self.radius if on_arc else 0.0
        return w if self.ccw else -w

    def pose(self, t: float) -> Pose2D:
        s = (self.phase + self.speed * t) % self.perimeter
        L, R, arc = self.length, self.radius, math.pi * self.radius
        sign = 1.0 if self.ccw else -1.0
        # Local frame: straights along +x at y = -sign R (outbound) and back at +sign R.
        if s < L:
            x, y, th = -L / 2 + s, -sign * R, 0.0
        elif s < L + arc:
            a = (s - L) / R
            x, y, th = L / 2 + R * math.sin(a), -sign * R * math.cos(a), sign * a
        elif s < 2 * L + arc:
            x, y, th = L / 2 - (s - L - arc), sign * R, math.pi
        else:
            a = (s - 2 * L - arc) / R
            x, y, th = -L / 2 - R * math.sin(a), sign * R * math.cos(a), math.pi + sign * a
        c, sn = math.cos(self.axis), math.sin(self.axis)
        cx, cy = float(self.center[0]), float(self.center[1])
        th += self.axis
        return (cx + c * x - sn * y, cy + sn * x + c * y, float(wrap_angle(th)))
