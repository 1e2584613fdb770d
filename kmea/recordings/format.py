"""Recordings: every frame's detections and per-marker poses, for ``--source replay:FILE``.

A recording is JSON lines (UTF-8, one object per line), zstd-compressed when its name ends
in ``.zst`` (:mod:`kmea.recordings.recfile`: whole lines survive a kill):

1. a header ``{"format": "kmead-recording", "version": 2, "created", "source", "camera",
   "map", "robots", "config"[, "part", "previous"]}``: the camera model at the frame size,
   the marker map with raw rotation matrices (so replay sees bit-identical numbers), the
   configuration; ``part`` (2, 3 ...) and ``previous`` (the file before it) when the
   recording was cut into parts (each part replays alone);
2. one line per frame ``{"frame", "t", "ids", "corners", "markers", "diag"[, "truth"]}``:
   ``markers`` holds every per-marker pose (``R``, ``t``, the reprojection errors of both
   IPPE solutions, and ``ambiguous``, ``flipped``, ``suspect`` when true); ``truth`` is the
   simulator's ground truth when known.

Version 2 keeps what a replay reads and nothing twice: a marker's ``corners`` are left out
when they are its detection's (``corners`` of the first detection with its id: they always
were; a fifth of a version 1 frame), and the other IPPE solution's pose (``alt_R``,
``alt_t``: 40 % of a compressed frame) is not written, since no stage after the pose reads
it (a replay reproduces the run's rows without it). Version 1 files (every marker's corners,
both solutions, every flag) still read.

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

from kmea.estimators.base import MarkerObservation
from kmea.maps.files import Marker, MarkerMap
from kmea.recordings.recfile import LineWriter, RecordingBytesError, read_lines
from kmea.vision.camera import CameraModel
from kmea.wire.jsonsafe import to_jsonable

FORMAT = "kmead-recording"
VERSION = 2
READS = (1, 2)  # the versions this module reads


class RecordingError(ValueError):
    """A recording that cannot be read; the message names the file and line."""


def _num(v: float) -> float | None:
    v = float(v)
    return v if math.isfinite(v) else None


def _arr(a: Any) -> Any:
    if a is None:
        return None
    v = np.asarray(a, dtype=float).reshape(-1)
    # tolist() and one finiteness test: a third of the CPU of to_jsonable's per-value walk.
    return v.tolist() if np.isfinite(v).all() else to_jsonable(v)


def _unarr(v: Any, shape: tuple[int, ...]) -> np.ndarray | None:
    return None if v is None else np.array(v, dtype=float).reshape(shape)  # null -> NaN


def _needarr(d: dict, key: str, shape: tuple[int, ...]) -> np.ndarray:
    """d[key] as an array of ``shape`` (a missing field is a broken recording: KeyError)."""
    return np.array(d[key], dtype=float).reshape(shape)


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


def obs_to_json(o: MarkerObservation, detected: np.ndarray | None = None) -> dict:
    """A marker's observation; ``detected``: the corners of its detection, which its own
    are not repeated when equal to (format version 2)."""
    # Not the other IPPE solution's pose (alt_R, alt_t): nothing after the pose stage reads
    # it, and its twelve full-precision floats were 40 % of a compressed frame.
    d = {"id": int(o.id), "R": _arr(o.marker2cam_R), "t": _arr(o.marker2cam_t),
         "length": float(o.length), "reproj": _num(o.reproj_error),
         "alt_reproj": _num(o.alt_reproj_error)}
    if detected is None or o.corners is None or not np.array_equal(
            np.asarray(o.corners, dtype=float).reshape(-1), detected.reshape(-1)):
        d["corners"] = _arr(o.corners)
    for flag in ("ambiguous", "flipped", "suspect"):
        if getattr(o, flag):
            d[flag] = True
    return d


def obs_from_json(d: dict, detected: dict[int, Any] | None = None) -> MarkerObservation:
    """``detected``: id -> the corners (JSON) of its first detection, for a marker written
    without its own (version 2)."""
    mid = int(d["id"])
    corners = d["corners"] if "corners" in d else (detected or {})[mid]
    return MarkerObservation(
        id=mid, marker2cam_R=_needarr(d, "R", (3, 3)), marker2cam_t=_needarr(d, "t", (3,)),
        corners=_unarr(corners, (4, 2)), length=float(d["length"]),
        reproj_error=unnum(d.get("reproj")), alt_R=_unarr(d.get("alt_R"), (3, 3)),
        alt_t=_unarr(d.get("alt_t"), (3,)), alt_reproj_error=unnum(d.get("alt_reproj")),
        ambiguous=bool(d.get("ambiguous", False)), flipped=bool(d.get("flipped", False)),
        suspect=bool(d.get("suspect", False)))


def frame_to_json(index: int, t: float, ids: np.ndarray, corners: np.ndarray,
                  observations: list[MarkerObservation], diag: dict,
                  truth: dict | None = None) -> dict:
    """One frame's line (version 2)."""
    id_list = [int(i) for i in np.asarray(ids).reshape(-1)]
    c = np.asarray(corners, dtype=float).reshape(-1, 4, 2)
    first: dict[int, int] = {}
    for k, mid in enumerate(id_list):
        first.setdefault(mid, k)
    line: dict[str, Any] = {
        "frame": int(index), "t": float(t), "ids": id_list, "corners": [_arr(x) for x in c],
        "markers": [obs_to_json(o, c[first[int(o.id)]] if int(o.id) in first else None)
                    for o in observations],
        "diag": to_jsonable(diag)}
    if truth is not None:
        line["truth"] = to_jsonable(truth)
    return line


def frame_from_json(d: dict) -> tuple[int, float, np.ndarray, np.ndarray,
                                      list[MarkerObservation], dict, Any]:
    """(index, t, ids, corners, observations, diag, truth) of a frame line (version 1 or
    2); KeyError, TypeError or ValueError when it is not one."""
    ids = np.array(d["ids"], dtype=np.int64).reshape(-1)
    corners = np.array(d["corners"], dtype=float).reshape(-1, 4, 2)
    detected: dict[int, Any] = {}
    for mid, c in zip(d["ids"], d["corners"], strict=True):
        detected.setdefault(int(mid), c)
    obs = [obs_from_json(m, detected) for m in d["markers"]]
    return (int(d["frame"]), float(d["t"]), ids, corners, obs, d.get("diag") or {},
            d.get("truth"))


class Recorder:
    """Writes a recording; one ``write_frame`` per frame, flushed (whole lines survive a
    kill; compressed when the name ends in ``.zst``).

    fast_path: the run used the fixed-camera fast path (``detector.fixed_camera`` on a live
    source); the header says so, so that a replay can say its rows will differ.
    part, previous: this file's part number and the file before it, when a recording is
    cut into parts (kmead's ``log.part_mb`` / ``log.part_min``)."""

    def __init__(self, path: str | Path, camera: CameraModel, world_map: MarkerMap,
                 source: str, config: dict, fast_path: bool = False, part: int = 1,
                 previous: str | None = None) -> None:
        self.path = Path(path)
        if self.path.parent and not self.path.parent.exists():
            self.path.parent.mkdir(parents=True, exist_ok=True)
        self._out = LineWriter(self.path)
        self.frames = 0
        self.mode = "create"  # how it was started: create, append, new name
        self.camera = camera
        self.part = part
        self.started = time.monotonic()
        header = {"format": FORMAT, "version": VERSION, "created": time.time(),
                  "source": source, "camera": camera_to_json(camera),
                  "map": map_to_json(world_map), "robots": config.get("robots", []),
                  "config": config,
                  # The fixed-camera fast path paces the floor fit (a replay refits every
                  # frame): its marker and robot rows differ from a replay's, slightly.
                  "fast_path": bool(fast_path)}
        if part > 1:
            header.update(part=part, previous=previous)
        try:
            self._line(header)
        except OSError:
            self._out.close()
            raise

    @property
    def bytes(self) -> int:
        """Bytes on disk (compressed when compressed)."""
        return self._out.bytes

    @property
    def compressed(self) -> bool:
        return self._out.compressed

    def _line(self, obj: dict) -> None:
        # A failed write (full disk) is cut back to the last whole line, then raised.
        self._out.write((json.dumps(obj, separators=(",", ":"), allow_nan=False)
                         + "\n").encode())

    def write_frame(self, index: int, t: float, ids: np.ndarray, corners: np.ndarray,
                    observations: list[MarkerObservation], diag: dict,
                    truth: dict | None = None) -> None:
        self._line(frame_to_json(index, t, ids, corners, observations, diag, truth))
        self.frames += 1

    def close(self) -> None:
        self._out.close()

    @property
    def closed(self) -> bool:
        return self._out.closed


def iter_lines(path: str | Path) -> Any:
    """(line number, bytes) of every line of the recording ``path`` (plain or zstd), the
    last one without its newline when the file was cut; a generator that closes the file
    when it ends. ``RecordingError`` naming the file and line for corrupt bytes."""
    path = Path(path)
    with open(path, "rb") as f:
        n = 0
        try:
            for n, line in enumerate(read_lines(f), start=1):
                yield n, line
        except RecordingBytesError as e:
            raise RecordingError(f"{path}: after line {n}: {e}") from None


def read_header(path: str | Path) -> dict:
    """The header of a recording (``RecordingError`` naming the file when it is not one)."""
    path = Path(path)
    lines = iter_lines(path)
    try:
        _, first = next(lines, (1, b""))
    except OSError as e:
        raise RecordingError(f"{path}: cannot read: {e.strerror or e}") from None
    finally:
        lines.close()
    try:
        head = json.loads(first)
    except UnicodeDecodeError:
        raise RecordingError(f"{path}: not a kmead recording (not text)") from None
    except json.JSONDecodeError:
        raise RecordingError(f"{path}: line 1: not a kmead recording (no JSON header)") from None
    if not isinstance(head, dict) or head.get("format") != FORMAT:
        raise RecordingError(f"{path}: line 1: not a kmead recording (format != {FORMAT!r})")
    if head.get("version") not in READS:
        raise RecordingError(f"{path}: line 1: recording version {head.get('version')!r} "
                             f"not supported (expected one of {', '.join(map(str, READS))})")
    for key in ("camera", "map"):
        if key not in head:
            raise RecordingError(f"{path}: line 1: header has no {key!r}")
    return head
