"""The fixed-camera fast path's outputs on 90 deterministic tracked frames (the background
detection in the calling thread), kmea and corner-pnp: one digest per algorithm of every
marker estimate, leave-one-out error and robot pose, so that two checkouts can be compared
bit for bit:

    PYTHONPATH=CHECKOUT .venv/bin/python scripts/fixed_camera_digest.py
"""
import hashlib
import inspect

import numpy as np

try:
    from kmea.sources.sim import SimSource
except ImportError:  # a checkout from before kmea/sources/
    from kmea.sim.source import SimSource
import kmea
from kmea.pipeline import FrameInput, Pipeline, PipelineSettings
from kmea.vision.detection import DetectorConfig

try:
    from kmea.fixed_camera import FixedCameraConfig, FixedCameraDetector
except ImportError:  # a checkout from before the kmea.fixed_camera package
    from kmea.vision.fixed_camera_detector import (  # type: ignore[no-redef]
        FixedCameraConfig,
        FixedCameraDetector,
    )

src = SimSource("sim:default", width=820, frames=90)
frames = [src.read() for _ in range(90)]
robot_ids = {m for r in src.scene.robot_specs() for m in r.markers}
static = frozenset(set(src.world_map.markers) - robot_ids)
for algo in ("kmea", "corner-pnp"):
    p = Pipeline(src.camera, src.world_map, PipelineSettings(
        robots=tuple(src.scene.robot_specs()), fixed_camera=True, algorithm=algo))
    p.observer.detector.close()
    # The background detection in the calling thread: the default jobs (Inline), executor=None
    # before the jobs came from the caller, background=False before the executor did.
    params = inspect.signature(FixedCameraDetector).parameters
    sync = ({} if "jobs" in params else {"executor": None} if "executor" in params
            else {"background": False})
    p.observer.detector = FixedCameraDetector(DetectorConfig(src.world_map.dictionary),
                                           FixedCameraConfig(static_ids=static), **sync)
    h = hashlib.sha256()
    n = 0
    for f in frames:
        r = p.process(FrameInput(f.index, f.timestamp, f.image))
        for mid in sorted(r.markers):
            pos, yaw = r.markers[mid]
            vals = [*np.asarray(pos).tolist(), float(yaw), float(r.loo.get(mid, float("nan")))]
            h.update(repr((mid, vals)).encode())
            n += len(vals)
        for name in sorted(r.robots):
            rb = r.robots[name]
            h.update(repr((name, [rb.x, rb.y, rb.theta, rb.sigma])).encode())
            n += 4
        h.update(r.detect_mode.encode())
    print(f"{algo}: {n} values, sha256 {h.hexdigest()[:16]} ({kmea.__file__})")
