"""One frame of images, as every source gives it and the simulator renders it.

It sits below both :mod:`kmea.sources` (which reads frames) and :mod:`kmea.sim` (whose
rendered frames carry their truth), so that neither has to import the other for it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["Frame"]


@dataclass
class Frame:
    """One frame.

    index: 0-based frame number in the source. timestamp: seconds (file sources: index / fps;
    cameras: ``time.monotonic()`` at capture; picamera: sensor timestamp). image: (H, W) uint8
    greyscale or (H, W, 3) uint8 BGR, or None when the frame could not be decoded (then
    ``meta["error"]`` says why). meta: source-specific extras (``path``, ``sensor_timestamp_ns``;
    ``unix_time``: True when ``timestamp`` is the Unix time of the exposure, as a
    wall-clock simulator's frames are stamped).
    """

    index: int
    timestamp: float
    image: np.ndarray | None
    meta: dict = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.image is not None

    @property
    def error(self) -> str | None:
        return self.meta.get("error")
