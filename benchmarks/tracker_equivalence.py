"""The tracking filter of git revision REV against the working tree's: same outputs, cost.

Loads ``kmea/tracking.py`` of revision REV (``git show REV:kmea/tracking.py``) as a
temporary module next to the working tree's ``kmea.tracking`` and runs both, measurement by
measurement, on the same drives: every drive of the tuning sets and the held-out sets of
``kmea.benchmarks.tracking`` (measurements with their outliers, as ``update_cost`` makes
them), the "tune C-like" drives with the "cv" model, with one model (no IMM) and with
shuffled (out-of-order) measurements, and a hand-move case (a standing robot carried away,
an outlier among the measurements at its new place, a gap that resets the track). Compares
every Outcome's kind, reason and retracted measurements, the states after each measurement
(x, y, theta, sigma, sigma_theta, vx, vy, speed, omega, cov) and each drive's prediction
50 ms after its last measurement.
Prints the largest differences, the number of differing decisions, and both versions' cost
per update (the mean of :meth:`Tracker.update` over the drives, each timed in turn on the
same measurements). Prints figures; no asserts (exit status 1 when decisions differ or a
state differs by more than 1e-9).

``--pipeline``: also the pipeline pattern (issue 14): the fixed-camera pipeline
(corner-pnp, tracking detector, ``filter_kind="kalman"``) on ``render(90)`` frames, once
with each version's ``Tracker``, timing every update inside the pipeline (thread CPU time);
then the two robots' recorded measurements replayed through both versions (compared as
above; best of 5, warm).

    .venv/bin/python benchmarks/tracker_equivalence.py REV [--quick] [--pipeline]
"""

from __future__ import annotations

import importlib.util
import math
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from kmea import tracking as new_mod
from kmea.benchmarks.tracking import (
    HELD_OUT,
    TUNE_HARD,
    drive_rows,
    tuning_sets,
)

FIELDS = ("x", "y", "theta", "sigma", "sigma_theta", "vx", "vy", "speed", "omega")


def load_rev(rev: str):
    """``kmea/tracking.py`` of git revision ``rev`` as a module."""
    root = Path(__file__).resolve().parents[1]
    src = subprocess.run(["git", "show", f"{rev}:kmea/tracking.py"], cwd=root, check=True,
                         capture_output=True, text=True).stdout
    path = Path(tempfile.mkdtemp()) / "tracking_rev.py"
    path.write_text(src)
    spec = importlib.util.spec_from_file_location("tracking_rev", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules["tracking_rev"] = mod  # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


def drives(quick: bool):
    """(name, config field changes, rows (t, x, y, theta, sigma)) of every drive."""
    sets = tuning_sets() + HELD_OUT
    if quick:
        sets = tuple(replace(s, seeds=s.seeds[:1], duration=15.0) for s in sets)
    for mset in sets:
        for seed in mset.seeds:
            rows = drive_rows(mset, seed)
            yield f"{mset.name} {seed}", {}, rows
            if mset.name == TUNE_HARD[0].name:
                yield f"{mset.name} {seed} cv", {"model": "cv"}, rows
                yield f"{mset.name} {seed} one model", {"manoeuvre_scale": 1.0}, rows
                # Out of order: every 7th measurement swapped with the one before it.
                sw = list(rows)
                for k in range(7, len(sw), 7):
                    sw[k - 1], sw[k] = sw[k], sw[k - 1]
                yield f"{mset.name} {seed} out-of-order", {}, sw
    # A hand move: standing at (0, 0), carried to (0.3, 0.2) with an outlier (15 cm off)
    # among the measurements there, then a gap (reset), then standing again.
    rng = np.random.default_rng(5)
    rows, t = [], 0.0
    place = [(0.0, 0.0)] * 30 + [(0.3, 0.2)] * 2 + [(0.45, 0.2)] + [(0.3, 0.2)] * 30
    for px, py in place:
        rows.append((t, px + rng.normal(0, 0.003), py + rng.normal(0, 0.003),
                     0.4 + rng.normal(0, 0.05), 0.003))
        t += 0.05
    t += 1.5
    for _ in range(20):
        rows.append((t, 0.3 + rng.normal(0, 0.003), 0.2 + rng.normal(0, 0.003),
                     0.4 + rng.normal(0, 0.05), 0.003))
        t += 0.05
    yield "hand move", {}, rows


def state_diff(a, b) -> float:
    if a is None or b is None:
        return 0.0 if a is b else math.inf
    d = max(abs(getattr(a, f) - getattr(b, f)) for f in FIELDS)
    return max(d, float(np.max(np.abs(a.cov - b.cov))), abs(a.t - b.t))


def run(mod, changes: dict, rows) -> tuple:
    trk = mod.Tracker(mod.TrackerConfig(**changes))
    outs = []
    t0 = time.perf_counter()
    for t, x, y, th, s in rows:
        outs.append(trk.update("r", t, x, y, th, s))
    spent = time.perf_counter() - t0
    return outs, spent, trk


def _timed(base: type, spent: list, calls: list | None) -> type:
    """``base`` (a Tracker class) whose updates are timed into ``spent`` (thread CPU time,
    s) and recorded into ``calls`` (when given)."""

    class Timed(base):
        def update(self, *a, **k):
            if calls is not None:
                calls.append((a, k))
            t0 = time.thread_time()
            out = super().update(*a, **k)
            spent.append(time.thread_time() - t0)
            return out

    return Timed


def pipeline(old_mod) -> tuple[list, float, float]:
    """The pipeline pattern: (the pipeline's Tracker.update calls (args), us per update
    inside the pipeline with REV's Tracker, with the working tree's)."""
    import kmea.pipeline as kp
    from kmea.benchmarks.pipeline import render
    from kmea.pipeline import FrameInput, Pipeline, PipelineSettings

    frames, scene = render(90)
    calls: list = []
    costs = []
    for mod in (old_mod, new_mod):
        spent: list[float] = []
        saved, kp.Tracker = kp.Tracker, _timed(mod.Tracker, spent,
                                               calls if mod is new_mod else None)
        try:
            p = Pipeline(scene.camera, scene.effective_map(), PipelineSettings(
                algorithm="corner-pnp", robots=tuple(scene.robot_specs()), tracking=True,
                filter_kind="kalman"))
            try:
                for f in frames:
                    det = p.detector.detect(f.image)
                    p.process(FrameInput(f.index, f.timestamp, f.image, detections=det))
            finally:
                p.close()
        finally:
            kp.Tracker = saved
        costs.append(float(np.median(spent[4:])) * 1e6)
    return calls, costs[0], costs[1]


def replay(old_mod, calls) -> None:
    """The pipeline's recorded updates through both versions: outputs and cost."""
    worst, bad, best = 0.0, 0, {}
    for name, mod in (("REV", old_mod), ("working tree", new_mod)):
        times = []
        for _ in range(5):
            trk = mod.Tracker(mod.TrackerConfig())
            t0 = time.perf_counter()
            outs = [trk.update(*a, **k) for a, k in calls]
            times.append((time.perf_counter() - t0) / len(calls))
        best[name] = (min(times), outs)
    for a, b in zip(best["REV"][1], best["working tree"][1], strict=True):
        bad += (a.kind, a.reason) != (b.kind, b.reason)
        worst = max(worst, state_diff(a.state, b.state))
    kinds = sorted({o.kind for o in best["REV"][1]})
    print(f"pipeline replay ({len(calls)} updates, {', '.join(kinds)}): largest state "
          f"difference {worst:.3g}, differing decisions {bad}; cost per update (best of 5): "
          f"REV {best['REV'][0] * 1e6:.0f} us, working tree "
          f"{best['working tree'][0] * 1e6:.0f} us")


def main(rev: str, quick: bool = False, pipe: bool = False) -> int:
    old_mod = load_rev(rev)
    if pipe:
        calls, c_old, c_new = pipeline(old_mod)
        print(f"in the pipeline (render(90), corner-pnp, tracking, kalman; median thread CPU "
              f"time per update): REV {c_old:.0f} us, working tree {c_new:.0f} us")
        replay(old_mod, calls)
    worst = {"state": 0.0, "predicted": 0.0, "d2": 0.0}
    decisions = updates = bit_identical = 0
    spent_old = spent_new = 0.0
    n_drives = 0
    for name, changes, rows in drives(quick):
        n_drives += 1
        outs_o, so, trk_o = run(old_mod, changes, rows)
        outs_n, sn, trk_n = run(new_mod, changes, rows)
        spent_old, spent_new = spent_old + so, spent_new + sn
        updates += len(rows)
        bad = 0
        for k, (a, b) in enumerate(zip(outs_o, outs_n, strict=True)):
            if (a.kind, a.reason, a.retracted_all) != (b.kind, b.reason, b.retracted_all):
                bad += 1
                if bad <= 3:
                    print(f"  {name} #{k}: {a.kind} {a.reason!r} vs {b.kind} {b.reason!r}")
            d = state_diff(a.state, b.state)
            worst["state"] = max(worst["state"], d)
            bit_identical += d == 0.0
            if not (math.isnan(a.d2) and math.isnan(b.d2)):
                worst["d2"] = max(worst["d2"], abs(a.d2 - b.d2))
        t_end = rows[-1][0] + 0.05
        worst["predicted"] = max(worst["predicted"], state_diff(
            trk_o.predict("r", t_end), trk_n.predict("r", t_end)))
        decisions += bad
    print(f"{n_drives} drives, {updates} updates, REV {rev} against the working tree")
    print(f"largest state difference (x, y, theta, sigma, sigma_theta, vx, vy, speed, omega, "
          f"cov): {worst['state']:.3g}")
    print(f"largest difference of a prediction 50 ms after a drive: {worst['predicted']:.3g}")
    print(f"largest d2 difference: {worst['d2']:.3g}")
    print(f"states bit-identical: {bit_identical} of {updates}")
    print(f"differing decisions (kind, reason, retracted): {decisions}")
    print(f"cost per update: REV {spent_old / updates * 1e6:.0f} us, "
          f"working tree {spent_new / updates * 1e6:.0f} us "
          f"({spent_old / spent_new:.2f}x)")
    return 0 if decisions == 0 and worst["state"] <= 1e-9 and worst["predicted"] <= 1e-9 else 1


if __name__ == "__main__":
    args = [a for a in sys.argv[1:] if not a.startswith("--")]
    if len(args) != 1:
        sys.exit(__doc__)
    sys.exit(main(args[0], "--quick" in sys.argv, "--pipeline" in sys.argv))
