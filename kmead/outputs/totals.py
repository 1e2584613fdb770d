"""What the daemon keeps and writes per frame, besides telemetry: whole-run totals, CSV rows,
the recording's truth record."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from kmea.maps.files import MarkerMap
from kmea.pipeline import FrameResult
from kmea.wire.jsonsafe import to_jsonable
from kmead.outputs.csvlog import row


@dataclass
class RunTotals:
    """Whole-run figures for the summary (times: ``time.perf_counter()`` s, latency ms)."""

    frames: int = 0
    bad_frames: int = 0
    not_estimated: int = 0
    markers_seen: set[int] = field(default_factory=set)
    robots_seen: set[str] = field(default_factory=set)
    loo_sum: float = 0.0
    loo_n: int = 0
    loo_max: float = 0.0
    t_start: float = 0.0
    t_end: float = 0.0
    csv_rows: int = 0
    csv_paths: list[str] = field(default_factory=list)
    record_paths: list[str] = field(default_factory=list)
    latency_ms: list[float] = field(default_factory=list)
    timing_sums: dict[str, float] = field(default_factory=dict)

    def add_frame(self, res: FrameResult) -> None:
        """Count one processed frame: markers seen, estimate failures, LOO errors (m)."""
        self.frames += 1
        self.markers_seen.update(int(i) for i in res.ids)
        if not res.estimate.ok:
            self.not_estimated += 1
        for e in res.loo.values():
            self.loo_sum += e
            self.loo_n += 1
            self.loo_max = max(self.loo_max, e)


def csv_lines(res: FrameResult, world_map: MarkerMap,
              robot_heights: dict[str, float]) -> list[str]:
    """The CSV rows of one frame (:mod:`kmead.outputs.csvlog`): markers with their LOO error (map
    markers only), robots at their plate height, then the markers a robust estimator
    rejected with the distance (m) it rejected them at."""
    est = res.estimate
    nref = len(est.references)
    alg, i, t = res.algorithm, res.index, res.timestamp
    lines = []
    for mid, (p, yaw) in res.markers.items():
        err = res.loo.get(mid) if mid in world_map else None
        lines.append(row(i, t, alg, "marker", mid, p[0], p[1], p[2], yaw, err, nref))
    for name, fix in res.robots.items():
        z = robot_heights.get(name)
        tr = t if fix.t is None else fix.t  # the pose's own instant (its markers' rows)
        lines.append(row(i, tr, alg, "robot", name, fix.x, fix.y, z, fix.theta, None, nref))
    for mid, d in sorted(est.rejected.items()):
        me = res.markers.get(mid)
        p = me[0] if me is not None else (None, None, None)
        yaw = me[1] if me is not None else None
        lines.append(row(i, t, alg, "rejected", mid, p[0], p[1], p[2], yaw, d, nref))
    for mid, plane in sorted(est.info.get("plane_geometry", {}).items()):
        n, off = plane if plane is not None else ((None, None, None), None)
        lines.append(row(i, t, alg, "plane", mid, n[0], n[1], n[2], None, off, nref))
    return lines


def truth_record(truth: Any) -> Any:
    """The simulator's ground truth of a frame as recorded: compact (the robots' true poses
    and the camera pose; markers are static) when it is a frame truth, JSON-safe."""
    if truth is not None and hasattr(truth, "robots"):
        truth = {"t": getattr(truth, "t", None), "robots": truth.robots,
                 "cam2world": getattr(truth, "cam2world", None)}
    return to_jsonable(truth)
