"""A live ``set`` that breaks the pipeline is taken back.

After a change the next ``window`` frames are its trial. If most of them fail (the frame
raised, or no estimate came out) while most frames before the change succeeded, the old
value returns and an event says why. Until the trial is over, ``save_config`` saves the old
value: a broken value never reaches the overlay file.
"""

from __future__ import annotations

import collections
from dataclasses import dataclass
from typing import Any

__all__ = ["ChangeGuard", "Trial"]


@dataclass
class Trial:
    """One change on trial: ``old`` returns if the frames after it fail."""

    key: str
    old: Any
    new: Any
    frames: int = 0
    failures: int = 0


class ChangeGuard:
    """Frame outcomes before and after live changes.

    window: frames a change is on trial for. ratio: failure fraction that condemns it.
    history: frames before the change that show whether the pipeline was healthy.
    """

    def __init__(self, window: int = 20, ratio: float = 0.5, history: int = 30) -> None:
        self.window = window
        self.ratio = ratio
        self.recent: collections.deque[bool] = collections.deque(maxlen=history)
        self.trials: dict[str, Trial] = {}
        self.rolled_back = 0

    def begin(self, key: str, old: Any, new: Any) -> None:
        """A change was applied; its frames start now (another change restarts the count)."""
        t = self.trials.get(key)
        self.trials[key] = Trial(key, t.old if t else old, new)
        for t in self.trials.values():
            t.frames = t.failures = 0

    def healthy_before(self) -> bool:
        return bool(self.recent) and sum(self.recent) > self.ratio * len(self.recent)

    def frame(self, ok: bool) -> list[Trial]:
        """Record one frame; returns the trials to undo (newest first), or []."""
        if not self.trials:
            self.recent.append(ok)
            return []
        condemned: list[Trial] = []
        for t in self.trials.values():
            t.frames += 1
            t.failures += not ok
        first = next(iter(self.trials.values()))
        if first.failures > self.ratio * self.window:
            if self.healthy_before():
                condemned = list(reversed(self.trials.values()))
                self.rolled_back += len(condemned)
            self.trials.clear()  # condemned, or the scene was already failing: not its fault
        elif first.frames >= self.window:
            self.trials.clear()  # passed
        if not self.trials:
            self.recent.append(ok)
        return condemned

    def saved_value(self, key: str, current: Any) -> Any:
        """What ``save_config`` may write for ``key``: the old value while on trial."""
        t = self.trials.get(key)
        return t.old if t is not None else current
