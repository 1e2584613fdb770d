"""The fixed-camera detector's discovery: full detections that find markers new to the view.

Every ``full_every`` frames, and when a tracked marker is lost, the detector asks for a full
detection of the frame (:class:`DiscoveryJob`, a synchronous unit of work); what it finds is
merged into a later frame (:meth:`kmea.fixed_camera.detector.FixedCameraDetector.detect`).
Where and when a job runs is the caller's (:class:`Jobs`): the library runs it at once in
the calling thread (:class:`Inline`) and starts no thread; the daemon runs it on a thread
of its own at a lower priority, after the frame's robots were sent
(:mod:`kmead.run.discovery`).

- :class:`TunedDetectors`: one thread's detectors, the configured one and ones with a
  single adaptive-threshold window;
- :func:`discover`: a full detection, at half resolution when asked;
- :class:`Jobs` / :class:`Background`: what the detector and the pipeline ask of the
  caller's scheduler.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple, Protocol

import cv2
import numpy as np

from kmea.vision.detection import Detections, DetectorConfig, MarkerDetector

__all__ = ["Background", "Discovered", "DiscoveryJob", "Inline", "Jobs", "TunedDetectors",
           "discover"]


class TunedDetectors:
    """One thread's detectors of ``config``: :attr:`full` (the configured parameters) and
    :meth:`window` (one adaptive-threshold window); OpenCV's detectors are not shared
    between threads."""

    def __init__(self, config: DetectorConfig) -> None:
        self.config = config
        self._full: MarkerDetector | None = None
        self._tuned: dict[int, MarkerDetector] = {}

    @property
    def full(self) -> MarkerDetector:
        if self._full is None:
            self._full = MarkerDetector(self.config)
        return self._full

    def window(self, win: int) -> MarkerDetector:
        """A detector with one adaptive-threshold window of ``win`` px (a third of the full
        parameters' three passes), made on first use."""
        det = self._tuned.get(win)
        if det is None:
            params = {**self.config.parameters, "adaptiveThreshWinSizeMin": win,
                      "adaptiveThreshWinSizeMax": win}
            det = self._tuned[win] = MarkerDetector(DetectorConfig(
                self.config.dictionary, self.config.corner_refinement, params))
        return det


def discover(det: MarkerDetector, image: np.ndarray, half: bool) -> Detections:
    """Full detection of ``image``, at half resolution when ``half`` (4x fewer pixels;
    corners mapped back to full-resolution pixels, to be refined there)."""
    if not half:
        return det.detect(image)
    h, w = image.shape[:2]
    small = cv2.resize(image, (w // 2, h // 2), interpolation=cv2.INTER_AREA)
    d = det.detect(small)
    # INTER_AREA by 2: small pixel i covers full pixels 2i and 2i+1 (centre 2i + 0.5).
    return Detections(d.ids, d.corners * 2.0 + 0.5, d.rejected)


class Discovered(NamedTuple):
    """A discovery's result: the frame it looked at, what it found, at half resolution?"""

    frame: int
    detections: Detections
    half: bool


@dataclass(frozen=True, eq=False)
class DiscoveryJob:
    """A full detection of frame ``frame``'s ``image`` (``half``: at half resolution, with
    one threshold window of ``win`` px when ``win`` > 0), with ``detectors``: those of the
    detector's discovery, used by one job at a time. Calling it runs it."""

    frame: int
    image: np.ndarray
    half: bool
    win: int
    detectors: TunedDetectors

    def __call__(self) -> Discovered:
        det = self.detectors.window(self.win) if self.win else self.detectors.full
        return Discovered(self.frame, discover(det, self.image, self.half), self.half)


class Jobs(Protocol):
    """Where one detector's discovery jobs run: one at a time, the newest queued replacing
    one not started; ``take`` gives a finished job's result once."""

    def submit(self, job: DiscoveryJob) -> None: ...
    def take(self) -> Discovered | None: ...
    def frame_started(self) -> None: ...
    def close(self) -> None: ...


class Background(Protocol):
    """The caller's scheduler of discovery jobs (:class:`kmea.pipeline.Pipeline`'s
    ``background``): ``jobs()`` a queue for one more detector; ``robots_sent()``: the frame's
    robots are out, a job may run now."""

    def jobs(self) -> Jobs: ...
    def robots_sent(self) -> None: ...


class Inline:
    """:class:`Jobs` in the calling thread: a job runs when submitted (the frame at which a
    discovery is merged is then deterministic)."""

    def __init__(self) -> None:
        self._result: Discovered | None = None

    def submit(self, job: DiscoveryJob) -> None:
        self._result = job()

    def take(self) -> Discovered | None:
        r, self._result = self._result, None
        return r

    def frame_started(self) -> None:
        pass

    def close(self) -> None:
        pass
