"""``kmea export mcap RECORDING [--csv FILE] --out FILE.mcap``: a recording as MCAP.

The MCAP file holds Foxglove schemas (protobuf) on the channels of
:mod:`kmead.viewers.foxglove`: the floor and map once, then per recorded frame the camera
calibration and the detected marker outlines (``/camera/annotations``; a recording holds no
images) and, when the CSV log of the same run is given, the estimated markers
(``/floor/markers``), the robots (``/floor/robots``, ``/robots/poses``) and their
transforms (``/tf``). Message log times are the recording's frame times.
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from kmea.vision.overlay import OverlayMarker

EXIT_ERROR = 2


class ExportError(ValueError):
    """A file that cannot be exported; the message names it (and the line)."""


@dataclass
class CsvFrame:
    markers: dict[int, tuple[np.ndarray, float, str]]  # id -> (position, yaw, kind)
    robots: dict[str, tuple[float, float, float]]  # name -> (x, y, theta)


def read_estimates(path: str | Path) -> dict[int, CsvFrame]:
    """The estimates of a kmead CSV log by frame (see :mod:`kmead.outputs.csvlog`)."""
    from kmead.outputs.csvlog import COLUMNS

    path = Path(path)
    out: dict[int, CsvFrame] = defaultdict(lambda: CsvFrame({}, {}))
    try:
        f = open(path, encoding="utf-8", newline="")  # noqa: SIM115 - closed below
    except OSError as e:
        raise ExportError(f"{path}: cannot read: {e.strerror or e}") from None
    with f:
        reader = csv.reader(f)
        try:
            head = next(reader, None)
        except (csv.Error, UnicodeDecodeError) as e:
            raise ExportError(f"{path}: line 1: not a kmead CSV log: {e}") from None
        if head != COLUMNS:
            raise ExportError(f"{path}: line 1: not a kmead CSV log (header must be "
                              f"{','.join(COLUMNS)})")
        line = 1
        try:
            for row in reader:
                line = reader.line_num
                if not row:
                    continue
                d = dict(zip(COLUMNS, row, strict=True))
                fr = out[int(d["frame"])]
                kind = d["kind"]
                if kind == "robot":
                    if d["x"] and d["y"] and d["yaw"]:
                        fr.robots[d["id"]] = (float(d["x"]), float(d["y"]), float(d["yaw"]))
                elif kind in ("marker", "rejected"):
                    if d["x"] and d["y"]:
                        p = np.array([float(d["x"]), float(d["y"]), float(d["z"] or 0.0)])
                        mid = int(d["id"])
                        yaw = float(d["yaw"]) if d["yaw"] else 0.0
                        if kind == "rejected" or mid not in fr.markers:
                            fr.markers[mid] = (p, yaw, "rejected" if kind == "rejected"
                                               else "detected")
                else:
                    raise ValueError(f"unknown kind {kind!r}")
        except (ValueError, csv.Error, UnicodeDecodeError) as e:
            raise ExportError(f"{path}: line {line}: bad row: {e}") from None
    return dict(out)


@dataclass
class ExportSummary:
    frames: int
    messages: dict[str, int]
    truncated: bool
    bad_lines: int


def export_mcap(recording: str | Path, out: str | Path, csv_path: str | Path | None = None,
                overwrite: bool = False) -> ExportSummary:
    """Write ``out`` from ``recording`` (and its CSV log); ``ExportError`` naming the file."""
    import foxglove

    from kmea.sources.base import SourceError
    from kmea.sources.replay import ReplaySource
    from kmead.viewers.foxglove import FoxgloveLog, FrameView, MarkerView, RobotView

    estimates = read_estimates(csv_path) if csv_path else {}
    try:
        src = ReplaySource(recording)
    except SourceError as e:
        raise ExportError(str(e)) from None
    out = Path(out)
    if out.exists() and not overwrite:
        src.close()
        raise ExportError(f"{out}: exists (use --force to overwrite)")
    ctx = foxglove.Context()
    try:
        writer = foxglove.open_mcap(str(out), allow_overwrite=True, context=ctx)
    except Exception as e:  # the SDK raises its own error types for an unwritable path
        src.close()
        raise ExportError(f"{out}: cannot write: {e}") from None
    flog = FoxgloveLog(ctx, src.world_map, src.camera)
    frames = bad = 0
    first = True
    try:
        while (fr := src.read()) is not None:
            rep = fr.meta.get("replay")
            if rep is None:
                bad += 1
                continue
            _ids, _corners, obs, _diag = rep
            t = fr.timestamp if math.isfinite(fr.timestamp) else 0.0
            ns = round(t * 1e9)
            if first:
                flog.log_map(t, log_time=ns)
                first = False
            outlines = [OverlayMarker(o.id, o.corners, "suspect" if o.suspect else "detected")
                        for o in obs if o.corners is not None]
            est = estimates.get(fr.index)
            markers = [MarkerView(mid, p, yaw, kind)
                       for mid, (p, yaw, kind) in sorted(est.markers.items())] if est else []
            robots = [RobotView(n, x, y, th) for n, (x, y, th) in sorted(est.robots.items())] \
                if est else []
            flog.log_frame(FrameView(t, fr.index, None, outlines, markers, robots),
                           log_time=ns)
            frames += 1
    finally:
        truncated = src.truncated
        src.close()
        writer.close()
        flog.close()
    return ExportSummary(frames, dict(flog.counts), truncated, bad)


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="format", required=True, metavar="FORMAT")
    m = sub.add_parser("mcap", help="MCAP with Foxglove schemas (needs the foxglove extra)",
                       description="Turn a kmead recording (--record) into an MCAP file "
                                   "for Foxglove: map, detections, and with --csv the "
                                   "estimated markers and robots.")
    m.add_argument("recording", metavar="RECORDING",
                   help="kmead recording (run.jsonl, or run.jsonl.zst compressed)")
    m.add_argument("--csv", metavar="FILE", help="the CSV log (--log) of the same run")
    m.add_argument("--out", metavar="FILE.mcap", required=True, help="output file")
    m.add_argument("--force", action="store_true", help="overwrite FILE.mcap")


def run(args: argparse.Namespace) -> int:
    try:
        import foxglove  # noqa: F401
    except ImportError:
        print("kmea export mcap: needs the foxglove extra: pip install 'kmea[foxglove]'",
              file=sys.stderr)
        return EXIT_ERROR
    try:
        s = export_mcap(args.recording, args.out, args.csv, overwrite=args.force)
    except ExportError as e:
        print(f"kmea export mcap: {e}", file=sys.stderr)
        return EXIT_ERROR
    total = sum(s.messages.values())
    print(f"wrote {args.out}: {s.frames} frames, {total} messages on {len(s.messages)} "
          f"channels ({', '.join(sorted(s.messages))})")
    if s.truncated:
        print(f"kmea export mcap: warning: {args.recording} ends with a partial line or "
              "without its end (a recording cut by a kill); exported the whole frames",
              file=sys.stderr)
    if s.bad_lines:
        print(f"kmea export mcap: warning: {s.bad_lines} unreadable frame lines skipped",
              file=sys.stderr)
    return 0
