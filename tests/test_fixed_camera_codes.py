"""A marker's code read at known corners (kmea.fixed_camera.codes), on rendered frames."""

from __future__ import annotations

import numpy as np

from kmea.fixed_camera import code_scores, marker_codes
from kmea.vision.detection import DetectorConfig, MarkerDetector


def test_code_scores_tell_a_marker_from_its_absence(default_frames):
    frames, src = default_frames
    d = MarkerDetector(DetectorConfig(src.world_map.dictionary)).detect(frames[0].image)
    codes = marker_codes(MarkerDetector(DetectorConfig(src.world_map.dictionary)).dictionary,
                         d.ids.tolist())
    own = code_scores(frames[0].image, d.corners, np.stack([codes[m] for m in d.ids.tolist()]))
    assert own.min() > 0.6  # FixedCameraConfig.min_score
    # The same places with another marker's code, and a blank frame, do not pass.
    wrong = code_scores(frames[0].image, d.corners,
                        np.stack([codes[m] for m in np.roll(d.ids, 1).tolist()]))
    assert np.median(wrong) < 0.5
    blank = code_scores(np.full_like(frames[0].image, 128), d.corners,
                        np.stack([codes[m] for m in d.ids.tolist()]))
    assert np.all(blank == 0.0)
    # The samples are bilinear: the same scores as a plain numpy bilinear interpolation at
    # the same points (OpenCV's remap weighs in 1/32 px steps and rounds to gray levels).
    from kmea.fixed_camera.codes import CodeSampler, _homographies

    gray = frames[0].image if frames[0].image.ndim == 2 else frames[0].image[..., 1]
    gray = np.ascontiguousarray(gray)
    m = codes[d.ids[0]].shape[0]
    grid = CodeSampler._grids[m]
    proj = _homographies(d.corners, m) @ grid.T
    x, y = proj[:, 0] / proj[:, 2], proj[:, 1] / proj[:, 2]
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    g = gray.astype(float)
    v = (g[y0, x0] * (1 - fx) * (1 - fy) + g[y0, x0 + 1] * fx * (1 - fy)
         + g[y0 + 1, x0] * (1 - fx) * fy + g[y0 + 1, x0 + 1] * fx * fy)
    vals = v.reshape(len(x), m * m, 4).mean(axis=2)
    vals -= vals.mean(axis=1, keepdims=True)
    ref = np.stack([codes[i] for i in d.ids.tolist()]).reshape(len(x), -1).astype(float)
    ref -= ref.mean(axis=1, keepdims=True)
    plain = (vals * ref).sum(1) / np.sqrt((vals ** 2).sum(1) * (ref ** 2).sum(1))
    np.testing.assert_allclose(code_scores(gray, d.corners, np.stack(
        [codes[i] for i in d.ids.tolist()])), plain, rtol=0, atol=3e-3)


def test_code_sampler_homographies_are_opencvs_and_a_degenerate_quad_spoils_only_itself():
    """The closed-form square-to-quad homographies equal ``cv2.getPerspectiveTransform``;
    a degenerate quad (corners on a line) scores 0 without zeroing the other quads' scores
    (a batched linear solve used to fail for all of them)."""
    import cv2

    from kmea.fixed_camera.codes import CodeSampler, _homographies

    rng = np.random.default_rng(7)
    quads = (np.array([[0, 0], [40, 2], [42, 41], [-1, 39]], float)[None]
             + rng.uniform(0, 500, (20, 1, 2)) + rng.normal(0, 3, (20, 4, 2)))
    H = _homographies(quads, 7)
    src = np.float32([[0, 0], [7, 0], [7, 7], [0, 7]])
    for q, h in zip(quads, H, strict=True):
        ref = cv2.getPerspectiveTransform(src, q.astype(np.float32))
        np.testing.assert_allclose(h / h[2, 2], ref / ref[2, 2], rtol=1e-4, atol=1e-4)
    gray = np.zeros((200, 200), np.uint8)
    code = marker_codes(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_5X5_50), [3])[3]
    side, x0, y0 = 70, 100, 60
    small = cv2.resize(code.astype(np.uint8) * 255, (side, side),
                       interpolation=cv2.INTER_NEAREST)
    gray[y0:y0 + side, x0:x0 + side] = small
    good = np.array([[x0, y0], [x0 + side, y0], [x0 + side, y0 + side], [x0, y0 + side]],
                    float) - 0.5
    flat = np.array([[5.0, 5.0], [10.0, 5.0], [15.0, 5.0], [20.0, 5.0]])
    s = CodeSampler(np.stack([flat, good]), np.stack([code, code]), gray.shape)
    scores = s.scores(gray)
    assert scores[0] == 0.0 and scores[1] > 0.95, scores
