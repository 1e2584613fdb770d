"""A per-robot tracking filter on (x, y, theta): Kalman filtering with gating, numpy only.

Each robot has a :class:`Track`, an extended Kalman filter whose measurement is the robot
pose (x, y in world metres, theta in radians) with the measurement's own uncertainty:
``sigma`` (1-sigma position, m, as :class:`kmea.robots.RobotPose` gives it) and a heading
sigma (rad; by default ``sigma / heading_lever``, the heading error of two points
``2 * heading_lever`` m apart each known to ``sigma``). Two motion models:

- ``"cv"`` constant velocity: state (x, y, theta, vx, vy, omega); position and heading move
  independently (holonomic robots, robots that reverse). Linear.
- ``"ctrv"`` constant turn rate and velocity: state (x, y, theta, v, omega); the robot drives
  along its heading (differential drive), v signed.

Process noise is white acceleration of spectral density ``accel_noise`` (m^2/s^3) and white
angular acceleration of ``turn_noise`` (rad^2/s^3). Heading innovations are wrapped to
[-pi, pi) and the heading state is kept wrapped.

Two models (``manoeuvre_scale`` > 1): the motion model runs twice, once with that process
noise ("cruise") and once with ``manoeuvre_scale`` times it ("manoeuvre": braking, starting,
entering a turn), as an interacting-multiple-model (IMM) filter: before each prediction the
two are mixed by their switching probabilities (mean times ``cruise_time_s`` and
``manoeuvre_time_s``), after each measurement their probabilities follow their likelihoods.
Gating, outputs and predictions use their combination (moment-matched mean and covariance),
so the reported sigma is small when cruising and widens as soon as a manoeuvre shows.

Gating: a measurement whose Mahalanobis distance d^2 to the prediction exceeds the
chi-square quantile of 3 degrees of freedom at ``gate_probability`` is rejected (not
followed) and reported with the reason (a position jump, a heading flip). Rejected
measurements that agree with each other (each inside the gate of a track started from the
first) are candidates: after ``reacquire_n`` of them within ``reacquire_window_s`` the track
restarts from them (the robot really was moved by hand); an accepted measurement clears them.

Bounded update: an accepted measurement at Mahalanobis distance d > ``robust_k`` moves the
state by ``robust_k / d`` of the Kalman correction (Huber weight), and no accepted
measurement moves the position by more than ``step_k`` sigmas of the position covariance
after it (the weight is lowered until it does not); the covariance is that of the gain used,
so it stays honest. Cumulative bound (``step_cumulative``): the measurement right after a
suspicious one (d > robust_k) may not move the position further than ``step_k`` sigmas from
the track that skipped the suspicious one either, unless it confirms it (fits the track that
took it in full inside the chi-square quantile at ``confirm_probability``): two outliers in
a row cannot add their bounded steps up.

Look-back: an outlier inside the gate pulls the track so that the good measurements after it
are rejected. When a measurement is rejected, the track is rebuilt without the last accepted
one (up to ``look_back_n`` of them) through the measurements rejected since and the new one;
if each fits it well (inside the chi-square quantile at ``look_back_probability``), and the
retracted one misses the rebuilt track (by that quantile when that implies fewer outliers, by
the gate when as many), the accepted one is retracted and reported as rejected, late
(:attr:`Outcome.retracted`, :attr:`Outcome.retracted_all`, :attr:`Tracker.rejections`).

Recovery (``recover``): when the two measurements right after an accepted one are both
rejected, lie close to each other and fit the track rebuilt without that accepted one (the
first inside the gate, the second inside the confirmation quantile), the accepted one is
retracted and reported (one outlier instead of two) and the track goes on from the rebuilt
one through both, with full Kalman updates.

Re-acquisition candidates must also be reachable from each other at ``max_speed``; once 2
agree, a measurement inside the gate that fits them well and the track poorly is the next
candidate (``reacquire_follow``); a measurement that breaks their chain is dropped when the
next one continues it (``reacquire_skip_outlier``).

Time: ``t`` is in seconds on any clock shared by the measurements of one robot.
:meth:`Track.predict` gives the state at another time (latency compensation: predict to the
send time). A measurement older than the track's last one (out of order, e.g. from a slower
camera) is applied at its own time through the model (retrodicted); one more than
``reset_after_s`` older is dropped and reported.
"""

from __future__ import annotations

import functools
import math
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from typing import Any

import numpy as np

try:
    # The gufuncs behind np.linalg.inv and np.linalg.det: the same LAPACK calls, without
    # the public functions' per-call argument checks and error-state switch (most of the
    # cost of a 3x3 inverse). Private to numpy; without them, the public functions.
    from numpy.linalg import _umath_linalg as _gufuncs
except ImportError:  # pragma: no cover
    _gufuncs = None

__all__ = [
    "MODELS",
    "Outcome",
    "Track",
    "TrackState",
    "Tracker",
    "TrackerConfig",
    "chi2_quantile_3",
]

MODELS = ("cv", "ctrv")
_TWO_PI = 2.0 * math.pi


def _wrap(a: float) -> float:
    return (a + math.pi) % _TWO_PI - math.pi


def _inv(S: np.ndarray) -> np.ndarray:
    """np.linalg.inv of float64 ``S`` (..., 3, 3), bit for bit. A singular S gives NaN
    here (numpy warns): callers check their result and call :func:`np.linalg.inv` itself
    when it is not finite (it raises LinAlgError as before)."""
    if _gufuncs is None:  # pragma: no cover
        return np.linalg.inv(S)
    return _gufuncs.inv(S, signature="d->d")


def _det(S: np.ndarray) -> np.ndarray:
    """np.linalg.det of float64 ``S`` (..., 3, 3), bit for bit (the same gufunc call)."""
    if _gufuncs is None:  # pragma: no cover
        return np.linalg.det(S)
    return _gufuncs.det(S, signature="d->d")


def _innovation(s: np.ndarray, P: np.ndarray, z: np.ndarray, R: np.ndarray
                ) -> tuple[list, np.ndarray, np.ndarray, float] | None:
    """Innovation of measurement ``z`` (x, y, theta) with covariance ``R`` (3, 3) against
    the predicted state ``s`` and covariance ``P``: (y (3 floats), S, S^-1, Mahalanobis
    d^2), or None when S is singular."""
    s0, s1, s2 = s[:3].tolist()
    z0, z1, z2 = z.tolist()
    y = [z0 - s0, z1 - s1, _wrap(z2 - s2)]
    S = P[:3, :3] + R
    Si = _inv(S)
    d2 = _mahalanobis(y, Si.tolist())
    if not math.isfinite(d2):
        # Singular (or overflowing) S: np.linalg.inv's own answer.
        try:
            Si = np.linalg.inv(S)
        except np.linalg.LinAlgError:
            return None
        d2 = _mahalanobis(y, Si.tolist())
    return y, S, Si, d2


def _mahalanobis(y: list, Si: list) -> float:
    """y^T Si y of 3 floats and a 3x3 nested list: (y Si) y, summed in order (as numpy's
    y @ Si @ y does, bit for bit)."""
    y0, y1, y2 = y
    (a, b, c), (d, e, f), (g, h, i) = Si
    return (y0 * a + y1 * d + y2 * g) * y0 + (y0 * b + y1 * e + y2 * h) * y1 \
        + (y0 * c + y1 * f + y2 * i) * y2


def _chi2_cdf_3(x: float) -> float:
    """CDF of the chi-square distribution with 3 degrees of freedom."""
    if x <= 0.0:
        return 0.0
    return math.erf(math.sqrt(x / 2.0)) - math.sqrt(2.0 * x / math.pi) * math.exp(-x / 2.0)


@functools.lru_cache(maxsize=64)
def chi2_quantile_3(p: float) -> float:
    """x with P(chi2_3 <= x) = p, 0 < p < 1 (bisection; 0.99 -> 11.34, 0.999 -> 16.27)."""
    if not 0.0 < p < 1.0:
        raise ValueError(f"chi-square probability must be in (0, 1), got {p!r}")
    lo, hi = 0.0, 200.0
    for _ in range(100):
        mid = (lo + hi) / 2.0
        if _chi2_cdf_3(mid) < p:
            lo = mid
        else:
            hi = mid
    return (lo + hi) / 2.0


@dataclass(frozen=True)
class TrackerConfig:
    """Tuning of the tracking filter (units: m, rad, s).

    model: "cv" or "ctrv" (module docstring). accel_noise: m^2/s^3; turn_noise: rad^2/s^3
    (defaults: tuned by ``kmea bench tracking``, as in config.toml).
    gate_probability: chi-square gate (3 dof). reacquire_n: consistent rejected measurements
    that restart a track; reacquire_window_s: they must fall within this time.
    reset_after_s: a track not updated for this long restarts from its next measurement.
    default_sigma: position sigma when a measurement has none; min_sigma: floor on any
    position sigma (estimators can be over-confident); heading_lever: m (heading sigma =
    sigma / heading_lever); min_sigma_theta: floor on heading sigma, rad.
    max_speed, max_turn_rate: 1-sigma of the initial velocity and turn rate (m/s, rad/s);
    max_speed is also the fastest a robot moves between two re-acquisition candidates.
    robust_k: Huber threshold on the Mahalanobis distance d = sqrt(d2): an accepted
    measurement with d > robust_k moves the state by only robust_k / d of the Kalman
    correction; a large value disables it. step_k: no accepted measurement moves the
    position by more than step_k sigmas of the position covariance after it (an outlier
    inside the gate cannot move the output by more than that); 1e9 disables it.
    look_back: a measurement outside the gate may retract the accepted one just before it
    when that one, not the new one, is the outlier (module docstring); the new one must
    then fit the prediction without it inside the chi-square quantile at
    look_back_probability. look_back_n: how many of the last accepted measurements a
    look-back may retract at once (1: only the one just before).
    step_cumulative: the measurement right after a suspicious one (beyond robust_k) may not
    move the position further than step_k sigmas from the track that skipped the suspicious
    one either, unless it confirms it: it fits the track that took it in full inside the
    chi-square quantile at confirm_probability (a manoeuvre, not two outliers in a row).
    max_speed also bounds re-acquisition: consecutive candidates further apart than
    max_speed allows (plus 3 sigma of the two measurements) are not the same robot.
    reacquire_follow: once 2 rejected measurements agree (candidates), a measurement inside
    the gate that fits the track poorly (outside the look-back quantile) but the
    candidates' track well (inside it, and better) is taken as the next candidate.
    reacquire_skip_outlier: a measurement that breaks the candidates' chain is dropped (an
    outlier among them) when the next one continues the chain.
    manoeuvre_scale: > 1 adds a second motion model whose process noise is this many times
    accel_noise and turn_noise (a manoeuvre: braking, starting, entering a turn) and runs
    both as an interacting-multiple-model filter (module docstring); 1 = one model.
    manoeuvre_time_s, cruise_time_s: the mean time (s) spent in a manoeuvre and between
    manoeuvres (the models' switching rates).
    outlier_mixture: the covariance after each accepted measurement includes the chance
    that it was an outlier (after a rejected one the track keeps the prediction's), as
    probabilistic data association does: with the posterior probability q that the
    measurement is an outlier (prior
    outlier_probability, an outlier's position uniform within outlier_radius m of the robot,
    a good one Gaussian with the innovation covariance), the covariance about the output is
    (1 - q) (the covariance if it was good) + q (the covariance if it was an outlier), each
    with the squared distance of its mean from the output.
    recover: two rejected measurements in a row right after an accepted one, close to each
    other (within 3 sigma of the two plus what the track's speed covers in between), the
    first inside the gate of the track rebuilt without that accepted one and the second
    inside the confirm_probability quantile of that track through the first: the accepted
    one is retracted and the track rebuilt through them with full Kalman updates, instead of
    rejecting the robot's measurements until re-acquisition (module docstring).
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
    min_sigma_theta: float = 0.01
    max_speed: float = 1.5
    max_turn_rate: float = 3.0
    robust_k: float = 3.0
    look_back: bool = True
    look_back_probability: float = 0.99
    look_back_n: int = 1
    step_cumulative: bool = True
    confirm_probability: float = 0.95
    reacquire_follow: bool = True
    reacquire_skip_outlier: bool = True
    step_k: float = 1.2
    outlier_mixture: bool = True
    recover: bool = True
    outlier_probability: float = 0.05
    outlier_radius: float = 0.2
    manoeuvre_scale: float = 200.0
    manoeuvre_time_s: float = 0.3
    cruise_time_s: float = 2.0

    def __post_init__(self) -> None:
        if self.model not in MODELS:
            raise ValueError(f"tracker model must be one of {', '.join(MODELS)}, "
                             f"got {self.model!r}")
        for f in fields(self):
            if f.name == "model":
                continue
            if f.name in ("look_back", "step_cumulative", "reacquire_follow",
                          "reacquire_skip_outlier", "outlier_mixture", "recover"):
                v = getattr(self, f.name)
                if not isinstance(v, bool):
                    raise ValueError(f"tracker {f.name} must be true or false, got {v!r}")
                continue
            v = getattr(self, f.name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) \
                    or v <= 0:
                raise ValueError(f"tracker {f.name} must be a finite number > 0, got {v!r}")
        for name in ("look_back_probability", "confirm_probability", "outlier_probability"):
            if not getattr(self, name) < 1.0:
                raise ValueError(f"tracker {name} must be in (0, 1), got "
                                 f"{getattr(self, name)!r}")
        if self.manoeuvre_scale < 1.0:
            raise ValueError(f"tracker manoeuvre_scale must be >= 1, got "
                             f"{self.manoeuvre_scale!r}")
        if not self.gate_probability < 1.0:
            raise ValueError(f"tracker gate_probability must be in (0, 1), got "
                             f"{self.gate_probability!r}")
        for name in ("reacquire_n", "look_back_n"):
            v = getattr(self, name)
            if int(v) != v:
                raise ValueError(f"tracker {name} must be an integer >= 1, got {v!r}")

    def with_(self, **changes: object) -> TrackerConfig:
        return replace(self, **changes)

    @classmethod
    def from_table(cls, table: Mapping[str, Any]) -> TrackerConfig:
        """From a ``[filter]`` configuration table: its keys named like this class's fields
        (the others, e.g. ``alpha`` and ``kind``, are not the tracking filter's); missing
        keys keep the defaults."""
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in table.items() if k in names})


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
    measurements), "reset" (restarted after ``reset_after_s`` without measurements).
    d2: Mahalanobis distance squared to the prediction (nan when not computed).
    retracted: when this measurement showed that the previous accepted one was an outlier
    (module docstring, "look-back"), that one: (t, x, y, theta, reason); it is reported as
    a rejection, late. retracted_all: every measurement retracted (the look-back may
    retract up to ``look_back_n`` accepted ones at once), oldest first; ``retracted`` is
    the newest of them.
    state: the track's state after the measurement, at the measurement's time (a rejected
    one: the prediction; an out-of-order one: at the track's newest time; None when a too-old
    measurement was dropped).
    """

    kind: str
    reason: str
    d2: float
    state: TrackState | None
    retracted: tuple[float, float, float, float, str] | None = None
    retracted_all: tuple[tuple[float, float, float, float, str], ...] = ()

    @property
    def accepted(self) -> bool:
        return self.kind != "rejected"


class _Model:
    """Motion model: state transition f, its Jacobian and process noise."""

    n = 0

    def __init__(self, cfg: TrackerConfig) -> None:
        self.qa = cfg.accel_noise
        self.qw = cfg.turn_noise

    def init(self, z: np.ndarray, R: np.ndarray, cfg: TrackerConfig
             ) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def steps(self, ss: Any, Ps: np.ndarray, dt: float, qs: list[tuple[float, float]]
              ) -> tuple[np.ndarray, np.ndarray]:
        """M states (M, n) and covariances (M, n, n) moved by ``dt`` s (negative: backwards;
        the uncertainty still grows), model j with the process noise densities ``qs[j]`` =
        (accel_noise, turn_noise)."""
        raise NotImplementedError

    def velocity(self, s: np.ndarray) -> tuple[float, float, float, float]:
        """(vx, vy, speed, omega)."""
        raise NotImplementedError


class _CV(_Model):
    n = 6  # x, y, theta, vx, vy, omega

    def init(self, z, R, cfg):
        s = np.array([z[0], z[1], z[2], 0.0, 0.0, 0.0])
        P = np.zeros((6, 6))
        P[:3, :3] = R
        P[3, 3] = P[4, 4] = cfg.max_speed ** 2
        P[5, 5] = cfg.max_turn_rate ** 2
        return s, P

    def steps(self, ss, Ps, dt, qs):
        """:meth:`_Model.steps` (``ss`` an array or nested lists): F the identity with dt
        coupling each of x, y, theta to its rate; Q the continuous white-acceleration noise
        of each (position, rate) pair."""
        F = self._F(dt)
        out_s = np.array([F @ s for s in np.asarray(ss)])  # one state at a time (its rounding)
        out_s[:, 2] = (out_s[:, 2] + math.pi) % _TWO_PI - math.pi
        a = abs(dt)
        sg = float(np.sign(dt))
        c3, c2 = a ** 3 / 3.0, a * a / 2.0 * sg
        Q = np.zeros((len(qs), 6, 6))
        for j, (qa, qw) in enumerate(qs):
            for i, k, q in ((0, 3, qa), (1, 4, qa), (2, 5, qw)):
                Q[j, i, i], Q[j, i, k], Q[j, k, i], Q[j, k, k] = q * c3, q * c2, q * c2, q * a
        return out_s, F @ Ps @ F.T + Q

    @staticmethod
    def _F(dt: float) -> np.ndarray:
        F = np.eye(6)
        F[0, 3] = F[1, 4] = F[2, 5] = dt
        return F

    def velocity(self, s):
        return float(s[3]), float(s[4]), float(math.hypot(s[3], s[4])), float(s[5])


class _CTRV(_Model):
    n = 5  # x, y, theta, v, omega

    def init(self, z, R, cfg):
        s = np.array([z[0], z[1], z[2], 0.0, 0.0])
        P = np.zeros((5, 5))
        P[:3, :3] = R
        P[3, 3] = cfg.max_speed ** 2
        P[4, 4] = cfg.max_turn_rate ** 2
        return s, P

    def steps(self, ss, Ps, dt, qs):
        """:meth:`_Model.steps` (``ss`` an array or nested lists): constant turn rate and
        speed, F its Jacobian; Q white linear and angular acceleration mapped through the
        model (discretised): G diag(q) G^T / |dt|. In floats (numpy's per-call cost
        dominated it)."""
        a = abs(dt)
        h = a * a / 2.0
        out_s, Fs, Qs = [], [], []
        rows = ss.tolist() if isinstance(ss, np.ndarray) else ss
        for (x, y, th, v, w), (qa, qw) in zip(rows, qs, strict=True):
            c, sn = math.cos(th), math.sin(th)
            if abs(w * dt) > 1e-6:
                th2 = th + w * dt
                c2, s2 = math.cos(th2), math.sin(th2)
                nx = x + v / w * (s2 - sn)
                ny = y + v / w * (c - c2)
                f02 = v / w * (c2 - c)
                f03 = (s2 - sn) / w
                f04 = v * dt * c2 / w - v / (w * w) * (s2 - sn)
                f12 = v / w * (s2 - sn)
                f13 = (c - c2) / w
                f14 = v * dt * s2 / w - v / (w * w) * (c - c2)
            else:
                nx = x + v * dt * c
                ny = y + v * dt * sn
                f02 = -v * dt * sn
                f03 = dt * c
                f04 = -v * dt * dt * sn / 2.0
                f12 = v * dt * c
                f13 = dt * sn
                f14 = v * dt * dt * c / 2.0
            out_s += (nx, ny, _wrap(th + w * dt), v, w)
            Fs += (1.0, 0.0, f02, f03, f04, 0.0, 1.0, f12, f13, f14, 0.0, 0.0, 1.0, 0.0, dt,
                   0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
            if a > 0:
                # G (5, 2) = [[h c, 0], [h sn, 0], [0, h], [a, 0], [0, a]]: G diag(q) G^T / a,
                # each entry a single product (the two columns do not overlap).
                g0, g1 = h * c, h * sn
                u0, u1, u3 = g0 * qa, g1 * qa, a * qa
                w2, w4 = h * qw, a * qw
                Qs += (u0 * g0 / a, u0 * g1 / a, 0.0, u0 * a / a, 0.0,
                       u1 * g0 / a, u1 * g1 / a, 0.0, u1 * a / a, 0.0,
                       0.0, 0.0, w2 * h / a, 0.0, w2 * a / a,
                       u3 * g0 / a, u3 * g1 / a, 0.0, u3 * a / a, 0.0,
                       0.0, 0.0, w4 * h / a, 0.0, w4 * a / a)
            else:
                Qs += (0.0,) * 25
        # One array of all the numbers (cheaper than nested lists): F, Q, then the states.
        M = len(qs)
        flat = np.array(Fs + Qs + out_s)
        F = flat[:25 * M].reshape(M, 5, 5)
        Q = flat[25 * M:50 * M].reshape(M, 5, 5)
        return flat[50 * M:].reshape(M, 5), F @ Ps @ F.transpose(0, 2, 1) + Q

    def velocity(self, s):
        v, th = float(s[3]), float(s[2])
        return v * math.cos(th), v * math.sin(th), v, float(s[4])


# Derived configurations, made once per configuration (a candidates' track is made at
# most rejections; validating a configuration costs more than a filter update).
@functools.lru_cache(maxsize=16)
def _manoeuvre_config(cfg: TrackerConfig) -> TrackerConfig:
    """The second model's configuration: the process noise times ``manoeuvre_scale``."""
    return cfg.with_(accel_noise=cfg.accel_noise * cfg.manoeuvre_scale,
                     turn_noise=cfg.turn_noise * cfg.manoeuvre_scale)


@functools.lru_cache(maxsize=16)
def _candidates_config(cfg: TrackerConfig) -> TrackerConfig:
    """The candidates' own track: it takes every step (no step bound) and does not
    re-acquire."""
    return cfg.with_(reacquire_n=10 ** 9, step_k=1e9, reacquire_follow=False,
                     outlier_mixture=False)


def _model(cfg: TrackerConfig) -> _Model:
    return _CV(cfg) if cfg.model == "cv" else _CTRV(cfg)


def _moments(ss: np.ndarray, Ps: np.ndarray, w: np.ndarray, ref: float
             ) -> tuple[np.ndarray, np.ndarray]:
    """Mean and covariance of the mixture of states ``ss`` (M, n) with covariances ``Ps``
    (M, n, n) and weights ``w`` (M,); headings unwrapped around ``ref`` rad first."""
    if len(w) == 1:
        return ss[0].copy(), Ps[0].copy()
    if len(w) == 2:
        # The two models (the IMM filter): the mean in floats (w @ X in numpy's order).
        w0, w1 = w.tolist()
        a, b = ss.tolist()
        a[2] = ref + (a[2] - ref + math.pi) % _TWO_PI - math.pi
        b[2] = ref + (b[2] - ref + math.pi) % _TWO_PI - math.pi
        s = [w0 * u + w1 * v for u, v in zip(a, b, strict=True)]
        # D = X - s and D.T * w (as numpy's (D.T * w) @ D lays them out: the same product).
        da = [u - v for u, v in zip(a, s, strict=True)]
        db = [u - v for u, v in zip(b, s, strict=True)]
        DD = np.array(da + db + [v * w0 for v in da] + [v * w1 for v in db]).reshape(4, -1)
        P = w0 * Ps[0] + w1 * Ps[1] + DD[2:].T @ DD[:2]
        s[2] = _wrap(s[2])
        return np.array(s), P
    X = ss.copy()
    X[:, 2] = ref + (X[:, 2] - ref + math.pi) % _TWO_PI - math.pi
    s = w @ X
    D = X - s
    P = np.einsum("i,ijk->jk", w, Ps) + (D.T * w) @ D
    s[2] = _wrap(s[2])
    return s, P


class Track:
    """The tracking filter of one robot (see the module docstring).

    Its state is one (state, covariance) per motion model and the models' probabilities
    (``_fs``: ss (M, n), Ps (M, n, n), mu (M,)); ``s`` (n,) and ``P`` (n, n) are their
    combination (moment-matched), which is what is gated, reported and predicted."""

    def __init__(self, name: str = "", config: TrackerConfig | None = None) -> None:
        self.name = name
        self.config = cfg = config or TrackerConfig()
        self.gate = chi2_quantile_3(cfg.gate_probability)
        self.look_back_gate = chi2_quantile_3(cfg.look_back_probability)
        self.confirm_gate = chi2_quantile_3(cfg.confirm_probability)
        self._models = [_model(cfg)]
        if cfg.manoeuvre_scale > 1.0:
            self._models.append(_model(_manoeuvre_config(cfg)))
        self._n = self._models[0].n
        self._qs = [(m.qa, m.qw) for m in self._models]
        self._eyes = np.repeat(np.eye(self._n)[None], len(self._models), 0)
        self._fs: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self.s: np.ndarray | None = None
        self.P: np.ndarray | None = None
        self.t: float | None = None  # time of the newest measurement applied
        self._cand: list[tuple[float, np.ndarray, np.ndarray]] = []
        self._cand_track: Track | None = None
        # The chain a measurement broke (candidates, their track): kept one measurement.
        self._cand_prev: tuple[list, Track | None] = ([], None)
        # The last accepted measurements (up to look_back_n, consecutive, in order) and the
        # filter before each (for the look-back): (t_before, fs_before, t, z, R); and the
        # measurements rejected since the newest of them: (t, z, R).
        self._hist: list[tuple] = []
        self._last_combined: tuple | None = None  # (fs, _combine(fs))
        self._rej_run: list[tuple[float, np.ndarray, np.ndarray]] = []
        # While accepted measurements in a row are down-weighted: (t, the track that skipped
        # them, the track that took them in full), for the cumulative step bound.
        self._alt: tuple | None = None
        self._q_prior = cfg.outlier_probability / (1.0 - cfg.outlier_probability) / (
            math.pi * cfg.outlier_radius ** 2)

    # ------------------------------------------------------------------ the models
    def _predict(self, fs: tuple, dt: float) -> tuple:
        """``fs`` moved by ``dt`` s (negative: backwards): the models mixed by their
        switching probabilities over |dt| (IMM), then each moved by its own model."""
        ss, Ps, mu = fs
        if len(self._models) == 1:
            out_s, out_P = self._models[0].steps(ss, Ps, dt, self._qs)
            return out_s, out_P, mu
        cfg = self.config
        p01 = 1.0 - math.exp(-abs(dt) / cfg.cruise_time_s)
        p10 = 1.0 - math.exp(-abs(dt) / cfg.manoeuvre_time_s)
        # Pi[i][j]: from model i to model j; c[j] = (Pi^T mu)[j], model j's probability
        # after the switch. Both models' mixed priors (_moments for each j) at once: the
        # means in floats (summed in numpy's order, so bit for bit the same), the
        # covariances as one stacked product.
        Pi = ((1.0 - p01, p01), (p10, 1.0 - p10))
        m0, m1 = mu.tolist()
        c = [Pi[0][0] * m0 + Pi[1][0] * m1, Pi[0][1] * m0 + Pi[1][1] * m1]
        rows = ss.tolist()
        n = len(rows[0])
        W, Ds, DW, means = [], [], [], []
        for j in range(2):
            w0, w1 = Pi[0][j] * m0 / c[j], Pi[1][j] * m1 / c[j]
            ref = rows[j][2]
            x0, x1 = list(rows[0]), list(rows[1])
            x0[2] = ref + (x0[2] - ref + math.pi) % _TWO_PI - math.pi
            x1[2] = ref + (x1[2] - ref + math.pi) % _TWO_PI - math.pi
            m = [w0 * u + w1 * v for u, v in zip(x0, x1, strict=True)]
            d0 = [u - v for u, v in zip(x0, m, strict=True)]
            d1 = [u - v for u, v in zip(x1, m, strict=True)]
            Ds += d0 + d1
            DW += [v * w0 for v in d0] + [v * w1 for v in d1]  # D.T * w, as rows
            m[2] = _wrap(m[2])
            means.append(m)
            W += (w0, w1)
        flat = np.array(W + Ds + DW)
        W = flat[:4].reshape(2, 2, 1, 1)
        D = flat[4:4 + 4 * n].reshape(2, 2, n)
        DW = flat[4 + 4 * n:].reshape(2, 2, n)
        P0 = W[:, 0] * Ps[0] + W[:, 1] * Ps[1] + DW.transpose(0, 2, 1) @ D
        out_s, out_P = self._models[0].steps(means, P0, dt, self._qs)
        return out_s, out_P, np.array(c)

    def _combine(self, fs: tuple) -> tuple[np.ndarray, np.ndarray]:
        """The models' combined state (n,) and covariance (n, n). The same filter tuple is
        often combined twice in a row (gated, then bounded); nothing changes a filter
        tuple's arrays in place, so the last result is reused for the very same tuple
        (callers do not modify the returned arrays)."""
        last = self._last_combined
        if last is not None and last[0] is fs:
            return last[1]
        ss, Ps, mu = fs
        m = mu.tolist()
        out = _moments(ss, Ps, mu, float(ss[m.index(max(m)), 2]))
        self._last_combined = (fs, out)
        return out

    def _gains(self, fs: tuple, z: np.ndarray, R: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per model, the innovation of measurement ``z`` (M, 3) and the Kalman gain
        (M, n, 3); the models' probabilities after it, by their likelihoods (M,)."""
        ss, Ps, mu = fs
        # All models at once: stacked innovations, one batched inverse and determinant.
        z0, z1, z2 = z.tolist()
        yl = [[z0 - s0, z1 - s1, _wrap(z2 - s2)] for s0, s1, s2, *_ in ss.tolist()]
        S = Ps[:, :3, :3] + R
        Si = _inv(S)
        d2s = [_mahalanobis(y, Sij) for y, Sij in zip(yl, Si.tolist(), strict=True)]
        if not all(map(math.isfinite, d2s)):
            Si = np.linalg.inv(S)  # singular: raises LinAlgError
            d2s = [_mahalanobis(y, Sij) for y, Sij in zip(yl, Si.tolist(), strict=True)]
        Ks = Ps[:, :, :3] @ Si
        loglik = [-0.5 * d2 - 0.5 * math.log(max(det, 1e-300))
                  for d2, det in zip(d2s, _det(S).tolist(), strict=True)]
        if len(mu) > 1:
            # The likelihoods relative to the largest (floats, the same as numpy's).
            top = max(loglik)
            w = [m * math.exp(v - top) for m, v in zip(mu.tolist(), loglik, strict=True)]
            tot = sum(w)
            mu = np.array([v / tot for v in w])
        return np.array(yl), Ks, mu

    def _correct(self, fs: tuple, z: np.ndarray, R: np.ndarray, scale: float,
                 gains: tuple | None = None, ky: np.ndarray | None = None) -> tuple:
        """Each model corrected by measurement ``z`` with its Kalman gain times ``scale``;
        the models' probabilities by their likelihoods (``gains``: :meth:`_gains`; ``ky``:
        its gains times its innovations (M, n), when already known)."""
        ss, Ps, _ = fs
        ys, Ks, mu = gains if gains is not None else self._gains(fs, z, R)
        if scale != 1.0:
            K, ky = Ks * scale, None
        else:
            K = Ks  # (Ks * 1.0 == Ks; K is only read)
        if ky is None:
            ky = (K @ ys[:, :, None])[:, :, 0]
        out_s = ss + ky
        out_s[:, 2] = [_wrap(v) for v in out_s[:, 2].tolist()]
        I_KH = self._eyes.copy()
        I_KH[:, :, :3] -= K  # I - K H, H = [I3 0]
        Kt = K.transpose(0, 2, 1)
        # Joseph form: the true covariance of any gain (so the weighted one's reported
        # sigma stays honest), symmetric positive.
        out_P = I_KH @ Ps @ I_KH.transpose(0, 2, 1) + K @ R @ Kt
        return out_s, out_P, mu

    def _outlier_q(self, s: np.ndarray, P: np.ndarray, z: np.ndarray, R: np.ndarray) -> float:
        """The posterior probability that measurement ``z`` is an outlier, against the
        combined prediction ``s``, ``P``: its position innovation's Gaussian density against
        the outliers' (uniform within ``outlier_radius``), weighted by the prior."""
        (p00, p01), (p10, p11) = P[:2, :2].tolist()
        (r00, r01), (_, r11) = R[:2, :2].tolist()
        a = p00 + r00
        b = 0.5 * (p01 + p10) + r01
        d = p11 + r11
        det = a * d - b * b
        if not det > 0.0:
            return 0.0
        x, y = float(z[0] - s[0]), float(z[1] - s[1])
        d2 = (d * x * x - 2.0 * b * x * y + a * y * y) / det
        good = math.exp(-0.5 * d2) / (2.0 * math.pi * math.sqrt(det))
        r = self._q_prior
        return r / (r + good)

    def _set(self, fs: tuple, t: float) -> None:
        self._fs = fs
        self.s, self.P = self._combine(fs)
        self.t = float(t)

    # ------------------------------------------------------------------ measurement
    def noise(self, sigma: float | None, sigma_theta: float | None = None) -> np.ndarray:
        """(3, 3) measurement covariance of a pose with position sigma ``sigma`` m."""
        cfg = self.config
        sp = cfg.default_sigma if sigma is None or not math.isfinite(sigma) else float(sigma)
        sp = max(sp, cfg.min_sigma)
        if sigma_theta is None or not math.isfinite(sigma_theta):
            sigma_theta = sp / cfg.heading_lever
        st = max(float(sigma_theta), cfg.min_sigma_theta)
        v, vt = sp * sp, st * st
        return np.array([[v, 0.0, 0.0], [0.0, v, 0.0], [0.0, 0.0, vt]])

    def update(self, t: float, x: float, y: float, theta: float, sigma: float | None = None,
               sigma_theta: float | None = None) -> Outcome:
        """Apply one pose measurement taken at ``t`` s; see :class:`Outcome`."""
        if not (math.isfinite(t) and math.isfinite(x) and math.isfinite(y)
                and math.isfinite(theta)):
            return Outcome("rejected", "not finite", math.nan, self.state())
        z = np.array([float(x), float(y), _wrap(float(theta))])
        R = self.noise(sigma, sigma_theta)
        cfg = self.config
        if self.s is None:
            self._start(t, z, R)
            return Outcome("init", "first measurement", math.nan, self.state())
        dt = t - self.t
        if dt > cfg.reset_after_s:
            self._start(t, z, R)
            return Outcome("reset", f"no measurement for {dt:.2f} s", math.nan, self.state())
        if dt < -cfg.reset_after_s:
            return Outcome("rejected", f"too old ({-dt:.2f} s before the last measurement)",
                           math.nan, None)
        fs = fs_pred = self._predict(self._fs, dt)
        inn = _innovation(*self._combine(fs), z, R)
        if inn is None:
            return Outcome("rejected", "singular innovation covariance", math.nan, self.state())
        y_, S, _, d2 = inn
        retracted: list = []
        t_before, fs_before = self.t, self._fs
        if d2 > self.gate and dt >= 0 and cfg.look_back:
            back = self._look_back(t, z, R)
            if back is not None:
                fs, y_, S, d2, retracted, hist, t_before, fs_before = back
                self._hist = hist
        follows = d2 > self.gate or (dt >= 0 and not retracted and cfg.reacquire_follow
                                     and self._follows_candidates(t, z, R, d2))
        if follows:
            reason = self._reason(y_, S, d2)
            if self._candidate(t, z, R):
                return Outcome("reacquired", f"{cfg.reacquire_n} consistent measurements away "
                               f"from the track ({reason})", d2, self.state())
            if dt >= 0:
                self._rej_run.append((t, z, R))
                if cfg.recover and not retracted:
                    rec = self._recover()
                    if rec is not None:
                        return rec
            # The prediction to t (as self.predict(t) would compute it again).
            st = self._state(t, *self._combine(fs_pred)) if dt > 0 else self.predict(self.t)
            return Outcome("rejected", reason, d2, st)
        self._cand, self._cand_track, self._cand_prev = [], None, ([], None)
        self._rej_run = []
        if retracted or dt < 0:
            self._alt = None
        fs = self._bounded(fs, z, R, d2, t if dt >= 0 and not retracted else None)
        if dt >= 0:
            self._hist = [*self._hist, (t_before, fs_before, t, z, R)][-int(cfg.look_back_n):]
            self._set(fs, t)
        else:
            # Out of order: the correction is applied at the measurement's time, then the
            # track is brought back to its newest time.
            self._hist = []
            self._set(self._predict(fs, -dt), self.t)
        if retracted:
            which = ("the previous measurement was an outlier" if len(retracted) == 1 else
                     f"the previous {len(retracted)} accepted measurements were outliers")
            return Outcome("update", f"{which}: {retracted[-1][4]}", d2, self.state(),
                           retracted[-1], tuple(retracted))
        return Outcome("update", "", d2, self.state())

    def _bounded(self, fs: tuple, z: np.ndarray, R: np.ndarray, d2: float,
                 t: float | None = None) -> tuple:
        """``fs`` corrected by an accepted measurement at Mahalanobis distance d = sqrt(d2)
        from the combined prediction, with a bounded step. The Kalman correction is
        weighted by 1 up to d = robust_k, by robust_k / d beyond (Huber), then less until
        the combined position moves by at most ``step_k`` sigmas of its own covariance
        after the update (bisection on the weight): no measurement, an outlier inside the
        gate included, moves the output by more than step_k of the filter's reported
        sigma. The covariance is that of the weighted gain (Joseph form), so it stays
        honest and the next measurements correct more.

        Cumulative bound (``step_cumulative``, with the measurement's time ``t``): while
        measurements in a row are down-weighted, the track that skipped them all is kept;
        a down-weighted measurement that does not confirm the ones before it (it does not
        fit the track that took them in full, inside the look-back quantile) may not move
        the position further than ``step_k`` sigmas from that skipping track either: two
        outliers in a row cannot add their bounded steps up."""
        cfg = self.config
        gains = ys, Ks, mu = self._gains(fs, z, R)
        ss, Ps, _ = fs
        sc, Pc = self._combine(fs)
        s0 = (float(sc[0]), float(sc[1]))
        # The combined position after the update at weight w, in closed form: model j's
        # mean is ss[j, :2] + w g[j], its covariance (Joseph form) P0 - w (B + B^T) + w^2 C.
        KY = (Ks @ ys[:, :, None])[:, :, 0]  # each model's full Kalman correction K y
        g = KY[:, :2].tolist()
        # B = Kp P[:3, :2] (Kp: the gain's position rows); the quadratic coefficient
        # C = Kp S Kp^T equals it (K = P H^T S^-1), so B stands for both below.
        Bs = (Ks[:, :2, :] @ Ps[:, :3, :2]).tolist()
        P0s = Ps[:, :2, :2].tolist()
        mul = mu.tolist()
        sl = ss[:, :2].tolist()

        # The combined mean and covariance are polynomials in w: mean = a0 + w a1, each
        # model's spread D_j = d_j + w e_j, so cov = K0 + w K1 + w^2 K2 (2x2); their
        # coefficients once (in floats), then each weight of the bisection costs a few
        # float operations (it runs ~10 times a measurement).
        p0 = q0 = p1 = q1 = 0.0
        for m, (sx, sy), (gx, gy) in zip(mul, sl, g, strict=True):
            p0, q0, p1, q1 = p0 + m * sx, q0 + m * sy, p1 + m * gx, q1 + m * gy
        a_0 = a_1 = a_2 = b_0 = b_1 = b_2 = d_0 = d_1 = d_2 = 0.0
        for m, (sx, sy), (gx, gy), P, B in zip(mul, sl, g, P0s, Bs, strict=True):
            dx, dy, ex, ey = sx - p0, sy - q0, gx - p1, gy - q1
            a_0 += m * (P[0][0] + dx * dx)
            a_1 += m * (2.0 * (dx * ex - B[0][0]))
            a_2 += m * (B[0][0] + ex * ex)
            b_0 += m * (0.5 * (P[0][1] + P[1][0]) + dx * dy)
            b_1 += m * (dx * ey + ex * dy - (B[0][1] + B[1][0]))
            b_2 += m * (0.5 * (B[0][1] + B[1][0]) + ex * ey)
            d_0 += m * (P[1][1] + dy * dy)
            d_1 += m * (2.0 * (dy * ey - B[1][1]))
            d_2 += m * (B[1][1] + ey * ey)
        ka, kb, kd = (a_0, a_1, a_2), (b_0, b_1, b_2), (d_0, d_1, d_2)

        def moved(w: float, ref: tuple = s0) -> float:
            """Squared Mahalanobis length of the combined position at weight w from ``ref``
            (by default the prediction: the step) against the combined position covariance
            after the update."""
            rx, ry = float(ref[0]), float(ref[1])
            x, y = p0 + w * p1 - rx, q0 + w * q1 - ry
            ww = w * w
            a = ka[0] + w * ka[1] + ww * ka[2]
            b = kb[0] + w * kb[1] + ww * kb[2]
            d = kd[0] + w * kd[1] + ww * kd[2]
            det = a * d - b * b
            if not det > 0.0:
                cov = np.array([[a, b], [b, d]])
                dp = np.array([x, y])
                return float(dp @ np.linalg.solve(cov, dp))
            return (d * x * x - 2.0 * b * x * y + a * y * y) / det

        def largest(w: float, ok) -> float:
            """The largest weight in [0, w] with ok(weight), by bisection (0 if none)."""
            if ok(w):
                return w
            lo, hi = 0.0, w
            for _ in range(12):
                mid = (lo + hi) / 2.0
                if ok(mid):
                    lo = mid
                else:
                    hi = mid
            return lo

        k2 = cfg.step_k ** 2
        w0 = min(1.0, cfg.robust_k / max(math.sqrt(d2), 1e-12))
        w = largest(w0, lambda v: moved(v) <= k2)
        if t is not None and cfg.step_cumulative:
            alt, self._alt = self._alt, None
            if alt is not None:
                # The measurement right after a suspicious one.
                t_alt, skip, full = alt
                skip = self._predict(skip, t - t_alt)
                full = self._predict(full, t - t_alt)
                inn = _innovation(*self._combine(full), z, R)
                # Unless it confirms the one before (a manoeuvre), it may not move the
                # position further than step_k sigmas from the track that skipped that one.
                if inn is None or inn[3] > self.confirm_gate:
                    ref = self._combine(skip)[0][:2].tolist()
                    if moved(0.0, ref) > k2:
                        # Already that far: take the weight that stays closest.
                        cand = np.linspace(0.0, w, 9)
                        w = float(cand[int(np.argmin([moved(v, ref) for v in cand]))])
                    else:
                        w = largest(w, lambda v: moved(v, ref) <= k2)
            if w0 < 1.0:
                # Suspicious (beyond robust_k): the next measurement is bounded against the
                # track that skipped this one.
                self._alt = (t, fs, self._correct(fs, z, R, 1.0, gains, KY))
        out = self._correct(fs, z, R, w, gains, KY)
        if cfg.outlier_mixture:
            q = self._outlier_q(sc, Pc, z, R)
            if q > 1e-9:
                # The covariance about the output: (1 - q) that of the weighted update (the
                # measurement was good) + q that of the prediction plus the step taken.
                D = w * KY
                out_P = (1.0 - q) * out[1] + q * (Ps + D[:, :, None] * D[:, None, :])
                out = (out[0], out_P, out[2])
        return out

    def _look_back(self, t: float, z: np.ndarray, R: np.ndarray) -> tuple | None:
        """A measurement fell outside the gate: were the last accepted measurements the
        outliers instead? (An outlier inside the gate pulls the track, so that the good
        measurements after it are rejected; typical in hard manoeuvres.) For j = 1 ..
        ``look_back_n``: the track is rebuilt from before the j-th last accepted
        measurement without it and the ones after it, through the measurements rejected
        since and the new one; each must fit it well (inside the chi-square quantile at
        ``look_back_probability``, tighter than the gate: skipping measurements widens the
        prediction). The rebuilt track is taken when every retracted one falls outside it
        (the track through the new measurements with full corrections, smoothed back to its
        time) and it implies fewer outliers (j retracted against the rejected run and the
        new one) with the retracted ones outside the look-back quantile, or as many with them
        outside the gate. The smallest such j is taken.

        Returns (the rebuilt prediction at ``t``, the new measurement's innovation y, S, d2,
        the retracted measurements as (t, x, y, theta, reason) oldest first, the look-back
        history of the rebuilt track, the time and filter before the new measurement), or
        None."""
        hist = self._hist
        if not hist or hist[-1][2] != self.t:
            return None
        seq = [m for m in self._rej_run if m[0] > hist[-1][2]] + [(t, z, R)]
        for j in range(1, min(int(self.config.look_back_n), len(hist)) + 1):
            if j > len(seq):
                break
            tc, fs = hist[-j][0], hist[-j][1]
            full = fs  # the same track with full Kalman corrections (for the check below)
            new_hist, ok = [], True
            for k, (tk, zk, Rk) in enumerate(seq):
                fsp = self._predict(fs, tk - tc)
                inn = _innovation(*self._combine(fsp), zk, Rk)
                if inn is None or inn[3] > self.look_back_gate:
                    ok = False
                    break
                full = self._correct(self._predict(full, tk - tc), zk, Rk, 1.0)
                if k == len(seq) - 1:
                    break
                new_hist.append((tc, fs, tk, zk, Rk))
                fs, tc = self._bounded(fsp, zk, Rk, inn[3]), tk
            if not ok:
                continue
            y_, S, _, d2 = inn
            dropped = hist[-j:]
            out = []
            for _, _, tj, zj, Rj in dropped:
                inn1 = _innovation(*self._combine(self._predict(full, tj - t)), zj, Rj)
                if inn1 is None:
                    out = None
                    break
                y1, S1, _, d2_1 = inn1
                # It must disagree with the track (else: a manoeuvre, not an outlier), by the
                # gate when as many are retracted as the rejected run, by the tighter look-back
                # gate when fewer.
                if d2_1 <= (self.gate if j == len(seq) else self.look_back_gate):
                    out = None
                    break
                out.append((tj, float(zj[0]), float(zj[1]), float(zj[2]),
                            self._reason(y1, S1, d2_1)))
            if out is None:
                continue
            return fsp, y_, S, d2, out, new_hist, tc, fs
        return None

    def _recover(self) -> Outcome | None:
        """Recovery after a rejected run (``recover``): the last accepted measurement pulled
        the track (an outlier that fitted a prediction the robot no longer follows, e.g. at
        the end of a brake to a stop) and the robot's next measurements are rejected. When
        exactly two measurements in a row were rejected since it, they lie close to each
        other (a standing or moving robot, not outliers scattered around it: within 3 sigma
        of the two plus what the track's speed covers in between), the first fits the track
        rebuilt from before the accepted one without it (inside the gate) and the second
        confirms it (inside the confirmation quantile of that track through the first), the
        accepted one is retracted (one outlier instead of two) and the track goes on from
        the rebuilt one, through both with full Kalman updates (its covariance is the
        filter's own), instead of rejecting until re-acquisition.
        Returns the outcome, or None (nothing changed)."""
        hist, run = self._hist, self._rej_run
        if not hist or len(run) != 2 or hist[-1][2] != self.t or run[0][0] <= hist[-1][2]:
            return None
        tc, fs = hist[-1][0], hist[-1][1]
        speed = abs(self._models[0].velocity(self._combine(fs)[0])[2])
        if not self._reachable(run[0], *run[1], speed=speed):
            return None
        # The first inside the gate of the track rebuilt without the accepted one; the
        # second confirms the first: inside the confirmation quantile of the track through
        # it (as a manoeuvre's second measurement confirms its first, ``step_cumulative``).
        for gate, (tk, zk, Rk) in zip((self.gate, self.confirm_gate), run, strict=True):
            fsp = self._predict(fs, tk - tc)
            inn = _innovation(*self._combine(fsp), zk, Rk)
            if inn is None or inn[3] > gate:
                return None
            fs, tc = self._correct(fsp, zk, Rk, 1.0), tk
        # Two consistent measurements that fit the track without it against one that fit
        # the track with it: fewer outliers if it was the one. (Whether it misses the track
        # through the two cannot tell: that track, from two measurements, is wide.)
        _, _, tj, zj, Rj = hist[-1]
        inn1 = _innovation(*self._combine(self._predict(fs, tj - tc)), zj, Rj)
        if inn1 is None:
            return None
        y1, S1, _, d2_1 = inn1
        retracted = (tj, float(zj[0]), float(zj[1]), float(zj[2]),
                     self._reason(y1, S1, d2_1))
        self._set(fs, tc)
        self._forget()
        return Outcome("update", "recovered: the measurement before the last two was an "
                       f"outlier: {retracted[4]}", inn[3], self.state(), retracted,
                       (retracted,))

    def _reason(self, y_: np.ndarray, S: np.ndarray, d2: float) -> str:
        dpos = math.hypot(y_[0], y_[1])
        dth = abs(y_[2])
        sp = math.sqrt(max(S[0, 0], S[1, 1]))
        st = math.sqrt(S[2, 2])
        if dth > math.pi / 2:
            what = f"heading flip {math.degrees(dth):.0f} deg"
        elif dpos / sp >= dth / st:
            what = f"position jump {dpos * 100:.1f} cm"
        else:
            what = f"heading jump {math.degrees(dth):.1f} deg"
        return f"{what} (d2 {d2:.1f} > gate {self.gate:.1f})"

    def _follows_candidates(self, t: float, z: np.ndarray, R: np.ndarray, d2: float) -> bool:
        """A measurement inside the gate but a poor fit (outside the look-back quantile)
        that fits the candidates' track well (inside it) and better: it is taken as the
        next candidate, not by the track. (After a hand move the track's prediction widens
        while it rejects the measurements at the new place, until one passes its gate; the
        track would then walk over by bounded steps instead of re-acquiring.)"""
        c = self._cand_track
        if c is None or len(self._cand) < 2 or d2 <= self.look_back_gate:
            return False
        if t - self._cand[0][0] > self.config.reacquire_window_s or t < c.t:
            return False
        if not self._reachable(self._cand[-1], t, z, R):
            return False
        inn = _innovation(*c._combine(c._predict(c._fs, t - c.t)), z, R)
        return inn is not None and inn[3] <= self.look_back_gate and inn[3] < d2

    def _candidate(self, t: float, z: np.ndarray, R: np.ndarray) -> bool:
        """Keep a rejected measurement; True when the track restarted from the candidates.

        The candidates form a chain whose own track tests whether they agree with each
        other. A measurement that does not fit the chain starts a new one, and the chain it
        broke is kept: when the next measurement fits that one, the breaking measurement was
        an outlier among the candidates and the chain goes on without it."""
        cfg = self.config
        if self._joins(self._cand, self._cand_track, t, z, R):
            self._cand.append((t, z, R))
        elif cfg.reacquire_skip_outlier and self._joins(*self._cand_prev, t, z, R):
            # The measurement that broke the chain was an outlier: dropped.
            self._cand, self._cand_track = self._cand_prev
            self._cand.append((t, z, R))
            self._cand_prev = ([], None)
        else:
            if self._cand and t - self._cand[0][0] <= cfg.reacquire_window_s:
                self._cand_prev = (self._cand, self._cand_track)
            else:
                self._cand_prev = ([], None)
            # Their own track takes every step (no step bound) and does not re-acquire.
            c = Track(self.name, _candidates_config(cfg))
            c.update(t, z[0], z[1], z[2], math.sqrt(R[0, 0]), math.sqrt(R[2, 2]))
            self._cand, self._cand_track = [(t, z, R)], c
        if len(self._cand) >= cfg.reacquire_n:
            c = self._cand_track
            self._set(c._fs, c.t)
            self._forget()
            return True
        return False

    def _joins(self, cand: list, c: Track | None, t: float, z: np.ndarray,
               R: np.ndarray) -> bool:
        """Whether measurement ``z`` at ``t`` continues the candidate chain ``cand`` with its
        track ``c`` (updated with it when it does)."""
        cfg = self.config
        if c is None or not cand or t - cand[0][0] > cfg.reacquire_window_s:
            return False
        if not self._reachable(cand[-1], t, z, R):
            return False
        out = c.update(t, z[0], z[1], z[2], math.sqrt(R[0, 0]), math.sqrt(R[2, 2]))
        return out.kind == "update"

    def _reachable(self, last: tuple, t: float, z: np.ndarray, R: np.ndarray,
                   speed: float | None = None) -> bool:
        """Could the robot of candidate ``last`` (t, z, R) be at ``z`` at ``t``? Candidates
        further apart than it can drive (``speed`` m/s, by default max_speed, plus 3 sigma
        of the two measurements) are not one robot: random outliers in a row."""
        tp, zp, Rp = last
        v = self.config.max_speed if speed is None else speed
        reach = v * abs(t - tp) + 3.0 * math.sqrt(R[0, 0] + Rp[0, 0])
        return math.hypot(z[0] - zp[0], z[1] - zp[1]) <= reach

    def _forget(self) -> None:
        """Drop the look-back history, the rejected run, the cumulative bound's alternative
        track and the re-acquisition candidates (a new or restarted track)."""
        self._hist, self._rej_run, self._alt = [], [], None
        self._cand, self._cand_track, self._cand_prev = [], None, ([], None)

    def _start(self, t: float, z: np.ndarray, R: np.ndarray) -> None:
        cfg = self.config
        s, P = self._models[0].init(z, R, cfg)
        M = len(self._models)
        # The models' long-run probabilities (the fraction of time in each).
        mu = np.array([1.0]) if M == 1 else np.array(
            [cfg.cruise_time_s, cfg.manoeuvre_time_s]) / (cfg.cruise_time_s
                                                          + cfg.manoeuvre_time_s)
        self._set((np.repeat(s[None], M, 0), np.repeat(P[None], M, 0), mu), t)
        self._forget()

    # ------------------------------------------------------------------ output
    @property
    def started(self) -> bool:
        return self.s is not None

    def state(self) -> TrackState | None:
        """The state at the newest measurement's time, or None before the first one."""
        if self.s is None:
            return None
        return self._state(self.t, self.s, self.P)

    def predict(self, t: float) -> TrackState | None:
        """The state predicted to time ``t`` s (latency compensation); the track is not
        changed. None before the first measurement."""
        if self.s is None:
            return None
        if t == self.t:
            return self.state()
        s, P = self._combine(self._predict(self._fs, t - self.t))
        return self._state(t, s, P)

    def _state(self, t: float, s: np.ndarray, P: np.ndarray) -> TrackState:
        sl = s.tolist()
        vx, vy, speed, omega = self._models[0].velocity(sl)
        cov = P[:3, :3].copy()
        (a, _, _), (b, d, _), (_, _, c) = cov.tolist()
        # The larger eigenvalue of the symmetric 2x2 position block (its lower triangle, as
        # eigvalsh reads it), in closed form.
        h = 0.5 * (a - d)
        sig = math.sqrt(max(0.5 * (a + d) + math.sqrt(h * h + b * b), 0.0))
        return TrackState(float(t), sl[0], sl[1], _wrap(sl[2]), vx, vy, speed, omega, sig,
                          math.sqrt(max(c, 0.0)), cov)


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
        self.counts = {"init": 0, "update": 0, "rejected": 0, "reacquired": 0, "reset": 0}
        self._sources: dict[str, str] = {}  # the source of each robot's last measurement

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
        if out.kind == "rejected":
            self.rejections.append(Rejection(name, t, x, y, theta, out.reason, source))
        for rt, rx, ry, rth, reason in out.retracted_all:
            self.counts["rejected"] += 1
            self.rejections.append(Rejection(name, rt, rx, ry, rth,
                                             f"{reason}, found by a later measurement",
                                             self._sources.get(name, "")))
        self._sources[name] = source
        return out

    def predict(self, name: str, t: float) -> TrackState | None:
        tr = self.tracks.get(name)
        return None if tr is None else tr.predict(t)

    def reset(self, name: str | None = None) -> None:
        if name is None:
            self.tracks.clear()
        else:
            self.tracks.pop(name, None)
