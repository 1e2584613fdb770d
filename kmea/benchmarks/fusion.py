"""``kmea bench fusion``: two cameras, one picture, on the simulated wide scene.

Both cameras of ``sim:wide`` (two RobotAtFactory floors side by side, a 0.41 m overlap
strip) render the same instants; each frame goes through what a camera's daemon runs
(detection, marker poses, the estimator, the robot poses with their sigmas). The robots
drive across the overlap. Each camera's measurement reaches the fusion after a simulated
network and processing delay (40-60 ms, jittered, so the two cameras arrive out of order),
and :class:`kmea.robots.fusion.Fusion` applies them in arrival order.

Figures against the ground truth, per robot and over both:
- RMSE in the overlap (instants where both cameras measured the robot): each camera alone
  (raw, and through its own tracking filter), the two averaged by their sigmas, and fused.
- The largest position jump at a hand-over: the change of the output error between
  consecutive frames within 0.5 s of a change of the set of cameras seeing the robot;
  for the fused output and for a naive merge that relays every measurement as it comes.
- A camera stopped mid-run: camera 1 stops for a third of the run; the robots it alone saw
  go stale (no accepted measurement for 0.5 s), the others are unaffected; when it returns
  its robots are picked up again.
- What a clock offset does: camera 1's timestamps shifted by 30 and 100 ms.
"""

from __future__ import annotations

import itertools
import math
import time
from dataclasses import dataclass

import numpy as np

from kmea.robots.fusion import Fusion, Measurement
from kmea.robots.tracking import Track, TrackerConfig

__all__ = ["WideRun", "record", "run"]

STALE_AFTER_S = 0.5


@dataclass
class WideRun:
    """Per camera, per frame: t (s), truth name -> (x, y, theta), and measurements
    name -> (x, y, theta, sigma) for each camera."""

    t: np.ndarray
    truth: list[dict[str, tuple[float, float, float]]]
    meas: list[list[dict[str, tuple[float, float, float, float | None]]]]  # [camera][frame]


def record(frames: int, fps: float = 15.0, width: int = 820, speed: float = 0.4,
           algorithm: str = "kmea") -> WideRun:
    """Render and measure ``frames`` instants of both wide-scene cameras."""
    from kmea.pipeline import FrameInput, Pipeline, PipelineSettings
    from kmea.sim.renderer import Renderer
    from kmea.sim.scenes import get_scene

    ts = np.arange(frames) / fps
    truth: list[dict] = []
    meas: list[list[dict]] = [[], []]
    for cam in (0, 1):
        scene = get_scene("wide", camera=cam, width=width, fps=fps, speed=speed)
        rend = Renderer(scene)
        # What a camera's daemon computes (no leave-one-out; robots unfiltered: the raw
        # measurements with their sigmas, as a daemon sends them to a fusion node).
        pipe = Pipeline(scene.camera, scene.effective_map(), PipelineSettings(
            algorithm=algorithm, loo=False, robots=tuple(scene.robot_specs())))
        for i in range(frames):
            fr = rend.render(i)
            if cam == 0:
                truth.append(dict(fr.truth.robots))
            res = pipe.process(FrameInput(i, fr.timestamp, fr.image))
            meas[cam].append({n: (f.x, f.y, f.theta, f.sigma) for n, f in res.robots.items()}
                             if res.ok else {})
    return WideRun(ts, truth, meas)


def _err(a: tuple, b: tuple) -> float:
    return math.hypot(a[0] - b[0], a[1] - b[1])


def _arrivals(run: WideRun, seed: int, offset: tuple[float, float] = (0.0, 0.0),
              stop: tuple[int, int] | None = None) -> list[tuple[float, int, Measurement]]:
    """(arrival time, frame, measurement) sorted by arrival; camera 1 silent in ``stop``."""
    rng = np.random.default_rng(seed)
    out = []
    for cam in (0, 1):
        for k, t in enumerate(run.t):
            if cam == 1 and stop is not None and stop[0] <= k < stop[1]:
                continue
            for name, (x, y, th, sg) in run.meas[cam][k].items():
                arrive = t + rng.uniform(0.04, 0.06)
                out.append((arrive, k, Measurement(f"cam{cam}", name, t + offset[cam], x, y,
                                                   th, sg)))
    out.sort(key=lambda a: a[0])
    return out


def fused_outputs(run: WideRun, cfg: TrackerConfig, seed: int = 0,
                  offset: tuple[float, float] = (0.0, 0.0),
                  stop: tuple[int, int] | None = None) -> dict[str, list]:
    """Per robot, per frame: the fused (x, y, theta) at the frame's time once every
    measurement of it has arrived (None when stale: no accepted measurement for 0.5 s)."""
    fu = Fusion(cfg, max_age_s=0.5)
    arr = _arrivals(run, seed, offset, stop)
    names = sorted(run.truth[0])
    out: dict[str, list[tuple[float, float, float] | None]] = {
        n: [None] * len(run.t) for n in names}
    last_ok = dict.fromkeys(names, -math.inf)
    j = 0
    for k, t in enumerate(run.t):
        horizon = t + 0.06  # every measurement of frame k has arrived
        while j < len(arr) and arr[j][0] <= horizon:
            o = fu.add(arr[j][2])
            if o is not None and o.accepted:
                n = arr[j][2].name
                last_ok[n] = max(last_ok[n], arr[j][2].t)
            j += 1
        for n in names:
            st = fu.pose(n, t)
            if st is not None and t - last_ok[n] < STALE_AFTER_S:
                out[n][k] = (st.x, st.y, st.theta)
    return out


def _single(run: WideRun, cam: int, name: str, cfg: TrackerConfig) -> list:
    tr = Track(name, cfg)
    out = []
    for k, t in enumerate(run.t):
        m = run.meas[cam][k].get(name)
        if m is not None:
            tr.update(t, m[0], m[1], m[2], m[3])
            st = tr.state()
            if st is None:  # cannot happen: the track has just had a measurement
                raise RuntimeError(f"{name}: no track state after an update")
            out.append((st.x, st.y, st.theta))
        else:
            out.append(None)
    return out


def _rmse(errs: list[float]) -> float:
    return math.sqrt(sum(e * e for e in errs) / len(errs)) if errs else math.nan


def overlap_table(run: WideRun, cfg: TrackerConfig) -> list[tuple[str, float, float, int]]:
    """(label, RMSE mm, max error mm, n) in the overlap (both cameras measured the robot)."""
    fused = fused_outputs(run, cfg)
    rows: dict[str, list[float]] = {k: [] for k in (
        "camera 0 alone, raw", "camera 1 alone, raw", "camera 0 alone, tracking filter",
        "camera 1 alone, tracking filter", "both, averaged by sigma", "both, fused")}
    for name in sorted(run.truth[0]):
        s0, s1 = _single(run, 0, name, cfg), _single(run, 1, name, cfg)
        for k in range(len(run.t)):
            m0, m1 = run.meas[0][k].get(name), run.meas[1][k].get(name)
            if m0 is None or m1 is None or run.t[k] < 1.0:
                continue
            g = run.truth[k][name]
            rows["camera 0 alone, raw"].append(_err(m0, g))
            rows["camera 1 alone, raw"].append(_err(m1, g))
            rows["camera 0 alone, tracking filter"].append(_err(s0[k], g))
            rows["camera 1 alone, tracking filter"].append(_err(s1[k], g))
            w0 = 1.0 / max(m0[3] or 0.005, 0.001) ** 2
            w1 = 1.0 / max(m1[3] or 0.005, 0.001) ** 2
            avg = ((w0 * m0[0] + w1 * m1[0]) / (w0 + w1), (w0 * m0[1] + w1 * m1[1]) / (w0 + w1))
            rows["both, averaged by sigma"].append(_err(avg, g))
            if fused[name][k] is not None:
                rows["both, fused"].append(_err(fused[name][k], g))
    return [(k, _rmse(v) * 1000, max(v, default=math.nan) * 1000, len(v))
            for k, v in rows.items()]


def handover_jumps(run: WideRun, cfg: TrackerConfig) -> dict[str, tuple[float, int]]:
    """Largest change of the output error (mm) between consecutive frames within 0.5 s of
    a hand-over, fused and naive (the latest measurement, whichever camera); and the count
    of hand-overs."""
    fused = fused_outputs(run, cfg)
    fps = 1.0 / (run.t[1] - run.t[0])
    win = round(0.5 * fps)
    res = {"fused": 0.0, "naive": 0.0}
    count = 0
    for name in sorted(run.truth[0]):
        seen = [(name in run.meas[0][k], name in run.meas[1][k]) for k in range(len(run.t))]
        changes = [k for k in range(1, len(run.t)) if seen[k] != seen[k - 1]
                   and run.t[k] >= 1.0 and (any(seen[k]) and any(seen[k - 1]))]
        count += len(changes)
        # Naive: every measurement relayed as it comes; camera 1's arrives after camera 0's.
        naive: list[tuple[int, tuple]] = []  # (frame, measurement)
        for k in range(len(run.t)):
            for cam in (0, 1):
                m = run.meas[cam][k].get(name)
                if m is not None:
                    naive.append((k, m))
        for c in changes:
            lo, hi = c - win, c + win
            for series in ("fused", "naive"):
                if series == "fused":
                    pts = [(k, fused[name][k]) for k in range(max(lo, 0), min(hi, len(run.t)))
                           if fused[name][k] is not None]
                else:
                    pts = [(k, m) for k, m in naive if lo <= k < hi]
                for (ka, a), (kb, b) in itertools.pairwise(pts):
                    ga, gb = run.truth[ka][name], run.truth[kb][name]
                    step = math.hypot((a[0] - ga[0]) - (b[0] - gb[0]),
                                      (a[1] - ga[1]) - (b[1] - gb[1]))
                    res[series] = max(res[series], step)
    return {k: (v * 1000, count) for k, v in res.items()}


def stop_report(run: WideRun, cfg: TrackerConfig) -> list[str]:
    """Camera 1 silent for the middle third: per robot, what the fused output did."""
    n = len(run.t)
    stop = (n // 3, 2 * n // 3)
    fused = fused_outputs(run, cfg, stop=stop)
    lines = [f"camera 1 stopped at t = {run.t[stop[0]]:.1f} s, back at t = "
             f"{run.t[stop[1]]:.1f} s (stale after {STALE_AFTER_S:g} s without a measurement)"]
    for name in sorted(run.truth[0]):
        during = range(stop[0], stop[1])
        only1 = [k for k in during if name in run.meas[1][k] and name not in run.meas[0][k]]
        by0 = [k for k in during if name in run.meas[0][k]]
        valid_by0 = sum(fused[name][k] is not None for k in by0)
        stale_only1 = sum(fused[name][k] is None for k in only1)
        errs = [_err(fused[name][k], run.truth[k][name]) for k in during
                if fused[name][k] is not None]
        back = [k for k in range(stop[1], n) if name in run.meas[1][k]]
        pick = next((k for k in back if fused[name][k] is not None), None)
        lines.append(
            f"  {name}: frames seen by camera 0: {len(by0)}, valid {valid_by0}; frames seen "
            f"only by camera 1: {len(only1)}, stale {stale_only1}; RMSE of the valid outputs "
            f"{_rmse(errs) * 1000:.1f} mm; after the return: "
            + ("not seen by camera 1" if not back else
               f"valid again {1000 * (run.t[pick] - run.t[back[0]]):.0f} ms after camera 1's "
               "first measurement" if pick is not None else "never valid again"))
    return lines


def offset_table(run: WideRun, cfg: TrackerConfig) -> list[tuple[float, float, float, int]]:
    """(camera 1 clock offset s, fused RMSE mm in the overlap, elsewhere, rejected)."""
    rows = []
    for off in (0.0, 0.03, 0.1):
        fused = fused_outputs(run, cfg, offset=(0.0, off))
        ov, el = [], []
        for name in sorted(run.truth[0]):
            for k in range(len(run.t)):
                if fused[name][k] is None or run.t[k] < 1.0:
                    continue
                both = name in run.meas[0][k] and name in run.meas[1][k]
                (ov if both else el).append(_err(fused[name][k], run.truth[k][name]))
        fu = Fusion(cfg)
        for _, _, m in _arrivals(run, 0, (0.0, off)):
            fu.add(m)
        rows.append((off, _rmse(ov) * 1000, _rmse(el) * 1000, fu.tracker.counts["rejected"]))
    return rows


def run(quick: bool = False) -> None:
    from kmea.benchmarks.tracking import TUNED

    t0 = time.perf_counter()
    frames = 150 if quick else 450
    fps = 15.0
    wr = record(frames, fps)
    cfg = TUNED
    print(f"wide scene, both cameras at 820x616, {fps:g} fps, {frames} frames "
          f"({frames / fps:.0f} s), robots at 0.4 m/s, estimator kmea; tracking filter "
          f"{cfg.model} (accel {cfg.accel_noise:g}, turn {cfg.turn_noise:g}); measurement "
          f"delays 40-60 ms ({time.perf_counter() - t0:.0f} s to render and measure)")
    print("RMSE in the overlap (both cameras measured the robot):")
    print(f"  {'':<34} {'RMSE mm':>8} {'max mm':>8} {'n':>5}")
    for label, r, mx, n in overlap_table(wr, cfg):
        print(f"  {label:<34} {r:8.2f} {mx:8.2f} {n:5d}")
    hj = handover_jumps(wr, cfg)
    print(f"largest position jump at a hand-over ({hj['fused'][1]} hand-overs): fused "
          f"{hj['fused'][0]:.1f} mm, naive relay of every measurement {hj['naive'][0]:.1f} mm")
    for line in stop_report(wr, cfg):
        print(line)
    print("camera 1's clock offset: fused RMSE in the overlap / elsewhere, rejected:")
    for off, ov, el, rej in offset_table(wr, cfg):
        print(f"  +{off * 1000:3.0f} ms: {ov:6.2f} mm / {el:6.2f} mm, {rej} rejected")
    print(f"({time.perf_counter() - t0:.0f} s)")
