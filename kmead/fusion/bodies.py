"""The fusion node's telemetry bodies (``robots``, ``status``) and its ``get_state`` reply
(no frame, no marker statistics): kmead.fusion.node serves them."""

from __future__ import annotations

import math
import time
from typing import Any

from kmea.wire import protocol as P
from kmead.net.bodies import map_info

__all__ = ["map_status", "robots_body", "state_body", "status_body"]


def robots_body(node: Any) -> dict:
    assert node.relay is not None
    now = node.clock()
    out = []
    for tr in node.relay.channels.values():
        seen = tr.last_seen is not None
        srcs = node.fusion.sources(tr.name, node.cfg["relay"]["stale_after_s"])
        last = node.fusion.seen.get(tr.name)
        track = node.fusion.tracker.tracks.get(tr.name)
        st = track.state() if track is not None and track.started else None
        out.append({"name": tr.name, "markers": tr.markers,
                    "x": tr.x if seen else None, "y": tr.y if seen else None,
                    "theta": tr.theta if seen else None, "sigma": tr.sigma,
                    "valid": seen and not tr.stale and tr.unfit is None,
                    "age_s": (now - tr.last_seen) if tr.last_seen is not None else None,
                    "stale": tr.stale, "destinations": tr.destinations, "sent": tr.sent,
                    "seq": tr.seq, "send_errors": tr.errors,
                    "send_refused": tr.refused, "refused": tr.refused_now(),
                    "source": "+".join(srcs),
                    "sources": {s: now - t for s, t in last.last.items()} if last else {},
                    "vx": st.vx if st else None, "vy": st.vy if st else None,
                    "omega": st.omega if st else None})
    return {"t": now if math.isfinite(now) else time.time(), "frame": node.outputs,
            "robots": out}


def map_status(node: Any) -> P.MapInfo:
    """The status ``map``: the configured map with its markers; without ``map.file``, once
    a camera is used, that camera's map (its name and extent: cameras do not send their
    markers), else the built-in one."""
    ext = node.camera_extent
    if node.cfg["map"]["file"] or ext is None:
        return map_info(node.world_map, markers=True)
    return {"name": node.map_name, "n": 0, "extent": [round(v, 4) for v in ext]}


def status_body(node: Any) -> P.StatusBody:
    """The ``status`` body: a daemon's, without camera (zeros) and map (its robots),
    plus ``inputs`` (the cameras) and ``fusion``."""
    c = node.csv
    now_wall = time.time()
    lat = sorted(node.latency_ms)
    cams = list(node.cameras.values())
    return {
        "t": now_wall, "uptime": now_wall - node.t0,
        "source": f"fusion on zenoh site {node.site!r}: " + (", ".join(
            f"{c.label} {c.state}" for c in cams) or "no camera yet"),
        "config_file": node.cfg.user_file or "<default config>",
        "config_files": node.cfg.files, "algorithm": "fusion", "algorithms": ["fusion"],
        "logging": {"active": c is not None, "path": str(c.path) if c else None,
                    "rows": c.rows if c else 0, "bytes": c.bytes if c else 0,
                    "error": node.files.errors["log"] if node.files else None},
        "recording": {"active": False, "path": None, "frames": 0, "bytes": 0,
                      "error": None},
        "camera": {"width": 0, "height": 0, "fx": 0.0, "fy": 0.0},
        "map": map_status(node),
        "frames": node.outputs, "dropped": sum(i.dropped_old for i in cams),
        "bad_frames": sum(i.bad for i in cams),
        "inputs": [i.body(now_wall) for i in cams],
        "fusion": {"accepted": node.fusion.accepted,
                   "rejected": node.fusion.tracker.counts["rejected"],
                   "reacquired": node.fusion.tracker.counts["reacquired"],
                   "dropped_old": node.fusion.dropped_old,
                   "latency_ms_p50": lat[len(lat) // 2] if lat else None,
                   "latency_ms_p99": lat[min(len(lat) - 1, int(0.99 * len(lat)))]
                   if lat else None,
                   "node": node.node_id, "role": node.election.role,
                   "map_digest": node.map_digest, "overflow": node.overflow,
                   "strangers": node.foreign},
        "telemetry": node.telemetry.bound if node.telemetry else "",
        "control": node.control.bound if node.control else "",
    }


def state_body(node: Any) -> dict[str, Any]:
    """``get_state``: the status, no frame (``{}``) and the statistics of no marker (a node
    has no markers: the wire's ``stats`` body, empty, algorithm ``fusion``)."""
    stats: P.StatsBody = {"t": time.time(), "frame": None, "algorithm": "fusion", "window": 0,
                          "mean_error": None, "max_error": None, "markers": []}
    return {"status": status_body(node), "frame": {}, "stats": stats}
