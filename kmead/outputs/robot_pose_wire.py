"""The compact binary robot pose on ``<site>/robots/<robot>/pose``, for robots without ROS.

56 bytes, little-endian, fixed (``examples/kmea_pose.h`` decodes it in C; docs/ros2.md
gives the C struct)::

    offset size  field
     0     1     version        uint8   = 1
     1     1     valid          uint8   1 = a fix; 0 = stale, removed, or kmead stopping
     2     2     flags          uint16  bit 0 PREDICTED: t is the send time (filter.predict)
                                        bit 1 TRACKED: the tracking filter's covariance
                                        bit 2 STOPPING: kmead stops (with valid = 0)
     4     4     seq            uint32  this robot's message count (the UDP datagram's seq)
     8     8     t              float64 s since the epoch: the time the pose refers to
    16     4     x              float32 m, world frame
    20     4     y              float32 m
    24     4     theta          float32 rad in [-pi, pi)
    28     4     sigma_x        float32 m, 1-sigma
    32     4     sigma_y        float32 m
    36     4     sigma_theta    float32 rad
    40     4     vx             float32 m/s, world (0 when unknown)
    44     4     vy             float32 m/s
    48     4     omega          float32 rad/s
    52     4     age            float32 s from the newest measurement to t

A valid = 0 message repeats the last known pose (0 if never seen), as the datagram does.
Reading a message of another size or version is refused (:func:`unpack_pose`).
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

VERSION = 1
PREDICTED, TRACKED, STOPPING = 1, 2, 4
POSE = struct.Struct("<BBHId10f")
assert POSE.size == 56


@dataclass(frozen=True)
class BinaryPose:
    valid: bool
    flags: int
    seq: int
    t: float
    x: float
    y: float
    theta: float
    sigma_x: float
    sigma_y: float
    sigma_theta: float
    vx: float = 0.0
    vy: float = 0.0
    omega: float = 0.0
    age: float = 0.0


def _f(v: float | None) -> float:
    return v if v is not None and math.isfinite(v) else 0.0


def pack_pose(p: BinaryPose) -> bytes:
    return POSE.pack(VERSION, int(p.valid), p.flags, p.seq & 0xFFFFFFFF, _f(p.t), _f(p.x),
                     _f(p.y), _f(p.theta), _f(p.sigma_x), _f(p.sigma_y), _f(p.sigma_theta),
                     _f(p.vx), _f(p.vy), _f(p.omega), _f(p.age))


def unpack_pose(data: bytes) -> BinaryPose:
    """ValueError for anything that is not one version-1 pose (network input)."""
    if len(data) != POSE.size:
        raise ValueError(f"binary pose of {len(data)} bytes, expected {POSE.size}")
    version, valid, flags, *rest = POSE.unpack(data)
    if version != VERSION or valid not in (0, 1):
        raise ValueError(f"binary pose version {version} valid {valid}: not version 1")
    return BinaryPose(bool(valid), flags, *rest)
