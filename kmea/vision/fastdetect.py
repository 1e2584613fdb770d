"""Fast detection: tuned parameters first, the full detection when something is missing.

Most of ``detectMarkers``' time goes into thresholding the frame at several adaptive
window sizes (kmea's defaults: 5, 13 and 21 px). With a fixed overhead camera the markers
keep their size, so one window that suits them (``detector.fast_window``; 0 = a fifth of
the median marker side seen by the last full detection, e.g. 13 px for 60 mm markers 55-70
px wide at 1640x1232) finds nearly all of them at a third of the cost. Nearly is not
enough: every marker found in the previous frame must be found again, so a frame where one
is missing is detected again with the configured (full) parameters, and so is every
``full_every``-th frame: a marker entering the view (or found only now and then) may wait
up to ``full_every`` frames. A marker that really left the view costs one full detection;
then it is no longer expected.

Stateful: one instance per source, called on consecutive frames in order.
"""

from __future__ import annotations

import numpy as np

from kmea.vision.detection import Detections, DetectorConfig, MarkerDetector


class FastDetector:
    """``detect(image)`` like :class:`MarkerDetector` (see the module docstring).

    ``fast`` / ``full`` count the frames each detection answered.
    """

    def __init__(self, config: DetectorConfig, window: int = 0, full_every: int = 30) -> None:
        self.config = config
        self.full_detector = MarkerDetector(config)
        self.window = 0
        self.fast_detector: MarkerDetector | None = None
        self.fixed_window = int(window)
        if window:
            self._set_window(int(window))
        self.full_every = max(1, int(full_every))
        self._expected: set[int] | None = None
        self._since_full = 0
        self.fast = 0
        self.full = 0

    def _set_window(self, window: int) -> None:
        window = max(3, window | 1)  # odd, >= 3
        if window == self.window:
            return
        params = {**self.config.parameters, "adaptiveThreshWinSizeMin": window,
                  "adaptiveThreshWinSizeMax": window}
        self.fast_detector = MarkerDetector(DetectorConfig(
            self.config.dictionary, self.config.corner_refinement, params))
        self.window = window

    def detect(self, image: np.ndarray) -> Detections:
        self._since_full += 1
        det = None
        if (self._expected is not None and self._since_full < self.full_every
                and self.fast_detector is not None):
            det = self.fast_detector.detect(image)
            if not self._expected <= set(det.ids.tolist()):
                det = None  # a marker of the previous frame is missing: look properly
            else:
                self.fast += 1
        if det is None:
            det = self.full_detector.detect(image)
            self.full += 1
            self._since_full = 0
            if not self.fixed_window and len(det):
                side = np.linalg.norm(np.diff(det.corners, axis=1, append=det.corners[:, :1]),
                                      axis=2)
                self._set_window(round(float(np.median(side)) / 5.0))
        self._expected = set(det.ids.tolist())
        return det
