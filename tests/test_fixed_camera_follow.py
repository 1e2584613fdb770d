"""The moving markers (kmea.fixed_camera.follow): followed or detected near their prediction."""

from __future__ import annotations

import math

import numpy as np
from fixed_camera_helpers import (
    frames_of,
)
from fixed_camera_helpers import tracker as make_tracker

from kmea.fixed_camera import FixedCameraDetector
from kmea.fixed_camera.codes import CodeBook
from kmea.fixed_camera.discovery import TunedDetectors
from kmea.fixed_camera.follow import Follower
from kmea.fixed_camera.tracks import FixedCameraConfig
from kmea.pipeline import FrameInput, Pipeline, PipelineSettings
from kmea.vision.detection import DetectorConfig, MarkerDetector, as_gray


def _robot_corner_gaps(spec: str, n: int, width: int, **kw
                       ) -> tuple[list[float], FixedCameraDetector]:
    """Per robot marker look of a tracker over ``n`` frames of ``spec``: the largest corner
    gap (px) to a full detection of the same frame."""
    frames, src = frames_of(spec, n, width)
    robot_ids = {m for r in src.scene.robot_specs() for m in r.markers}
    full = MarkerDetector(DetectorConfig(src.world_map.dictionary))
    tracker = make_tracker(src, **kw)
    gaps = []
    for f in frames:
        a, b = full.detect(f.image), tracker.detect(f.image)
        A = dict(zip(a.ids.tolist(), a.corners, strict=True))
        for m, c in zip(b.ids.tolist(), b.corners, strict=True):
            if m in robot_ids and m in A:
                gaps.append(float(np.abs(c - A[m]).max()))
    return gaps, tracker


def test_followed_robot_corners_are_the_detectors():
    """Robot markers refined from their prediction (no region detection) have the corners a
    full detection of the frame gives, to its 0.01 px refinement accuracy."""
    gaps, tracker = _robot_corner_gaps("sim:default", 20, 1640)
    assert tracker.followed >= 0.8 * len(gaps), (tracker.followed, len(gaps))
    assert max(gaps) < 0.05, max(gaps)
    gaps_off, off = _robot_corner_gaps("sim:default", 20, 1640, follow=False)
    assert off.followed == 0 and max(gaps_off) < 0.05


def test_a_robot_turning_beyond_the_prediction_is_detected_not_followed():
    """At 1.5 m/s through the loops' curves the prediction is tens of pixels off: the
    refinement then catches other features; the shape test refuses those looks and the
    region detection answers, so no corner is off."""
    gaps, tracker = _robot_corner_gaps("sim:default?speed=1.5", 45, 1640)
    assert 0 < tracker.followed < len(gaps)  # both ways were taken
    assert max(gaps) < 0.05, max(gaps)
    assert max(tracker.shape_px) > 1.0  # wrong refinements were there to refuse


def test_robots_at_speed_keep_their_pose_every_frame():
    # 1.5 m/s along the default loops (their curves turn the robots at up to several rad/s).
    frames, src = frames_of("sim:default?speed=1.5", 30)
    specs = tuple(src.scene.robot_specs())
    p = Pipeline(src.camera, src.world_map, PipelineSettings(robots=specs, fixed_camera=True))
    p.observer.detector.close()
    p.observer.detector = make_tracker(src)
    yaw_rates = []
    prev = None
    for f in frames:
        res = p.process(FrameInput(f.index, f.timestamp, f.image))
        for spec in specs:
            if set(spec.markers) <= f.truth.visible:
                assert spec.name in res.robots, (f.index, spec.name, res.ids.tolist())
                x, y, _ = f.truth.robots[spec.name]
                fix = res.robots[spec.name]
                assert math.hypot(fix.x - x, fix.y - y) < 0.02, (f.index, spec.name)
        if prev is not None:
            yaw_rates += [abs(math.remainder(f.truth.robots[n][2] - prev.truth.robots[n][2],
                                             math.tau)) * 30.0 for n in f.truth.robots]
        prev = f
    assert max(yaw_rates) >= 3.0  # the run did include turns at 3 rad/s or more
    assert p.observer.detector.followed_frames >= 20


def test_the_follower_refines_a_prediction_to_the_detected_corners_and_refuses_a_wrong_one(
        pi_frames):
    """Follower.follow on its own: robot markers predicted from their two last detections
    (constant velocity) come back with the corners a full detection of the frame gives;
    a prediction 25 px off, where the code cannot read, gives nothing."""
    frames, src = pi_frames
    cfg = DetectorConfig(src.world_map.dictionary)
    dets = TunedDetectors(cfg)
    follower = Follower(FixedCameraConfig(), dets, CodeBook(dets.full.dictionary))
    robot_ids = {m for r in src.scene.robot_specs() for m in r.markers}
    seen = [dict(zip(d.ids.tolist(), d.corners, strict=True))
            for d in (dets.full.detect(f.image) for f in frames[:6])]
    refined = 0
    for k in range(2, 6):
        ms = [m for m in robot_ids if all(m in seen[j] for j in (k - 2, k - 1, k))]
        preds = {m: 2 * seen[k - 1][m] - seen[k - 2][m] for m in ms}
        got = follower.follow(as_gray(frames[k].image), preds, {m: seen[k - 1][m] for m in ms})
        for m, c in got.items():
            assert np.abs(c - seen[k][m]).max() < 0.05, (k, m)
        refined += len(got)
        off = {m: p + 25.0 for m, p in preds.items()}
        assert follower.follow(as_gray(frames[k].image), off,
                               {m: seen[k - 1][m] for m in ms}) == {}
    assert refined >= 6 and follower.followed == refined
