"""Python's cyclic garbage collector, run between frames instead of inside them.

CPython starts a collection whenever enough container objects were allocated, in whichever
thread allocates next, and every thread waits for it (it holds the GIL): on a live source
that lands inside a frame's path from capture to the robots' datagrams. Measured with the
default collector on ``kmea bench latency`` (2-core machine, busy): about 70 collections in
8 s, the youngest generation's up to 4 ms and the middle one's up to 10 ms, each one a
latency spike for the frame it hit.

While a live source runs, :class:`GcPacing` turns the automatic collector off, moves the
objects that exist after start-up (modules, the map, the models: they live as long as the
daemon) out of the collector's sight with ``gc.freeze()``, and collects the same
generations the automatic collector would, with its thresholds, after each frame's outputs
are done (the time until the next frame is idle) and when the main loop waits without a
frame. File sources keep the default collector: they have no idle time and no latency.

Process-wide: several daemons in one process (the tests) share one pacing; the collector is
restored when the last one closes.
"""

from __future__ import annotations

import gc
import threading

__all__ = ["GcPacing"]

_lock = threading.Lock()
_users = 0
_was_enabled = True


class GcPacing:
    """Collector paced by the caller: ``idle()`` between frames, ``close()`` at the end."""

    def __init__(self) -> None:
        global _users, _was_enabled
        self.thresholds = gc.get_threshold()
        self.collections = 0
        self._open = True
        with _lock:
            if _users == 0:
                _was_enabled = gc.isenabled()
                gc.disable()
                gc.freeze()
            _users += 1

    def idle(self) -> int:
        """Collect what the automatic collector would have by now (the generation, -1 for
        nothing); cheap when nothing is due."""
        t0, t1, t2 = self.thresholds
        c0, c1, c2 = gc.get_count()
        if t0 <= 0 or c0 < t0:
            return -1
        gen = 2 if (c1 >= t1 and c2 >= t2) else 1 if c1 >= t1 else 0
        gc.collect(gen)
        self.collections += 1
        return gen

    def close(self) -> None:
        global _users
        if not self._open:
            return
        self._open = False
        with _lock:
            _users -= 1
            if _users == 0:
                gc.unfreeze()
                if _was_enabled:
                    gc.enable()
