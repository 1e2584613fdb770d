"""Re-acquisition: rejected measurements that agree with each other restart the track.

A robot moved by hand (kidnapped) gives measurements far from its track, which the gate
rejects. Rejected measurements that agree with each other form a chain with a track of its
own (it takes every step: no step bound); after ``reacquire_n`` of them within
``reacquire_window_s`` the robot's track restarts from the chain's. Links further apart than
the robot can drive (``max_speed``) are not one robot: random outliers in a row.

Two rules keep a chain going:

- a measurement that breaks the chain starts a new one, and the chain it broke is kept for
  one measurement: when the next one continues it, the breaking one was an outlier among
  the candidates and the chain goes on without it;
- once two links agree, a measurement inside the robot track's gate that fits that track
  poorly (outside the :data:`FIT_PROBABILITY` quantile) but the chain's track well (inside
  it, and better) joins the chain instead of the track: after a hand move the track's
  prediction widens while it rejects the measurements at the new place, until one passes
  its gate, and the track would then walk over by bounded steps instead of re-acquiring.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np

from kmea.robots.tracking.config import TrackerConfig
from kmea.robots.tracking.gating import innovation
from kmea.stats.chi2 import chi2_quantile

__all__ = ["FIT_PROBABILITY", "Candidates", "Link", "reachable"]

#: A measurement "fits" a track when its squared Mahalanobis distance is inside this
#: chi-square quantile (3 dof): tighter than the gate.
FIT_PROBABILITY = 0.99


class Link(NamedTuple):
    """One rejected measurement of a chain: time t (s), pose z (x, y, theta), covariance R."""

    t: float
    z: np.ndarray
    R: np.ndarray


def reachable(last: Link, t: float, z: np.ndarray, R: np.ndarray, speed: float) -> bool:
    """Could the robot at ``last`` be at ``z`` at ``t``, driving at ``speed`` m/s (plus 3
    sigma of the two measurements)?"""
    reach = speed * abs(t - last.t) + 3.0 * math.sqrt(R[0, 0] + last.R[0, 0])
    return math.hypot(z[0] - last.z[0], z[1] - last.z[1]) <= reach


class Candidates:
    """The chain of rejected measurements of one robot, the chain's own track, and the
    chain a measurement just broke.

    new_track: makes an empty track for a new chain (the robot's track class, with a
    configuration that takes every step and never re-acquires itself).
    """

    def __init__(self, cfg: TrackerConfig, new_track: Callable[[], Any]) -> None:
        self.cfg = cfg
        self.new_track = new_track
        self.fit = chi2_quantile(FIT_PROBABILITY, 3)
        self.chain: list[Link] = []
        self.track: Any = None
        self.broken: tuple[list[Link], Any] = ([], None)

    def clear(self) -> None:
        self.chain, self.track, self.broken = [], None, ([], None)

    def follows(self, t: float, z: np.ndarray, R: np.ndarray, d2: float) -> bool:
        """A measurement inside the gate at squared distance ``d2`` from the robot's track
        that fits the chain's track better, and well: it joins the chain."""
        c = self.track
        if c is None or len(self.chain) < 2 or d2 <= self.fit:
            return False
        if t - self.chain[0].t > self.cfg.reacquire_window_s or t < c.t:
            return False
        if not reachable(self.chain[-1], t, z, R, self.cfg.max_speed):
            return False
        s, P = c.mode_set.combine(c.mode_set.predict(c.modes, t - c.t))
        inn = innovation(s, P, z, R)
        return inn is not None and inn.d2 <= self.fit and inn.d2 < d2

    def add(self, t: float, z: np.ndarray, R: np.ndarray) -> Any:
        """Keep a measurement the robot's track does not take; the chain's track when
        ``reacquire_n`` agree (the caller restarts from it), else None."""
        window = self.cfg.reacquire_window_s
        if self._joins(self.chain, self.track, t, z, R):
            self.chain.append(Link(t, z, R))
        elif self._joins(*self.broken, t, z, R):
            # The measurement that broke the chain was an outlier among the candidates.
            self.chain, self.track = self.broken
            self.chain.append(Link(t, z, R))
            self.broken = ([], None)
        else:
            recent = self.chain and t - self.chain[0].t <= window
            self.broken = (self.chain, self.track) if recent else ([], None)
            self.track = self.new_track()
            self.track.update(t, z[0], z[1], z[2], math.sqrt(R[0, 0]), math.sqrt(R[2, 2]))
            self.chain = [Link(t, z, R)]
        if len(self.chain) >= self.cfg.reacquire_n:
            track = self.track
            self.clear()
            return track
        return None

    def _joins(self, chain: list[Link], track: Any, t: float, z: np.ndarray,
               R: np.ndarray) -> bool:
        """Whether ``z`` at ``t`` continues ``chain`` (its ``track`` updated with it if so)."""
        if track is None or not chain or t - chain[0].t > self.cfg.reacquire_window_s:
            return False
        if not reachable(chain[-1], t, z, R, self.cfg.max_speed):
            return False
        out = track.update(t, z[0], z[1], z[2], math.sqrt(R[0, 0]), math.sqrt(R[2, 2]))
        return out.kind == "update"
