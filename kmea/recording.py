"""Recordings: every frame's detections and per-marker poses, for ``--source replay:FILE``.

A recording is JSON lines (UTF-8, one object per line):

1. a header ``{"format": "kmead-recording", "version": 1, "created", "source", "camera",
   "map", "robots", "config"}``: the camera model at the frame size, the marker map with
   raw rotation matrices (so replay sees bit-identical numbers), and the configuration;
2. one line per frame ``{"frame", "t", "ids", "corners", "markers", "diag"[, "truth"]}``:
   ``markers`` holds every per-marker pose (both IPPE solutions, reprojection errors,
   ``ambiguous``, ``flipped`` and ``suspect``); ``truth`` is the simulator's ground truth
   when known.

Floats are written with Python's shortest round-trip repr, so replaying with the same
settings reproduces the recorded run's estimates exactly. NaN is written as ``null``.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from kmea import wholewrite
from kmea.estimators.base import MarkerObservation
from kmea.jsonsafe import to_jsonable
from kmea.maps import Marker, MarkerMap
from kmea.vision.camera import CameraModel

FORMAT = "kmead-recording"
VERSION = 1


class RecordingError(ValueError):
    """A recording that cannot be read; the message names the file and line."""


def _num(v: float) -> float | None:
    v = float(v)
    return v if math.isfinite(v) else None


def _arr(a: Any) -> Any:
    return None if a is None else to_jsonable(np.asarray(a, dtype=float).reshape(-1))


def unnum(v: Any) -> float:
    return math.nan if v is None else float(v)


def camera_to_json(c: CameraModel) -> dict:
    return {"camera_matrix": _arr(c.camera_matrix), "dist_coeffs": _arr(c.dist_coeffs),
            "width": c.width, "height": c.height}


def camera_from_json(d: dict) -> CameraModel:
    return CameraModel(np.array(d["camera_matrix"], dtype=float).reshape(3, 3),
                       np.array(d["dist_coeffs"], dtype=float), int(d["width"]), int(d["height"]))


def map_to_json(m: MarkerMap) -> dict:
    return {"name": m.name, "source": m.source, "dictionary": m.dictionary,
            "default_length": m.default_length, "origin_id": m.origin_id, "x_id": m.x_id,
            "y_id": m.y_id, "reference_length": m.reference_length,
            "markers": [{"id": mid, "position": _arr(mk.position), "rotation": _arr(mk.rotation),
                         "length": mk.length} for mid, mk in sorted(m.markers.items())]}


def map_from_json(d: dict) -> MarkerMap:
    markers = {int(r["id"]): Marker(int(r["id"]), np.array(r["position"], dtype=float),
                                    np.array(r["rotation"], dtype=float).reshape(3, 3),
                                    float(r["length"])) for r in d["markers"]}
    return MarkerMap(markers, dictionary=d["dictionary"], default_length=d["default_length"],
                     origin_id=d["origin_id"], x_id=d["x_id"], y_id=d["y_id"],
                     reference_length=d["reference_length"], name=d["name"],
                     source=d.get("source", "<recording>"))


def obs_to_json(o: MarkerObservation) -> dict:
    return {"id": int(o.id), "R": _arr(o.marker2cam_R), "t": _arr(o.marker2cam_t),
            "corners": _arr(o.corners), "length": float(o.length),
            "reproj": _num(o.reproj_error), "alt_R": _arr(o.alt_R), "alt_t": _arr(o.alt_t),
            "alt_reproj": _num(o.alt_reproj_error), "ambiguous": bool(o.ambiguous),
            "flipped": bool(o.flipped), "suspect": bool(o.suspect)}


def obs_from_json(d: dict) -> MarkerObservation:
    def arr(key: str, shape: tuple[int, ...]) -> np.ndarray | None:
        v = d.get(key)
        return None if v is None else np.array([unnum(x) for x in v]).reshape(shape)

    return MarkerObservation(
        id=int(d["id"]), marker2cam_R=arr("R", (3, 3)), marker2cam_t=arr("t", (3,)),
        corners=arr("corners", (4, 2)), length=float(d["length"]),
        reproj_error=unnum(d.get("reproj")), alt_R=arr("alt_R", (3, 3)),
        alt_t=arr("alt_t", (3,)), alt_reproj_error=unnum(d.get("alt_reproj")),
        ambiguous=bool(d.get("ambiguous", False)), flipped=bool(d.get("flipped", False)),
        suspect=bool(d.get("suspect", False)))


class Recorder:
    """Writes a recording; one ``write`` per frame, flushed (whole lines survive a kill).

    fast_path: the run used the fixed-camera fast path (``detector.tracking`` on a live
    source); the header says so, so that a replay can say its rows will differ."""

    def __init__(self, path: str | Path, camera: CameraModel, world_map: MarkerMap,
                 source: str, config: dict, fast_path: bool = False) -> None:
        self.path = Path(path)
        if self.path.parent and not self.path.parent.exists():
            self.path.parent.mkdir(parents=True, exist_ok=True)
        self._f = wholewrite.open_output(self.path)
        self._end = 0  # the byte after the last whole line
        self.frames = 0
        self.mode = "create"  # how it was started: create, append, new name
        self.bytes = 0
        self.camera = camera
        header = {"format": FORMAT, "version": VERSION, "created": time.time(),
                  "source": source, "camera": camera_to_json(camera),
                  "map": map_to_json(world_map), "robots": config.get("robots", []),
                  "config": config,
                  # The fixed-camera fast path paces the floor fit (a replay refits every
                  # frame): its marker and robot rows differ from a replay's, slightly.
                  "fast_path": bool(fast_path)}
        try:
            self._line(header)
        except OSError:
            self._f.close()
            raise

    def _line(self, obj: dict) -> None:
        data = (json.dumps(obj, separators=(",", ":"), allow_nan=False) + "\n").encode()
        # A failed write (full disk) is cut back to the last whole line, then raised.
        wholewrite.write_whole(self._f, data, self._end)
        self._end += len(data)
        self.bytes += len(data)

    def write_frame(self, index: int, t: float, ids: np.ndarray, corners: np.ndarray,
                    observations: list[MarkerObservation], diag: dict,
                    truth: dict | None = None) -> None:
        line: dict[str, Any] = {
            "frame": int(index), "t": float(t),
            "ids": [int(i) for i in np.asarray(ids).reshape(-1)],
            "corners": [_arr(c) for c in np.asarray(corners, dtype=float).reshape(-1, 4, 2)],
            "markers": [obs_to_json(o) for o in observations],
            "diag": to_jsonable(diag)}
        if truth is not None:
            line["truth"] = to_jsonable(truth)
        self._line(line)
        self.frames += 1

    def close(self) -> None:
        if not self._f.closed:
            self._f.close()

    @property
    def closed(self) -> bool:
        return self._f.closed


def read_header(path: str | Path) -> dict:
    """The header of a recording (``RecordingError`` naming the file when it is not one)."""
    path = Path(path)
    try:
        with open(path, encoding="utf-8") as f:
            first = f.readline()
    except OSError as e:
        raise RecordingError(f"{path}: cannot read: {e.strerror or e}") from None
    except UnicodeDecodeError:
        raise RecordingError(f"{path}: not a kmead recording (not text)") from None
    try:
        head = json.loads(first)
    except json.JSONDecodeError:
        raise RecordingError(f"{path}: line 1: not a kmead recording (no JSON header)") from None
    if not isinstance(head, dict) or head.get("format") != FORMAT:
        raise RecordingError(f"{path}: line 1: not a kmead recording (format != {FORMAT!r})")
    if head.get("version") != VERSION:
        raise RecordingError(f"{path}: line 1: recording version {head.get('version')!r} "
                             f"not supported (expected {VERSION})")
    for key in ("camera", "map"):
        if key not in head:
            raise RecordingError(f"{path}: line 1: header has no {key!r}")
    return head
