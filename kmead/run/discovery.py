"""The tracking detector's discoveries on one thread of the daemon, below the frame path.

The library's fixed-camera detector asks for full detections of a frame now and then
(:class:`kmea.fixed_camera.discovery.DiscoveryJob`, new markers in the view) and starts no
thread. :class:`Discovery` is the daemon's :class:`kmea.fixed_camera.discovery.Background`:
one worker thread at a lower priority (nice 5) runs the jobs of every detector the
pipeline makes (:meth:`Discovery.jobs`, one queue each: one job at a time, the newest
replacing one not started), each after the frame's robots were sent (the gate:
:meth:`Discovery.robots_sent`, cleared when a detector starts a frame), so it does not
share the cores with the frame path.
"""

from __future__ import annotations

import contextlib
import os
import threading
from concurrent.futures import ThreadPoolExecutor

from kmea.fixed_camera.discovery import Discovered, DiscoveryJob

__all__ = ["GATE_WAIT_S", "Discovery", "DiscoveryQueue"]

# Longest wait (s) of a discovery for the frame path's gate: it never starves.
GATE_WAIT_S = 0.25
# The worker's nice value: on one core the tracked frames preempt discovery (nice 5: a third
# of the frame path's share; at nice 10 a loaded machine starved it).
NICE = 5


class DiscoveryQueue:
    """One detector's jobs on the shared worker (:class:`kmea.fixed_camera.discovery.Jobs`)."""

    def __init__(self, executor: ThreadPoolExecutor, gate: threading.Event,
                 gate_wait_s: float = GATE_WAIT_S) -> None:
        self._executor = executor
        self._gate = gate
        self.gate_wait_s = gate_wait_s
        self._job: DiscoveryJob | None = None
        self._result: Discovered | None = None
        self._draining = False  # a _drain task is queued or running on the executor
        self._cond = threading.Condition()
        self._closed = False
        self.done = threading.Event()  # set when a result arrives (for tests and tools)

    @property
    def busy(self) -> bool:
        """A job is queued or running."""
        with self._cond:
            return self._draining

    def submit(self, job: DiscoveryJob) -> None:
        with self._cond:
            if self._closed:
                return
            self._job = job
            if self._draining:
                return  # the running task takes it next
            self._draining = True
        try:
            self._executor.submit(self._drain)
        except RuntimeError:  # the executor was shut down (the daemon stops): no discovery
            with self._cond:
                self._draining = False

    def _drain(self) -> None:
        """The worker's task: run the queued job, and the next one queued meanwhile, until
        none is left (newest wins: a job replaced before it started is dropped)."""
        with contextlib.suppress(OSError, AttributeError):
            # The executor's thread keeps it: the executor is for this work.
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), NICE)
        while True:
            with self._cond:
                if self._job is None or self._closed:
                    self._draining = False
                    return
                job, self._job = self._job, None
            # Run in the gap after the frame's robots were sent, not beside the frame
            # path: OpenCV's worker threads (not niced) would share the cores with it.
            self._gate.wait(self.gate_wait_s)
            try:
                got: Discovered | None = job()
            except Exception:  # a frame the detector cannot digest: no result
                got = None
            with self._cond:
                if got is not None:
                    self._result = got
                    self.done.set()

    def take(self) -> Discovered | None:
        with self._cond:
            r, self._result = self._result, None
            self.done.clear()
        return r

    def frame_started(self) -> None:
        self._gate.clear()  # this frame's path runs until the pipeline's robots are sent

    def close(self) -> None:
        """No more jobs (a queued one is dropped; one running finishes on the worker)."""
        with self._cond:
            self._closed = True
            self._job = None


class Discovery:
    """The daemon's worker for discoveries (see the module docstring), started on first
    use; :meth:`shutdown` when the daemon closes."""

    def __init__(self, gate_wait_s: float = GATE_WAIT_S) -> None:
        self._executor = ThreadPoolExecutor(1, thread_name_prefix="kmead-discover")
        self.gate = threading.Event()
        self.gate_wait_s = gate_wait_s

    def jobs(self) -> DiscoveryQueue:
        return DiscoveryQueue(self._executor, self.gate, self.gate_wait_s)

    def robots_sent(self) -> None:
        self.gate.set()

    def shutdown(self, wait: bool = False, cancel_futures: bool = True) -> None:
        """Stop the worker (a detection under way finishes on its own: it holds nothing of
        the daemon's)."""
        self.gate.set()
        self._executor.shutdown(wait=wait, cancel_futures=cancel_futures)
