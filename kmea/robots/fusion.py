"""Multi-camera fusion of robot poses through the tracking filter, numpy only.

Several cameras measure the same robots in one world frame. Each measurement (robot pose
with its own sigma, capture time ``t`` s) goes through the robot's
:class:`kmea.robots.tracking.Track` in arrival order: the Kalman update weighs each
camera's measurement by its uncertainty, so a robot in the overlap of two cameras gets both,
and a robot handed over from one camera to the other keeps one continuous track.
Measurements arriving late (a slower camera) are applied at their own time (retrodiction);
those older than ``max_age_s`` behind the newest measurement time seen (the fusion clock, so
any shared clock works: Unix time from the Pis, or simulated time) are dropped and counted.

The camera clocks must agree: a camera whose clock is ahead by d seconds makes its robots
look d s further along (a position error of speed x d) and, if d > ``max_age_s``, makes the
fusion clock run ahead so that the other cameras' measurements are dropped as too old.
See ``docs/fusion.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from kmea.robots.tracking import Outcome, Tracker, TrackerConfig, TrackState

__all__ = ["Fusion", "Measurement", "RobotSeen"]


@dataclass(frozen=True)
class Measurement:
    """One camera's pose of one robot: source (camera label), robot name, capture time t
    (s), x, y (m), theta (rad), sigma (1-sigma position, m, or None)."""

    source: str
    name: str
    t: float
    x: float
    y: float
    theta: float
    sigma: float | None = None


@dataclass
class RobotSeen:
    """Which camera saw a robot: source -> time of its last accepted measurement (s);
    rejected: source -> rejected measurements; last_source: the latest accepted one."""

    last: dict[str, float] = field(default_factory=dict)
    rejected: dict[str, int] = field(default_factory=dict)
    last_source: str = ""


class Fusion:
    """Fuses measurements of several cameras per robot (module docstring)."""

    def __init__(self, config: TrackerConfig | None = None, max_age_s: float = 0.5) -> None:
        if not (isinstance(max_age_s, (int, float)) and math.isfinite(max_age_s)
                and max_age_s > 0):
            raise ValueError(f"fusion max_age_s must be a finite time > 0 s, got {max_age_s!r}")
        self.tracker = Tracker(config)
        self.max_age_s = float(max_age_s)
        self.now = -math.inf  # newest measurement time seen
        self.seen: dict[str, RobotSeen] = {}
        self.dropped_old = 0
        self.accepted = 0
        self.restarted = 0  # tracks started again after a coast (_restart_if_lost)

    def add(self, m: Measurement) -> Outcome | None:
        """Apply one measurement; None when it was older than ``max_age_s`` (dropped)."""
        if not math.isfinite(m.t):
            self.dropped_old += 1
            return None
        if m.t < self.now - self.max_age_s:
            self.dropped_old += 1
            return None
        self.now = max(self.now, m.t)
        self._restart_if_lost(m)
        out = self.tracker.update(m.name, m.t, m.x, m.y, m.theta, m.sigma, source=m.source)
        seen = self.seen.setdefault(m.name, RobotSeen())
        if out.accepted:
            self.accepted += 1
            seen.last[m.source] = max(seen.last.get(m.source, -math.inf), m.t)
            seen.last_source = m.source
        else:
            seen.rejected[m.source] = seen.rejected.get(m.source, 0) + 1
        return out

    def _restart_if_lost(self, m: Measurement) -> None:
        """A track coasted so long that its predicted position is less certain than the
        outlier model's radius (no camera saw the robot through a fast turn: the cameras
        together leave shorter gaps than ``reset_after_s``, which restarts one camera's
        track) starts again from this measurement: updated, its step bound would leave it
        between the prediction and the measurement, far from both, and the next
        re-acquisition would jump back."""
        tr = self.tracker.tracks.get(m.name)
        if tr is None or tr.t is None or not m.t > tr.t:
            return
        st = tr.predict(m.t)
        if st is not None and st.sigma is not None \
                and st.sigma > self.tracker.config.outlier_radius:
            self.tracker.reset(m.name)
            self.restarted += 1

    def pose(self, name: str, t: float | None = None) -> TrackState | None:
        """Fused state of robot ``name`` at time ``t`` (default: its newest measurement)."""
        tr = self.tracker.tracks.get(name)
        if tr is None or not tr.started:
            return None
        return tr.state() if t is None else tr.predict(t)

    def sources(self, name: str, within_s: float) -> list[str]:
        """Cameras with an accepted measurement of ``name`` in the last ``within_s`` s of
        the fusion clock, sorted."""
        seen = self.seen.get(name)
        if seen is None:
            return []
        return sorted(s for s, t in seen.last.items() if t >= self.now - within_s)
