"""``kmea bench fixed-camera``: nothing lost with the tracking detector (1640x1232 sim).

Frames are rendered beforehand, then fed to :class:`kmea.pipeline.Pipeline` with tracking
(:mod:`kmea.fixed_camera.detector`, its discoveries in the calling thread) at the camera's
30 frames/s (the loop waits for each frame's due time). Printed, per scene:

- robots at 1.5 m/s on the default loops (their curves turn them at several rad/s): frames
  in which a robot is visible (truth) and frames in which it got a pose;
- a robot driving into the view (``enter_at``): seconds from its marker's first visible
  frame to its first report;
- a bumped camera (``bump_at``): seconds from the bump to the restart and to the first
  frame estimated again, and the floor's leave-one-out error before and after.
"""

from __future__ import annotations

import math
import time

import numpy as np

from kmea.geometry.rotations import wrap_angle
from kmea.pipeline import FrameInput, Pipeline, PipelineSettings

FPS = 30.0


def _run(spec: str, n: int):
    from kmea.sources.sim import SimSource

    src = SimSource(spec, frames=n)
    frames = src.take(n)
    p = Pipeline(src.camera, src.world_map, PipelineSettings(
        robots=tuple(src.scene.robot_specs()), fixed_camera=True))
    out = []
    t0 = time.perf_counter()
    for f in frames:
        due = t0 + f.index / FPS
        if due > time.perf_counter():
            time.sleep(due - time.perf_counter())
        out.append(p.process(FrameInput(f.index, f.timestamp, f.image)))
    p.close()
    return frames, out, src


def run(quick: bool = False) -> None:
    n = 24 if quick else 45
    frames, res, src = _run("sim:default?speed=1.5", n)
    specs = src.scene.robot_specs()
    visible = posed = 0
    rates = [0.0]
    for k, (f, r) in enumerate(zip(frames, res, strict=True)):
        for spec in specs:
            if set(spec.markers) & f.truth.visible:
                visible += 1
                posed += spec.name in r.robots
        if k:
            prev = frames[k - 1].truth.robots
            rates += [abs(wrap_angle(f.truth.robots[m][2] - prev[m][2])) * FPS
                      for m in prev]
    print(f"robots at 1.5 m/s (turning at up to {max(rates):.1f} rad/s), {n} frames "
          f"1640x1232 at 30 frames/s: {posed} poses for {visible} robot-frames visible; "
          f"{sum(r.detect_mode == 'full' for r in res)} full detections in the frame path")

    frames, res, _ = _run("sim:default?enter_at=-1.0", n)
    seen = next((f.index for f in frames if 43 in f.truth.visible), None)
    rep = next((r.index for r in res if 43 in r.ids.tolist()), None)
    if seen is None or rep is None:
        print(f"robot entering the view: visible from frame {seen}, reported from {rep}")
    else:
        print(f"robot entering the view: visible from frame {seen}, reported from frame "
              f"{rep}: {(rep - seen) / FPS:.2f} s")

    frames, res, _ = _run("sim:default?bump_at=0.5&bump_deg=1.0", n)
    b = math.ceil(0.5 * FPS)
    restart = next((r.index for r in res if r.restart), None)
    ok = next((r.index for r in res[b:] if r.ok), None)
    before = [e for r in res[2:b] for e in r.loo.values()]
    after = [e for r in res[b:] for e in r.loo.values()]
    print(f"camera bumped by 1 degree at frame {b}: restart at frame {restart}, estimated "
          f"again at frame {ok} ({((ok if ok is not None else n) - b) / FPS:.2f} s); floor "
          f"leave-one-out error {np.mean(before) * 1e3:.2f} mm before, "
          f"{np.mean(after) * 1e3 if after else math.nan:.2f} mm after")
