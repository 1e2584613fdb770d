"""The geometry kernel: rotations, rigid/similarity transforms, the camera model, ray-plane.

Every other module takes its geometry from here (numpy only):

- :mod:`kmea.geometry.rotations`: elementary rotations, Rodrigues both ways (batched),
  projection onto SO(3), Kabsch, yaw and angle wrapping.
- :mod:`kmea.geometry.frames`: homogeneous transforms and the marker's corner model.
- :mod:`kmea.geometry.camera`: OpenCV's projection and distortion model, its Jacobians,
  undistortion (the estimators' and the simulator's lens).
- :mod:`kmea.geometry.planes`: ray-plane intersection.

Units: metres and radians; frames are named ``a2b`` (``R_a2b @ p_a = p_b``); the camera frame
is OpenCV's (x right, y down, z forward).
"""

from kmea.geometry.camera import (
    check_camera_matrix,
    check_distortion,
    distort,
    distort_jacobian,
    distort_jacobian_entries,
    distort_xy,
    project,
    project_jac_pc,
    project_world,
    rotation_increment_jacobian,
    undistort,
)
from kmea.geometry.frames import (
    check_transform,
    invert_transform,
    make_transform,
    marker_corners_local,
)
from kmea.geometry.planes import (
    intersect_ray_height,
    intersect_rays_planes,
    ray_plane_parameter,
    unit_rays_plane_depth,
)
from kmea.geometry.rotations import (
    check_rotation,
    check_rotvecs,
    euler_zyx_fixed_deg,
    kabsch,
    matrices_to_rotvecs,
    project_to_so3,
    rot_x,
    rot_y,
    rot_z,
    rotvec_to_matrix,
    rotvecs_to_matrices,
    skew,
    wrap_angle,
    yaw_of,
)

__all__ = [
    "check_camera_matrix",
    "check_distortion",
    "check_rotation",
    "check_rotvecs",
    "check_transform",
    "distort",
    "distort_jacobian",
    "distort_jacobian_entries",
    "distort_xy",
    "euler_zyx_fixed_deg",
    "intersect_ray_height",
    "intersect_rays_planes",
    "invert_transform",
    "kabsch",
    "make_transform",
    "marker_corners_local",
    "matrices_to_rotvecs",
    "project",
    "project_jac_pc",
    "project_to_so3",
    "project_world",
    "ray_plane_parameter",
    "rot_x",
    "rot_y",
    "rot_z",
    "rotation_increment_jacobian",
    "rotvec_to_matrix",
    "rotvecs_to_matrices",
    "skew",
    "undistort",
    "unit_rays_plane_depth",
    "wrap_angle",
    "yaw_of",
]
