"""A floor marker partly hidden by a robot's plate, on the fixed-camera path.

Full detection finds such a marker with the hidden corner pulled by the plate's edge (pixels
off): its pose is off by centimetres and ``estimate_marker_poses`` flags it ``suspect``
(not a reference, no leave-one-out error; the UI's "S"). The fixed-camera path never
reports such a quadrilateral for a floor marker (:mod:`kmea.fixed_camera.detector`):

- a floor marker it tracks is reported at its reference corners (averaged clean full
  detections) while its code reads there (:mod:`kmea.fixed_camera.floor`); a plate over a
  corner does not move them, so the pose is as good as an unhidden marker's and the marker
  is rightly not suspect;
- a floor marker it does not track yet is adopted from a discovery only at a clean look
  (:meth:`FixedCameraDetector.merge`: "wait for a clean look"); until then it is not
  reported at all (the UI: not detected), never as a good marker with pulled corners.

So on ``sim:misplaced?robots=true`` (frame 32: amr2's plate over a corner of marker 25) the
live daemon shows no "S": the UI's recorded stream, which demonstrates the flag, is recorded
on the full-detection path (``scripts/record_telemetry.py``).
"""

from __future__ import annotations

import numpy as np
import pytest
from fixed_camera_helpers import frames_of, tracker

from kmea.pipeline import FrameInput, Pipeline, PipelineSettings
from kmead.config.layers import load_config

SCENE = "sim:misplaced?robots=true"
N = 34
# A clean detection's corners are within ~0.3 px of the truth at 1640x1232 (oblique wall
# markers: ~1.5 px, the detector's own bias); a corner pulled by a plate is pixels off.
CLEAN_PX = 0.5


@pytest.fixture(scope="module")
def runs():
    """Per frame (truth, the live daemon's fixed-camera result, a full-detection result);
    per fixed marker the farthest (px, at least CLEAN_PX) full detection put its
    corners from the truth when nothing hid it; the fixed markers."""
    frames, src = frames_of(SCENE, N, width=1640)
    settings = PipelineSettings.from_config(load_config(None, use_local=False).data, live=True)
    assert settings.fixed_camera
    live = Pipeline(src.camera, src.world_map, settings)
    live.observer.detector.close()
    live.observer.detector = tracker(src)  # discoveries in the calling thread: deterministic
    full = Pipeline(src.camera, src.world_map,
                    PipelineSettings.from_config(load_config(None, use_local=False).data))
    assert not full.settings.fixed_camera
    out = []
    for f in frames:
        inp = FrameInput(f.index, f.timestamp, f.image)
        out.append((f.truth, live.process(inp), full.process(inp)))
    static = set(src.world_map.markers) - {m for r in src.scene.robot_specs()
                                           for m in r.markers}
    # Per fixed marker: how far from the truth full detection puts it when nothing hides it.
    clean: dict[int, float] = {}
    for truth, _, r in out:
        for o in r.observations:
            if o.id in static and o.id in truth.visible and not o.suspect:
                err = float(np.abs(_corners(r, o.id) - truth.corners[o.id]).max())
                clean[o.id] = max(clean.get(o.id, CLEAN_PX), err)
    return out, clean, static


def _corners(r, mid: int) -> np.ndarray | None:
    ids = r.ids.tolist()
    return r.corners[ids.index(mid)] if mid in ids else None


def _suspect(r) -> set[int]:
    return {o.id for o in r.observations if o.suspect}


def test_marker_25_under_the_plate_is_not_a_good_marker_on_the_fixed_camera_path(runs):
    frames, _, _ = runs
    truth, live, full = frames[32]
    assert 25 in _suspect(full)  # what the UI's recorded stream shows
    assert np.abs(_corners(full, 25) - truth.corners[25]).max() > 2.0  # a pulled corner
    # Never looked at cleanly yet: not adopted, so not reported (not a good marker).
    assert 25 not in live.ids.tolist() or 25 in _suspect(live)
    assert 25 not in {o.id for o in live.observations if not o.suspect}


def test_a_suspect_marker_of_full_detection_is_never_reported_with_its_pulled_corners(runs):
    """Every floor marker full detection flags suspect is, on the fixed-camera path,
    suspect too, not reported, or reported at corners as close to the truth as a clean
    detection's (its reference: the pose is right, not suspect)."""
    frames, clean, static = runs
    checked = {}
    for truth, live, full in frames:
        for mid in _suspect(full) & static:
            c = _corners(live, mid)
            if c is None or mid in _suspect(live):
                checked[(live.index, mid)] = "flagged or absent"
                continue
            err = float(np.abs(c - truth.corners[mid]).max())
            assert err <= clean.get(mid, CLEAN_PX), (live.index, mid, err)
            checked[(live.index, mid)] = f"reference {err:.2f} px"
    # The scene's cases: 26 and 0 hidden at the start, 3 and 25 under amr2's plate.
    assert {(31, 3), (31, 25), (32, 25)} <= checked.keys(), checked
    assert checked[(31, 3)].startswith("reference")


def test_every_good_floor_marker_of_the_fixed_camera_path_has_clean_corners(runs):
    """The fixed-camera path's fixed markers that are not suspect are where a clean
    detection puts them, also while a plate covers part of one (3 and 24 here)."""
    frames, clean, _ = runs
    partly_hidden = set()
    for truth, live, _ in frames:
        good = {o.id for o in live.observations if not o.suspect} & clean.keys()
        for mid in good:
            err = float(np.abs(_corners(live, mid) - truth.corners[mid]).max())
            assert err <= clean[mid], (live.index, mid, err)
            if mid not in truth.visible:
                partly_hidden.add(mid)
    assert {3, 24} <= partly_hidden
