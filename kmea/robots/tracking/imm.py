"""The interacting-multiple-model (IMM) filter's mode set: predict, gains, correct, combine.

With ``manoeuvre_scale`` > 1 the motion model runs twice, once with the configured process
noise ("cruise") and once with ``manoeuvre_scale`` times it ("manoeuvre": braking, starting,
entering a turn). Before each prediction the modes are mixed by their switching
probabilities (mean times ``cruise_time_s`` and ``manoeuvre_time_s``); after each
measurement their probabilities follow their likelihoods (Bar-Shalom, Li, Kirubarajan,
*Estimation with Applications to Tracking and Navigation*, ch. 11.6). Gating, outputs and
predictions use the combination (moment-matched mean and covariance), so the reported
sigma is small when cruising and widens as soon as a manoeuvre shows. With one mode this
is an extended Kalman filter.

The modes are kept stacked in arrays (M modes of n states): one batched inverse, one
stacked product per step. Gating and the step bound stay with the caller (:mod:`.track`).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from kmea.geometry.rotations import wrap_angle
from kmea.robots.tracking.config import TrackerConfig
from kmea.robots.tracking.gating import det3, inv3, mahalanobis
from kmea.robots.tracking.models import MotionModel, motion_model

__all__ = ["Gains", "ModeSet", "Modes", "moments"]

_TWO_PI = 2.0 * math.pi


class Modes(NamedTuple):
    """The filter's state: each mode's state ``ss`` (M, n) and covariance ``Ps`` (M, n, n),
    and the modes' probabilities ``mu`` (M,). Never changed in place."""

    ss: np.ndarray
    Ps: np.ndarray
    mu: np.ndarray


class Gains(NamedTuple):
    """A measurement against each mode: innovations ``ys`` (M, 3), Kalman gains ``Ks``
    (M, n, 3), the modes' probabilities after it ``mu`` (M,)."""

    ys: np.ndarray
    Ks: np.ndarray
    mu: np.ndarray


def moments(ss: np.ndarray, Ps: np.ndarray, w: np.ndarray, ref: float
            ) -> tuple[np.ndarray, np.ndarray]:
    """Mean and covariance of the mixture of states ``ss`` (M, n) with covariances ``Ps``
    (M, n, n) and weights ``w`` (M,); headings unwrapped around ``ref`` rad first."""
    if len(w) == 1:
        return ss[0].copy(), Ps[0].copy()
    if len(w) == 2:
        # Two modes (the shipped filter): the general path below in floats (the same sums
        # in numpy's order); the arrays cost about 30 % more per update (docs/tracking.md).
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
        s[2] = wrap_angle(s[2])
        return np.array(s), P
    X = ss.copy()
    X[:, 2] = ref + (X[:, 2] - ref + math.pi) % _TWO_PI - math.pi
    s = w @ X
    D = X - s
    P = np.einsum("i,ijk->jk", w, Ps) + (D.T * w) @ D
    s[2] = wrap_angle(s[2])
    return s, P


class ModeSet:
    """The modes of one configuration: their motion model and process noises, the
    switching times; the operations on :class:`Modes`."""

    def __init__(self, cfg: TrackerConfig) -> None:
        self.model: MotionModel = motion_model(cfg.model)
        self.qs = [(cfg.accel_noise, cfg.turn_noise)]
        if cfg.manoeuvre_scale > 1.0:
            self.qs.append((cfg.accel_noise * cfg.manoeuvre_scale,
                            cfg.turn_noise * cfg.manoeuvre_scale))
        self.cruise_time_s = cfg.cruise_time_s
        self.manoeuvre_time_s = cfg.manoeuvre_time_s
        self.n = self.model.n
        self._eyes = np.repeat(np.eye(self.n)[None], len(self.qs), 0)

    def start(self, z: np.ndarray, R: np.ndarray, max_speed: float, max_turn_rate: float
              ) -> Modes:
        """Every mode at measurement ``z``, with the modes' long-run probabilities (the
        fraction of time in each)."""
        s, P = self.model.init(z, R, max_speed, max_turn_rate)
        M = len(self.qs)
        mu = np.array([1.0]) if M == 1 else np.array(
            [self.cruise_time_s, self.manoeuvre_time_s]) / (self.cruise_time_s
                                                            + self.manoeuvre_time_s)
        return Modes(np.repeat(s[None], M, 0), np.repeat(P[None], M, 0), mu)

    def predict(self, m: Modes, dt: float) -> Modes:
        """``m`` moved by ``dt`` s (negative: backwards): the modes mixed by their switching
        probabilities over |dt|, then each moved by its own process noise."""
        ss, Ps, mu = m
        if len(self.qs) == 1:
            out_s, out_P = self.model.steps(ss, Ps, dt, self.qs)
            return Modes(out_s, out_P, mu)
        Pi = self.transitions(abs(dt))
        c = Pi.T @ mu  # each mode's probability after the switch
        # W[i, j]: the probability that the track was in mode i, given mode j after it.
        W = Pi * mu[:, None] / c[None, :]
        mixed = [moments(ss, Ps, W[:, j], float(ss[j, 2])) for j in range(len(c))]
        out_s, out_P = self.model.steps(np.array([s for s, _ in mixed]),
                                        np.array([P for _, P in mixed]), dt, self.qs)
        return Modes(out_s, out_P, c)

    def transitions(self, dt: float) -> np.ndarray:
        """(M, M) mode switching probabilities over ``dt`` >= 0 s, from mode i (row) to
        mode j: cruise to manoeuvre at the rate 1 / ``cruise_time_s``, back at
        1 / ``manoeuvre_time_s``."""
        p01 = 1.0 - math.exp(-dt / self.cruise_time_s)
        p10 = 1.0 - math.exp(-dt / self.manoeuvre_time_s)
        return np.array([[1.0 - p01, p01], [p10, 1.0 - p10]])

    @staticmethod
    def combine(m: Modes) -> tuple[np.ndarray, np.ndarray]:
        """The modes' combined state (n,) and covariance (n, n)."""
        ss, Ps, mu = m
        w = mu.tolist()
        return moments(ss, Ps, mu, float(ss[w.index(max(w)), 2]))

    @staticmethod
    def gains(m: Modes, z: np.ndarray, R: np.ndarray) -> Gains:
        """Each mode's innovation of measurement ``z`` and Kalman gain; the modes'
        probabilities after it, by their likelihoods."""
        ss, Ps, mu = m
        z0, z1, z2 = z.tolist()
        yl = [[z0 - s0, z1 - s1, wrap_angle(z2 - s2)] for s0, s1, s2, *_ in ss.tolist()]
        S = Ps[:, :3, :3] + R
        Si = inv3(S)
        d2s = [mahalanobis(y, Sij) for y, Sij in zip(yl, Si.tolist(), strict=True)]
        if not all(map(math.isfinite, d2s)):
            Si = np.linalg.inv(S)  # singular: raises LinAlgError
            d2s = [mahalanobis(y, Sij) for y, Sij in zip(yl, Si.tolist(), strict=True)]
        Ks = Ps[:, :, :3] @ Si
        loglik = [-0.5 * d2 - 0.5 * math.log(max(det, 1e-300))
                  for d2, det in zip(d2s, det3(S).tolist(), strict=True)]
        if len(mu) > 1:
            # The likelihoods relative to the largest (floats, the same as numpy's).
            top = max(loglik)
            w = [p * math.exp(v - top) for p, v in zip(mu.tolist(), loglik, strict=True)]
            tot = sum(w)
            mu = np.array([v / tot for v in w])
        return Gains(np.array(yl), Ks, mu)

    def correct(self, m: Modes, R: np.ndarray, g: Gains, scale: float = 1.0,
                ky: np.ndarray | None = None) -> Modes:
        """Each mode corrected with its Kalman gain times ``scale`` (``g``: :meth:`gains` of
        the measurement, with covariance ``R``; ``ky``: the gains times the innovations
        (M, n) at scale 1, when already known). Joseph form: the true covariance of any
        gain, so a down-weighted update's reported sigma stays honest."""
        ss, Ps, _ = m
        ys, Ks, mu = g
        if scale != 1.0:
            K, ky = Ks * scale, None
        else:
            K = Ks  # (Ks * 1.0 == Ks; K is only read)
        if ky is None:
            ky = (K @ ys[:, :, None])[:, :, 0]
        out_s = ss + ky
        out_s[:, 2] = [wrap_angle(v) for v in out_s[:, 2].tolist()]
        I_KH = self._eyes.copy()
        I_KH[:, :, :3] -= K  # I - K H, H = [I3 0]
        Kt = K.transpose(0, 2, 1)
        out_P = I_KH @ Ps @ I_KH.transpose(0, 2, 1) + K @ R @ Kt
        return Modes(out_s, out_P, mu)
