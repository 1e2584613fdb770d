"""``replay:FILE``: a recording (:mod:`kmea.recordings.format`) as a frame source: its detections
and poses, no images. Plain or compressed, version 1 or 2; a recording cut by a kill (or
one part of a recording cut into parts) replays up to its last whole line."""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Any

from kmea.recordings.format import (
    RecordingError,
    camera_from_json,
    frame_from_json,
    iter_lines,
    map_from_json,
    read_header,
)
from kmea.sources.base import Frame, FrameSource, SourceError

__all__ = ["ReplaySource", "open_replay"]


class ReplaySource(FrameSource):
    """``replay:FILE``: the frames of a recording, with detections and poses, no images.

    Each :class:`Frame` has ``image = None`` and ``meta["replay"] = (ids, corners,
    observations, diag)``; a line that cannot be parsed gives ``meta["error"]``.
    ``camera`` and ``world_map`` come from the header.
    """

    live = False

    def __init__(self, path: str | Path) -> None:
        super().__init__()
        self.path = Path(path)
        self.spec = f"replay:{path}"
        try:
            self.header = read_header(self.path)
            self.camera = camera_from_json(self.header["camera"])
            self.world_map = map_from_json(self.header["map"])
        except RecordingError as e:
            raise SourceError(str(e)) from None
        except (KeyError, TypeError, ValueError) as e:
            raise SourceError(f"{self.path}: line 1: bad recording header: {e}") from None
        self.size = (self.camera.width, self.camera.height)
        self._lines = iter_lines(self.path)
        self._line = 0
        self._count = 0
        self.truncated = False  # the last line was partial (a recording cut by a kill)
        try:
            self._next()  # the header
        except SourceError:
            self._lines.close()
            raise

    def _next(self) -> bytes | None:
        try:
            self._line, text = next(self._lines)
        except StopIteration:
            return None
        except (RecordingError, OSError) as e:
            raise SourceError(str(e)) from None
        return text

    def read(self) -> Frame | None:
        if self._closed:
            return None
        text = self._next()
        if text is None:
            return None
        if not text.endswith(b"\n"):  # a recording cut by a kill: the last line is partial
            self.truncated = True
            what = (f"line {self._line} is partial" if text else
                    f"the compressed stream ends after line {self._line - 1} without its end")
            logging.getLogger("kmead").warning(
                "%s: %s (a recording cut short?); replay ends at frame %d", self.path.name,
                what, self._count)
            return None
        where = f"{self.path.name}: line {self._line}"
        try:
            index, t, ids, corners, obs, diag, truth = frame_from_json(json.loads(text))
            frame = Frame(index, t, None, {"replay": (ids, corners, obs, diag),
                                           "truth": truth})
        except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError,
                ValueError) as e:
            frame = Frame(self._count, math.nan, None, {"error": f"{where}: bad frame: {e}"})
        self._count += 1
        return frame

    def close(self) -> None:
        if not self._closed:
            self._lines.close()
        super().close()


def open_replay(rest: str, **opts: Any) -> ReplaySource:
    """The ``replay:FILE`` source of :func:`kmea.sources.registry.open_source` (no options)."""
    if opts:
        raise SourceError(f"replay:{rest}: takes no options (got {', '.join(sorted(opts))})")
    if not rest:
        raise SourceError("replay: expected replay:FILE")
    p = Path(rest)
    if not p.is_file():
        raise SourceError(f"replay:{rest}: no such file")
    return ReplaySource(p)

