"""The fixed-camera frame path up to the robots' datagrams, in CPU time.

Per frame of the default scene (1640x1232, two robots, tracking on): the tracking
detector's ``detect()`` and then ``Pipeline.process(..., on_robots=...)``, timed with
``time.thread_time()`` from the start of the detection to the relay callback (what the
daemon's latency pays, without its thread hand-offs and the scheduler), and to the end of
the frame (the floor's update, leave-one-out). CPU time, so a busy machine inflates it
less than wall time. Prints figures; no asserts.

    kmea bench frame-path [FRAMES] [ESTIMATOR]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from kmea.benchmarks.pipeline import render
from kmea.pipeline import FrameInput, Pipeline, PipelineSettings


def measure(n: int = 240, algorithm: str = "corner-pnp") -> None:
    frames, scene = render(n)
    p = Pipeline(scene.camera, scene.effective_map(), PipelineSettings(
        algorithm=algorithm, robots=tuple(scene.robot_specs()), fixed_camera=True))
    detect, path, whole = [], [], []
    try:
        for f in frames:
            t0 = time.thread_time()
            det = p.detector.detect(f.image)
            t1 = time.thread_time()
            sent: list[float] = []
            p.process(FrameInput(f.index, f.timestamp, f.image, detections=det),
                      on_robots=lambda t, fixes, sent=sent: sent.append(time.thread_time()))
            t2 = time.thread_time()
            detect.append((t1 - t0) * 1e3)
            path.append((sent[0] - t0) * 1e3 if sent else np.nan)
            whole.append((t2 - t0) * 1e3)
    finally:
        p.close()

    def stats(x: list[float]) -> str:
        a = np.asarray(x)[5:]  # the first frames: full detection, cold fit
        return (f"median {np.nanmedian(a):.2f} ms, p90 {np.nanpercentile(a, 90):.2f}, "
                f"p99 {np.nanpercentile(a, 99):.2f}, max {np.nanmax(a):.2f}")

    print(f"{n} frames {scene.size[0]}x{scene.size[1]}, {algorithm}, tracking; CPU time:")
    print(f"  detection:                 {stats(detect)}")
    print(f"  detection to the relay:    {stats(path)}")
    print(f"  the whole frame:           {stats(whole)}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="kmea bench frame-path",
                                description=(__doc__ or "").split("\n\n")[0])
    p.add_argument("frames", nargs="?", type=int, default=240, metavar="FRAMES")
    p.add_argument("algorithm", nargs="?", default="corner-pnp", metavar="ESTIMATOR")
    a = p.parse_args(argv)
    measure(a.frames, a.algorithm)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
