"""Motion models of the tracking filter: state transition, its Jacobian and process noise.

- ``"cv"`` constant velocity: state (x, y, theta, vx, vy, omega); position and heading move
  independently (holonomic robots, robots that reverse). Linear.
- ``"ctrv"`` constant turn rate and velocity: state (x, y, theta, v, omega); the robot drives
  along its heading (differential drive), v signed.

Units: m, rad, s; process noise densities (accel m^2/s^3, turn rad^2/s^3). The heading state
is kept wrapped to [-pi, pi).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from kmea.geometry.rotations import wrap_angle

__all__ = ["CTRV", "CV", "MotionModel", "motion_model"]

_TWO_PI = 2.0 * math.pi


class MotionModel:
    """A motion model; ``n`` state components, the first three (x, y, theta)."""

    n = 0

    def init(self, z: np.ndarray, R: np.ndarray, max_speed: float, max_turn_rate: float
             ) -> tuple[np.ndarray, np.ndarray]:
        """A new track's state (n,) and covariance (n, n) from measurement ``z`` (x, y,
        theta) with covariance ``R`` (3, 3); unknown rates have 1-sigma ``max_speed`` m/s
        and ``max_turn_rate`` rad/s."""
        raise NotImplementedError

    def steps(self, ss: Any, Ps: np.ndarray, dt: float, qs: list[tuple[float, float]]
              ) -> tuple[np.ndarray, np.ndarray]:
        """M states (M, n) and covariances (M, n, n) moved by ``dt`` s (negative: backwards;
        the uncertainty still grows), state j with the process noise densities ``qs[j]`` =
        (accel_noise, turn_noise)."""
        raise NotImplementedError

    def velocity(self, s: Any) -> tuple[float, float, float, float]:
        """(vx, vy, speed, omega) of state ``s``: m/s, m/s, m/s, rad/s."""
        raise NotImplementedError


class CV(MotionModel):
    n = 6  # x, y, theta, vx, vy, omega

    def init(self, z, R, max_speed, max_turn_rate):
        s = np.array([z[0], z[1], z[2], 0.0, 0.0, 0.0])
        P = np.zeros((6, 6))
        P[:3, :3] = R
        P[3, 3] = P[4, 4] = max_speed ** 2
        P[5, 5] = max_turn_rate ** 2
        return s, P

    def steps(self, ss, Ps, dt, qs):
        """F the identity with dt coupling each of x, y, theta to its rate; Q the
        continuous white-acceleration noise of each (position, rate) pair."""
        F = np.eye(6)
        F[0, 3] = F[1, 4] = F[2, 5] = dt
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

    def velocity(self, s):
        return float(s[3]), float(s[4]), float(math.hypot(s[3], s[4])), float(s[5])


class CTRV(MotionModel):
    n = 5  # x, y, theta, v, omega

    def init(self, z, R, max_speed, max_turn_rate):
        s = np.array([z[0], z[1], z[2], 0.0, 0.0])
        P = np.zeros((5, 5))
        P[:3, :3] = R
        P[3, 3] = max_speed ** 2
        P[4, 4] = max_turn_rate ** 2
        return s, P

    def steps(self, ss, Ps, dt, qs):
        """Constant turn rate and speed, F its Jacobian; Q white linear and angular
        acceleration mapped through the model (discretised): G diag(q) G^T / |dt|. In
        floats (numpy's per-call cost dominated it)."""
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
            out_s += (nx, ny, wrap_angle(th + w * dt), v, w)
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


def motion_model(name: str) -> MotionModel:
    """The model called ``name`` ("cv" or "ctrv")."""
    return CV() if name == "cv" else CTRV()
