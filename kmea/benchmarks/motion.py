"""Robots in motion: poses at 0.5-1.5 m/s under the IMX219's rolling shutter, on the
held-out motion scenes (kmea/experiments/motion.py), truth at each pose's own time.

    kmea bench motion --jobs 2            # the table
    kmea bench motion --split tuning --sweep-only --exposures 1,2,3,4 --widths 1640
                                          # what chose it
    kmea bench motion --sensor imx219,imx708,imx296 --sweep-only --exposures 2 --jobs 2
                                          # each camera module at its recommended mode

Columns (each over robot-frames after the first WARMUP frames of a run): posed = frames in
which a visible robot got a valid pose; "meas" = the robot measurement (the pose the
markers give, before the tracking filter), "filter" = the tracking filter's output (what
the datagram carries; "settled": from the 7th frame on after a robot enters the view,
where its new track learns the velocity); both stamped with the pose's own time (its
markers' mid-exposure) and compared with the truth then; "no time" = the same measurement
stamped with the frame's timestamp (the sensor timestamp: row 0 read out), as without
exposure timing. Heading "turning":
robot-frames on the half circles (3 rad/s). Last column: the one-marker robot's measured
heading with and without the correction of its square's rolling-shutter skew.
"""

from __future__ import annotations

import argparse
import math
import sys
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from kmea.camera_advice import RECOMMENDED
from kmea.experiments.motion import EXPOSURES_MS, HELDOUT_SEEDS, SPEEDS, TUNING_SEEDS, MotionCase
from kmea.experiments.motion_eval import CaseResult, evaluate_case, rms

#: The exposure kmead asks of the Pi camera by default (camera.max_exposure_ms), ms:
#: chosen on the tuning seeds (docs/motion.md).
DEFAULT_EXPOSURE_MS = 2.0


def _run(args: tuple[MotionCase, int]) -> CaseResult:
    return evaluate_case(*args)


def _fmt(v: float, k: float = 1e3, nd: int = 2) -> str:
    return "-" if not math.isfinite(v) else f"{v * k:.{nd}f}"


def row(label: str, rs: list[CaseResult]) -> str:
    def cat(variant: str, key: str) -> list[float]:
        return [x for r in rs for x in getattr(getattr(r, variant), key)]

    vis = sum(r.timed.visible for r in rs)
    posed = sum(r.timed.posed for r in rs)
    turning = np.array(cat("timed", "turning"), dtype=bool)
    raw_head = np.array(cat("timed", "raw_head"))
    filt_head = np.array(cat("timed", "head"))
    settled = np.array(cat("timed", "settled"), dtype=bool)
    filt_pos = np.array(cat("timed", "pos"))
    deg = math.degrees(1.0)
    return (f"| {label} | {posed}/{vis} ({100.0 * posed / max(vis, 1):.1f} %) "
            f"| {_fmt(rms(cat('timed', 'raw_pos')))} | {_fmt(rms(cat('frame', 'raw_pos')))} "
            f"| {_fmt(rms(filt_pos))} / {_fmt(rms(filt_pos[settled]))} "
            f"| {_fmt(rms(raw_head), deg)} "
            f"| {_fmt(rms(raw_head[turning]) if turning.any() else math.nan, deg)} "
            f"| {_fmt(rms(filt_head), deg)} / {_fmt(rms(filt_head[settled]), deg)} "
            f"| {_fmt(rms(cat('timed', 'single_head')), deg)} / "
            f"{_fmt(rms(cat('noskew', 'single_head')), deg)} |")


HEADER = ("| case | posed / visible | meas. pos RMSE mm | no time: pos RMSE mm "
          "| filter pos RMSE mm: all / settled | meas. heading RMSE deg | turning (3 rad/s) deg "
          "| filter heading deg: all / settled | one marker: heading deg, skew corrected / not "
          "|\n|---|---|---|---|---|---|---|---|---|")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="kmea bench motion",
                                 description=(__doc__ or "").split("\n\n")[0])
    ap.add_argument("--split", choices=("heldout", "tuning"), default="heldout")
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--seeds", type=int, default=1, help="seeds per case")
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--widths", default=None,
                    help="image widths, px (default: 1640,820 for the imx219, each other "
                         "sensor's recommended width)")
    ap.add_argument("--sensor", default="imx219",
                    help="camera modules, comma-separated: " + ", ".join(RECOMMENDED)
                         + " (the shutter and aspect ratio of each; default imx219)")
    ap.add_argument("--exposures", default=",".join(f"{e:g}" for e in EXPOSURES_MS),
                    help="the sweep at 1.5 m/s, ms")
    ap.add_argument("--default-ms", type=float, default=DEFAULT_EXPOSURE_MS)
    ap.add_argument("--sweep-only", action="store_true")
    a = ap.parse_args(argv)
    seeds = (HELDOUT_SEEDS if a.split == "heldout" else TUNING_SEEDS)[:a.seeds]
    sensors = [x.strip().lower() for x in a.sensor.split(",") if x.strip()]
    bad = [x for x in sensors if x not in RECOMMENDED]
    if bad:
        ap.error(f"--sensor {','.join(bad)}: one of {', '.join(RECOMMENDED)}")
    exposures = [float(e) for e in a.exposures.split(",")]
    groups: dict[str, list[MotionCase]] = {}
    for sensor in sensors:
        widths = ([int(w) for w in a.widths.split(",")] if a.widths else
                  [1640, 820] if sensor == "imx219" else [RECOMMENDED[sensor][0]])
        who = "" if sensors == ["imx219"] else f"{sensor} "
        for w in widths:
            h = MotionCase(1.5, width=w, sensor=sensor).height
            if not a.sweep_only:
                for v in SPEEDS[::-1]:
                    groups[f"{who}{w}x{h}, {v:g} m/s, {a.default_ms:g} ms (default)"] = [
                        MotionCase(v, exposure_ms=a.default_ms, width=w, seed=s,
                                   sensor=sensor) for s in seeds]
            for e in exposures:
                if e == a.default_ms and not a.sweep_only:
                    continue
                groups[f"{who}{w}x{h}, 1.5 m/s, {e:g} ms"] = [
                    MotionCase(1.5, exposure_ms=e, width=w, seed=s, sensor=sensor)
                    for s in seeds]
    jobs = [(c, a.frames) for cs in groups.values() for c in cs]
    print(f"{a.split} seeds {list(seeds)}, {a.frames} frames a case at 30 frames/s, "
          f"{len(jobs)} runs", flush=True)
    results = []
    with ProcessPoolExecutor(max(1, a.jobs)) as ex:
        for r in ex.map(_run, jobs):
            print(f"  {r.case.label}: {r.timed.posed}/{r.timed.visible} posed, meas. pos "
                  f"RMSE {_fmt(rms(r.timed.raw_pos))} mm ({r.seconds:.0f} s)", flush=True)
            results.append(r)
    by = dict(zip([j[0] for j in jobs], results, strict=True))
    print(HEADER)
    for label, cs in groups.items():
        print(row(label, [by[c] for c in cs]))
    print(f"({sum(r.seconds for r in results):.0f} s of rendering and processing)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
