"""A fixed marker's reference corners averaged over full-resolution looks
(kmea.fixed_camera.tracks.averaged)."""

from __future__ import annotations

import numpy as np

from kmea.fixed_camera.tracks import FixedCameraConfig, Track, averaged


def _square(x: float, y: float, side: float = 40.0) -> np.ndarray:
    return np.array([[x, y], [x + side, y], [x + side, y + side], [x, y + side]], float)


def test_looks_in_place_are_averaged_up_to_the_configured_count() -> None:
    s = FixedCameraConfig(average=4, move_px=1.0)
    rng = np.random.default_rng(3)
    truth = _square(100.0, 50.0)
    looks = [truth + rng.normal(0.0, 0.1, (4, 2)) for _ in range(12)]
    t = Track(looks[0].copy(), np.zeros((4, 2)), True, 0)
    for k, c in enumerate(looks[1:4], start=1):
        t = averaged(t, c, k, s)
    # The first four looks: their plain mean (a running mean, n = 2, 3, 4).
    np.testing.assert_allclose(t.corners, np.mean(looks[:4], axis=0), atol=1e-12)
    assert t.looks == 4 and t.static and t.seen == 3
    for k, c in enumerate(looks[4:], start=4):
        t = averaged(t, c, k, s)
    assert t.looks == 4  # from then on an exponential mean of weight 1/4
    assert np.abs(t.corners - truth).max() < 0.2


def test_a_look_elsewhere_replaces_the_reference_and_the_same_corners_keep_the_track() -> None:
    s = FixedCameraConfig(average=8, move_px=1.0)
    t = Track(_square(10.0, 10.0), np.zeros((4, 2)), True, 0, looks=5)
    moved = _square(12.0, 10.0)  # 2 px > 1.5 move_px: it moved
    n = averaged(t, moved, 7, s)
    assert n is not t and n.looks == 1 and n.seen == 7
    np.testing.assert_array_equal(n.corners, moved)
    assert averaged(t, t.corners.copy(), 8, s) is t  # nothing new: the same track
