"""Discoveries (kmea.fixed_camera.discovery): full detections for markers new to the view."""

from __future__ import annotations

from fixed_camera_helpers import (
    frames_of,
)
from fixed_camera_helpers import tracker as make_tracker


def test_marker_entering_the_view_is_reported_within_0_3_s():
    fps = 30.0
    frames, src = frames_of("sim:default?enter_at=0.6", 60)
    tracker = make_tracker(src)
    first_visible = first_reported = None
    for f in frames:
        ids = tracker.detect(f.image).ids.tolist()
        if first_visible is None and 43 in f.truth.visible:
            first_visible = f.index
        if first_reported is None and 43 in ids:
            first_reported = f.index
    assert first_visible is not None, "the entering robot never became visible"
    assert first_reported is not None, "the entering marker was never reported"
    assert (first_reported - first_visible) / fps <= 0.3, (first_visible, first_reported)
