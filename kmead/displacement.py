"""When does a map marker "look displaced"? Persistence over the frames it was seen.

A single frame's leave-one-out error can be large for reasons other than a moved marker: a
corner hidden by a passing robot that the pose quality check (``suspect``, see
``docs/vision.md``) did not catch, a motion-blurred frame. A marker moved on the floor is
wrong in every frame. So each map marker keeps its last ``frames`` displacement figures (its
LOO error, or a robust estimator's rejection distance, in metres) from the frames where it
was a usable measurement, and looks displaced when their median exceeds the threshold, i.e.
in most of them, with at least ``min(frames, 3)`` figures.
"""

from __future__ import annotations

import collections
import statistics

__all__ = ["DisplacementMonitor"]


class DisplacementMonitor:
    """Per-marker windows of displacement figures (m) and the "looks displaced" decision.

    threshold: metres; frames: window length (frames where the marker was measured).
    """

    def __init__(self, threshold: float, frames: int = 5) -> None:
        if frames < 1:
            raise ValueError(f"displacement window: frames must be >= 1, got {frames}")
        self.threshold = float(threshold)
        self.frames = int(frames)
        self.need = min(self.frames, 3)
        self.history: dict[int, collections.deque[float]] = {}

    def update(self, figures: dict[int, float]) -> dict[int, float]:
        """Add one frame's figures (id -> m); return id -> median (m) of the markers that look
        displaced now. Markers not in ``figures`` (unseen, suspect) keep their window."""
        out: dict[int, float] = {}
        for mid, e in figures.items():
            h = self.history.get(mid)
            if h is None:
                h = self.history[mid] = collections.deque(maxlen=self.frames)
            h.append(float(e))
            if len(h) >= self.need:
                m = statistics.median(h)
                if m > self.threshold:
                    out[mid] = m
        return out

    def clear(self) -> None:
        self.history.clear()
