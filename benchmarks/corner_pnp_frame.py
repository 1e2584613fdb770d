"""corner-pnp's estimate on a fixed camera, per frame, in CPU time (issue 14).

The default scene (1640x1232, two robots on three markers, tracking on) through the tracked
pipeline; the estimator's calls are timed with ``time.thread_time()``: the robots placed
from their corners with the last fit before the relay (``place_on_planes``), and
``estimate_with_loo`` (and ``estimate`` for the robots sent first when the floor changed).
An estimate whose camera fit is the previous call's (the floor unchanged: the robots'
placements are taken from ``place_on_planes``) is a "same fit" call; the others refit the
camera (one more averaged look at the references, a reference back in view). Also prints
the pipeline's own wall-clock ``timings["estimate"]``. Prints figures; no asserts.

    .venv/bin/python benchmarks/corner_pnp_frame.py [FRAMES]
"""

from __future__ import annotations

import sys
import time

import numpy as np

from kmea.benchmarks.pipeline import render
from kmea.pipeline import FrameInput, Pipeline, PipelineSettings


def main(n: int = 240) -> None:
    frames, scene = render(n)
    p = Pipeline(scene.camera, scene.effective_map(), PipelineSettings(
        algorithm="corner-pnp", robots=tuple(scene.robot_specs()), fixed_camera=True))
    est = p.estimator
    calls: list[tuple[int, float, bool]] = []  # (frame, CPU ms, same fit as the last call)
    frame = [0]
    last = [None]

    def timed(method):
        def call(*args, **kwargs):
            t0 = time.thread_time()
            out = method(*args, **kwargs)
            ms = (time.thread_time() - t0) * 1e3
            fit = est._warm.fit if est._warm is not None else None
            calls.append((frame[0], ms, fit is not None and fit is last[0]))
            last[0] = fit
            return out
        return call

    placing: list[tuple[int, float]] = []

    def timed_place(*args, **kwargs):
        t0 = time.thread_time()
        out = place(*args, **kwargs)
        placing.append((frame[0], (time.thread_time() - t0) * 1e3))
        return out

    place = est.place_on_planes
    est.place_on_planes = timed_place
    est.estimate_with_loo = timed(est.estimate_with_loo)
    est.estimate = timed(est.estimate)
    wall = []
    try:
        for f in frames:
            frame[0] = f.index
            det = p.detector.detect(f.image)
            r = p.process(FrameInput(f.index, f.timestamp, f.image, detections=det),
                          on_robots=lambda t, fixes: None)
            wall.append(r.timings["estimate"])
    finally:
        p.close()

    def stats(x) -> str:
        a = np.asarray(x, dtype=float)
        if a.size == 0:
            return "none"
        return (f"median {np.median(a):.3f} ms, p90 {np.percentile(a, 90):.3f}, "
                f"p99 {np.percentile(a, 99):.3f} ({a.size} calls)")

    warm = [c for c in calls if c[0] >= 5]  # the first frames: full detection, cold fit
    print(f"{n} frames {scene.size[0]}x{scene.size[1]}, corner-pnp, tracking; CPU time of "
          f"the estimator's calls:")
    print(f"  robots before the relay:     {stats([ms for k, ms in placing if k >= 5])}")
    print(f"  estimate, the same fit:      {stats([ms for _, ms, same in warm if same])}")
    print(f"  with a refit of the camera:  {stats([ms for _, ms, same in warm if not same])}")
    print(f"  timings['estimate'] (wall):  {stats(wall[5:])}")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 240)
