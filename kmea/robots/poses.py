"""Robot poses from the world poses of the markers they carry, numpy only.

Conventions (shared by the simulator, the daemon and the configuration): a robot carries one
marker or a pair, flat on a top plate ``height`` m above the floor, each marker's x axis
pointing to the robot's forward.

- Single marker: robot (x, y) = marker centre, theta = marker yaw.
- Pair ``markers = (left, right)``, left/right as seen by the robot looking forward, mounted
  at (0, +d) and (0, -d) in the robot frame with d = separation / 2: (x, y) = midpoint and
  theta = heading of (right - left) rotated +90 deg CCW. Forward is therefore the side
  from which the left marker is on the left: e.g. left at (0, 0.05), right at (0, -0.05)
  gives right - left = (0, -0.1), rotated +90 deg -> (0.1, 0): theta = 0, facing +x.
- Pair with one marker seen: that marker's position and yaw, with the known offset d to the
  side: centre = left - d * (-sin theta, cos theta) or right + d * (-sin theta, cos theta).

Time (a rolling shutter sees each marker at its own rows' instant, :mod:`kmea.timing`): a
robot's measurement is at the mean of its markers' times. A pair seen in different rows
is two looks at two instants: the midpoint of the two positions is the robot's centre at
the mean time whatever the velocity (for a motion straight over that millisecond or two),
but the vector between them has the robot's travel in it (at 1.5 m/s, 1 ms between the
rows is 1.5 mm over the 0.10 m separation: 0.9 deg of heading). Given the robot's motion
(the tracking filter's velocity and turn rate at that time), each marker is moved to the
mean time before the heading is taken; without it (first fix, IIR filter) it is not.

A single marker is itself seen over its rows: a square moving at v is drawn as a
parallelogram (a point p of it is seen dt = g . (p - centre) later, g the marker's row time
gradient, s/m), whose fitted yaw is off by half the shear, (v_y g_x - v_x g_y) / 2: at
1.5 m/s across the rows of an 820x616 IMX219 frame, 0.96 deg. Given the motion and g
(``rates``), that is taken off the marker's yaw. Its centre is seen at its mean time and
needs nothing.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from kmea.estimators.base import MarkerEstimate
from kmea.geometry import wrap_angle

__all__ = ["ROBOT_DEFAULTS", "RobotPose", "RobotSpec", "check_robot_spec", "robot_from_table",
           "robot_pose", "robot_time", "skew_yaw"]


# What a robot table may leave out (m). One place: the daemon's configuration, the
# simulator and the library read these.
ROBOT_DEFAULTS = {"height": 0.0, "length": 0.06, "separation": 0.10}

_NAME_RE = re.compile(r"^[A-Za-z0-9_-]+$")


@dataclass(frozen=True)
class RobotSpec:
    """A robot and its markers.

    name: unique name; markers: (id,) or (left, right); height: marker plane above the floor,
    m (default 0.0: on the floor; give a robot's real plate height); length: marker side, m;
    separation: centre-to-centre distance of a pair (2 d), m; destinations: where the
    daemon's relay sends its pose, ``"udp:HOST:PORT"`` (checked by the daemon's
    configuration, not here). Lists are accepted and stored as tuples;
    ``check_robot_spec`` runs on creation. The defaults are :data:`ROBOT_DEFAULTS`.
    """

    name: str
    markers: tuple[int, ...]
    height: float = 0.0
    length: float = 0.06
    separation: float = 0.10
    destinations: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if isinstance(self.markers, (int, np.integer)) and not isinstance(self.markers, bool):
            object.__setattr__(self, "markers", (int(self.markers),))
        elif isinstance(self.markers, (list, np.ndarray)):
            object.__setattr__(self, "markers", tuple(int(m) for m in self.markers))
        if isinstance(self.destinations, list):
            object.__setattr__(self, "destinations", tuple(self.destinations))
        check_robot_spec(self)

    @property
    def is_pair(self) -> bool:
        return len(self.markers) == 2


def _finite(v: object, where: str, positive: bool = False) -> None:
    if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v) or (
            positive and v <= 0) or (not positive and v < 0):
        raise ValueError(f"{where} must be a finite number {'> 0' if positive else '>= 0'} m, "
                         f"got {v!r}")


def check_robot_spec(spec: RobotSpec) -> RobotSpec:
    """Raise ``ValueError`` naming the robot and field when ``spec`` is inconsistent."""
    name = spec.name
    if not isinstance(name, str) or not name.strip():
        raise ValueError(f"robot name must be a non-empty string, got {name!r}")
    where = f"robot {name!r}"
    ms = spec.markers
    if not isinstance(ms, tuple) or len(ms) not in (1, 2):
        raise ValueError(f"{where}: markers must be one id or a pair [left, right], got {ms!r}")
    for m in ms:
        if isinstance(m, bool) or not isinstance(m, (int, np.integer)) or m < 0:
            raise ValueError(f"{where}: marker id must be an integer >= 0, got {m!r}")
    if len(ms) == 2 and ms[0] == ms[1]:
        raise ValueError(f"{where}: the two markers of a pair must differ, got {list(ms)}")
    _finite(spec.height, f"{where}: height")
    _finite(spec.length, f"{where}: length", positive=True)
    _finite(spec.separation, f"{where}: separation", positive=True)
    if len(ms) == 2 and spec.separation < spec.length:
        raise ValueError(f"{where}: separation {spec.separation} m is less than the marker "
                         f"length {spec.length} m (the markers would overlap)")
    if not isinstance(spec.destinations, tuple) or not all(
            isinstance(d, str) for d in spec.destinations):
        raise ValueError(f"{where}: destinations must be a list of names")
    return spec


def robot_from_table(row: Mapping, where: str = "robot") -> RobotSpec:
    """A :class:`RobotSpec` from a configuration table (``name``, ``markers`` = one id or
    ``[left, right]``, optional ``height``, ``length``, ``separation`` in m; other keys are
    the caller's). ``ValueError`` whose message starts with ``where`` and the field.

    The name goes into datagrams and topics: letters, digits, ``_`` and ``-`` only.
    """
    for k in ("name", "markers"):
        if k not in row:
            raise ValueError(f"{where}: missing key {k!r}")
    name = row["name"]
    if not isinstance(name, str) or not _NAME_RE.match(name):
        raise ValueError(f"{where}.name: use letters, digits, '_' or '-' (it goes in "
                         f"datagrams and topics), got {name!r}")
    markers = row["markers"]
    if isinstance(markers, int) and not isinstance(markers, bool):
        markers = [markers]
    if (not isinstance(markers, list) or len(markers) not in (1, 2)
            or any(isinstance(m, bool) or not isinstance(m, int) or m < 0 for m in markers)):
        raise ValueError(f"{where}.markers: expected one marker id or a pair [left, right], "
                         f"got {row['markers']!r}")
    if len(markers) == 2 and markers[0] == markers[1]:
        raise ValueError(f"{where}.markers: the pair needs two different ids, got {markers}")
    values = {}
    for key, default in ROBOT_DEFAULTS.items():
        v = row.get(key, default)
        positive = key != "height"
        ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
        if not ok or (positive and v <= 0) or (not positive and v < 0):
            raise ValueError(f"{where}.{key}: must be a finite number "
                             f"{'> 0' if positive else '>= 0'} m, got {v!r}")
        values[key] = float(v)
    if len(markers) == 2 and values["separation"] < values["length"]:
        raise ValueError(f"{where}.separation: {values['separation']} m is less than the marker "
                         f"length {values['length']} m (the two markers would overlap)")
    return RobotSpec(name, tuple(markers), **values)


@dataclass(frozen=True)
class RobotPose:
    """World pose of a robot.

    x, y: floor position of its centre (m); theta: heading (rad, CCW from world x, in
    [-pi, pi)); z: estimated height of its marker plane (m); markers_seen: ids used;
    sigma: 1-sigma position uncertainty (m) or None: for one marker, that marker's own sigma
    (from estimators that give one, e.g. corner-pnp); for a pair seen whole, the larger of
    the midpoint's propagated sigma hypot(sigma_l, sigma_r) / 2 (when both markers have one)
    and the pair's consistency |measured separation - spec separation|. t: the instant the
    pose stands for (s; the mean of its markers' times), or None when they were not given.
    """

    name: str
    x: float
    y: float
    theta: float
    z: float
    markers_seen: tuple[int, ...]
    sigma: float | None = None
    t: float | None = None


def _left_dir(theta: float) -> np.ndarray:
    return np.array([-math.sin(theta), math.cos(theta)])


def robot_time(spec: RobotSpec, seen: tuple[int, ...],
               times: Mapping[int, float] | None) -> float | None:
    """The instant a measurement from markers ``seen`` stands for: their times' mean (s)."""
    if not times or any(m not in times for m in seen):
        return None
    return float(sum(times[m] for m in seen) / len(seen))


def skew_yaw(yaw: float, rate_local: tuple[float, float], v: tuple[float, float]) -> float:
    """The yaw error (rad) of a marker at ``yaw`` moving at ``v`` (world m/s) whose points
    are seen later by ``rate_local`` (s/m along its own x and y axes): half the shear of the
    parallelogram it is drawn as (module docstring)."""
    c, s = math.cos(yaw), math.sin(yaw)
    gx = c * rate_local[0] - s * rate_local[1]
    gy = s * rate_local[0] + c * rate_local[1]
    return 0.5 * (v[1] * gx - v[0] * gy)


def robot_pose(spec: RobotSpec, estimates: Mapping[int, MarkerEstimate],
               times: Mapping[int, float] | None = None,
               motion: tuple[float, float, float] | None = None,
               rates: Mapping[int, tuple[float, float]] | None = None) -> RobotPose | None:
    """Pose of ``spec``'s robot from marker world estimates (id -> MarkerEstimate), or None
    when none of its markers was estimated.

    times: marker id -> the instant it was seen (s); the pose's ``t`` is their mean.
    motion: (vx, vy, omega) (m/s, rad/s) of the robot near that time: a pair seen at two
    instants is brought to the mean one before its heading is taken; rates: marker id ->
    its row time gradient (s/m along its own x, y): a single marker's yaw loses its skew
    (module docstring)."""
    seen = tuple(m for m in spec.markers if m in estimates)
    if not seen:
        return None
    t = robot_time(spec, seen, times)
    if len(seen) == 2:
        pl = np.asarray(estimates[spec.markers[0]].position, dtype=float)
        pr = np.asarray(estimates[spec.markers[1]].position, dtype=float)
        if t is not None and motion is not None and times is not None:
            vx, vy, om = motion
            c = (pl[:2] + pr[:2]) / 2.0
            pl, pr = pl.copy(), pr.copy()
            for p, m in ((pl, spec.markers[0]), (pr, spec.markers[1])):
                dt = t - times[m]
                r = p[:2] - c  # the marker's velocity: the centre's plus omega x r
                p[0] += (vx - om * r[1]) * dt
                p[1] += (vy + om * r[0]) * dt
        v = pr[:2] - pl[:2]
        mid = (pl + pr) / 2.0
        # Heading: (right - left) rotated +90 deg CCW, i.e. (-vy, vx).
        theta = math.atan2(v[0], -v[1])
        sigma = abs(float(np.hypot(*v)) - spec.separation)
        sl = estimates[spec.markers[0]].sigma
        sr = estimates[spec.markers[1]].sigma
        if sl is not None and sr is not None:
            sigma = max(sigma, math.hypot(sl, sr) / 2.0)
        return RobotPose(spec.name, float(mid[0]), float(mid[1]), float(wrap_angle(theta)),
                         float(mid[2]), seen, sigma, t)
    mid_ = seen[0]
    me = estimates[mid_]
    p = np.asarray(me.position, dtype=float)
    theta = float(me.yaw)
    d = spec.separation / 2.0 if spec.is_pair else 0.0
    side = (1.0 if mid_ == spec.markers[0] else -1.0) if spec.is_pair else 0.0
    if motion is not None and rates is not None and mid_ in rates:
        vx, vy, om = motion
        r = side * d * _left_dir(theta)  # the marker from the robot's centre
        theta -= skew_yaw(theta, rates[mid_], (vx - om * r[1], vy + om * r[0]))
    xy = p[:2].copy()
    if spec.is_pair:
        xy -= side * d * _left_dir(theta)
    return RobotPose(spec.name, float(xy[0]), float(xy[1]), float(wrap_angle(theta)),
                     float(p[2]), seen, me.sigma, t)
