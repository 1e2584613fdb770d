"""A simulated RobotAtFactory floor: fast, faithful renders with exact ground truth.

See ``docs/simulation.md``. Main entry points: :func:`get_scene`, :class:`Renderer`; the
simulator as a frame source is :class:`kmea.sources.sim.SimSource`.
"""

from kmea.sim.motion import CrossingPath, LoopPath, Stationary
from kmea.sim.renderer import FrameTruth, Renderer, SimFrame
from kmea.sim.scene import PALETTE, Effects, Occluder, Scene, SimRobot, look_at, marker_pose
from kmea.sim.scenes import (
    DEFAULT_FLEET,
    apply_options,
    available_scenes,
    default_robots,
    get_scene,
    raised_overrides,
    scenario1_camera,
    scenario2_camera,
    scene_from_spec,
)

__all__ = [
    "DEFAULT_FLEET",
    "PALETTE",
    "CrossingPath",
    "Effects",
    "FrameTruth",
    "LoopPath",
    "Occluder",
    "Renderer",
    "Scene",
    "SimFrame",
    "SimRobot",
    "Stationary",
    "apply_options",
    "available_scenes",
    "default_robots",
    "get_scene",
    "look_at",
    "marker_pose",
    "raised_overrides",
    "scenario1_camera",
    "scenario2_camera",
    "scene_from_spec",
]
