"""Telemetry bodies from explicit inputs: one function per message type of
:mod:`kmea.wire.protocol`, each returning that type.

Nothing here reads the daemon: the daemon (and the control thread) pass the frame result,
the statistics, the relay's tracks and the configuration snapshot they hold. Values may be
numpy scalars or arrays; :func:`kmea.wire.protocol.encode_body` turns them into JSON.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Mapping
from typing import TYPE_CHECKING, Any, Protocol

from kmea.stats.moved import MovedEvidence
from kmea.wire.protocol import (
    FrameBody,
    MapInfo,
    MarkerRow,
    MarkersBody,
    RobotRow,
    RobotsBody,
    StatsBody,
    StatusBody,
)

if TYPE_CHECKING:
    from kmea.maps.files import MarkerMap
    from kmea.pipeline import FrameResult
    from kmea.vision.camera import CameraModel
    from kmead.outputs.relay import RobotChannel


def frame_body(res: FrameResult, *, source: str, fps: float, dropped: int,
               bad_frames: int) -> FrameBody:
    """``frame``: the frame's estimate summary, per-stage timings (ms) and counters."""
    d = res.diagnostics
    return {"t": res.timestamp, "frame": res.index, "source": source,
            "algorithm": res.algorithm, "ok": res.estimate.ok, "reason": res.estimate.reason,
            "n_detected": len(res.ids), "n_refs": len(res.estimate.references),
            "fps": fps, "dropped": dropped,
            "timings_ms": {k: round(v, 4) for k, v in res.timings.items()},
            "flips": int(d.get("n_flipped", 0)), "ambiguous": int(d.get("n_ambiguous", 0)),
            "suspect": int(d.get("n_suspect", 0)),
            "bad_frames": bad_frames, "scale": res.estimate.scale,
            "rejected": sorted(int(i) for i in res.estimate.rejected)}


def markers_body(res: FrameResult, world_map: MarkerMap,
                 moved: Callable[[int], MovedEvidence]) -> MarkersBody:
    """``markers``: every map marker and every detected marker, sorted by id.

    moved: id -> the moved-marker monitor's evidence (:meth:`kmea.stats.moved.MovedMonitor.get`).
    """
    est = res.estimate
    planes = est.info.get("unknown_planes", {})
    stats = est.info.get("plane_statistics", {})
    obs = {o.id: o for o in res.observations}
    map_markers = world_map.markers
    ids = sorted(map_markers.keys() | {int(i) for i in res.ids})
    out: list[MarkerRow] = []
    for mid in ids:
        mk = map_markers.get(mid)
        me = res.markers.get(mid)
        o = obs.get(mid)
        p = me[0] if me is not None else None
        ev = moved(mid) if mk is not None else None
        out.append({
            "id": mid, "in_map": mk is not None, "detected": o is not None,
            "x": None if p is None else p[0], "y": None if p is None else p[1],
            "z": None if p is None else p[2], "yaw": None if me is None else me[1],
            "map_x": None if mk is None else mk.position[0],
            "map_y": None if mk is None else mk.position[1],
            "map_z": None if mk is None else mk.position[2],
            "error": res.loo.get(mid), "ambiguous": bool(o.ambiguous) if o else False,
            "flipped": bool(o.flipped) if o else False,
            "suspect": bool(o.suspect) if o else False, "rejected": mid in est.rejected,
            "rejection": est.rejected.get(mid),
            "reference": mid in est.references,
            "moved": bool(ev.moved) if ev else False,
            "moved_offset": ev.offset if ev else None,
            "moved_frames": ev.frames if ev else 0,
            "moved_threshold": ev.threshold if ev else None,
            "plane": planes.get(mid),
            "plane_stat": (float(stats[mid]) if mid in stats and math.isfinite(stats[mid])
                           else None),
        })
    return {"t": res.timestamp, "frame": res.index, "algorithm": res.algorithm,
            "markers": out}


def robots_body(res: FrameResult, tracks: Iterable[RobotChannel]) -> RobotsBody:
    """``robots``: every configured robot's last pose and relay counters."""
    out: list[RobotRow] = []
    for tr in tracks:
        last = tr.last_seen
        seen = last is not None
        out.append({"name": tr.name, "markers": list(tr.markers),
                    "x": tr.x if seen else None, "y": tr.y if seen else None,
                    "theta": tr.theta if seen else None, "sigma": tr.sigma,
                    "valid": tr.name in res.robots and tr.unfit is None,
                    "age_s": (res.timestamp - last) if last is not None else None,
                    "stale": tr.stale, "destinations": list(tr.destinations),
                    "sent": tr.sent, "seq": tr.seq, "send_errors": tr.errors,
                    "send_refused": tr.refused, "refused": tr.refused_now()})
    return {"t": res.timestamp, "frame": res.index, "robots": out}


class StatsWindow(Protocol):
    """The window statistics a ``stats`` body is made of (kmea.stats.metrics.WindowStats;
    a fusion node's is an empty window)."""

    @property
    def window(self) -> int: ...
    @property
    def mean_error(self) -> float | None: ...
    @property
    def max_error(self) -> float | None: ...
    def per_marker(self) -> Mapping[int, Any]: ...
    def reset(self) -> None: ...


def stats_body(stats: StatsWindow, algorithm: str, res: FrameResult | None) -> StatsBody:
    """``stats``: the window statistics; ``res`` the last frame (None before the first)."""
    pm = stats.per_marker()
    return {"t": res.timestamp if res else time.time(), "frame": res.index if res else None,
            "algorithm": algorithm, "window": stats.window,
            "mean_error": stats.mean_error, "max_error": stats.max_error,
            "markers": [{"id": mid, **m.as_dict()} for mid, m in pm.items()]}  # type: ignore[typeddict-item]


def status_body(*, t0: float, source: str, config_file: str, config_files: list[str],
                algorithm: str, algorithms: list[str], csv: Any, recorder: Any,
                camera: CameraModel, world_map: MarkerMap, frames: int, dropped: int,
                bad_frames: int, telemetry: str, control: str,
                stopped: bool = False,
                output_errors: dict[str, str | None] | None = None) -> StatusBody:
    """``status``: the daemon's state. t0: unix start time; csv, recorder: the open CSV log
    and recording (``path``, ``rows``/``frames``, ``bytes``) or None; stopped: the last
    status, at shutdown (adds ``"state": "stopped"``); output_errors: ``{"log", "record"}``
    -> why that output stopped or was refused on its own (a write error, the free-space
    floor), None when it did not."""
    errors = output_errors or {}
    now = time.time()
    c, r = csv, recorder
    body: StatusBody = {
        "t": now, "uptime": now - t0, "source": source,
        "config_file": config_file, "config_files": list(config_files),
        "algorithm": algorithm, "algorithms": list(algorithms),
        "logging": {"active": c is not None, "path": str(c.path) if c else None,
                    "rows": c.rows if c else 0, "bytes": c.bytes if c else 0,
                    "error": errors.get("log")},
        "recording": {"active": r is not None, "path": str(r.path) if r else None,
                      "frames": r.frames if r else 0, "bytes": r.bytes if r else 0,
                      "error": errors.get("record")},
        "camera": {"width": camera.width, "height": camera.height, "fx": camera.fx,
                   "fy": camera.fy},
        "map": map_info(world_map),
        "frames": frames, "dropped": dropped, "bad_frames": bad_frames,
        "telemetry": telemetry, "control": control,
    }
    if stopped:
        body["state"] = "stopped"
    return body


def map_info(world_map: Any, markers: bool = False) -> MapInfo:
    """The ``status`` body's ``map``: name, marker count and floor extent (m); with
    ``markers`` every marker's [id, x, y, z] (m; a fusion node, which sends no markers
    telemetry)."""
    info: MapInfo = {"name": world_map.name, "n": len(world_map),
                     "extent": [round(v, 4) for v in world_map.floor_extent()]}
    if markers:
        info["markers"] = [[i, *(round(float(v), 4) for v in world_map.positions([i])[0])]
                           for i in world_map.ids]
    return info
