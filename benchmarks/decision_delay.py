"""The tracking filter if robots could take more delay: each frame's output sent L frames
late, from the track after frame k + L (retrodicted to frame k's time through the motion
model; not a smoother: the backward prediction widens the covariance).

Issue 16's remaining outlier-caused jumps are outliers that land on the filter's
prediction; the look-back and recovery identify some of them one or two frames later, after
the output for their frame was sent. This measures what waiting for those frames buys on
the held-out sets A-N (never tuned on), with the shipped filter: outlier-caused jumps > 3
sigma (:func:`kmea.benchmarks.tracking.outlier_effect`), position RMSE with the outliers and
NEES (2 when the reported sigma is honest). The outputs refer to frame k's time, so their
lag against the truth is 0; the delay is L frames of delivery. Prints figures; no asserts.

    .venv/bin/python benchmarks/decision_delay.py [--frames 0,1,2] [--jobs 2] [--sets A,C]
"""

from __future__ import annotations

import argparse
import multiprocessing

import numpy as np

from kmea.benchmarks.tracking import (
    HELD_OUT,
    TUNED,
    Measurements,
    MotionSet,
    aggregate,
    make_measurements,
    metrics,
    trajectory,
)
from kmea.tracking import Tracker


def run_delayed(ms: Measurements, delay: int) -> tuple[np.ndarray, dict]:
    """Outputs (M, 3) at the measurement times, each from the track after the measurement
    ``delay`` frames later, and the info :func:`metrics` reads."""
    trk = Tracker(TUNED, keep=len(ms.t) + 1)
    n = len(ms.t)
    out, sig, cov = np.zeros_like(ms.z), np.zeros(n), np.zeros((n, 2, 2))
    rejected, reacquired = np.zeros(n, bool), []
    for k in range(n + delay):
        if k < n:
            o = trk.update("r", float(ms.t[k]), *ms.z[k], float(ms.sigma[k]))
            rejected[k] = o.kind == "rejected"
            for r in o.retracted_all:
                rejected[int(np.searchsorted(ms.t, r[0]))] = True
            if o.kind == "reacquired":
                reacquired.append(float(ms.t[k]))
        j = k - delay
        if j >= 0:
            st = trk.predict("r", float(ms.t[j]))
            out[j], sig[j], cov[j] = (st.x, st.y, st.theta), st.sigma, st.cov[:2, :2]
    return out, {"rejected": rejected, "reported": rejected, "reacquired": reacquired,
                 "sigma": sig, "cov": cov}


def _set(args: tuple[MotionSet, int]) -> tuple[str, int, dict]:
    mset, delay = args
    rows = []
    for seed in mset.seeds:
        tr = trajectory(seed, mset.duration, mset.max_speed, mset.max_turn, mset.max_accel,
                        mset.stops)
        ms = make_measurements(tr, seed, mset.fps, mset.sigma, 0.05, burst=mset.burst,
                               manoeuvre_outliers=mset.manoeuvre_outliers,
                               stop_outliers=mset.stop_outliers)
        out, info = run_delayed(ms, delay)
        clean, _ = run_delayed(make_measurements(tr, seed, mset.fps, mset.sigma, 0.0), delay)
        rows.append(metrics(tr, ms, out, info, clean))
    return mset.name, delay, aggregate(rows)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", default="0,1,2", help="delays in frames (default 0,1,2)")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--sets", default="", help="held-out set letters (default all)")
    a = ap.parse_args(argv)
    delays = [int(v) for v in a.frames.split(",")]
    sets = [s for s in HELD_OUT if not a.sets or s.name[-1] in a.sets.split(",")]
    with multiprocessing.get_context("spawn").Pool(a.jobs) as pool:
        res = pool.map(_set, [(s, d) for d in delays for s in sets])
    print(f"{'delay':>5} {'set':<12} {'caused>3s':>11} {'max s':>6} {'pos mm':>7} "
          f"{'lag ms':>6} {'NEES':>5}")
    for d in delays:
        tot = [0, 0]
        for name, dd, g in res:
            if dd != d:
                continue
            tot[0] += g["caused_big"]
            tot[1] += g["outliers"]
            print(f"{d:5d} {name:<12} {g['caused_big']:5d}/{g['outliers']:<5d} "
                  f"{g['caused_max_sig']:6.1f} {g['pos'] * 1000:7.2f} "
                  f"{round(g['lag'] * 1000):6d} {g['nees_sum'] / g['n']:5.2f}")
        print(f"{d:5d} {'all':<12} {tot[0]:5d}/{tot[1]:<5d}")
    print("delay: frames between a measurement and the output for its time; caused: outliers "
          "whose output (with outliers minus without, outlier frame and 3 after) exceeds 3 of "
          "the reported sigma; pos: RMSE with the outliers; NEES: 2 when the sigma is honest")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
