"""What the simulator renders: a marker map, a camera and its pose, robots, effects.

Frames: world x right / y up / z up from the floor, metres; the camera frame is OpenCV's
(x right, y down, z forward); ``cam2world`` is a (4, 4) rigid transform. Marker poses are
(4, 4) ``marker2world`` transforms; a marker's local corners are
:func:`kmea.geometry.marker_corners_local` (TL, TR, BR, BL).

Truth versus map: ``world_map`` is the surveyed (nominal) map. ``overrides`` move map markers
and the effective map follows them (:meth:`Scene.effective_map`, e.g. markers raised on a
support and re-surveyed); ``misplaced`` markers are printed or stuck off their map pose and
the map does not know it (the truth is displaced, :meth:`Scene.effective_map` is not).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from kmea.geometry import check_rotation, euler_zyx_fixed_deg, rot_z, yaw_of
from kmea.maps.files import Marker, MarkerMap
from kmea.sim.motion import CrossingPath, Path, Stationary, WallClock
from kmea.vision.camera import CameraModel

__all__ = [
    "PALETTE",
    "Effects",
    "Occluder",
    "Scene",
    "SimRobot",
    "look_at",
    "marker_pose",
    "pose_matrix",
]

#: Albedos (fraction of full scale; 1.0 renders as 255 at exposure 1) of the scene's materials.
PALETTE: dict[str, float] = {
    "canvas": 0.74,      # the printed floor
    "surround": 0.30,    # beyond the floor's edge
    "line": 0.64,        # faint floor lines
    "white": 0.94,       # marker paper
    "black": 0.07,       # marker ink
    "wall": 0.82,        # wall panels carrying wall markers
    "plate": 0.52,       # robot top plate
    "side": 0.30,        # robot and support sides
    "support": 0.74,     # top of a support under a raised marker
    "occluder": 0.42,    # arms, people, sheets
}


def pose_matrix(R: np.ndarray, t: ArrayLike) -> np.ndarray:
    """(4, 4) rigid transform from a (3, 3) rotation and a (3,) translation."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def marker_pose(value: Any, where: str = "pose") -> np.ndarray:
    """Normalise a marker pose to a (4, 4) marker2world transform.

    Accepts a :class:`~kmea.maps.files.Marker`, a (4, 4) array, or a pair of a (3,) position and a
    (3, 3) rotation in either order.
    """
    if isinstance(value, Marker):
        return pose_matrix(value.rotation, value.position)
    if isinstance(value, (tuple, list)) and len(value) == 2:
        a, b = (np.asarray(v, dtype=float) for v in value)
        if a.shape == (3, 3) and b.shape == (3,):
            a, b = b, a
        if a.shape != (3,) or b.shape != (3, 3):
            raise ValueError(f"{where}: expected (position (3,), rotation (3, 3)), got shapes "
                             f"{a.shape} and {b.shape}")
        return pose_matrix(check_rotation(b, name=where), a)
    T = np.asarray(value, dtype=float)
    if T.shape != (4, 4):
        raise ValueError(f"{where}: expected a Marker, a (4, 4) transform or (position, "
                         f"rotation), got shape {T.shape}")
    check_rotation(T[:3, :3], name=where)
    return T.copy()


def _offset(value: Any, where: str) -> tuple[np.ndarray, np.ndarray]:
    """Normalise a misplacement to (offset (3,) m, rotation (3, 3))."""
    if (isinstance(value, (tuple, list)) and len(value) == 2 and np.ndim(value[0]) == 1
            and np.size(value[0]) == 3):
        off, rot = np.asarray(value[0], dtype=float), np.asarray(value[1], dtype=float)
    else:
        off, rot = np.asarray(value, dtype=float).reshape(-1), np.eye(3)
    if off.shape != (3,) or not np.all(np.isfinite(off)):
        raise ValueError(f"{where}: offset must be 3 finite metres, got {value!r}")
    if rot.shape == (3,):
        rot = euler_zyx_fixed_deg(float(rot[0]), float(rot[1]), float(rot[2]))
    elif rot.shape != (3, 3):
        raise ValueError(f"{where}: rotation must be (3, 3) or (rx, ry, rz) degrees")
    return off, check_rotation(rot, name=where)


@dataclass
class SimRobot:
    """A robot: a box of square section ``plate`` m and ``height`` m carrying its markers.

    markers: (id,) or (left, right); a pair is mounted at (0, +separation/2) and
    (0, -separation/2) in the robot frame (x forward). Markers lie flat on the top plate with
    their x axis forward. ``path`` gives the robot pose (x, y, theta) over time; for a pair
    (x, y) is the midpoint. ``plate`` None: the markers' extent plus 2.5 cm on each side.
    """

    name: str
    markers: tuple[int, ...]
    height: float = 0.20
    length: float = 0.06
    separation: float = 0.10
    path: Path = field(default_factory=lambda: Stationary(0.0, 0.0, 0.0))
    plate: float | None = None

    def __post_init__(self) -> None:
        if isinstance(self.markers, (int, np.integer)):
            self.markers = (int(self.markers),)
        self.markers = tuple(int(m) for m in self.markers)
        where = f"robot {self.name!r}"
        if len(self.markers) not in (1, 2):
            raise ValueError(f"{where}: markers must be (id,) or (left, right)")
        for key in ("height", "length", "separation"):
            v = getattr(self, key)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"{where}: {key} must be > 0 m, got {v!r}")
        if not hasattr(self.path, "pose"):
            raise ValueError(f"{where}: path must have pose(t) -> (x, y, theta)")
        if self.plate is None:
            span = self.length + (self.separation if len(self.markers) == 2 else 0.0)
            self.plate = span + 0.05
        if self.plate <= 0:
            raise ValueError(f"{where}: plate must be > 0 m")

    def mount(self) -> dict[int, np.ndarray]:
        """Marker id -> (2,) position in the robot frame (x forward, y left), metres."""
        if len(self.markers) == 1:
            return {self.markers[0]: np.zeros(2)}
        d = self.separation / 2.0
        return {self.markers[0]: np.array([0.0, d]), self.markers[1]: np.array([0.0, -d])}


@dataclass
class Occluder:
    """A box that hides what is behind it: an arm, a person, a sheet over markers.

    size: (lx, ly) footprint in metres (lx along its heading); z: (bottom, top) heights, m;
    path: its centre's pose over time (None from ``pose`` = absent); shade: albedo 0..1.
    """

    size: tuple[float, float]
    z: tuple[float, float]
    path: Path
    shade: float = PALETTE["occluder"]
    name: str = "occluder"

    def __post_init__(self) -> None:
        lx, ly = (float(v) for v in self.size)
        z0, z1 = (float(v) for v in self.z)
        if not (lx > 0 and ly > 0 and z1 > z0 >= -1e-9):
            raise ValueError(f"occluder {self.name!r}: need size > 0 m and 0 <= z0 < z1 m")
        self.size, self.z = (lx, ly), (z0, z1)

    @property
    def moving(self) -> bool:
        return not isinstance(self.path, Stationary)

    @classmethod
    def arm(cls, y: float = 0.0, z: float = 0.45, t0: float = 1.0, duration: float = 2.0,
            period: float = 0.0, x_from: float = -1.3, x_to: float = 1.3) -> Occluder:
        """A forearm (0.45 x 0.09 m, 9 cm thick) crossing the floor along x at height z."""
        return cls((0.45, 0.09), (z - 0.045, z + 0.045),
                   CrossingPath((x_from, y), (x_to, y), t0, duration, period), name="arm")

    @classmethod
    def person(cls, x: float = -0.75, y_from: float = -0.9, y_to: float = 0.9,
               t0: float = 0.0, duration: float = 6.0, period: float = 0.0) -> Occluder:
        """Someone walking past the floor's edge (0.30 x 0.50 m, 1.1 m tall: under the
        camera, only the part that enters the view matters)."""
        return cls((0.30, 0.50), (0.0, 1.1),
                   CrossingPath((x, y_from), (x, y_to), t0, duration, period, theta=0.0),
                   name="person")

    @classmethod
    def covering(cls, world_map: MarkerMap, ids: Sequence[int], margin: float = 0.01,
                 height: float = 0.01) -> list[Occluder]:
        """Static sheets lying over the given floor markers (``height`` m thick)."""
        out = []
        for mid in ids:
            if mid not in world_map:
                raise ValueError(f"Occluder.covering: marker {mid} is not in the map")
            m = world_map[mid]
            side = m.length * 9 / 7 + 2 * margin
            yaw = float(yaw_of(m.rotation))  # one matrix: a float
            out.append(cls((side, side), (m.position[2], m.position[2] + height),
                           Stationary(m.position[0], m.position[1], yaw),
                           name=f"sheet over {mid}"))
        return out


@dataclass
class Effects:
    """Image effects, applied in this order: lighting, blur, vignetting and exposure, noise.

    noise_sigma: Gaussian sensor noise, grey levels (0..255), at analogue gain 1.
    blur_sigma: Gaussian optical blur, pixels (0: none). exposure: gain on the whole image
    (brightness, not time). vignetting: fractional loss at the image corners (gain
    1 - vignetting * (r / r_corner)^2). gradient: (gx, gy) lighting change per metre
    over the world floor, light = 1 + gx x + gy y (world metres).
    occluders: boxes that move or stand over the scene.

    Time (all 0 by default: every row seen at the frame's instant, as before):
    exposure_time_s: each row integrates the scene over this long (moving robots smear).
    line_time_s: rolling shutter, row r is read out at the frame time + r x line_time_s
    (:mod:`kmea.timing`: 18.9 us for the IMX219 at 1640x1232). light_exposure_s: the
    exposure that fills the image at analogue gain 1 in this light; a shorter exposure is
    made up by gain g = light_exposure_s / exposure_time_s (same image brightness) and the
    noise grows as sqrt(0.7 g + 0.3 g^2) (shot noise goes with sqrt(g), read noise with g;
    the 70/30 split of the noise at gain 1 is this simulator's choice). 0: no gain model.
    """

    noise_sigma: float = 2.0
    blur_sigma: float = 0.5
    exposure: float = 1.0
    vignetting: float = 0.2
    gradient: tuple[float, float] = (0.0, 0.0)
    occluders: list[Occluder] = field(default_factory=list)
    exposure_time_s: float = 0.0
    line_time_s: float = 0.0
    light_exposure_s: float = 0.0

    def __post_init__(self) -> None:
        for key in ("noise_sigma", "blur_sigma", "exposure", "vignetting", "exposure_time_s",
                    "line_time_s", "light_exposure_s"):
            v = getattr(self, key)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"effects: {key} must be a finite number >= 0, got {v!r}")
        if self.vignetting >= 1:
            raise ValueError("effects: vignetting must be < 1")
        gx, gy = (float(v) for v in self.gradient)
        self.gradient = (gx, gy)
        self.occluders = list(self.occluders)

    @property
    def gain(self) -> float:
        """Analogue gain making up for a short exposure (1 without the gain model)."""
        if self.light_exposure_s <= 0 or self.exposure_time_s <= 0:
            return 1.0
        return max(1.0, self.light_exposure_s / self.exposure_time_s)

    @property
    def sensor_noise_sigma(self) -> float:
        """The noise at this exposure's gain, grey levels."""
        g = self.gain
        if g == 1.0:
            return self.noise_sigma
        return self.noise_sigma * math.sqrt(0.7 * g + 0.3 * g * g)

    @property
    def timed(self) -> bool:
        """Do rows see the scene at their own times (exposure or rolling shutter)?"""
        return self.exposure_time_s > 0 or self.line_time_s > 0


def look_at(position: Sequence[float], target: Sequence[float],
            up: Sequence[float] = (0.0, 0.0, 1.0)) -> np.ndarray:
    """cam2world (4, 4) of a camera at ``position`` looking at ``target`` (world metres).

    The image's up direction is the projection of ``up``; looking along ``up`` is an error.
    """
    p = np.asarray(position, dtype=float)
    z = np.asarray(target, dtype=float) - p
    if np.linalg.norm(z) < 1e-9:
        raise ValueError("look_at: position and target coincide")
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=float))
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("look_at: viewing direction parallel to up; give another up vector")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return pose_matrix(np.column_stack([x, y, z]), p)


@dataclass
class Scene:
    """Everything needed to render frames; see the module docstring for truth versus map.

    world_map: nominal map. camera: intrinsics and distortion (its width x height is the
    image size). cam2world: (4, 4). robots: moving robots. effects: image effects and
    occluders. misplaced: id -> (offset (3,) world metres, rotation (3, 3) or (rx, ry, rz)
    degrees applied in the marker's frame), or just an offset; for a robot marker the offset
    is in the robot frame. overrides: id -> new true pose of a map marker (Marker, (4, 4) or
    (position, rotation)); the effective map follows. extra_markers: markers drawn but not in
    the map. seed: noise seed. fps: frame rate (frame i is at t = i / fps s). floor: (xmin,
    xmax, ymin, ymax) of the printed canvas, m (None: the RobotAtFactory 1.7 x 1.2 m for the
    default map, else the markers' extent + 0.15 m). floor_lines: faint lines ((x0, y0),
    (x1, y1)) in m (None: a default track). supports: draw a pillar under overridden markers
    that face up above the floor.
    """

    world_map: MarkerMap
    camera: CameraModel
    cam2world: np.ndarray
    robots: list[SimRobot] = field(default_factory=list)
    effects: Effects = field(default_factory=Effects)
    misplaced: dict[int, Any] = field(default_factory=dict)
    overrides: dict[int, Any] = field(default_factory=dict)
    extra_markers: list[Marker] = field(default_factory=list)
    seed: int = 0
    fps: float = 30.0
    floor: tuple[float, float, float, float] | None = None
    floor_lines: list[tuple[tuple[float, float], tuple[float, float]]] | None = None
    supports: bool = True
    name: str = "custom"

    def __post_init__(self) -> None:
        T = np.asarray(self.cam2world, dtype=float)
        if T.shape != (4, 4):
            raise ValueError(f"scene: cam2world must be (4, 4), got {T.shape}")
        check_rotation(T[:3, :3], name="scene: cam2world rotation")
        self.cam2world = T
        if not (math.isfinite(self.fps) and self.fps > 0):
            raise ValueError(f"scene: fps must be > 0, got {self.fps!r}")
        self.robots = list(self.robots)
        self.extra_markers = list(self.extra_markers)
        robot_ids = {m: r.name for r in self.robots for m in r.markers}
        names = [r.name for r in self.robots]
        if len(set(names)) != len(names):
            raise ValueError(f"scene: duplicate robot names {names}")
        if sum(len(r.markers) for r in self.robots) != len(robot_ids):
            raise ValueError("scene: a marker id is carried by two robots")
        seen = set(self.world_map.ids)
        for m in self.extra_markers:
            if m.id in seen or m.id in robot_ids:
                raise ValueError(f"scene: extra marker {m.id} duplicates a map or robot marker")
            seen.add(m.id)
        for mid in robot_ids:
            if mid in self.world_map:
                raise ValueError(f"scene: robot {robot_ids[mid]!r} carries map marker {mid}")
        self.misplaced = {int(k): _offset(v, f"scene: misplaced[{k}]")
                          for k, v in self.misplaced.items()}
        for mid in self.misplaced:
            if mid not in seen and mid not in robot_ids:
                raise ValueError(f"scene: misplaced marker {mid} is not in the scene")
        self.overrides = {int(k): marker_pose(v, f"scene: overrides[{k}]")
                          for k, v in self.overrides.items()}
        for mid in self.overrides:
            if mid not in self.world_map:
                raise ValueError(f"scene: overrides[{mid}]: not a map marker")

    # ------------------------------------------------------------------ truth
    @property
    def size(self) -> tuple[int, int]:
        """(width, height) of the images, pixels."""
        return self.camera.width, self.camera.height

    @property
    def cam_position(self) -> np.ndarray:
        return self.cam2world[:3, 3].copy()

    def effective_map(self) -> MarkerMap:
        """The map with ``overrides`` applied (what a re-survey would give); ``misplaced``
        markers keep their nominal pose."""
        markers = dict(self.world_map.markers)
        for mid, T in self.overrides.items():
            markers[mid] = Marker(mid, T[:3, 3].copy(), T[:3, :3].copy(), markers[mid].length)
        return replace(self.world_map, markers=markers, extra=dict(self.world_map.extra))

    def static_markers(self) -> dict[int, Marker]:
        """True poses of every map and extra marker (overrides and misplacements applied)."""
        out = dict(self.effective_map().markers)
        for m in self.extra_markers:
            out[m.id] = m
        for mid, (off, R) in self.misplaced.items():
            if mid in out:
                m = out[mid]
                out[mid] = Marker(mid, m.position + off, m.rotation @ R, m.length)
        return out

    @property
    def wall_clock(self) -> bool:
        """True when a robot is driven by the Unix time (:class:`kmea.sim.motion.WallClock`):
        frames are then rendered and stamped at the Unix time they are read."""
        return any(isinstance(r.path, WallClock) for r in self.robots)

    def robot_poses(self, t: float) -> dict[str, tuple[float, float, float]]:
        """Robot name -> true (x, y, theta) at ``t`` seconds."""
        out = {}
        for r in self.robots:
            p = r.path.pose(t)
            if p is None:
                raise ValueError(f"robot {r.name!r}: path gives no pose at t = {t} s")
            out[r.name] = (float(p[0]), float(p[1]), float(p[2]))
        return out

    def robot_marker_poses(self, robot: SimRobot,
                           pose: tuple[float, float, float]) -> dict[int, np.ndarray]:
        """True (4, 4) marker2world of ``robot``'s markers (misplacements applied)."""
        x, y, th = pose
        R = rot_z(th)
        out = {}
        for mid, (a, b) in robot.mount().items():
            local = np.array([a, b, 0.0])
            Rm = R
            if mid in self.misplaced:
                off, Roff = self.misplaced[mid]
                local = local + off
                Rm = R @ Roff
            out[mid] = pose_matrix(Rm, np.array([x, y, robot.height]) + R @ local)
        return out

    def robot_specs(self) -> list:
        """The robots as :class:`kmea.robots.poses.RobotSpec` (what the daemon's configuration
        would say)."""
        from kmea.robots.poses import RobotSpec

        return [RobotSpec(r.name, tuple(r.markers), r.height, r.length, r.separation)
                for r in self.robots]

    def floor_rect(self) -> tuple[float, float, float, float]:
        """(xmin, xmax, ymin, ymax) of the printed floor canvas, metres."""
        if self.floor is not None:
            return tuple(float(v) for v in self.floor)  # type: ignore[return-value]
        if self.world_map.name.startswith("RobotAtFactory"):
            return (-0.85, 0.85, -0.6, 0.6)
        x0, x1, y0, y1 = self.world_map.floor_extent()
        return (x0 - 0.15, x1 + 0.15, y0 - 0.15, y1 + 0.15)

    def lines(self) -> list[tuple[tuple[float, float], tuple[float, float]]]:
        """Faint floor lines, metres (default: a track joining the marker rows)."""
        if self.floor_lines is not None:
            return list(self.floor_lines)
        x0, x1, y0, y1 = self.floor_rect()
        if self.world_map.name.startswith("RobotAtFactory"):
            rows = [-0.355, -0.15, 0.0, 0.15, 0.355]
            cols = [-0.695, 0.0, 0.695]
            return ([((-0.695, y), (0.695, y)) for y in rows]
                    + [((x, -0.355), (x, 0.355)) for x in cols])
        return [((x0 + 0.05, y), (x1 - 0.05, y)) for y in (y0 + 0.05, y1 - 0.05)]

    def with_(self, **changes: Any) -> Scene:
        """A copy with dataclass fields replaced."""
        return replace(self, **changes)
