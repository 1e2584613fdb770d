"""The paper's first-order IIR filter of positions and headings, numpy only.

y = a * x + (1 - a) * y_prev per key (a marker id or a robot name); a = 1 means no
filtering. Headings are filtered through their wrapped difference, so 179 deg and -179 deg
average to 180 deg, not 0. A key not updated for ``reset_after_s`` seconds (a lost track)
restarts from its next sample.
"""

from __future__ import annotations

import math
from collections.abc import Hashable

import numpy as np

from kmea.geometry import wrap_angle

__all__ = ["PoseFilter"]


class PoseFilter:
    """Per-key exponential smoothing of (position (3,) m, yaw rad).

    alpha: weight of the new sample, in (0, 1]; reset_after_s: seconds without an update
    after which a key's state is dropped (> 0).
    """

    def __init__(self, alpha: float = 1.0, reset_after_s: float = 1.0) -> None:
        if isinstance(alpha, bool) or not (isinstance(alpha, (int, float))
                                           and 0.0 < alpha <= 1.0):
            raise ValueError(f"alpha must be in (0, 1], got {alpha!r}")
        if not (math.isfinite(reset_after_s) and reset_after_s > 0.0):
            raise ValueError(f"reset_after_s must be a finite time > 0 s, got {reset_after_s!r}")
        self.alpha = float(alpha)
        self.reset_after_s = float(reset_after_s)
        self._state: dict[Hashable, tuple[float, np.ndarray, float]] = {}

    def update(self, key: Hashable, t: float, position: np.ndarray,
               yaw: float) -> tuple[np.ndarray, float]:
        """Filter one sample taken at time ``t`` (s); returns (position (3,), yaw in [-pi, pi))."""
        x = np.asarray(position, dtype=float).reshape(-1)
        if x.shape != (3,) or not np.all(np.isfinite(x)):
            raise ValueError(f"filter {key!r}: position must be 3 finite numbers")
        if not (math.isfinite(yaw) and math.isfinite(t)):
            raise ValueError(f"filter {key!r}: yaw and t must be finite")
        prev = self._state.get(key)
        a = self.alpha
        # A gap longer than the timeout, or time running backwards, starts a new track.
        if prev is None or not (0.0 <= t - prev[0] <= self.reset_after_s):
            y, th = x.copy(), float(wrap_angle(yaw))
        else:
            _, y_prev, th_prev = prev
            y = a * x + (1.0 - a) * y_prev
            th = float(wrap_angle(th_prev + a * float(wrap_angle(yaw - th_prev))))
        self._state[key] = (float(t), y, th)
        return y.copy(), th

    def reset(self, key: Hashable | None = None) -> None:
        """Forget one key's state, or every key's when ``key`` is None."""
        if key is None:
            self._state.clear()
        else:
            self._state.pop(key, None)

    def keys(self) -> list[Hashable]:
        """Keys with a live state."""
        return list(self._state)
