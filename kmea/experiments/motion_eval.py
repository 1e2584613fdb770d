"""Robot poses on the motion scenes (:mod:`kmea.experiments.motion`), truth at each pose's
own time.

Every frame is rendered once and run through two pipelines (the daemon's defaults for a
file source: full detection, corner-pnp, the tracking filter): ``timed`` gets the frame's
timing (``meta["timing"]``, as the simulator and the Pi camera give it), so each robot's
pose is stamped with its markers' mid-exposure; ``frame`` gets none, as a camera without
exposure timing: every pose stamped with the frame's timestamp (the instant row 0 is read
out); ``noskew`` is ``timed`` without the single marker's skew correction. Each pose is
compared with the truth at the time it claims.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from kmea.experiments.motion import MotionCase, motion_scene
from kmea.geometry.rotations import wrap_angle
from kmea.pipeline import FrameInput, Pipeline, PipelineSettings
from kmea.sim.renderer import Renderer

__all__ = ["CaseResult", "Errors", "evaluate_case", "rms"]

#: Frames (0.2 s) after a robot (re)appears before its filtered pose counts as settled.
SETTLE = 6

#: Frames at the start of a run left out of the figures (a third of a second): the
#: tracking filter's first measurements, before it knows the velocity.
WARMUP = 10


@dataclass
class Errors:
    """Per robot-frame errors of one variant: position (m) and heading (rad) of the
    filter's output and of the raw measurement, |truth turn rate| (rad/s) at that time,
    and the robot-frames where a robot was visible and where it got a pose."""

    pos: list[float] = field(default_factory=list)
    head: list[float] = field(default_factory=list)
    raw_pos: list[float] = field(default_factory=list)
    raw_head: list[float] = field(default_factory=list)
    turning: list[bool] = field(default_factory=list)
    single_head: list[float] = field(default_factory=list)  # raw, one-marker robot (amr2)
    # the filter's output SETTLE frames or more into a run of frames with a pose (a robot
    # entering the view starts a new track, which learns its velocity over a few frames)
    settled: list[bool] = field(default_factory=list)
    visible: int = 0
    posed: int = 0


@dataclass
class CaseResult:
    case: MotionCase
    frames: int
    timed: Errors
    frame: Errors
    noskew: Errors
    seconds: float = 0.0


class _NoSkew(Pipeline):
    """The timed pipeline without the single marker's skew correction (its figure)."""

    def observation_times(self, inp, ids, corners):  # type: ignore[no-untyped-def]
        out = super().observation_times(inp, ids, corners)
        self._rates = {}
        return out


def rms(v: list[float] | np.ndarray) -> float:
    a = np.asarray(v, dtype=float)
    return float(np.sqrt(np.mean(a * a))) if a.size else math.nan


def evaluate_case(case: MotionCase, frames: int, start: int = 0) -> CaseResult:
    """Run ``frames`` frames of ``case`` from frame ``start``; see the module docstring."""
    import time

    t0 = time.perf_counter()
    scene = motion_scene(case)
    renderer = Renderer(scene)
    specs = tuple(scene.robot_specs())
    settings = PipelineSettings(robots=specs, filter_kind="kalman", loo=False)
    pipes = {k: (_NoSkew if k == "noskew" else Pipeline)(scene.camera, scene.effective_map(),
                                                          settings)
             for k in ("timed", "frame", "noskew")}
    errs = {k: Errors() for k in pipes}
    paths = {r.name: r.path for r in scene.robots}
    runs = {(v, s.name): 0 for v in pipes for s in specs}  # consecutive frames with a pose
    for k in range(frames):
        i = start + k
        f = renderer.render(i)
        truth = f.truth
        for variant, p in pipes.items():
            meta = {} if variant == "frame" else {"timing": truth.timing}
            res = p.process(FrameInput(i, f.timestamp, f.image, meta=meta))
            for spec in specs:
                key = (variant, spec.name)
                runs[key] = runs[key] + 1 if spec.name in res.robots else 0
            if k < WARMUP:
                continue
            e = errs[variant]
            for spec in specs:
                if not set(spec.markers) & truth.visible:
                    continue
                e.visible += 1
                fix = res.robots.get(spec.name)
                if fix is None:
                    continue
                e.posed += 1
                e.settled.append(runs[(variant, spec.name)] > SETTLE)
                t = f.timestamp if fix.t is None else fix.t
                x, y, th = truth.robot_at(spec.name, t)
                e.pos.append(math.hypot(fix.x - x, fix.y - y))
                e.head.append(wrap_angle(fix.theta - th))
                if fix.raw is not None:
                    e.raw_pos.append(math.hypot(fix.raw[0] - x, fix.raw[1] - y))
                    e.raw_head.append(wrap_angle(fix.raw[2] - th))
                    if len(spec.markers) == 1:
                        e.single_head.append(wrap_angle(fix.raw[2] - th))
                rate = getattr(paths[spec.name], "turn_rate", None)
                e.turning.append(bool(rate is not None and abs(rate(t)) > 0.5 * case.omega))
    for p in pipes.values():
        p.close()
    return CaseResult(case, frames, errs["timed"], errs["frame"], errs["noskew"],
                      time.perf_counter() - t0)
