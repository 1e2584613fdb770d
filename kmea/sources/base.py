"""What every frame source is: :class:`FrameSource` (read until None, close), the
:class:`Frame` it gives (defined in :mod:`kmea.frame`, below the simulator too) and the
errors it raises.

A frame that cannot be decoded does not stop a file source: :meth:`FrameSource.read` returns
a :class:`Frame` with ``image = None`` and ``meta["error"]`` (e.g. ``"b.png: cannot decode"``);
callers skip it and go on. A source that cannot be opened, or a live camera that stops
delivering, raises :class:`SourceError`. The sources themselves are the sibling modules;
:mod:`kmea.sources.registry` opens one from a spec string.
"""

from __future__ import annotations

from collections.abc import Iterator

from kmea.frame import Frame

__all__ = ["IMAGE_SUFFIXES", "Frame", "FrameSource", "SourceError", "SourceOptionError"]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".pbm",
                  ".webp")


class SourceError(RuntimeError):
    """A source cannot be opened or stopped delivering; the message names the source."""


class SourceOptionError(SourceError, TypeError):
    """An option the source does not take (a TypeError too, as for a wrong keyword)."""


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
