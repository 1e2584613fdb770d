"""``replay:FILE``: a recording (:mod:`kmea.recording`) as a frame source: its detections
and poses, no images."""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np

from kmea.recording import (
    RecordingError,
    camera_from_json,
    map_from_json,
    obs_from_json,
    read_header,
    unnum,
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
        self._f = open(self.path, encoding="utf-8")  # noqa: SIM115 - closed in close()
        self._f.readline()
        self._line = 1
        self._count = 0
        self.truncated = False  # the last line was partial (a recording cut by a kill)

    def read(self) -> Frame | None:
        if self._closed:
            return None
        text = self._f.readline()
        if not text:
            return None
        self._line += 1
        if not text.endswith("\n"):  # a recording cut by a kill: the last line is partial
            self.truncated = True
            logging.getLogger("kmead").warning(
                "%s: line %d is partial (a recording cut short?); replay ends at frame %d",
                self.path.name, self._line, self._count)
            return None
        where = f"{self.path.name}: line {self._line}"
        try:
            d = json.loads(text)
            ids = np.array(d["ids"], dtype=np.int64)
            corners = np.array([[unnum(x) for x in c] for c in d["corners"]],
                               dtype=float).reshape(-1, 4, 2)
            obs = [obs_from_json(m) for m in d["markers"]]
            frame = Frame(int(d["frame"]), float(d["t"]), None,
                          {"replay": (ids, corners, obs, d.get("diag") or {}),
                           "truth": d.get("truth")})
        except (json.JSONDecodeError, KeyError, TypeError, ValueError) as e:
            frame = Frame(self._count, math.nan, None, {"error": f"{where}: bad frame: {e}"})
        self._count += 1
        return frame

    def close(self) -> None:
        if not self._closed:
            self._f.close()
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

