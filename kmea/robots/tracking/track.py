"""A robot's track and the tracker of a fleet: the coordinator of gate, step bound and
re-acquisition around the IMM filter.

One measurement (:meth:`Track.update`): predicted to its time; gated (:mod:`.gating`); an
accepted one corrects the modes with the step-bounded weight (:mod:`.step_bound`; a new
track's first accepted update takes the whole correction, its velocity unknown before); a
rejected one, or one that fits a chain of rejected ones better than the track, is kept as a
re-acquisition candidate (:mod:`.reacquire`). The covariance after an accepted one includes
the chance that it was an outlier (:mod:`.mixture`). A measurement older
than the track's last one (out of order, e.g. from a slower camera) is applied at its own
time and the track brought back to its newest time; one more than ``reset_after_s`` older
is dropped and reported.
"""

from __future__ import annotations

import functools
import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from kmea.geometry.rotations import wrap_angle
from kmea.robots.tracking.config import TrackerConfig
from kmea.robots.tracking.gating import innovation, rejection_reason
from kmea.robots.tracking.imm import Modes, ModeSet
from kmea.robots.tracking.mixture import mixed, outlier_posterior, prior_density_ratio
from kmea.robots.tracking.reacquire import Candidates
from kmea.robots.tracking.step_bound import step_weight
from kmea.stats.chi2 import chi2_quantile

__all__ = ["MAX_POSITION", "Outcome", "Rejection", "Track", "TrackState", "Tracker"]

#: m: a position beyond this is no floor's; its square (a covariance term) would overflow
#: long before a float does.
MAX_POSITION = 1e9


@dataclass(frozen=True)
class TrackState:
    """A robot's estimated state at time ``t`` (s).

    x, y: m; theta: rad in [-pi, pi); vx, vy: world velocity, m/s; speed: |v| m/s (signed
    along the heading for "ctrv"); omega: turn rate, rad/s; sigma: 1-sigma position
    uncertainty (m, the larger axis of the position covariance); sigma_theta: rad.
    cov: (3, 3) covariance of (x, y, theta).
    """

    t: float
    x: float
    y: float
    theta: float
    vx: float
    vy: float
    speed: float
    omega: float
    sigma: float
    sigma_theta: float
    cov: np.ndarray = field(repr=False, compare=False)


@dataclass(frozen=True)
class Outcome:
    """What one measurement did to a track.

    kind: "init" (track started), "update" (accepted), "rejected" (gated out or too old;
    ``reason`` says why), "reacquired" (the track restarted from consistent rejected
    measurements), "reset" (restarted after ``reset_after_s`` without measurements),
    "failed" (refused: it would have left a non-finite or singular state; the track was
    reset, ``state`` is None).
    d2: squared Mahalanobis distance to the prediction (nan when not computed).
    state: the track's state after the measurement, at the measurement's time (a rejected
    one: the prediction; an out-of-order one: at the track's newest time; None when a
    too-old measurement was dropped).
    """

    kind: str
    reason: str
    d2: float
    state: TrackState | None

    @property
    def accepted(self) -> bool:
        return self.kind not in ("rejected", "failed")


@functools.lru_cache(maxsize=16)
def _candidates_config(cfg: TrackerConfig) -> TrackerConfig:
    """A candidate chain's own track takes every step and never re-acquires (made once per
    configuration: validating one costs more than a filter update)."""
    return cfg.with_(reacquire_n=10 ** 9, step_k=1e9)


class Track:
    """The tracking filter of one robot (docs/tracking.md).

    ``modes``: the IMM filter's state (:class:`kmea.robots.tracking.imm.Modes`); ``s`` (n,) and
    ``P`` (n, n) its combination, what is gated, reported and predicted; ``t``: the time of
    the newest measurement applied (s)."""

    def __init__(self, name: str = "", config: TrackerConfig | None = None,
                 candidate: bool = False) -> None:
        self.name = name
        self.config = cfg = config or TrackerConfig()
        # A re-acquisition chain's own track: every step, no outlier mixture.
        self.candidate = candidate
        self._outlier_ratio = prior_density_ratio(cfg.outlier_probability,
                                                  cfg.outlier_radius)
        self.gate = chi2_quantile(cfg.gate_probability, 3)
        self.mode_set = ModeSet(cfg)
        self.modes: Modes | None = None
        self.s: np.ndarray | None = None
        self.P: np.ndarray | None = None
        self.t: float | None = None
        # True from a start until the track's first accepted update (see update()).
        self.fresh = False
        self.candidates = Candidates(cfg, lambda: Track(name, _candidates_config(cfg), True))

    def noise(self, sigma: float | None, sigma_theta: float | None = None) -> np.ndarray:
        """(3, 3) measurement covariance of a pose with position sigma ``sigma`` m (and
        heading sigma ``sigma_theta`` rad: by default sigma / heading_lever)."""
        cfg = self.config
        sp = cfg.default_sigma if sigma is None or not math.isfinite(sigma) else float(sigma)
        if sigma_theta is None or not math.isfinite(sigma_theta):
            # The heading's own sigma: the position sigma's over the lever (before the floor
            # on position sigma; the heading has its own floor).
            sigma_theta = sp / cfg.heading_lever
        sp = max(sp, cfg.min_sigma)
        st = max(float(sigma_theta), cfg.min_sigma_theta)
        v, vt = sp * sp, st * st
        return np.array([[v, 0.0, 0.0], [0.0, v, 0.0], [0.0, 0.0, vt]])

    def update(self, t: float, x: float, y: float, theta: float, sigma: float | None = None,
               sigma_theta: float | None = None) -> Outcome:
        """Apply one pose measurement taken at ``t`` s (x, y m; theta rad; sigma m).

        The track never holds a state that is not finite or a covariance that is not
        positive: a measurement that would leave one (values beyond any floor, e.g. 1e300 m)
        is refused and the track reset (kind ``"failed"``); the next one starts it again."""
        if not (math.isfinite(t) and math.isfinite(x) and math.isfinite(y)
                and math.isfinite(theta)):
            return Outcome("rejected", "not finite", math.nan, self.state())
        try:
            with np.errstate(all="ignore"):
                out = self._update(t, x, y, theta, sigma, sigma_theta)
        except (np.linalg.LinAlgError, ArithmeticError):  # ZeroDivision, Overflow
            out = None
        if out is not None and self._healthy():
            return out
        self.reset()
        return Outcome("failed", "the step would leave a non-finite or singular state: "
                       "measurement refused, track reset", math.nan, None)

    def _healthy(self) -> bool:
        """Every mode's state and covariance finite, the variances positive, and the
        position small enough that its square is finite too."""
        if self.modes is None or self.s is None or self.P is None:
            return True
        ss, Ps, mu = self.modes
        if not (np.isfinite(ss).all() and np.isfinite(Ps).all() and np.isfinite(mu).all()):
            return False
        if not (np.diagonal(Ps, axis1=1, axis2=2) > 0.0).all():
            return False
        return bool(np.abs(ss[:, :2]).max() < MAX_POSITION and np.isfinite(self.P).all())

    def reset(self) -> None:
        """Forget the state: the next measurement starts the track."""
        self.modes = self.s = self.P = self.t = None
        self.fresh = False
        self.candidates.clear()

    def _update(self, t: float, x: float, y: float, theta: float, sigma: float | None,
                sigma_theta: float | None) -> Outcome:
        z = np.array([float(x), float(y), wrap_angle(float(theta))])
        R = self.noise(sigma, sigma_theta)
        cfg = self.config
        if self.modes is None or self.t is None:
            self._start(t, z, R)
            return Outcome("init", "first measurement", math.nan, self.state())
        dt = t - self.t
        if dt > cfg.reset_after_s:
            self._start(t, z, R)
            return Outcome("reset", f"no measurement for {dt:.2f} s", math.nan, self.state())
        if dt < -cfg.reset_after_s:
            return Outcome("rejected", f"too old ({-dt:.2f} s before the last measurement)",
                           math.nan, None)
        pred = self.mode_set.predict(self.modes, dt)
        sc, Pc = self.mode_set.combine(pred)
        inn = innovation(sc, Pc, z, R)
        if inn is None:
            return Outcome("rejected", "singular innovation covariance", math.nan, self.state())
        if inn.d2 > self.gate or (dt >= 0 and self.candidates.follows(t, z, R, inn.d2)):
            reason = rejection_reason(inn, self.gate)
            restart = self.candidates.add(t, z, R)
            if restart is not None:
                self._set(restart.modes, restart.t)
                self.fresh = False
                return Outcome("reacquired", f"{cfg.reacquire_n} consistent measurements away "
                               f"from the track ({reason})", inn.d2, self.state())
            st = self._state(t, sc, Pc) if dt > 0 else self.predict(self.t)
            return Outcome("rejected", reason, inn.d2, st)
        self.candidates.clear()
        g = self.mode_set.gains(pred, z, R)
        ky = (g.Ks @ g.ys[:, :, None])[:, :, 0]
        # A new track knows no velocity (1-sigma max_speed): its prediction is no reference
        # for the step bound, and its first accepted update takes the whole correction, so the
        # velocity comes from its first two measurements.
        w = 1.0 if self.fresh else step_weight(pred, g, ky, (float(sc[0]), float(sc[1])),
                                               cfg.step_k)
        self.fresh = False
        new = self.mode_set.correct(pred, R, g, w, ky)
        if not self.candidate:
            q = outlier_posterior(sc, Pc, z, R, self._outlier_ratio)
            new = mixed(pred, new, w * ky, q)
        if dt >= 0:
            self._set(new, t)
        else:
            # Out of order: corrected at the measurement's time, then brought back to the
            # track's newest time.
            self._set(self.mode_set.predict(new, -dt), self.t)
        return Outcome("update", "", inn.d2, self.state())

    def _set(self, modes: Modes, t: float) -> None:
        self.modes = modes
        self.s, self.P = self.mode_set.combine(modes)
        self.t = float(t)

    def _start(self, t: float, z: np.ndarray, R: np.ndarray) -> None:
        cfg = self.config
        self._set(self.mode_set.start(z, R, cfg.max_speed, cfg.max_turn_rate), t)
        self.fresh = True
        self.candidates.clear()

    # ------------------------------------------------------------------ output
    @property
    def started(self) -> bool:
        return self.s is not None

    def state(self) -> TrackState | None:
        """The state at the newest measurement's time, or None before the first one."""
        if self.s is None or self.P is None or self.t is None:
            return None
        return self._state(self.t, self.s, self.P)

    def predict(self, t: float) -> TrackState | None:
        """The state predicted to time ``t`` s (latency compensation); the track is not
        changed. None before the first measurement."""
        if self.modes is None or self.t is None:
            return None
        if t == self.t:
            return self.state()
        s, P = self.mode_set.combine(self.mode_set.predict(self.modes, t - self.t))
        return self._state(t, s, P)

    def _state(self, t: float, s: np.ndarray, P: np.ndarray) -> TrackState:
        sl = s.tolist()
        vx, vy, speed, omega = self.mode_set.model.velocity(sl)
        cov = P[:3, :3].copy()
        (a, _, _), (b, d, _), (_, _, c) = cov.tolist()
        # The larger eigenvalue of the symmetric 2x2 position block (its lower triangle, as
        # eigvalsh reads it), in closed form.
        h = 0.5 * (a - d)
        sig = math.sqrt(max(0.5 * (a + d) + math.sqrt(h * h + b * b), 0.0))
        return TrackState(float(t), sl[0], sl[1], wrap_angle(sl[2]), vx, vy, speed, omega,
                          sig, math.sqrt(max(c, 0.0)), cov)


@dataclass(frozen=True)
class Rejection:
    """A rejected measurement, for reports: robot, time (s), measured pose, reason."""

    name: str
    t: float
    x: float
    y: float
    theta: float
    reason: str
    source: str = ""


class Tracker:
    """Tracks of several robots by name; keeps the last ``keep`` rejections for reports."""

    def __init__(self, config: TrackerConfig | None = None, keep: int = 1000) -> None:
        self.config = config or TrackerConfig()
        self.tracks: dict[str, Track] = {}
        self.rejections: deque[Rejection] = deque(maxlen=keep)
        self.counts = {"init": 0, "update": 0, "rejected": 0, "reacquired": 0, "reset": 0,
                       "failed": 0}

    def track(self, name: str) -> Track:
        tr = self.tracks.get(name)
        if tr is None:
            tr = self.tracks[name] = Track(name, self.config)
        return tr

    def update(self, name: str, t: float, x: float, y: float, theta: float,
               sigma: float | None = None, sigma_theta: float | None = None,
               source: str = "") -> Outcome:
        """One measurement of robot ``name`` (see :meth:`Track.update`)."""
        out = self.track(name).update(t, x, y, theta, sigma, sigma_theta)
        self.counts[out.kind] += 1
        if not out.accepted:
            self.rejections.append(Rejection(name, t, x, y, theta, out.reason, source))
        return out

    def predict(self, name: str, t: float) -> TrackState | None:
        tr = self.tracks.get(name)
        return None if tr is None else tr.predict(t)

    def reset(self, name: str | None = None) -> None:
        if name is None:
            self.tracks.clear()
        else:
            self.tracks.pop(name, None)
