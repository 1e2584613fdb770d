"""Compatibility name for the frame helpers, which live in :mod:`kmea.geometry`.

Kept only so that code written against ``kmea.transforms`` (the daemon's pipeline until it
moves into the library) keeps importing; new code imports :mod:`kmea.geometry`. Nothing is
defined here.
"""

from kmea.geometry import (
    check_rotation,
    euler_zyx_fixed_deg,
    make_transform,
    marker_corners_local,
    rot_x,
    rot_y,
    rot_z,
    rotvec_to_matrix,
    wrap_angle,
    yaw_of,
)

__all__ = [
    "check_rotation",
    "euler_zyx_fixed_deg",
    "make_transform",
    "marker_corners_local",
    "rot_x",
    "rot_y",
    "rot_z",
    "rotvec_to_matrix",
    "wrap_angle",
    "yaw_of",
]
