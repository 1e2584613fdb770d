"""The tracking filter's configuration (units: m, rad, s)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, fields, replace
from typing import Any

__all__ = ["MODELS", "TrackerConfig"]

MODELS = ("cv", "ctrv")


@dataclass(frozen=True)
class TrackerConfig:
    """Tuning of the tracking filter (defaults: tuned by ``kmea bench tracking``, as in
    config.toml).

    model: "cv" (constant velocity) or "ctrv" (constant turn rate and velocity).
    accel_noise: white acceleration density, m^2/s^3; turn_noise: white angular
    acceleration density, rad^2/s^3 (the cruise mode's).
    gate_probability: chi-square gate (3 dof) of a measurement against the prediction.
    reacquire_n: rejected measurements that agree with each other and restart the track (the
    robot was moved by hand); reacquire_window_s: they must fall within this time.
    reset_after_s: a track not updated for this long restarts from its next measurement.
    default_sigma: position sigma (m) of a measurement that has none; min_sigma: the floor
    on any position sigma (estimators can be over-confident); heading_lever: m (a heading
    without its own sigma has the measurement's position sigma, before min_sigma, over
    heading_lever); min_sigma_theta: the floor on heading sigma, rad.
    max_speed, max_turn_rate: 1-sigma of a new track's velocity and turn rate (m/s, rad/s);
    max_speed is also the fastest a robot moves between two re-acquisition candidates.
    step_k: no accepted measurement moves the position by more than step_k sigmas of the
    position covariance after it (an outlier inside the gate moves the output by at most
    that); 1e9 disables it.
    outlier_probability, outlier_radius: the outlier mixture's prior: the fraction of
    measurements that are outliers, and the distance (m) within which an outlier falls
    anywhere around the robot (the reported covariance after an accepted measurement
    includes the chance that it was one).
    manoeuvre_scale: > 1 adds a manoeuvre mode whose process noise is this many times the
    cruise mode's, the two run as an interacting-multiple-model filter; 1 = one mode.
    manoeuvre_time_s, cruise_time_s: the mean time (s) in a manoeuvre and between
    manoeuvres (the modes' switching rates).
    """

    model: str = "ctrv"
    accel_noise: float = 0.06
    turn_noise: float = 2.5
    gate_probability: float = 0.9999
    reacquire_n: int = 3
    reacquire_window_s: float = 1.0
    reset_after_s: float = 1.0
    default_sigma: float = 0.005
    min_sigma: float = 0.002
    heading_lever: float = 0.05
    min_sigma_theta: float = 0.0125
    max_speed: float = 1.5
    max_turn_rate: float = 3.0
    step_k: float = 1.2
    outlier_probability: float = 0.05
    outlier_radius: float = 0.2
    manoeuvre_scale: float = 200.0
    manoeuvre_time_s: float = 0.3
    cruise_time_s: float = 2.0

    def __post_init__(self) -> None:
        check_tracker_config(self)

    def with_(self, **changes: object) -> TrackerConfig:
        return replace(self, **changes)

    @classmethod
    def from_table(cls, table: Mapping[str, Any]) -> TrackerConfig:
        """From a ``[filter]`` configuration table: its keys named like this class's fields
        (the others, e.g. ``alpha`` and ``kind``, are not the tracking filter's); missing
        keys keep the defaults."""
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in table.items() if k in names})


def check_tracker_config(cfg: TrackerConfig) -> None:
    """``ValueError`` naming the first field that no filter can run with."""
    if cfg.model not in MODELS:
        raise ValueError(f"tracker model must be one of {', '.join(MODELS)}, "
                         f"got {cfg.model!r}")
    for f in fields(cfg):
        if f.name == "model":
            continue
        v = getattr(cfg, f.name)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) \
                or v <= 0:
            raise ValueError(f"tracker {f.name} must be a finite number > 0, got {v!r}")
    if cfg.manoeuvre_scale < 1.0:
        raise ValueError(f"tracker manoeuvre_scale must be >= 1, got {cfg.manoeuvre_scale!r}")
    for name in ("gate_probability", "outlier_probability"):
        if not getattr(cfg, name) < 1.0:
            raise ValueError(f"tracker {name} must be in (0, 1), got {getattr(cfg, name)!r}")
    if int(cfg.reacquire_n) != cfg.reacquire_n:
        raise ValueError(f"tracker reacquire_n must be an integer >= 1, got "
                         f"{cfg.reacquire_n!r}")
