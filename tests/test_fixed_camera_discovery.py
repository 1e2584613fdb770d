"""Discoveries (kmea.fixed_camera.discovery): full detections for markers new to the view."""

from __future__ import annotations

import numpy as np
from fixed_camera_helpers import frames_of, static_ids
from fixed_camera_helpers import tracker as make_tracker

from kmea.fixed_camera import FixedCameraConfig, FixedCameraDetector
from kmea.fixed_camera.discovery import DiscoveryJob, Inline, TunedDetectors, discover
from kmea.vision.detection import DetectorConfig, MarkerDetector


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


def test_half_resolution_discovery_uses_one_window_sized_for_the_markers(pi_frames):
    """Discovery at half resolution thresholds with one window (a fifth of the markers'
    side there) and still finds what the full parameters find there."""
    frames, src = pi_frames
    tracker = make_tracker(src)
    used: list[int] = []
    dets = tracker._discovery  # the discoveries' detectors
    orig = dets.window

    def spy(win):
        used.append(win)
        return orig(win)

    dets.window = spy
    for f in frames:
        tracker.detect(f.image)
    assert used and all(3 <= w <= 15 and w % 2 == 1 for w in used), used
    full = MarkerDetector(DetectorConfig(src.world_map.dictionary))
    one = TunedDetectors(DetectorConfig(src.world_map.dictionary)).window(used[0])
    seen = lost = 0
    for f in frames[::3]:
        a = discover(full, f.image, True).ids.tolist()
        b = discover(one, f.image, True).ids.tolist()
        seen += len(a)
        lost += len(set(a) - set(b))
    assert seen >= 100 and lost <= 0.02 * seen, (seen, lost)


def test_a_half_resolution_discovery_gives_full_resolution_corners(pi_frames):
    """Corners found at half resolution are mapped back to full-resolution pixels: within
    the 2 px the merge allows a half-resolution find (it detects the marker again there)."""
    frames, src = pi_frames
    cfg = DetectorConfig(src.world_map.dictionary)
    dets = TunedDetectors(cfg)
    img = frames[0].image
    job = DiscoveryJob(5, img, True, 0, dets)
    got = job()
    assert got.frame == 5 and got.half
    full = dets.full.detect(img)
    A = dict(zip(full.ids.tolist(), full.corners, strict=True))
    common = [m for m in got.detections.ids.tolist() if m in A]
    assert len(common) >= 0.9 * len(A), (len(common), len(A))
    gaps = [np.abs(c - A[m]).max() for m, c in zip(got.detections.ids.tolist(),
                                                  got.detections.corners, strict=True)
            if m in A]
    assert np.median(gaps) < 1.5 and max(gaps) < 2.0, (np.median(gaps), max(gaps))


def test_inline_jobs_run_when_submitted_and_give_the_result_once(default_frames):
    frames, src = default_frames
    dets = TunedDetectors(DetectorConfig(src.world_map.dictionary))
    jobs = Inline()
    assert jobs.take() is None
    jobs.submit(DiscoveryJob(3, frames[0].image, False, 0, dets))
    got = jobs.take()
    assert got is not None and got.frame == 3 and not got.half
    assert set(got.detections.ids.tolist()) == set(dets.full.detect(frames[0].image).ids.tolist())
    assert jobs.take() is None  # taken once


def test_the_detector_asks_its_jobs_for_discoveries_and_merges_what_they_return(default_frames):
    """The detector hands each discovery to the jobs it was given and merges a result only
    when the jobs return one: held back, a marker entering the view waits; returned, it
    is reported."""
    frames, src = default_frames

    class Held:
        """Jobs that keep what they are given until released."""

        def __init__(self) -> None:
            self.queued: list[DiscoveryJob] = []
            self.result = None
            self.started = 0

        def submit(self, job):
            self.queued.append(job)

        def take(self):
            r, self.result = self.result, None
            return r

        def frame_started(self):
            self.started += 1

        def close(self):
            self.queued.clear()

    held = Held()
    tracker = FixedCameraDetector(DetectorConfig(src.world_map.dictionary),
                                  FixedCameraConfig(static_ids=static_ids(src)), jobs=held)
    for f in frames[:8]:
        tracker.detect(f.image)
    assert held.started == 8 and len(held.queued) == tracker.background >= 1
    assert all(j.detectors is tracker._discovery for j in held.queued)
    job = held.queued[-1]
    held.result = job()  # run where the caller says, returned on the next frame
    before = tracker.frame
    tracker.detect(frames[8].image)
    assert tracker.frame == before + 1 and held.result is None  # taken and merged
    tracker.close()
    assert held.queued == []
