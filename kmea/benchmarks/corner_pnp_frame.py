"""corner-pnp's estimate on a fixed camera, per frame, in CPU time.

The default scene (1640x1232, two robots on three markers, tracking on) through the tracked
pipeline; the estimator's calls are timed with ``time.thread_time()``: the robots placed
from their corners with the last fit before the relay (``place_on_planes``), and
``estimate_with_loo`` (and ``estimate`` for the robots sent first when the floor changed).
An estimate whose camera fit is the previous call's (the floor unchanged: the robots'
placements are taken from ``place_on_planes``) is a "same fit" call; the others refit the
camera (one more averaged look at the references, a reference back in view). Also prints
the pipeline's own wall-clock ``timings["estimate"]``. Prints figures; no asserts.

    kmea bench corner-pnp-frame [FRAMES]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from kmea.benchmarks.pipeline import render
from kmea.estimators.corner_pnp.estimator import CornerPnP
from kmea.pipeline import FrameInput, Pipeline, PipelineSettings


def measure(n: int = 240) -> None:
    frames, scene = render(n)
    p = Pipeline(scene.camera, scene.effective_map(), PipelineSettings(
        algorithm="corner-pnp", robots=tuple(scene.robot_specs()), fixed_camera=True))
    est = p.estimator
    assert isinstance(est, CornerPnP)
    calls: list[tuple[int, float, bool]] = []  # (frame, CPU ms, same fit as the last call)
    frame = [0]
    last: list[object] = [None]

    def timed(method):
        def call(*args, **kwargs):
            t0 = time.thread_time()
            out = method(*args, **kwargs)
            ms = (time.thread_time() - t0) * 1e3
            fit = est.warm_fit
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


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="kmea bench corner-pnp-frame",
                                description=(__doc__ or "").split("\n\n")[0])
    p.add_argument("frames", nargs="?", type=int, default=240, metavar="FRAMES")
    measure(p.parse_args(argv).frames)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
