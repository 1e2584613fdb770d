"""Robot poses from one marker or a pair, by hand and through a full KMEA estimate."""

from __future__ import annotations

import math

import numpy as np
import pytest

from kmea.estimators import MarkerObservation, get
from kmea.estimators.base import MarkerEstimate
from kmea.geometry import rot_x, rot_z
from kmea.maps.files import default_map
from kmea.robots.poses import RobotSpec, robot_pose


def me(mid: int, x: float, y: float, z: float = 0.2, yaw: float = 0.0,
       sigma: float | None = None) -> MarkerEstimate:
    return MarkerEstimate(mid, np.array([x, y, z]), rot_z(yaw), yaw, sigma)


def pair_markers(x: float, y: float, theta: float, d: float = 0.05, z: float = 0.2):
    """World estimates of a pair (left 40, right 41) on a robot at (x, y, theta)."""
    left = np.array([x, y]) + d * np.array([-math.sin(theta), math.cos(theta)])
    right = np.array([x, y]) - d * np.array([-math.sin(theta), math.cos(theta)])
    return {40: me(40, *left, z=z, yaw=theta), 41: me(41, *right, z=z, yaw=theta)}


AMR1 = RobotSpec("amr1", (40, 41), height=0.2, separation=0.10)
AMR2 = RobotSpec("amr2", (42,))


def test_single_marker_robot() -> None:
    pose = robot_pose(AMR2, {42: me(42, 0.3, -0.1, 0.21, yaw=2.0, sigma=0.004), 7: me(7, 0, 0)})
    assert (pose.name, pose.x, pose.y, pose.z, pose.theta) == ("amr2", 0.3, -0.1, 0.21, 2.0)
    assert pose.markers_seen == (42,) and pose.sigma == 0.004
    assert robot_pose(AMR2, {7: me(7, 0, 0)}) is None


def test_pair_convention_by_hand() -> None:
    # The brief's example: left at (0, +0.05), right at (0, -0.05): right - left = (0, -0.1),
    # rotated +90 deg CCW -> (0.1, 0): theta = 0, the robot faces +x.
    est = {40: me(40, 0.0, 0.05), 41: me(41, 0.0, -0.05)}
    pose = robot_pose(AMR1, est)
    assert (pose.x, pose.y, pose.theta) == pytest.approx((0.0, 0.0, 0.0))
    assert pose.markers_seen == (40, 41) and pose.sigma == pytest.approx(0.0)
    # Facing +y: the robot's left is -x. Left (-0.05, 1), right (0.05, 1): right - left =
    # (0.1, 0) -> rotated (0, 0.1): theta = 90 deg. The marker yaws are not used.
    est = {40: me(40, -0.05, 1.0, yaw=1.0), 41: me(41, 0.05, 1.0, yaw=-2.0)}
    pose = robot_pose(AMR1, est)
    assert (pose.x, pose.y, pose.theta) == pytest.approx((0.0, 1.0, math.pi / 2))
    # Markers measured 0.12 m apart instead of 0.10: sigma says 0.02 m.
    est = {40: me(40, 0.0, 0.06), 41: me(41, 0.0, -0.06)}
    assert robot_pose(AMR1, est).sigma == pytest.approx(0.02)


@pytest.mark.parametrize("theta", [0.0, 0.7, -2.5, math.pi - 1e-9])
def test_pair_with_one_marker_seen_uses_the_known_offset(theta: float) -> None:
    est = pair_markers(0.3, -0.2, theta)
    both = robot_pose(AMR1, est)
    assert (both.x, both.y) == pytest.approx((0.3, -0.2), abs=1e-12)
    assert math.remainder(both.theta - theta, 2 * math.pi) == pytest.approx(0.0, abs=1e-12)
    for mid in (40, 41):
        one = robot_pose(AMR1, {mid: est[mid]})
        assert one.markers_seen == (mid,)
        assert (one.x, one.y) == pytest.approx((0.3, -0.2), abs=1e-12)
        assert math.remainder(one.theta - theta, 2 * math.pi) == pytest.approx(0.0, abs=1e-12)
        assert -math.pi <= one.theta < math.pi


def test_robot_pose_through_a_kmea_estimate() -> None:
    """Render exact observations of the floor and of amr1 at (0.25, -0.1, 30 deg) and get the
    pose back through KMEA and robot_pose."""
    m = default_map()
    R = rot_z(0.2) @ rot_x(math.pi + 0.05)  # cam2world: camera looking down from 2 m
    t = np.array([0.0, 0.1, 2.0])
    theta = math.radians(30)
    truth = pair_markers(0.25, -0.1, theta)
    obs = [MarkerObservation(i, R.T @ m[i].rotation, R.T @ (m[i].position - t))
           for i in m.ids if m[i].on_floor]
    obs += [MarkerObservation(i, R.T @ e.rotation, R.T @ (e.position - t))
            for i, e in truth.items()]
    est = get("kmea").estimate(obs, m, plane_heights={40: 0.2, 41: 0.2})
    pose = robot_pose(AMR1, est.markers)
    assert (pose.x, pose.y, pose.z) == pytest.approx((0.25, -0.1, 0.2), abs=1e-9)
    assert pose.theta == pytest.approx(theta, abs=1e-9)


def test_spec_validation_and_normalisation() -> None:
    s = RobotSpec("r", [40, 41], destinations=["dock", "A"])
    assert s.markers == (40, 41) and s.destinations == ("dock", "A") and s.is_pair
    assert RobotSpec("r", 42).markers == (42,)
    bad = [
        (dict(name="", markers=(1,)), "robot name must be a non-empty string"),
        (dict(name="r", markers=(1, 2, 3)), "markers must be one id or a pair"),
        (dict(name="r", markers=()), "markers must be one id or a pair"),
        (dict(name="r", markers=(5, 5)), "the two markers of a pair must differ"),
        (dict(name="r", markers=(True,)), "marker id must be an integer >= 0"),
        (dict(name="r", markers=(-1,)), "marker id must be an integer >= 0"),
        (dict(name="r", markers=(1,), height=-0.1), "height must be a finite number >= 0"),
        (dict(name="r", markers=(1,), length=0.0), "length must be a finite number > 0"),
        (dict(name="r", markers=(1,), separation=math.nan), "separation must be a finite"),
        (dict(name="r", markers=(1, 2), separation=0.05), "the markers would overlap"),
        (dict(name="r", markers=(1,), destinations=("a", 3)), "destinations must be a list"),
    ]
    for kwargs, msg in bad:
        with pytest.raises(ValueError, match=msg):
            RobotSpec(**kwargs)


def test_pair_sigma_propagates_marker_sigmas_when_larger_than_consistency() -> None:
    # Markers exactly 0.10 m apart (consistency 0) with 3 mm and 4 mm sigmas:
    # the midpoint's sigma is hypot(3, 4) / 2 = 2.5 mm.
    est = {40: me(40, 0.0, 0.05, 0.2, sigma=0.003), 41: me(41, 0.0, -0.05, 0.2, sigma=0.004)}
    assert robot_pose(AMR1, est).sigma == pytest.approx(0.0025)
    # 0.12 m apart: the 20 mm inconsistency dominates.
    est = {40: me(40, 0.0, 0.06, 0.2, sigma=0.003), 41: me(41, 0.0, -0.06, 0.2, sigma=0.004)}
    assert robot_pose(AMR1, est).sigma == pytest.approx(0.02)
