"""Motion scenes: robots driving fast under a rolling-shutter camera with a real exposure.

The motion evaluation's scenes, fixed before any tuning. Each :class:`MotionCase` is a
scenario-1 camera (1.35 m above the floor, looking down) with the IMX219's rolling shutter
(:func:`kmea.timing.imx219_line_time` at the image height), an exposure of ``exposure_ms``
and the light of an indoor floor (``LIGHT_MS``: the exposure that fills the image at gain
1; shorter exposures are made up with gain, and noise). Two robots with 60 mm markers on
0.20 m plates drive stadiums at ``speed`` m/s, turning at ``omega`` rad/s on the half
circles (radius speed / omega):

- amr1 (pair [40, 41]): straights along world y, so it crosses the whole image height
  (1.04 m of the floor is in view at its plate height);
- amr2 (single [42]): straights along world x, across the image.

``sensor`` (imx219 by default; imx708, imx296, imx477) puts another camera module's shutter
at its recommended output size (:data:`kmea.camera_advice.RECOMMENDED` aspect ratio, the
width given): its line time at that size, 0 for the IMX296's global shutter. The lens keeps
the Camera Module v2's horizontal field of view, so the cases differ in the shutter, the
resolution and the aspect ratio only.

``seed`` draws the stadiums' centres (within 0.15 m of the floor's centre), their sense and
where on them each robot starts, and the sensor noise.

The split: ``TUNING_SEEDS`` (2601...) were the only seeds used while choosing anything
(the default exposure, the blur warning level); ``HELDOUT_SEEDS`` (2701...) give every
figure reported (``kmea bench motion``). A case never shares a seed with the other split.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from kmea.camera_advice import RECOMMENDED
from kmea.sim.motion import StadiumPath
from kmea.sim.scene import Scene, SimRobot
from kmea.sim.scenes import get_scene
from kmea.vision.camera import CameraModel, pi_camera_v2

__all__ = ["HELDOUT_SEEDS", "LIGHT_MS", "SPEEDS", "TUNING_SEEDS", "MotionCase",
           "motion_scene"]

#: Robot speeds (m/s) and the turn rate on the half circles (rad/s) of the issue.
SPEEDS = (0.5, 1.0, 1.5)
OMEGA = 3.0
#: Exposures of the sweep, ms.
EXPOSURES_MS = (1.0, 2.0, 4.0, 8.0, 16.0)
#: Exposure (ms) that fills the image at analogue gain 1 on the reference floor's light:
#: indoors, auto exposure picks 10-30 ms at low gain.
LIGHT_MS = 16.0

TUNING_SEEDS = tuple(range(2601, 2611))
HELDOUT_SEEDS = tuple(range(2701, 2711))


@dataclass(frozen=True)
class MotionCase:
    """One motion scene: speed m/s, turn rate rad/s, exposure ms, image width px (the
    height follows the sensor's recommended aspect ratio), seed, sensor model."""

    speed: float
    omega: float = OMEGA
    exposure_ms: float = 2.0
    width: int = 1640
    seed: int = 2701
    sensor: str = "imx219"

    @property
    def height(self) -> int:
        rw, rh = RECOMMENDED[self.sensor]
        return round(self.width * rh / rw)

    @property
    def label(self) -> str:
        who = "" if self.sensor == "imx219" else f"{self.sensor}, "
        return (f"{who}{self.speed:g} m/s, {self.omega:g} rad/s, {self.exposure_ms:g} ms, "
                f"{self.width}x{self.height}, seed {self.seed}")


def _robots(case: MotionCase) -> list[SimRobot]:
    rng = np.random.default_rng([case.seed, 27])
    R = case.speed / case.omega
    out = []
    for name, markers, axis, length in (("amr1", (40, 41), math.pi / 2, 0.90),
                                        ("amr2", (42,), 0.0, 0.70)):
        c = rng.uniform(-0.15, 0.15, size=2)
        path = StadiumPath((float(c[0]), float(c[1])), length, R, case.speed, axis=axis,
                           phase=float(rng.uniform(0.0, 2 * length + 2 * math.pi * R)),
                           ccw=bool(rng.integers(0, 2)))
        out.append(SimRobot(name, markers, 0.20, 0.06, 0.10, path=path))
    return out


def motion_scene(case: MotionCase, line_time: bool = True) -> Scene:
    """The scene of ``case`` (``line_time`` False: a global shutter, for comparisons)."""
    if case.sensor == "imx219":
        h = round(case.width * 1232 / 1640)
        sc = get_scene("scenario1", width=case.width, height=h, seed=case.seed,
                       exposure_ms=case.exposure_ms, light_ms=LIGHT_MS,
                       rolling=1 if line_time else 0)
    else:
        w, h = case.width, case.height
        v2 = pi_camera_v2()
        f = v2.fx * w / v2.width  # the v2's horizontal field of view at this width
        K = np.array([[f, 0.0, (w - 1) / 2], [0.0, f, (h - 1) / 2], [0.0, 0.0, 1.0]])
        sc = get_scene("scenario1", camera=CameraModel(K, v2.dist_coeffs, w, h),
                       seed=case.seed, exposure_ms=case.exposure_ms, light_ms=LIGHT_MS,
                       **({"sensor": case.sensor} if line_time else {"line_us": 0}))
    return sc.with_(robots=_robots(case), name=f"motion {case.label}")
