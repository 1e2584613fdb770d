"""Frame sources shared by ``kmea calibrate`` and the daemon.

A source is opened from a spec string (see ``docs/camera.md``):

- ``images:DIR``   image files in DIR, in natural name order (``img2`` before ``img10``);
- ``video:PATH``   a video file read with ``cv2.VideoCapture``; ends cleanly;
- ``camera:INDEX`` a V4L2/OpenCV camera; options ``width``, ``height``, ``fps``;
- ``picamera``     the Raspberry Pi camera through picamera2 (imported only here): greyscale
  Y plane of a YUV420 stream; options ``width``, ``height``, ``fps``;
- ``sim:SCENE``    the simulator (:func:`kmea.sim.source.open_sim`);
- ``replay:FILE``  a recording's detections and poses (:func:`kmea.recording.open_replay`);
- anything added with :func:`register_source`.

Options come as keyword arguments of :func:`open_source` or after a ``?`` in the spec:
``camera:0?width=1280&height=960&fps=30``.

A frame that cannot be decoded does not stop a file source: :meth:`FrameSource.read` returns
a :class:`Frame` with ``image = None`` and ``meta["error"]`` (e.g. ``"b.png: cannot decode"``);
callers skip it and go on. A source that cannot be opened, or a live camera that stops
delivering, raises :class:`SourceError`.
"""

from __future__ import annotations

import re
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "IMAGE_SUFFIXES",
    "CameraSource",
    "Frame",
    "FrameSource",
    "ImageFolderSource",
    "SourceError",
    "SourceOptionError",
    "SourceSpec",
    "VideoSource",
    "open_source",
    "parse_source_spec",
    "register_source",
    "source_prefixes",
]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".pbm",
                  ".webp")


class SourceError(RuntimeError):
    """A source cannot be opened or stopped delivering; the message names the source."""


class SourceOptionError(SourceError, TypeError):
    """An option the source does not take (a TypeError too, as for a wrong keyword)."""


@dataclass
class Frame:
    """One frame.

    index: 0-based frame number in the source. timestamp: seconds (file sources: index / fps;
    cameras: ``time.monotonic()`` at capture; picamera: sensor timestamp). image: (H, W) uint8
    greyscale or (H, W, 3) uint8 BGR, or None when the frame could not be decoded (then
    ``meta["error"]`` says why). meta: source-specific extras (``path``, ``sensor_timestamp_ns``).
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


class FrameSource:
    """Base class: ``read()`` until None, ``close()``; a context manager and an iterator.

    ``live``: True for cameras (frames arrive in real time and never end by themselves),
    False for files. ``size``: (width, height) in pixels, or None until known.
    """

    live: bool = False
    spec: str = ""

    def __init__(self) -> None:
        self.size: tuple[int, int] | None = None
        self._closed = False

    def read(self) -> Frame | None:
        """The next frame, or None at the end of a file source."""
        raise NotImplementedError

    def close(self) -> None:
        self._closed = True

    @property
    def closed(self) -> bool:
        return self._closed

    def __enter__(self) -> FrameSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __iter__(self) -> Iterator[Frame]:
        while True:
            frame = self.read()
            if frame is None:
                return
            yield frame

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.spec!r}>"


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


# ---------------------------------------------------------------------------- registry

SourceFactory = Callable[..., FrameSource]
_REGISTRY: dict[str, SourceFactory] = {}


def register_source(prefix: str, factory: SourceFactory) -> None:
    """Make ``open_source("PREFIX:REST", **opts)`` call ``factory(REST, **opts)``.

    For sources outside the library (tests, site plug-ins). Registering a prefix again
    replaces the factory; a registered prefix wins over a built-in one.
    """
    if not re.fullmatch(r"[a-z][a-z0-9_-]*", prefix):
        raise ValueError(f"source prefix {prefix!r}: use lower-case letters, digits, - and _")
    _REGISTRY[prefix] = factory


def source_prefixes() -> list[str]:
    """Every prefix :func:`open_source` accepts (built in and registered), sorted."""
    return sorted({*_BUILTIN, *_REGISTRY})


_BOOL = {"1": True, "true": True, "yes": True, "on": True,
         "0": False, "false": False, "no": False, "off": False}


def _parse_value(text: str) -> Any:
    if text.lower() in _BOOL:
        return _BOOL[text.lower()]
    for conv in (int, float):
        try:
            return conv(text)
        except ValueError:
            pass
    return text


@dataclass(frozen=True)
class SourceSpec:
    """A parsed source spec ``PREFIX[:REST][?key=value&...]``.

    prefix: ``images``, ``camera``, ``sim`` ...; rest: what follows the first ``:`` (a
    folder, a file, a camera index, a scene name; "" if none); options: the query's values
    as bool, int, float or str.
    """

    prefix: str
    rest: str = ""
    options: dict[str, Any] = field(default_factory=dict)


# What REST must look like for each built-in prefix, and the form to suggest.
_REST_RULES: dict[str, tuple[str, str]] = {
    "images": (r".+", "images:DIR"), "video": (r".+", "video:PATH"),
    "camera": (r"\d*", "camera:INDEX"), "replay": (r".+", "replay:FILE"),
    "picamera": (r"", "picamera?width=W&height=H&fps=F"), "sim": (r".*", "sim:SCENE"),
}


def parse_source_spec(spec: str, check: bool = False) -> SourceSpec:
    """The one parser of source specs (``SourceError`` naming the spec when malformed).

    check: also require a known prefix and a REST of the right form (``camera:INDEX``,
    ``images:DIR`` ...): what a configuration file is validated with.
    """
    spec = str(spec)
    base, _, query = spec.partition("?")
    prefix, _, rest = base.partition(":")
    opts: dict[str, Any] = {}
    for part in filter(None, query.split("&")):
        key, eq, value = part.partition("=")
        if not eq or not key:
            raise SourceError(f"{spec}: option {part!r} is not key=value")
        opts[key] = _parse_value(value)
    if check:
        if prefix not in source_prefixes():
            raise SourceError(f"{spec}: unknown source {prefix!r} (known: "
                              f"{', '.join(p + ':' for p in source_prefixes())})")
        rule = _REST_RULES.get(prefix)
        if rule is not None and not re.fullmatch(rule[0], rest):
            raise SourceError(f"{spec}: expected {rule[1]}")
    return SourceSpec(prefix, rest, opts)


def _images(rest: str, **opts: Any) -> FrameSource:
    return ImageFolderSource(rest, **opts)


def _video(rest: str, **opts: Any) -> FrameSource:
    return VideoSource(rest, **opts)


def _camera(rest: str, **opts: Any) -> FrameSource:
    try:
        index = int(rest or "0")
    except ValueError:
        raise SourceError(f"camera:{rest}: INDEX must be an integer (camera:0)") from None
    return CameraSource(index, **opts)


def _picamera(rest: str, **opts: Any) -> FrameSource:
    if rest:
        raise SourceError(f"picamera:{rest}: the Pi camera takes no argument; use options "
                          f"(picamera?width=1640&height=1232&fps=30)")
    from kmea.vision.picamera_source import PiCameraSource  # picamera2 only on the Pi

    return PiCameraSource(**opts)


def _sim(rest: str, **opts: Any) -> FrameSource:
    from kmea.sim.source import open_sim  # the simulator depends on this module, not back

    return open_sim(rest, **opts)


def _replay(rest: str, **opts: Any) -> FrameSource:
    from kmea.recording import open_replay

    return open_replay(rest, **opts)


_BUILTIN: dict[str, SourceFactory] = {"images": _images, "video": _video, "camera": _camera,
                                      "picamera": _picamera, "sim": _sim, "replay": _replay}


def open_source(spec: str, **options: Any) -> FrameSource:
    """Open a frame source from ``PREFIX:REST`` (see the module docstring).

    ``options`` are passed to the source (e.g. ``width``, ``height``, ``fps``, ``gray``) and
    override options given in the spec after ``?``. Raises ``SourceError`` for an unknown
    prefix, bad options, or a source that cannot be opened.
    """
    parsed = parse_source_spec(spec)
    prefix, rest, spec_opts = parsed.prefix, parsed.rest, {**parsed.options, **options}
    factory = _REGISTRY.get(prefix) or _BUILTIN.get(prefix)
    if factory is None:
        raise SourceError(f"{spec}: unknown source {prefix!r} (known: "
                          f"{', '.join(p + ':' for p in source_prefixes())})")
    try:
        return factory(rest, **spec_opts)
    except TypeError as e:
        # An option the source does not take: name it rather than show a traceback.
        m = re.search(r"unexpected keyword argument '(\w+)'", str(e))
        if m:
            raise SourceOptionError(f"{spec}: option {m.group(1)!r} is not supported by "
                                    f"{prefix}:") from None
        raise
