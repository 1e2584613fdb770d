"""File sources: an image folder (``images:DIR``) and a video file (``video:PATH``)."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np

from kmea.sources.base import IMAGE_SUFFIXES, Frame, FrameSource, SourceError

__all__ = ["ImageFolderSource", "VideoSource"]


def _cap_size(cap: Any) -> tuple[int, int] | None:
    import cv2

    w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
    return (w, h) if w > 0 and h > 0 else None


def _natural_key(name: str) -> list:
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def _to_gray(img: np.ndarray) -> np.ndarray:
    import cv2

    if img.ndim == 2:
        return img
    if img.shape[2] == 4:
        return cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY)
    return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)


class ImageFolderSource(FrameSource):
    """Image files of a folder in natural name order; other files are ignored.

    Options: ``gray`` (bool, default False: BGR as decoded), ``fps`` (timestamps = index / fps,
    default 30). A file that cannot be decoded gives a Frame with image None and
    ``meta["error"]``.
    """

    live = False

    def __init__(self, folder: str | Path, gray: bool = False, fps: float = 30.0) -> None:
        super().__init__()
        self.folder = Path(folder)
        self.spec = f"images:{folder}"
        if not self.folder.is_dir():
            raise SourceError(f"{self.spec}: not a folder")
        if fps <= 0:
            raise SourceError(f"{self.spec}: fps must be > 0, got {fps}")
        self.files = sorted((p for p in self.folder.iterdir()
                             if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES),
                            key=lambda p: _natural_key(p.name))
        if not self.files:
            raise SourceError(f"{self.spec}: no image files ({', '.join(IMAGE_SUFFIXES)})")
        self.gray = bool(gray)
        self.fps = float(fps)
        self._next = 0

    def __len__(self) -> int:
        return len(self.files)

    def read(self) -> Frame | None:
        import cv2

        if self._closed or self._next >= len(self.files):
            return None
        i = self._next
        self._next += 1
        path = self.files[i]
        meta: dict[str, Any] = {"path": str(path)}
        img = None
        try:
            buf = np.fromfile(path, dtype=np.uint8)
        except OSError as e:
            meta["error"] = f"{path.name}: cannot read: {e.strerror or e}"
        else:
            # imdecode rather than imread: no warning printed for a corrupt file.
            img = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE if self.gray else cv2.IMREAD_COLOR) \
                if buf.size else None
            if img is None:
                meta["error"] = f"{path.name}: cannot decode"
        if img is not None and self.size is None:
            self.size = (int(img.shape[1]), int(img.shape[0]))
        return Frame(i, i / self.fps, img, meta)


class VideoSource(FrameSource):
    """A video file. Options: ``gray`` (bool). Timestamps: index / the file's frame rate."""

    live = False

    def __init__(self, path: str | Path, gray: bool = False) -> None:
        import cv2

        super().__init__()
        self.path = Path(path)
        self.spec = f"video:{path}"
        if not self.path.is_file():
            raise SourceError(f"{self.spec}: no such file")
        self._cap = cv2.VideoCapture(str(self.path))
        if not self._cap.isOpened():
            raise SourceError(f"{self.spec}: cannot open as a video")
        fps = self._cap.get(cv2.CAP_PROP_FPS)
        self.fps = float(fps) if fps and fps > 0 else 30.0
        self.size = _cap_size(self._cap)
        self.gray = bool(gray)
        self._index = 0
        # Frames the container announces (0 if unknown): fewer decoded means a cut file.
        n = self._cap.get(cv2.CAP_PROP_FRAME_COUNT)
        self.expected_frames = int(n) if n and 0 < n < 1e9 else 0

    @property
    def frames_read(self) -> int:
        return self._index

    def read(self) -> Frame | None:
        if self._closed:
            return None
        ok, img = self._cap.read()
        if not ok or img is None:
            return None
        i = self._index
        self._index += 1
        if self.gray:
            img = _to_gray(img)
        return Frame(i, i / self.fps, img, {"path": str(self.path)})

    def close(self) -> None:
        if not self._closed:
            self._cap.release()
        super().close()
