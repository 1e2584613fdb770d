"""Shared by the fixed-camera tests: rendered simulator frames (seeded scenes, real ArUco
detection), a deterministic tracker (discoveries in the calling thread, so the frame at
which one is merged does not depend on scheduling) and a tracking pipeline. Frames are
820x616 (half the Pi's 1640x1232) to keep the suite fast; markers are then ~30 px wide."""

from __future__ import annotations

from kmea.fixed_camera import FixedCameraConfig, FixedCameraDetector
from kmea.pipeline import Pipeline, PipelineSettings
from kmea.sources.sim import SimSource
from kmea.vision.detection import DetectorConfig

WIDTH = 820


def frames_of(spec: str, n: int, width: int = WIDTH):
    src = SimSource(spec, width=width, frames=n)
    return [src.read() for _ in range(n)], src


def static_ids(src: SimSource) -> frozenset[int]:
    robot_ids = {m for r in src.scene.robot_specs() for m in r.markers}
    return frozenset(set(src.world_map.markers) - robot_ids)


def tracker(src: SimSource, **kw) -> FixedCameraDetector:
    """A tracking detector of ``src``'s floor; discoveries in the calling thread."""
    return FixedCameraDetector(DetectorConfig(src.world_map.dictionary),
                               FixedCameraConfig(static_ids=static_ids(src), **kw))


def tracked_pipeline(src: SimSource, algorithm: str | None = None, **kw) -> Pipeline:
    """A tracking pipeline of ``src``'s robots with a deterministic tracker (:func:`tracker`)."""
    extra = {} if algorithm is None else {"algorithm": algorithm}
    p = Pipeline(src.camera, src.world_map, PipelineSettings(
        robots=tuple(src.scene.robot_specs()), fixed_camera=True, **extra))
    p.observer.detector.close()
    p.observer.detector = tracker(src, **kw)
    return p

