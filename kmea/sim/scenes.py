"""Named scenes: the paper's two camera placements, the default fleet, and option parsing.

``get_scene("default")``: scenario 1 camera, the RobotAtFactory map, robots amr1 (pair
[40, 41], separation 0.10 m) and amr2 (single [42]), both 0.20 m high with 60 mm markers,
looping between the warehouses and the machines. See ``docs/simulation.md``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from kmea.maps.files import MarkerMap, default_map
from kmea.sim.motion import CrossingPath, LoopPath, WallClock
from kmea.sim.scene import Effects, Occluder, Scene, SimRobot, look_at, pose_matrix
from kmea.timing import imx219_line_time, line_time
from kmea.vision.camera import CameraModel, pi_camera_v2

__all__ = [
    "DEFAULT_FLEET",
    "apply_options",
    "available_scenes",
    "default_robots",
    "get_scene",
    "raised_overrides",
    "scenario1_camera",
    "scenario2_camera",
    "scene_from_spec",
    "wide_cameras",
    "wide_map",
]

#: The default fleet (as in config.toml): name, markers, height m, length m, separation m.
DEFAULT_FLEET = (
    ("amr1", (40, 41), 0.20, 0.06, 0.10),
    ("amr2", (42,), 0.20, 0.06, 0.10),
)

# Loops between the incoming warehouse (top left), the machines (centre) and the outgoing
# warehouse (bottom right), clear of the machines' wall panels; metres.
_LOOPS = {
    "amr1": [(-0.50, 0.36), (0.0, 0.36), (0.14, 0.27), (0.0, 0.18), (-0.50, 0.18)],
    "amr2": [(0.55, -0.37), (0.0, -0.37), (-0.15, -0.26), (0.05, -0.17), (0.22, -0.05),
             (0.45, -0.20)],
}


def scenario1_camera(height: float | None = 1.35, camera: CameraModel | None = None,
                     center: Sequence[float] = (0.0, 0.0), yaw: float = 0.0) -> np.ndarray:
    """cam2world of a camera ``height`` m above ``center`` looking straight down.

    The optical axis is world -z and the image x axis world +x (rotated by ``yaw`` rad about
    the vertical), so the image looks like the plan. ``height`` None: the lowest height at
    which ``camera`` (default Pi Camera v2) sees the whole RobotAtFactory floor (1.7 x 1.2 m).
    """
    if height is None:
        cam = camera or pi_camera_v2()
        hx = 0.85 * cam.fx / (cam.width / 2.0)
        hy = 0.60 * cam.fy / (cam.height / 2.0)
        height = 1.05 * max(hx, hy)
    if not (math.isfinite(height) and height > 0):
        raise ValueError(f"scenario1_camera: height must be > 0 m, got {height!r}")
    c, s = math.cos(yaw), math.sin(yaw)
    x = np.array([c, s, 0.0])
    y = np.array([s, -c, 0.0])
    z = np.array([0.0, 0.0, -1.0])
    return pose_matrix(np.column_stack([x, y, z]), [center[0], center[1], height])


def scenario2_camera(position: Sequence[float] = (-0.80, 0.60, 1.05),
                     target: Sequence[float] = (0.05, -0.05, 0.0)) -> np.ndarray:
    """cam2world of a camera above the top-left part of the floor looking obliquely at the
    origin (default 1.05 m up at the corner (-0.80, 0.60); about 45 degrees from vertical)."""
    return look_at(position, target)


def default_robots(speed: float = 0.12) -> list[SimRobot]:
    """The default fleet on its loops, driving at ``speed`` m/s."""
    out = []
    for name, markers, height, length, sep in DEFAULT_FLEET:
        path = LoopPath(_LOOPS[name], speed=speed)
        out.append(SimRobot(name, markers, height, length, sep, path))
    return out


def entering_robot(t0: float, speed: float = 0.5) -> SimRobot:
    """Robot "amr3" (marker 43, 0.20 m high) that waits beyond the left edge of the
    scenario 1 view (x = -1.3 m) and drives into it at ``t0`` s, at ``speed`` m/s along
    y = -0.05 m, for 3 s (scene option ``enter_at``)."""
    if not math.isfinite(t0):
        raise ValueError(f"scene option enter_at: must be a finite time in s, got {t0!r}")
    return SimRobot("amr3", (43,), 0.20, 0.06, 0.10,
                    _DriveIn(CrossingPath((-1.3, -0.05), (-1.3 + 3.0 * speed, -0.05), t0=t0,
                                          duration=3.0)))


class _DriveIn:
    """A crossing that waits at its start before and stays at its end after (a robot always
    has a pose)."""

    def __init__(self, crossing: CrossingPath) -> None:
        self.crossing = crossing

    def pose(self, t: float) -> tuple[float, float, float]:
        c = self.crossing
        t = min(max(t, c.t0), c.t0 + c.duration)
        p = c.pose(t)
        assert p is not None  # inside the crossing's time span
        return p


def raised_overrides(world_map: MarkerMap, ids: Sequence[int],
                     dz: float = 0.20) -> dict[int, np.ndarray]:
    """Overrides lifting floor markers ``ids`` by ``dz`` m (Part II: a 20 cm support)."""
    out = {}
    for mid in ids:
        if mid not in world_map:
            raise ValueError(f"raised_overrides: marker {mid} is not in the map")
        m = world_map[mid]
        out[mid] = pose_matrix(m.rotation, m.position + np.array([0.0, 0.0, dz]))
    return out


# ---------------------------------------------------------------------------- wide floor
#: The wide scene: floor B is floor A moved by WIDE_DX m along +x; its floor markers carry
#: ids 66-98 (A's floor ids in order), so one DICT_5X5_100 map holds both floors.
WIDE_DX = 1.70
WIDE_CAMERA_HEIGHT = 1.75
#: Each camera 0.15 m inward of its floor's centre: the Pi Camera v2 (62.2 deg wide) covers
#: +-1.055 m in x at the floor from 1.75 m, so each sees all of its floor and the views
#: overlap on x = 0.50-1.20 m (0.70 m) at the floor, x = 0.62-1.09 m (0.47 m) at the robots'
#: marker plane 0.20 m up; both floors' facing marker columns (x = 0.695, 1.005) lie in it.
WIDE_CAMERA_X = (0.15, WIDE_DX - 0.15)
_WIDE_LOOPS = {
    "amr1": [(0.75, 0.44), (2.10, 0.42), (2.28, 0.32), (2.10, 0.22), (0.85, 0.24),
             (-0.40, 0.22), (-0.58, 0.32), (-0.40, 0.42)],
    "amr2": [(2.10, -0.44), (0.85, -0.42), (-0.40, -0.44), (-0.58, -0.34), (-0.40, -0.24),
             (0.85, -0.26), (2.10, -0.24), (2.28, -0.34)],
}


def wide_map() -> MarkerMap:
    """Two RobotAtFactory floors side by side (module constants above); floor A keeps its
    markers (walls included), floor B has its 33 floor markers as ids 66-98."""
    from dataclasses import replace

    from kmea.maps.files import Marker

    base = default_map()
    markers = dict(base.markers)
    floor_ids = [i for i in base.ids if base[i].on_floor]
    for k, mid in enumerate(floor_ids):
        m = base[mid]
        markers[66 + k] = Marker(66 + k, m.position + np.array([WIDE_DX, 0.0, 0.0]),
                                 m.rotation, m.length)
    return replace(base, markers=markers, reference_length=None,
                   name="RobotAtFactory 4.0 wide (two floors)",
                   source="<built-in wide scene map>", extra={})


def wide_cameras() -> list[np.ndarray]:
    """cam2world of the wide scene's two cameras (1.75 m up, looking down, at
    x = WIDE_CAMERA_X)."""
    return [scenario1_camera(WIDE_CAMERA_HEIGHT, center=(x, 0.0)) for x in WIDE_CAMERA_X]


def _wide(opts: dict[str, Any]) -> Scene:
    opts = dict(opts)
    idx = opts.pop("camera", 0)
    if isinstance(idx, CameraModel):  # a camera model, as for the other scenes
        opts["camera"], idx = idx, 0
    if isinstance(idx, bool):  # the source-spec parser reads "0"/"1" as booleans
        idx = int(idx)
    if idx not in (0, 1):
        raise ValueError(f"scene 'wide': camera must be 0 or 1, got {idx!r}")
    speed = float(opts.pop("speed", 0.25))
    clock = opts.pop("clock", "frame")
    epoch = float(opts.pop("epoch", 0.0))
    if clock not in ("frame", "wall"):
        raise ValueError(f"scene 'wide': clock must be frame or wall, got {clock!r}")
    if opts.get("robots", True) is True:
        paths = {n: LoopPath(_WIDE_LOOPS[n], speed=speed) for n in _WIDE_LOOPS}
        opts["robots"] = [SimRobot(name, markers, height, length, sep,
                                   WallClock(paths[name], epoch) if clock == "wall"
                                   else paths[name])
                          for name, markers, height, length, sep in DEFAULT_FLEET]
    opts.setdefault("world_map", wide_map())
    opts.setdefault("floor", (-0.85, 0.85 + WIDE_DX, -0.6, 0.6))
    rows, cols = [-0.355, -0.15, 0.0, 0.15, 0.355], [-0.695, 0.0, 0.695]
    opts.setdefault("floor_lines", [((-0.695 + dx, y), (0.695 + dx, y))
                                    for dx in (0.0, WIDE_DX) for y in rows]
                    + [((x + dx, -0.355), (x + dx, 0.355))
                       for dx in (0.0, WIDE_DX) for x in cols])
    name = "wide" if idx == 0 else "wide-cam1"
    return _build(name, lambda c: wide_cameras()[idx], True, opts)


# ---------------------------------------------------------------------------- registry

def _effects(opts: dict[str, Any], width: int, height: int) -> Effects:
    e = _effects_update(Effects(), opts, width, height)
    occ = opts.pop("occluders", [])
    if isinstance(occ, str):
        occ = [occ]
    for o in occ:
        if isinstance(o, Occluder):
            e.occluders.append(o)
        elif o == "arm":
            e.occluders.append(Occluder.arm(period=6.0))
        elif o == "person":
            e.occluders.append(Occluder.person(period=10.0))
        else:
            raise ValueError(f"scene option occluders: unknown occluder {o!r} (arm, person, "
                             f"or Occluder objects)")
    e.__post_init__()
    return e


def _resized(camera: CameraModel, width: Any, height: Any) -> CameraModel:
    """``camera`` scaled to the options ``width`` and/or ``height`` (one alone keeps the
    aspect ratio; neither: ``camera`` itself)."""
    if width is not None:
        w = int(width)
        h = int(height) if height is not None else round(w * camera.height / camera.width)
    elif height is not None:
        h = int(height)
        w = round(h * camera.width / camera.height)
    else:
        return camera
    return camera.scaled_to(w, h)


def _build(name: str, cam2world: Callable[[CameraModel], np.ndarray], robots: bool,
           opts: dict[str, Any]) -> Scene:
    opts = dict(opts)
    world_map = opts.pop("world_map", None) or default_map()
    camera = opts.pop("camera", None) or pi_camera_v2()
    camera = _resized(camera, opts.pop("width", None), opts.pop("height", None))
    pose = opts.pop("cam2world", None)
    if pose is None:
        pose = cam2world(camera)
    with_robots = opts.pop("robots", robots)
    if with_robots is True:
        fleet = default_robots(float(opts.pop("speed", 0.12)))
    elif with_robots is False or with_robots is None:
        fleet = []
    else:
        fleet = list(with_robots)
    opts.pop("speed", None)
    enter_at = opts.pop("enter_at", None)
    if enter_at is not None:
        fleet.append(entering_robot(float(enter_at)))
    effects = _effects(opts, camera.width, camera.height)
    raised = opts.pop("raised", None)
    overrides = dict(opts.pop("overrides", {}) or {})
    if raised:
        overrides.update(raised_overrides(world_map, raised, float(opts.pop("raise_by", 0.20))))
    opts.pop("raise_by", None)
    covered = opts.pop("covered", None)
    if isinstance(covered, int) and not isinstance(covered, bool):
        covered = [covered]  # ?covered=4 parses as one number, not a list
    elif covered is True:
        raise ValueError(f"scene {name!r}: covered: expected marker ids, got {covered!r}")
    if covered:
        effects.occluders += Occluder.covering(world_map, covered)
    kw = {k: opts.pop(k) for k in ("misplaced", "extra_markers", "seed", "fps", "floor",
                                    "floor_lines", "supports") if k in opts}
    if opts:
        raise ValueError(f"scene {name!r}: unknown option(s) {sorted(opts)}; see "
                         f"docs/simulation.md")
    if "seed" in kw:
        kw["seed"] = int(kw["seed"])
    if "fps" in kw:
        kw["fps"] = float(kw["fps"])
    return Scene(world_map, camera, pose, fleet, effects, overrides=overrides, name=name, **kw)


_SCENES: dict[str, tuple[str, Callable[[dict[str, Any]], Scene]]] = {
    "default": ("scenario 1 camera (1.35 m, looking down) with the two default robots",
                lambda o: _build("default", lambda c: scenario1_camera(1.35), True, o)),
    "scenario1": ("scenario 1 camera, no robots",
                  lambda o: _build("scenario1", lambda c: scenario1_camera(1.35), False, o)),
    "scenario2": ("scenario 2 camera (top-left, oblique), no robots",
                  lambda o: _build("scenario2", lambda c: scenario2_camera(), False, o)),
    "scenario2-robots": ("scenario 2 camera with the two default robots",
                         lambda o: _build("scenario2-robots", lambda c: scenario2_camera(),
                                          True, o)),
    "occlusion": ("default scene with an arm sweeping across every 6 s",
                  lambda o: _build("occlusion", lambda c: scenario1_camera(1.35), True,
                                   {"occluders": ["arm"], **o})),
    "misplaced": ("scenario 1 with markers 7 (+2 cm x) and 20 (+10 deg yaw) misplaced",
                  lambda o: _build("misplaced", lambda c: scenario1_camera(1.35), False,
                                   {"misplaced": {7: (0.02, 0.0, 0.0),
                                                  20: ((0.0, 0.0, 0.0), (0.0, 0.0, 10.0))},
                                    **o})),
    "wide": ("two floors side by side (3.4 x 1.2 m), camera 0 over the left one; "
             "camera=1: over the right one; the default robots drive across the 0.47 m "
             "overlap at 0.25 m/s (amr1 starts in it); clock=wall&epoch=T: robots move "
             "with the Unix time - T (separate daemons agree)", _wide),
    "wide-cam1": ("the wide scene seen by camera 1 (the same as wide?camera=1)",
                  lambda o: _wide({"camera": 1, **o})),
}


def available_scenes() -> dict[str, str]:
    """Scene name -> one-line description."""
    return {k: v[0] for k, v in _SCENES.items()}


def get_scene(name: str = "default", **options: Any) -> Scene:
    """A named scene, adjusted by ``options``.

    Options: width, height (pixels; the camera is rescaled, 4:3 kept when only one is given),
    camera (CameraModel), cam2world, robots (True/False or a list of SimRobot), speed (m/s),
    noise, blur (px), exposure, vignetting, gradient (gx or (gx, gy) per metre), occluders
    ("arm", "person" or Occluder objects), covered (floor marker ids under sheets), misplaced,
    overrides, raised (ids lifted by raise_by = 0.20 m, the effective map follows),
    extra_markers, seed, fps, floor, floor_lines, supports, world_map, enter_at (s: robot
    amr3 with marker 43 drives into the view then, :func:`entering_robot`).
    """
    key = name.strip().lower() if isinstance(name, str) else name
    if key not in _SCENES:
        raise ValueError(f"unknown scene {name!r} (known: {', '.join(_SCENES)})")
    return _SCENES[key][1](options)


def _parse_value(text: str) -> Any:
    low = text.lower()
    if low in ("true", "yes", "on"):
        return True
    if low in ("false", "no", "off"):
        return False
    for conv in (int, float):
        try:
            return conv(text)
        except ValueError:
            pass
    if "," in text or text.startswith("["):
        return [_parse_value(p) for p in text.strip("[]").split(",") if p.strip()]
    return text


def scene_from_spec(spec: str = "sim", **options: Any) -> Scene:
    """A scene from a source spec: ``sim``, ``sim:NAME``, ``NAME``, with options after ``?``
    (``sim:scenario2?noise=3&width=640``; lists with commas: ``covered=4,13``).
    ``options`` override the spec's."""
    base, _, query = str(spec).strip().partition("?")
    if base.startswith("sim:"):
        base = base[4:]
    elif base == "sim":
        base = ""
    opts: dict[str, Any] = {}
    for part in filter(None, query.split("&")):
        k, eq, v = part.partition("=")
        if not eq or not k:
            raise ValueError(f"{spec}: option {part!r} is not key=value")
        opts[k.strip()] = _parse_value(v.strip())
    opts.update(options)
    return get_scene(base or "default", **opts)


def describe(scene: Scene) -> Mapping[str, Any]:
    """A short summary of a scene (for logs)."""
    return {"name": scene.name, "size": scene.size, "robots": [r.name for r in scene.robots],
            "camera_position": scene.cam_position.round(3).tolist(),
            "occluders": [o.name for o in scene.effects.occluders],
            "misplaced": sorted(scene.misplaced), "overrides": sorted(scene.overrides)}


_SIMPLE = {"width", "height", "fps", "seed", "noise", "noise_sigma", "blur", "blur_sigma",
           "exposure", "vignetting", "gradient", "exposure_ms", "line_us", "light_ms",
           "rolling", "sensor"}


def apply_options(scene: Scene, **options: Any) -> Scene:
    """``scene`` adjusted by :func:`get_scene` options.

    Resolution, fps, seed and image effects apply to any scene; other options rebuild a
    named scene from its name (custom scenes accept only the former).
    """
    if not options:
        return scene
    if not set(options) <= _SIMPLE:
        if scene.name in _SCENES:
            return get_scene(scene.name, **options)
        raise ValueError(f"scene {scene.name!r}: options {sorted(set(options) - _SIMPLE)} need "
                         f"a named scene; only {sorted(_SIMPLE)} apply to a custom one")
    opts = dict(options)
    camera = scene.camera
    camera = _resized(camera, opts.pop("width", None), opts.pop("height", None))
    changes: dict[str, Any] = {"camera": camera}
    if "fps" in opts:
        changes["fps"] = float(opts.pop("fps"))
    if "seed" in opts:
        changes["seed"] = int(opts.pop("seed"))
    eff = scene.effects
    e = replace(eff, occluders=list(eff.occluders))
    changes["effects"] = _effects_update(e, opts, camera.width, camera.height)
    return scene.with_(**changes)


def _effects_update(e: Effects, opts: dict[str, Any], width: int, height: int) -> Effects:
    keys = {"noise": "noise_sigma", "noise_sigma": "noise_sigma", "blur": "blur_sigma",
            "blur_sigma": "blur_sigma", "exposure": "exposure", "vignetting": "vignetting"}
    for k, field_name in keys.items():
        if k in opts:
            setattr(e, field_name, float(opts.pop(k)))
    if "gradient" in opts:
        g = opts.pop("gradient")
        e.gradient = (float(g), 0.0) if isinstance(g, (int, float)) else tuple(g)
    # Time: exposure_ms, light_ms (ms), line_us (us per image row), rolling=1 (the
    # IMX219's line time at this image height, kmea.timing) or sensor=NAME (that camera
    # module's at this image size).
    if "exposure_ms" in opts:
        e.exposure_time_s = float(opts.pop("exposure_ms")) * 1e-3
    if "light_ms" in opts:
        e.light_exposure_s = float(opts.pop("light_ms")) * 1e-3
    if "line_us" in opts:
        e.line_time_s = float(opts.pop("line_us")) * 1e-6
    if "rolling" in opts:
        on = opts.pop("rolling")
        if on not in (0, 1, True, False):
            raise ValueError(f"scene option rolling: 0 or 1, got {on!r}")
        e.line_time_s = imx219_line_time(round(height * 1640 / 1232), height) if on else 0.0
    if "sensor" in opts:
        # A camera module's shutter at this image size (kmea.timing; 0: global shutter).
        name = str(opts.pop("sensor"))
        line = line_time(name, width, height)
        if line is None:
            raise ValueError(f"scene option sensor: no timing table for {name!r} (one of "
                             f"imx219, imx708, imx296, imx477)")
        e.line_time_s = line
    e.__post_init__()
    return e
