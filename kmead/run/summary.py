"""The short summary printed when the daemon stops."""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np

from kmea.maps.files import MarkerMap


class Daemon(Protocol):
    """What the summary reads of the daemon (``kmead.run.daemon.Daemon``; declared here so
    this module does not import the daemon, which calls it)."""

    @property
    def totals(self) -> Any: ...  # kmead.outputs.totals.RunTotals
    @property
    def world_map(self) -> MarkerMap: ...
    @property
    def source_spec(self) -> str: ...
    @property
    def pipeline(self) -> Any: ...
    @property
    def dropped(self) -> int: ...
    @property
    def cfg(self) -> Any: ...
    @property
    def csv(self) -> Any: ...


def format_summary(d: Daemon) -> str:
    """Frames, markers seen, robots tracked, LOO error statistics, frames/s, drops, files."""
    t = d.totals
    wall = max(t.t_end - t.t_start, 1e-9) if t.t_end else 0.0
    fps = t.frames / wall if wall else 0.0
    in_map = sorted(i for i in t.markers_seen if i in d.world_map)
    robot_ids = {i for r in d.cfg["robots"]
                 for i in (r["markers"] if isinstance(r["markers"], list) else [r["markers"]])}
    on_robots = sorted(i for i in t.markers_seen if i not in d.world_map and i in robot_ids)
    other = sorted(i for i in t.markers_seen if i not in d.world_map and i not in robot_ids)
    lines = [
        f"kmead summary: {t.frames} frames in {wall:.1f} s ({fps:.1f} frames/s), "
        f"source {d.source_spec}, algorithm {d.pipeline.algorithm}",
        f"  dropped frames: {d.dropped}, bad frames: {t.bad_frames}, "
        f"not estimated: {t.not_estimated}",
    ]
    why = []
    if d.dropped:
        why.append(f"{d.dropped} dropped: the pipeline was slower than the source, so the "
                   "newest frame was taken and older ones skipped (see frames/s)")
    if t.bad_frames:
        why.append(f"{t.bad_frames} bad: frames that could not be read or processed "
                   "(the log says which)")
    if t.not_estimated:
        why.append(f"{t.not_estimated} not estimated: too few usable map markers in view "
                   "(the frame telemetry's 'reason' says which)")
    lines += [f"    ({w})" for w in why]
    lines += [
        f"  markers seen: {len(t.markers_seen)} ({len(in_map)} in the map of {len(d.world_map)}"
        + (f", {len(on_robots)} on robots: {' '.join(map(str, on_robots))}" if on_robots else "")
        + (f", {len(other)} unknown: {' '.join(map(str, other))}" if other else "") + ")",
        f"  robots tracked: {len(t.robots_seen)} of {len(d.cfg['robots'])}"
        f"{': ' + ', '.join(sorted(t.robots_seen)) if t.robots_seen else ''}",
    ]
    for r in d.cfg["robots"]:
        if r["name"] in t.robots_seen:
            continue
        ids = r["markers"] if isinstance(r["markers"], list) else [r["markers"]]
        seen = [i for i in ids if i in t.markers_seen]
        missing = [i for i in ids if i not in t.markers_seen]
        reason = (f"marker {', '.join(map(str, missing))} never detected" if missing
                  else "its markers were seen but never together as a pair in one frame"
                  if len(ids) == 2 else "no pose (its marker was only seen as suspect)")
        if seen and missing:
            reason += f" (seen: {', '.join(map(str, seen))})"
        lines.append(f"    {r['name']} not tracked: {reason}")
    if t.loo_n:
        lines.append(f"  leave-one-out error: mean {t.loo_sum / t.loo_n * 1e3:.3f} mm, "
                     f"max {t.loo_max * 1e3:.3f} mm over {t.loo_n} marker estimates")
    else:
        lines.append("  leave-one-out error: none computed")
    if t.latency_ms:
        lat = np.asarray(t.latency_ms)
        lines.append(f"  capture-to-relay latency: median {np.median(lat):.1f} ms, "
                     f"p99 {np.percentile(lat, 99):.1f} ms")
    rows = t.csv_rows + (d.csv.rows if d.csv is not None else 0)
    if t.csv_paths:
        lines.append(f"  CSV log: {', '.join(t.csv_paths)} ({rows} rows)")
    if t.record_paths:
        lines.append(f"  recording: {', '.join(t.record_paths)}")
    overlay = overlay_files(d.cfg.files)
    if overlay:
        lines.append(f"  configuration overlay in effect: {', '.join(overlay)} (saved "
                     "settings; delete it to undo)")
    return "\n".join(lines)


def overlay_files(files: list[str]) -> list[str]:
    """The overlays among the configuration files read (``*.local.toml``: what a Save
    wrote, loaded by every later start)."""
    return [f for f in files if str(f).endswith(".local.toml")]
