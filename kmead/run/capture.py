"""Getting frames from a source: threaded for live sources, in order for files.

A live source (camera, Pi camera, paced simulator) is read by its own thread into a
one-slot mailbox: when processing is slower than the camera the newest frame wins and the
replaced one is counted as dropped, so the pipeline always works on the freshest image and
never blocks the camera. A file source is read in the caller's thread, every frame in
order. Both give ``(frame, capture_ms, t_capture)`` tuples.

Where detection happens is a *feed* (:func:`open_feed`): in the main thread
(:class:`NoDetect`: the pipeline detects), on a thread of its own for live sources
(:class:`LiveDetect`) or on a pool for in-order sources (:class:`DetectPool`). Every feed
has ``get(timeout) -> ((frame, capture_ms, t_capture), detections | None, detect_ms)`` or
None on timeout, raises :class:`CaptureEnded` at the end, and has ``dropped`` and
``close()``; the daemon's one run loop reads whichever it is given.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Iterator

from kmea.sources.base import Frame, FrameSource, SourceError

__all__ = ["Capture", "CaptureEnded", "DetectPool", "LiveDetect", "NoDetect", "open_feed"]


class CaptureEnded(Exception):
    """The source ended or failed; ``error`` holds the message when it failed."""


class Capture:
    """Frames from ``source``; ``threaded`` for live sources (see the module docstring).

    pace_fps: for sources that render rather than wait for a sensor (the simulator), the
    capture thread sleeps to deliver at most this rate (0 = no pacing).
    """

    def __init__(self, source: FrameSource, threaded: bool, pace_fps: float = 0.0) -> None:
        self.source = source
        self.threaded = threaded
        self.pace_fps = pace_fps
        self.dropped = 0
        self.captured = 0
        self.error: str | None = None
        self.ended = False
        self._slot: tuple[Frame, float, float] | None = None
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        if threaded:
            self._thread = threading.Thread(target=self._run, name="kmead-capture", daemon=True)
            self._thread.start()

    def _run(self) -> None:
        period = 1.0 / self.pace_fps if self.pace_fps > 0 else 0.0
        next_t = time.perf_counter()
        try:
            while not self._stop.is_set():
                if period:
                    delay = next_t - time.perf_counter()
                    if delay > 0:
                        self._stop.wait(delay)
                    next_t = max(next_t + period, time.perf_counter() - period)
                t0 = time.perf_counter()
                frame = self.source.read()
                t1 = time.perf_counter()
                if frame is None:
                    break
                with self._cond:
                    self.captured += 1
                    if self._slot is not None:
                        self.dropped += 1
                    self._slot = (frame, (t1 - t0) * 1e3, t1)
                    self._cond.notify()
        except SourceError as e:
            self.error = str(e)
        except Exception as e:  # a broken driver must end the run cleanly, not hang it
            self.error = f"{self.source.spec}: {type(e).__name__}: {e}"
        with self._cond:
            self.ended = True
            self._cond.notify_all()

    def get(self, timeout: float = 0.1) -> tuple[Frame, float, float] | None:
        """The next frame (newest for live sources), None on timeout.

        Raises :class:`CaptureEnded` when the source is finished or failed.
        """
        if not self.threaded:
            if self.ended:
                raise CaptureEnded(self.error)
            t0 = time.perf_counter()
            try:
                frame = self.source.read()
            except SourceError as e:
                self.error = str(e)
                frame = None
            t1 = time.perf_counter()
            if frame is None:
                self.ended = True
                raise CaptureEnded(self.error)
            self.captured += 1
            return frame, (t1 - t0) * 1e3, t1
        with self._cond:
            if self._slot is None and not self.ended:
                self._cond.wait(timeout)
            if self._slot is not None:
                item, self._slot = self._slot, None
                return item
            if self.ended:
                raise CaptureEnded(self.error)
            return None

    def __iter__(self) -> Iterator[tuple[Frame, float, float]]:
        while True:
            try:
                item = self.get()
            except CaptureEnded:
                return
            if item is not None:
                yield item

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        with contextlib.suppress(Exception):
            self.source.close()


class DetectPool:
    """Detection on worker threads for in-order sources (files, unpaced simulator).

    OpenCV releases the GIL in ``detectMarkers``, so ``workers`` threads detect that many
    frames at once while the main thread runs the rest of the pipeline; results come back
    in frame order. Each thread has its own detector, rebuilt when the pipeline's detector
    configuration changes (``detector_generation``).
    """

    def __init__(self, capture: Capture, pipeline, workers: int) -> None:
        from concurrent.futures import ThreadPoolExecutor

        self.capture = capture
        self.pipeline = pipeline
        self.workers = workers
        self._pool = ThreadPoolExecutor(workers, thread_name_prefix="kmead-detect")
        self._local = threading.local()
        self._iter = iter(self)

    @property
    def dropped(self) -> int:
        return self.capture.dropped

    def get(self, timeout: float = 0.1):
        """The next frame in order with its detections (see the module docstring); blocks
        until its detection is done; :class:`CaptureEnded` after the last one."""
        try:
            return next(self._iter)
        except StopIteration:
            raise CaptureEnded(self.capture.error) from None

    def _detect(self, frame: Frame):
        if frame.image is None:
            return None, 0.0
        gen = self.pipeline.detector_generation
        loc = self._local
        if getattr(loc, "gen", None) != gen:
            loc.det, loc.gen = self.pipeline.new_detector(), gen
        t0 = time.perf_counter()
        d = loc.det.detect(frame.image)
        return d, (time.perf_counter() - t0) * 1e3

    def __iter__(self):
        from collections import deque

        pending: deque = deque()
        ended = False
        while True:
            while not ended and len(pending) < self.workers + 1:
                try:
                    item = self.capture.get()
                except CaptureEnded:
                    ended = True
                    break
                if item is not None:
                    pending.append((item, self._pool.submit(self._detect, item[0])))
            if not pending:
                return
            item, fut = pending.popleft()
            try:
                det, ms = fut.result()
            except Exception:  # the main thread detects again and reports the problem
                det, ms = None, 0.0
            yield item, det, ms

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)


class LiveDetect:
    """Detection on its own thread for live sources: capture -> detect -> main thread.

    Takes the newest captured frame, detects it, and leaves the result in a one-slot
    mailbox for the main thread (newest wins; replaced results are counted in ``dropped``
    with the capture's own drops). Detection of frame i+1 then overlaps the rest of the
    pipeline on frame i: two cores busy instead of one.
    """

    def __init__(self, capture: Capture, pipeline) -> None:
        self.capture = capture
        self.pipeline = pipeline
        self._dropped = 0
        self._slot = None
        self._ended = False
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="kmead-detect", daemon=True)
        self._thread.start()

    @property
    def dropped(self) -> int:
        return self.capture.dropped + self._dropped

    def _run(self) -> None:
        det, gen = None, None
        try:
            while not self._stop.is_set():
                try:
                    item = self.capture.get(timeout=0.1)
                except CaptureEnded:
                    break
                if item is None:
                    continue
                frame = item[0]
                result, ms = None, 0.0
                if frame.image is not None:
                    if gen != self.pipeline.detector_generation:
                        if det is not None and hasattr(det, "close"):
                            det.close()  # a tracking detector's discoveries
                        det, gen = (self.pipeline.new_detector(),
                                    self.pipeline.detector_generation)
                    t0 = time.perf_counter()
                    try:
                        assert det is not None  # made above for this generation
                        result = det.detect(frame.image)  # Detections
                    except Exception:  # the main thread detects again and reports it
                        result = None
                    ms = (time.perf_counter() - t0) * 1e3
                with self._cond:
                    if self._slot is not None:
                        self._dropped += 1
                    self._slot = (item, result, ms)
                    self._cond.notify()
        finally:
            if det is not None and hasattr(det, "close"):
                det.close()
            with self._cond:
                self._ended = True
                self._cond.notify_all()

    def get(self, timeout: float = 0.1):
        """((frame, capture_ms, t_capture), detections, detect_ms), None on timeout;
        :class:`CaptureEnded` when the source is finished or failed."""
        with self._cond:
            if self._slot is None and not self._ended:
                self._cond.wait(timeout)
            if self._slot is not None:
                out, self._slot = self._slot, None
                return out
            if self._ended:
                raise CaptureEnded(self.capture.error)
            return None

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)


class NoDetect:
    """The feed of :class:`Capture` alone: the pipeline detects in the main thread."""

    def __init__(self, capture: Capture) -> None:
        self.capture = capture

    @property
    def dropped(self) -> int:
        return self.capture.dropped

    def get(self, timeout: float = 0.1):
        item = self.capture.get(timeout=timeout)
        return None if item is None else (item, None, 0.0)

    def close(self) -> None:
        pass


def open_feed(capture: Capture, pipeline, workers: int, live: bool, replay: bool):
    """Where detection happens: ``workers`` = 0 (or a replay, nothing to detect) in the main
    thread; else a thread of its own for a live source, a pool of ``workers`` threads for an
    in-order source."""
    if workers < 1 or replay:
        return NoDetect(capture)
    if live:
        return LiveDetect(capture, pipeline)
    return DetectPool(capture, pipeline, workers)
