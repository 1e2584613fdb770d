"""An OpenCV / V4L2 camera (``camera:INDEX``)."""

from __future__ import annotations

import sys
import time
from pathlib import Path

from kmea.sources.base import Frame, FrameSource, SourceError
from kmea.sources.files import _cap_size, _to_gray

__all__ = ["CameraSource"]


class CameraSource(FrameSource):
    """An OpenCV camera (V4L2 on Linux). Options: ``width``, ``height``, ``fps``, ``gray``.

    Raises ``SourceError`` when the camera cannot be opened or stops delivering frames.
    """

    live = True

    def __init__(self, index: int, width: int | None = None, height: int | None = None,
                 fps: float | None = None, gray: bool = False) -> None:
        import cv2

        super().__init__()
        self.index = int(index)
        self.spec = f"camera:{self.index}"
        dev = Path(f"/dev/video{self.index}")
        if sys.platform.startswith("linux") and not dev.exists():
            # Checked first so OpenCV does not print its own warnings for a missing device.
            raise SourceError(f"{self.spec}: cannot open camera {self.index}: {dev} does not exist "
                              f"(is the camera connected? `v4l2-ctl --list-devices`)")
        backend = getattr(cv2, "CAP_V4L2", cv2.CAP_ANY) if dev.exists() else cv2.CAP_ANY
        self._cap = cv2.VideoCapture(self.index, backend)
        if not self._cap.isOpened():
            self._cap.release()
            raise SourceError(f"{self.spec}: cannot open camera {self.index} (in use by another "
                              f"program, or not a capture device?)")
        if width and height:
            self._cap.set(cv2.CAP_PROP_FRAME_WIDTH, int(width))
            self._cap.set(cv2.CAP_PROP_FRAME_HEIGHT, int(height))
        if fps:
            self._cap.set(cv2.CAP_PROP_FPS, float(fps))
        self.size = _cap_size(self._cap)
        self.gray = bool(gray)
        self._index = 0

    def read(self) -> Frame | None:
        if self._closed:
            return None
        ok, img = self._cap.read()
        t = time.monotonic()
        if not ok or img is None:
            raise SourceError(f"{self.spec}: the camera stopped delivering frames")
        if self.gray:
            img = _to_gray(img)
        i = self._index
        self._index += 1
        self.size = (int(img.shape[1]), int(img.shape[0]))
        return Frame(i, t, img, {})

    def close(self) -> None:
        if not self._closed:
            self._cap.release()
        super().close()
