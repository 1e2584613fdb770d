"""Camera overlay helpers on a rendered floor: expected markers, focus, thumbnail, drawing."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from kmea.sim.renderer import Renderer
from kmea.sim.scenes import scene_from_spec
from kmea.vision.overlay import (
    OverlayMarker,
    draw_overlay,
    expected_marker_corners,
    focus_measure,
    thumbnail,
)


@pytest.fixture(scope="module")
def rendered():
    scene = scene_from_spec("sim:scenario1?width=640&height=480")
    frame = Renderer(scene).render(0)
    return scene, frame


def test_expected_corners_match_the_true_projection(rendered):
    scene, frame = rendered
    truth = frame.truth
    world_map = scene.effective_map()
    got = expected_marker_corners(truth.cam2world, scene.camera, world_map)
    in_map = {i for i in truth.corners if i in world_map}
    assert in_map and set(got) == in_map
    for mid in in_map:
        np.testing.assert_allclose(got[mid], truth.corners[mid], atol=0.05)
    # Detected markers are left out on request.
    some = sorted(in_map)[:3]
    assert set(expected_marker_corners(truth.cam2world, scene.camera, world_map,
                                       exclude=some)) == in_map - set(some)


def test_expected_corners_follow_the_scale_of_a_similarity(rendered):
    scene, frame = rendered
    T = frame.truth.cam2world.copy()
    # KMEA's cam2world carries a scale: world = s R cam + t. Same camera, same pixels.
    S = T.copy()
    S[:3, :3] *= 1.7
    world_map = scene.effective_map()
    a = expected_marker_corners(T, scene.camera, world_map)
    b = expected_marker_corners(S, scene.camera, world_map)
    assert set(a) == set(b)
    for mid in a:
        np.testing.assert_allclose(a[mid], b[mid], atol=1e-6)


def test_focus_drops_when_the_image_is_blurred(rendered):
    _, frame = rendered
    quads = list(frame.truth.corners.values())
    sharp = focus_measure(frame.image, quads)
    blurred = focus_measure(cv2.GaussianBlur(frame.image, (0, 0), 2.0), quads)
    assert sharp is not None and blurred is not None
    assert blurred < 0.5 * sharp
    assert focus_measure(frame.image, []) is None


def test_thumbnail_keeps_aspect_and_never_enlarges(rendered):
    _, frame = rendered
    th, s = thumbnail(frame.image, 160, 160)
    assert th.shape == (120, 160) and s == pytest.approx(0.25)
    same, s1 = thumbnail(frame.image, 4000, 4000)
    assert same.shape == frame.image.shape and s1 == 1.0


def test_draw_overlay_colours_the_outlines(rendered):
    _, frame = rendered
    (mid, q), (mid2, q2) = list(frame.truth.corners.items())[:2]
    out = draw_overlay(frame.image, [OverlayMarker(mid, q, "detected"),
                                     OverlayMarker(mid2, q2, "expected")], focus=12.0)
    assert out.shape == (*frame.image.shape, 3)
    x, y = np.round(q[0]).astype(int)
    b, g, r = out[y, x]
    assert g > 150 and r < 80 and b < 80  # the detected marker's corner dot is green
    assert frame.image.ndim == 2  # the input is left alone
