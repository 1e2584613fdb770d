"""The batched IPPE-square of kmea.vision.ippe equals cv2.solvePnPGeneric(IPPE_SQUARE).

Both solutions of every marker (rotation, translation, RMS reprojection error) must match
OpenCV's to 1e-9, on projected corners (with and without lens distortion, noisy, nearly
face-on, near the image border) and on corners detected in a rendered 1640x1232 frame; and
estimate_marker_poses must give the same observations as the per-marker OpenCV path.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from kmea.geometry import marker_corners_local, rot_x, rot_y, rot_z
from kmea.vision.camera import CameraModel, pi_camera_v2
from kmea.vision.ippe import ippe_square, solve_pnp_pair
from kmea.vision.marker_pose import estimate_marker_poses

TOL = 1e-9


def opencv_both(corners: np.ndarray, length: float, camera: CameraModel
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """OpenCV's two IPPE_SQUARE solutions, lowest pixel error first."""
    n, rvecs, tvecs, errs = cv2.solvePnPGeneric(
        marker_corners_local(length), corners, camera.camera_matrix, camera.dist_coeffs,
        flags=cv2.SOLVEPNP_IPPE_SQUARE)
    assert n == 2
    R = np.array([cv2.Rodrigues(r)[0] for r in rvecs])
    t = np.asarray(tvecs, float).reshape(2, 3)
    e = np.asarray(errs, float).reshape(2)
    order = [1, 0] if e[1] < e[0] else [0, 1]
    return R[order], t[order], e[order]


def assert_same(corners: np.ndarray, lengths: np.ndarray, camera: CameraModel) -> None:
    got = ippe_square(corners, lengths / 2.0, camera.camera_matrix, camera.dist_coeffs)
    assert got is not None
    R, t, e = got
    for i in range(len(corners)):
        Rc, tc, ec = opencv_both(corners[i], float(lengths[i]), camera)
        np.testing.assert_allclose(R[i], Rc, rtol=0, atol=TOL, err_msg=f"marker {i}: R")
        np.testing.assert_allclose(t[i], tc, rtol=0, atol=TOL, err_msg=f"marker {i}: t")
        np.testing.assert_allclose(e[i], ec, rtol=0, atol=TOL, err_msg=f"marker {i}: error")


def random_markers(rng: np.random.Generator, camera: CameraModel, n: int, max_tilt: float,
                   sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Corners (n, 4, 2) of markers 0.8-1.6 m in front of a camera looking at them, tilted
    by up to ``max_tilt`` rad from face-on, with Gaussian corner noise (px)."""
    corners, lengths = [], []
    while len(corners) < n:
        L = float(rng.choice([0.04, 0.06, 0.1]))
        z = rng.uniform(0.8, 1.6)
        x, y = rng.uniform(-0.45, 0.45) * z, rng.uniform(-0.35, 0.35) * z
        # Face-on = marker z axis towards the camera (rot_x(pi)), then a small tilt.
        R = rot_z(rng.uniform(-np.pi, np.pi)) @ rot_x(np.pi) @ rot_x(
            rng.uniform(-max_tilt, max_tilt)) @ rot_y(rng.uniform(-max_tilt, max_tilt))
        img, _ = cv2.projectPoints(marker_corners_local(L), cv2.Rodrigues(R)[0],
                                   np.array([x, y, z]), camera.camera_matrix,
                                   camera.dist_coeffs)
        c = img.reshape(4, 2) + rng.normal(0.0, sigma, (4, 2))
        if ((c >= 0) & (c < [camera.width, camera.height])).all():
            corners.append(c)
            lengths.append(L)
    return np.array(corners), np.array(lengths)


DISTORTED = pi_camera_v2()
PINHOLE = CameraModel(DISTORTED.camera_matrix.copy(), np.zeros(5), 1640, 1232)
RATIONAL = CameraModel(DISTORTED.camera_matrix.copy(),
                       np.array([0.1, -0.2, 1e-3, -5e-4, 0.05, 0.01, -0.02, 0.01]), 1640, 1232)


@pytest.mark.parametrize("camera", [DISTORTED, PINHOLE, RATIONAL],
                         ids=["pi-camera-v2", "pinhole", "rational-8"])
@pytest.mark.parametrize(("max_tilt", "sigma"), [(0.8, 0.3), (0.05, 0.2), (0.01, 0.05)],
                         ids=["tilted", "nearly-face-on", "face-on-within-0.6deg"])
def test_projected_markers_match_opencv(camera: CameraModel, max_tilt: float,
                                        sigma: float) -> None:
    assert np.any(camera.dist_coeffs) == (camera is not PINHOLE)
    rng = np.random.default_rng(7)
    corners, lengths = random_markers(rng, camera, 60, max_tilt, sigma)
    assert_same(corners, lengths, camera)


def test_rendered_frame_markers_match_opencv() -> None:
    from kmea.sim.renderer import Renderer
    from kmea.sim.scenes import get_scene
    from kmea.vision.detection import DetectorConfig, MarkerDetector

    scene = get_scene("default")
    frame = Renderer(scene).render(0).image
    assert frame.shape[:2] == (1232, 1640)
    det = MarkerDetector(DetectorConfig(scene.effective_map().dictionary)).detect(frame)
    assert len(det.ids) >= 30
    camera = scene.camera
    assert np.any(camera.dist_coeffs)
    corners = np.asarray(det.corners, float).reshape(-1, 4, 2)
    assert_same(corners, np.full(len(corners), 0.06), camera)

    # The whole per-marker stage: same observations as OpenCV marker by marker.
    obs, diag = estimate_marker_poses(det.ids, corners, camera, world_map=scene.effective_map())
    assert len(obs) == len(corners) and not diag.failed_ids
    for o, c in zip(obs, corners, strict=True):
        R2, t2, e2 = solve_pnp_pair(marker_corners_local(o.length), c, camera.camera_matrix,
                                camera.dist_coeffs, False)
        k = 1 if o.flipped else 0
        np.testing.assert_allclose(o.marker2cam_R, R2[k], rtol=0, atol=TOL)
        np.testing.assert_allclose(o.marker2cam_t, t2[k], rtol=0, atol=TOL)
        assert abs(o.reproj_error - e2[k]) < TOL
        np.testing.assert_allclose(o.alt_R, R2[1 - k], rtol=0, atol=TOL)


def test_degenerate_squares_are_left_to_opencv() -> None:
    """Collinear corners give no usable batched pose; estimate_marker_poses then takes
    OpenCV's per-marker answer (IPPE, then SQPnP) exactly as before batching."""
    cam = DISTORTED
    line = np.array([[[100.0, 100.0], [200.0, 100.0], [300.0, 100.0], [400.0, 100.0]]])
    R, t, e = ippe_square(line, np.array([0.03]), cam.camera_matrix, cam.dist_coeffs)
    assert not (np.isfinite(R).all() and np.isfinite(t).all() and np.isfinite(e).all()
                and e[0, 0] < 1.0)
    obs, diag = estimate_marker_poses([5], line, cam)
    ref = solve_pnp_pair(marker_corners_local(0.06), line[0], cam.camera_matrix,
                     cam.dist_coeffs, False)
    if ref is None:
        assert obs == [] and diag.failed_ids == [5]
    else:
        assert len(obs) == 1 and not diag.failed_ids
        np.testing.assert_allclose(obs[0].marker2cam_t, ref[1][0], rtol=0, atol=TOL)
        assert obs[0].reproj_error == pytest.approx(ref[2][0], abs=TOL)


def test_tilted_sensor_model_is_not_batched() -> None:
    d = np.zeros(14)
    d[12] = 0.01
    assert ippe_square(np.zeros((1, 4, 2)), np.array([0.03]), DISTORTED.camera_matrix, d) is None


def test_a_few_markers_take_opencv_per_marker_with_the_same_result(monkeypatch) -> None:
    """Up to SMALL_N markers (a fixed camera's tracked robots) are posed by OpenCV marker by
    marker, not by the batched replica: the same observations as in the whole frame."""
    from kmea.sim.renderer import Renderer
    from kmea.sim.scenes import get_scene
    from kmea.vision import marker_pose
    from kmea.vision.detection import DetectorConfig, MarkerDetector

    scene = get_scene("default")
    wmap = scene.effective_map()
    det = MarkerDetector(DetectorConfig(wmap.dictionary)).detect(Renderer(scene).render(3).image)
    corners = np.asarray(det.corners, float).reshape(-1, 4, 2)
    assert len(det.ids) > marker_pose.SMALL_N
    whole, diag = estimate_marker_poses(det.ids, corners, scene.camera, world_map=wmap)
    by_id = {o.id: o for o in whole}
    ids = det.ids.tolist()
    pick = [k for k, m in enumerate(ids) if m in (40, 41, 42)]
    pick += [k for k, m in enumerate(ids) if m in (13, 16)]  # two floor markers
    assert 3 <= len(pick) <= marker_pose.SMALL_N

    def no_batch(*a, **k):
        raise AssertionError("the batched replica was used for a few markers")

    monkeypatch.setattr(marker_pose, "ippe_square", no_batch)
    few, _ = estimate_marker_poses(det.ids[pick], corners[pick], scene.camera, world_map=wmap,
                                   world2cam_R=diag.world2cam_R)
    assert [o.id for o in few] == det.ids[pick].tolist()
    for o in few:
        w = by_id[o.id]
        np.testing.assert_allclose(o.marker2cam_R, w.marker2cam_R, rtol=0, atol=TOL)
        np.testing.assert_allclose(o.marker2cam_t, w.marker2cam_t, rtol=0, atol=TOL)
        np.testing.assert_allclose(o.alt_t, w.alt_t, rtol=0, atol=TOL)
        assert abs(o.reproj_error - w.reproj_error) < TOL
        assert (o.flipped, o.ambiguous, o.suspect) == (w.flipped, w.ambiguous, w.suspect)
