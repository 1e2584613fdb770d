"""The ROS 2 messages kmead publishes, serialized by ``rosbags`` (CDR, REP-2011 type hashes).

- ``geometry_msgs/msg/PoseWithCovarianceStamped`` per robot: ``header.stamp`` the pose's
  time (the frame's capture instant, or the send time when ``filter.predict`` predicts to
  it), the position on the floor (z = 0) and the heading as a quaternion about z, and the
  6x6 covariance (row-major x, y, z, rot x, rot y, rot z; m^2, m rad, rad^2).
- ``tf2_msgs/msg/TFMessage`` with one transform, ``frame_id`` -> ``<robot>/kmea``.

The covariance is the tracking filter's (3, 3) covariance of (x, y, theta) where there is
one; with the IIR filter it is built from the pose's 1-sigma (isotropic in x, y; heading
sigma = sigma / the tracking filter's heading lever). z, roll and pitch are not estimated
(a robot on the floor): they get :data:`UNESTIMATED_VARIANCE`, large, so a fusion filter
ignores them instead of trusting a zero. Never zeros on the estimated axes either: each
variance is floored at the tracking filter's ``min_sigma`` / ``min_sigma_theta``.

Needs the optional extra (``pip install 'kmea[zenoh]'``).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from rosbags.typesys import Stores, get_typestore

from kmea.robots.tracking.config import TrackerConfig

POSE_TYPE = "geometry_msgs/msg/PoseWithCovarianceStamped"
TF_TYPE = "tf2_msgs/msg/TFMessage"
UNESTIMATED_VARIANCE = 1e6  # m^2 (z), rad^2 (roll, pitch): not estimated
_TRACKING = TrackerConfig()

# Jazzy's definitions: the two types and their hashes are the same in Kilted (a test
# checks both stores).
_TS = get_typestore(Stores.ROS2_JAZZY)
_T = _TS.types
Header, Time = _T["std_msgs/msg/Header"], _T["builtin_interfaces/msg/Time"]
Point, Quaternion, Pose = (_T["geometry_msgs/msg/Point"], _T["geometry_msgs/msg/Quaternion"],
                           _T["geometry_msgs/msg/Pose"])
PoseWithCovariance = _T["geometry_msgs/msg/PoseWithCovariance"]
PoseWithCovarianceStamped = _T[POSE_TYPE]
Vector3, Transform = _T["geometry_msgs/msg/Vector3"], _T["geometry_msgs/msg/Transform"]
TransformStamped, TFMessage = _T["geometry_msgs/msg/TransformStamped"], _T[TF_TYPE]


def type_hash(ros_type: str) -> str:
    """The REP-2011 ``RIHS01_...`` hash of a message type."""
    return _TS.hash_rihs01(ros_type)


def stamp(t: float) -> Any:  # the typestore's message class: no static type
    """builtin_interfaces/Time of ``t`` (s since the epoch): whole seconds and nanoseconds.
    The seconds are split off first: ``t * 1e9`` of an epoch time is past a double's 53 bits
    and would be off by up to 256 ns."""
    sec = math.floor(t)
    ns = round((t - sec) * 1e9)
    if ns >= 1_000_000_000:
        sec, ns = sec + 1, ns - 1_000_000_000
    return Time(sec=int(sec), nanosec=int(ns))


def covariance3(sigma: float | None, cov3: np.ndarray | None) -> list[list[float]]:
    """The (x, y, theta) covariance kmead reports: the filter's, symmetrised, else from
    ``sigma``; variances floored (module docstring). Plain floats: numpy's per-call
    overhead on 3x3 arrays was 0.2 ms a robot on a loaded Pi-class core."""
    c = cov3.tolist() if cov3 is not None else None
    if c is None or not all(math.isfinite(v) for row in c for v in row):
        s = sigma if sigma is not None and math.isfinite(sigma) else _TRACKING.default_sigma
        c = [[s * s, 0.0, 0.0], [0.0, s * s, 0.0], [0.0, 0.0, (s / _TRACKING.heading_lever) ** 2]]
    out = [[0.5 * (c[i][j] + c[j][i]) for j in range(3)] for i in range(3)]
    floors = (_TRACKING.min_sigma ** 2, _TRACKING.min_sigma ** 2,
              _TRACKING.min_sigma_theta ** 2)
    for i in range(3):
        out[i][i] = max(out[i][i], floors[i])
    return out


def covariance6(c3: list[list[float]]) -> np.ndarray:
    """The 36-entry ROS covariance (row-major x, y, z, rot x, rot y, rot z) of
    :func:`covariance3`'s block; z, roll, pitch :data:`UNESTIMATED_VARIANCE`."""
    out = [0.0] * 36
    for i in (2, 3, 4):
        out[i * 7] = UNESTIMATED_VARIANCE
    ix = (0, 1, 5)  # x, y, rot z
    for a in range(3):
        for b in range(3):
            out[ix[a] * 6 + ix[b]] = c3[a][b]
    return np.array(out)


def _quaternion(theta: float) -> Any:
    return Quaternion(x=0.0, y=0.0, z=math.sin(theta / 2), w=math.cos(theta / 2))


def pose_cdr(t: float, frame_id: str, x: float, y: float, theta: float,
             cov6: np.ndarray) -> bytes:
    """PoseWithCovarianceStamped as CDR, with its 4-byte encapsulation header; ``cov6``
    from :func:`covariance6`."""
    msg = PoseWithCovarianceStamped(
        header=Header(stamp=stamp(t), frame_id=frame_id),
        pose=PoseWithCovariance(pose=Pose(position=Point(x=x, y=y, z=0.0),
                                          orientation=_quaternion(theta)),
                                covariance=cov6))
    return bytes(_TS.serialize_cdr(msg, POSE_TYPE))


def tf_cdr(t: float, frame_id: str, child: str, x: float, y: float, theta: float) -> bytes:
    """TFMessage with the one transform ``frame_id`` -> ``child`` as CDR."""
    tr = TransformStamped(header=Header(stamp=stamp(t), frame_id=frame_id),
                          child_frame_id=child,
                          transform=Transform(translation=Vector3(x=x, y=y, z=0.0),
                                              rotation=_quaternion(theta)))
    return bytes(_TS.serialize_cdr(TFMessage(transforms=[tr]), TF_TYPE))


def decode(data: bytes, ros_type: str) -> object:
    """A CDR message back into a rosbags object (tests, the check script)."""
    return _TS.deserialize_cdr(data, ros_type)
