"""The simulator as a frame source (``sim`` and ``sim:SCENE`` specs of ``open_source``).

The one simulator source: the daemon, ``open_source`` and the benchmarks all use
:class:`SimSource`.
"""

from __future__ import annotations

import math
import time
from typing import Any

import cv2
import numpy as np

from kmea.sim.motion import WallClock
from kmea.sim.renderer import Renderer, SimFrame
from kmea.sim.scene import Scene
from kmea.sim.scenes import apply_options, scene_from_spec
from kmea.sources.base import FrameSource, SourceError

__all__ = ["SimSource", "open_sim"]


class SimSource(FrameSource):
    """Frames of ``scene`` from frame ``start`` on, forever (or ``frames`` of them).

    ``realtime``: ``read`` waits so frames come at the scene's fps (a live source); otherwise
    frames come as fast as they render, timestamps still index / fps. ``gray`` False gives
    BGR images. Other keyword options adjust the scene (a spec string: options of
    :func:`kmea.sim.scenes.scene_from_spec`; a :class:`Scene`:
    :func:`kmea.sim.scenes.apply_options`: width, height, fps, seed, noise, blur, ...).
    rendered: frames rendered beforehand (frame i = ``rendered[i - start]``), served instead
    of rendering (benchmarks that must not count rendering). ``camera`` is the true camera,
    ``world_map`` the scene's surveyed map.

    bump_at, bump_deg: the camera is bumped at ``bump_at`` s: from then on it is turned by
    ``bump_deg`` degrees (default 1) about its own x axis, as if knocked (spec options too:
    ``sim:default?bump_at=2``). Robots and floor stay; the truth follows the new camera.
    """

    def __init__(self, scene: Scene | str = "sim", start: int = 0, *, frames: int | None = None,
                 realtime: bool = False, gray: bool = True,
                 rendered: list[SimFrame] | None = None, **options: Any) -> None:
        super().__init__()
        bump_at, bump_deg = options.pop("bump_at", None), options.pop("bump_deg", None)
        if isinstance(scene, str):
            scene, spec_bump = split_bump(scene)
            bump_at = spec_bump.get("bump_at", bump_at)
            bump_deg = spec_bump.get("bump_deg", bump_deg)
            self.scene = scene_from_spec(scene, **options)
        else:
            self.scene = apply_options(scene, **options)
        if start < 0:
            raise ValueError(f"sim: start must be >= 0, got {start}")
        self.spec = f"sim:{self.scene.name}"
        self.renderer = Renderer(self.scene)
        self.bump_at: float | None = None
        self.bumped_renderer: Renderer | None = None
        if bump_at is not None:
            self.bump_at = float(bump_at)
            deg = 1.0 if bump_deg is None else float(bump_deg)
            if not (math.isfinite(self.bump_at) and math.isfinite(deg)):
                raise ValueError(f"sim: bump_at and bump_deg must be finite, got {bump_at!r}, "
                                 f"{bump_deg!r}")
            a = math.radians(deg)
            turn = np.eye(4)
            turn[1:3, 1:3] = [[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]
            self.bumped_renderer = Renderer(self.scene.with_(
                cam2world=self.scene.cam2world @ turn))
        self.size = self.scene.size
        self.fps = self.scene.fps
        self.camera = self.scene.camera
        self.world_map = self.scene.effective_map()
        self.rendered = rendered
        if rendered is not None and frames is None:
            frames = len(rendered)
        self.live = bool(realtime)
        self.gray = bool(gray)
        self.start = int(start)
        self.frames = frames
        self._next = self.start
        self._t0: float | None = None

    def take(self, n: int) -> list[SimFrame]:
        """The next ``n`` frames (``ValueError`` when the scene ends before)."""
        out = []
        for _ in range(n):
            f = self.read()
            if f is None:
                raise ValueError(f"the simulator ended after {len(out)} of {n} frames")
            out.append(f)
        return out

    def read(self) -> SimFrame | None:
        if self._closed:
            return None
        if self.frames is not None and self._next - self.start >= self.frames:
            return None
        i = self._next
        self._next += 1
        if self.live:
            now = time.monotonic()
            if self._t0 is None:
                self._t0 = now
            due = self._t0 + (i - self.start) / self.fps
            if due > now:
                time.sleep(due - now)
        if self.rendered is not None:
            return self.rendered[i - self.start]
        # Robots on the Unix time (clock=wall), paced: the frame is the Unix instant now,
        # its rows rendered at it and stamped with it (kmea.sim.motion.WallClock).
        walls = [r.path.anchor for r in self.scene.robots if isinstance(r.path, WallClock)]
        wall = time.time()
        if self.live:
            for a in walls:
                a.offset = wall - i / self.fps
        renderer = self.renderer
        if (self.bumped_renderer is not None and self.bump_at is not None
                and i / self.fps >= self.bump_at):
            renderer = self.bumped_renderer
        frame = renderer.render(i)
        if self.live and walls:
            frame.timestamp = wall
            frame.meta["sensor_timestamp_ns"] = int(wall * 1e9)  # as a camera's own stamp
        if not self.gray:
            frame.image = cv2.cvtColor(frame.pixels, cv2.COLOR_GRAY2BGR)
        return frame

    def seek(self, index: int) -> None:
        """Make the next ``read`` return frame ``index``."""
        self._next = int(index)
        self._t0 = None


def split_bump(spec: str) -> tuple[str, dict[str, float]]:
    """(spec without ``bump_at`` / ``bump_deg``, their values): source options, not scene
    options."""
    base, q, query = spec.partition("?")
    keep, bump = [], {}
    for part in filter(None, query.split("&")):
        k, _, v = part.partition("=")
        if k.strip() in ("bump_at", "bump_deg"):
            try:
                bump[k.strip()] = float(v)
            except ValueError:
                raise ValueError(f"{spec}: option {k.strip()} must be a number, got {v!r}"
                                 ) from None
        else:
            keep.append(part)
    return base + (q + "&".join(keep) if keep else ""), bump


def open_sim(rest: str, **options: Any) -> SimSource:
    """The ``sim[:SCENE]`` source of :func:`kmea.sources.registry.open_source`."""
    spec = f"sim:{rest}" if rest else "sim"
    try:
        return SimSource(spec, **options)
    except ValueError as e:
        raise SourceError(f"{spec}: {e}") from None
