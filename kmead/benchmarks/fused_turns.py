"""``kmea bench fused-turns``: the fused stream against the truth where the wide scene's loops
turn tightly (x = -0.58 m and 2.28 m, radius about 0.1 m), at the robots' speeds.

Both cameras of ``sim:wide`` render the same instants (sim time: the measurement times are
exact); each frame goes through the pipeline a camera's ``kmead`` runs (detection, poses,
the estimator, the robot poses, its own tracking filter). The fusion node's filter
(:class:`kmea.robots.fusion.Fusion`, the node's configuration) gets the cameras'
measurements after 30-60 ms each (jittered, out of order) and outputs one pose per
accepted measurement, as ``kmea fuse`` does. Per stream, against the truth at each
message's time:

- **jumps**: messages whose error changed from the previous message by more than 3 (and 10)
  times the message's own sigma (the tracking filter's rule, docs/tracking.md), per 1,000
  messages, everywhere and within 0.3 m of a turn;
- the largest such step in mm, and the RMSE.

Streams: the node fed every measurement (what cameras send), the node fed only the
measurements each camera's own filter accepted (what they sent before: the node missed the
evidence of a camera's re-acquisition after a turn and lagged behind), and each camera's own
filter.
"""

from __future__ import annotations

import argparse
import math
import time
from typing import Any

import numpy as np

__all__ = ["main"]

TURNS_X = (-0.58, 2.28)
NEAR_TURN_M = 0.3


def _record(speed: float, seconds: float, width: int, height: int, fps: float,
            sets: list[str], drop: float = 0.0) -> dict:
    """Per camera, per frame: (fixes name -> (t, x, y, sigma), measured name -> (t, x, y,
    theta, sigma), accepted name -> the same)."""
    from kmea.pipeline import FrameInput, Pipeline, PipelineSettings
    from kmea.sources.sim import SimSource
    from kmead.config.layers import load_config

    settings = PipelineSettings.from_config(load_config(None, sets).data, live=True)
    out: dict = {}
    for cam in (0, 1):
        src = SimSource(f"wide?camera={cam}&speed={speed}", width=width, height=height,
                        fps=fps)
        pipe = Pipeline(src.camera, src.world_map, settings)
        rows = []
        # A camera that cannot keep up drops frames: the pipeline never sees them.
        rng = np.random.default_rng(cam)
        for _ in range(int(seconds * fps)):
            fr = src.read()
            if fr is None:
                break
            if drop and rng.uniform() < drop:
                continue
            res = pipe.process(FrameInput(fr.index, fr.timestamp, fr.image, meta=fr.meta))
            fixes = {n: (fr.timestamp if f.t is None else f.t, f.x, f.y, f.sigma or 0.0)
                     for n, f in res.robots.items()}
            accepted = {n: (fixes[n][0], *f.raw) for n, f in res.robots.items()
                        if f.raw is not None}
            rows.append((fixes, dict(pipe.measured), accepted))
        out[cam] = rows
    return out


def _fused(rec: dict, which: int, sets: list[str], seed: int = 0) -> dict[str, list[tuple]]:
    """The node's outputs (t, x, y, sigma) per robot, fed ``rec``'s measured (1) or
    accepted (2) measurements in arrival order."""
    from kmea.robots.fusion import Fusion, Measurement
    from kmead.config.layers import load_config
    from kmead.fusion.node import tracker_config

    cfg = load_config(None, sets)
    rng = np.random.default_rng(seed)
    arr = []
    for cam in (0, 1):
        for row in rec[cam]:
            for n, (t, x, y, th, sg) in row[which].items():
                arr.append((t + rng.uniform(0.03, 0.06), Measurement(f"cam{cam}", n, t, x, y,
                                                                     th, sg)))
    arr.sort(key=lambda a: a[0])
    fu = Fusion(tracker_config(cfg), cfg["fusion"]["max_age_s"])
    outs: dict[str, list[tuple]] = {}
    for _, m in arr:
        o = fu.add(m)
        if o is None or o.kind == "rejected":
            continue
        tr = fu.tracker.tracks[m.name]
        st = tr.predict(tr.t) if tr.t is not None else None
        if st is not None:
            outs.setdefault(m.name, []).append((st.t, st.x, st.y, st.sigma))
    return outs


def _score(msgs: list[tuple], path: Any) -> dict:
    """``msgs`` (t, x, y, sigma) against ``path`` (a simulated robot's, ``pose(t)``)."""
    n = j3 = j10 = n_turn = j3_turn = 0
    worst = step = 0.0
    sq: list[float] = []
    prev = None
    for t, x, y, sigma in msgs:
        tx, ty, _ = path.pose(t)
        e = (x - tx, y - ty)
        sq.append(e[0] ** 2 + e[1] ** 2)
        near = min(abs(tx - xt) for xt in TURNS_X) < NEAR_TURN_M
        n += 1
        n_turn += near
        if prev is not None and sigma > 0:
            d = math.hypot(e[0] - prev[0], e[1] - prev[1])
            k = d / sigma
            j3 += k > 3
            j10 += k > 10
            j3_turn += near and k > 3
            worst = max(worst, k)
            step = max(step, d)
        prev = e
    return {"n": n, "j3": j3, "j10": j10, "n_turn": n_turn, "j3_turn": j3_turn,
            "worst": worst, "step": step, "rmse": math.sqrt(sum(sq) / len(sq)) if sq else 0.0}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="kmea bench fused-turns",
                                description="the fused stream at the wide scene's turns")
    p.add_argument("--speed", type=float, action="append",
                   help="robots' speed, m/s (repeatable; default 0.25 and 1.5)")
    p.add_argument("--seconds", type=float, default=60.0,
                   help="simulated time (default %(default)s s; 0 = one loop of the slower robot)")
    p.add_argument("--width", type=int, default=820)
    p.add_argument("--height", type=int, default=616)
    p.add_argument("--fps", type=float, default=30.0,
                   help="the cameras' frame rate (default 30, kmead's source.fps)")
    p.add_argument("--drop", type=float, default=0.0, metavar="P",
                   help="each camera drops each frame with probability P (seeded), as a "
                        "camera that cannot keep up does")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="a configuration key for the cameras and the node, as kmead's --set "
                        "(e.g. filter.step_k=1e9; repeatable)")
    a = p.parse_args(argv)
    from kmea.sim.scenes import get_scene

    print("| speed m/s | stream | messages | jumps > 3 sigma per 1,000 | > 10 sigma | "
          "near a turn: messages, > 3 sigma | largest sigma | largest step mm | RMSE mm |")
    print("|---|---|---|---|---|---|---|---|---|")
    for speed in a.speed or [0.25, 1.5]:
        paths: dict[str, Any] = {r.name: r.path for r in get_scene("wide",
                                                                    speed=speed).robots}
        seconds = a.seconds or max(pt.length for pt in paths.values()) / speed + 1.0
        t0 = time.perf_counter()
        rec = _record(speed, seconds, a.width, a.height, a.fps, a.set, a.drop)
        streams: list[tuple[str, dict[str, list[tuple]]]] = [
            ("node, every measurement", _fused(rec, 1, a.set)),
            ("node, accepted ones only", _fused(rec, 2, a.set))]
        for cam in (0, 1):
            own: dict[str, list[tuple]] = {}
            for fixes, _m, _a in rec[cam]:
                for n, v in fixes.items():
                    own.setdefault(n, []).append(v)
            streams.append((f"camera {cam}'s own filter", own))
        for label, outs in streams:
            tot = {"n": 0, "j3": 0, "j10": 0, "n_turn": 0, "j3_turn": 0, "worst": 0.0,
                   "step": 0.0, "sq": 0.0}
            for name, msgs in outs.items():
                s = _score(msgs, paths[name])
                for k in ("n", "j3", "j10", "n_turn", "j3_turn"):
                    tot[k] += s[k]
                tot["worst"] = max(tot["worst"], s["worst"])
                tot["step"] = max(tot["step"], s["step"])
                tot["sq"] += s["rmse"] ** 2 * s["n"]
            n = max(tot["n"], 1)
            print(f"| {speed:g} | {label} | {tot['n']} | {1000 * tot['j3'] / n:.1f} | "
                  f"{tot['j10']} | {tot['n_turn']}, {tot['j3_turn']} | {tot['worst']:.1f} | "
                  f"{tot['step'] * 1e3:.1f} | {math.sqrt(tot['sq'] / n) * 1e3:.1f} |")
        print(f"(speed {speed:g}: {seconds:.0f} s simulated, {time.perf_counter() - t0:.0f} s "
              "to render and measure)", flush=True)
    return 0
