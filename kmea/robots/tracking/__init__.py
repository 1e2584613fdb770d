"""A per-robot tracking filter on (x, y, theta), numpy only (docs/tracking.md).

Each robot has a :class:`Track`: an interacting-multiple-model Kalman filter
(:mod:`.imm`: a cruise and a manoeuvre mode of one motion model, :mod:`.models`) whose
measurement is the robot pose (x, y in world metres, theta in radians) with its own
uncertainty; a chi-square gate (:mod:`.gating`); a bound on the step any accepted measurement
may cause (:mod:`.step_bound`); re-acquisition after a hand move (:mod:`.reacquire`).
:class:`Tracker` keeps the tracks of a fleet. Time: ``t`` in seconds on any clock shared
by the measurements of one robot.
"""

from kmea.robots.tracking.config import MODELS, TrackerConfig
from kmea.robots.tracking.track import Outcome, Rejection, Track, Tracker, TrackState

__all__ = ["MODELS", "Outcome", "Rejection", "Track", "TrackState", "Tracker",
           "TrackerConfig"]
