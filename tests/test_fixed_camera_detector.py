"""Tracking for a fixed camera: real ArUco detection on rendered simulator frames.

The tracking detector (kmea.vision.fixed_camera_detector) against full detection of the same
frames and against the simulator's truth; the pipeline's incremental poses and
leave-one-out errors (kmea.fixed_camera) against recomputation. Frames are 820x616 (half
the Pi's 1640x1232) to keep the suite fast; markers are then ~30 px wide.
"""

from __future__ import annotations

import itertools
import math
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace

import numpy as np
import pytest
from deadlines import DEADLINE, JOIN

from kmea.pipeline import FrameInput, Pipeline, PipelineSettings
from kmea.sources.sim import SimSource
from kmea.vision.detection import DetectorConfig, MarkerDetector
from kmea.vision.fixed_camera_detector import (
    FixedCameraConfig,
    FixedCameraDetector,
    code_scores,
    marker_codes,
)

WIDTH = 820


def _frames(spec: str, n: int, width: int = WIDTH):
    src = SimSource(spec, width=width, frames=n)
    return [src.read() for _ in range(n)], src


def _static_ids(src: SimSource) -> frozenset[int]:
    robot_ids = {m for r in src.scene.robot_specs() for m in r.markers}
    return frozenset(set(src.world_map.markers) - robot_ids)


def _tracker(src: SimSource, **kw) -> FixedCameraDetector:
    # No executor: the background detection runs in the calling thread, so the
    # frame at which a discovery is merged is deterministic.
    return FixedCameraDetector(DetectorConfig(src.world_map.dictionary),
                            FixedCameraConfig(static_ids=_static_ids(src), **kw))


def _tracked_pipeline(src: SimSource, algorithm: str | None = None, **tracker) -> Pipeline:
    """A tracking pipeline of ``src``'s robots with a deterministic tracker (``_tracker``)."""
    extra = {} if algorithm is None else {"algorithm": algorithm}
    p = Pipeline(src.camera, src.world_map, PipelineSettings(
        robots=tuple(src.scene.robot_specs()), fixed_camera=True, **extra))
    p.observer.detector.close()
    p.observer.detector = _tracker(src, **tracker)
    return p


@pytest.fixture(scope="module")
def default_frames():
    return _frames("sim:default", 24)


@pytest.fixture(scope="module")
def pi_frames():
    return _frames("sim:default", 14, width=1640)


def test_tracked_detection_matches_full_detection(pi_frames):
    # At the Pi's 1640x1232: floor markers 55-70 px wide.
    frames, src = pi_frames
    full = MarkerDetector(DetectorConfig(src.world_map.dictionary))
    tracker = _tracker(src)
    modes = []
    err_full, err_tracked, diff = [], [], []
    since: dict[int, int] = {}  # marker -> first frame of its current run of clean frames
    due = tracker.settings.full_every + 1  # a marker new in the view may wait this long
    for f in frames:
        a, b = full.detect(f.image), tracker.detect(f.image)
        modes.append(b.mode)
        A = dict(zip(a.ids.tolist(), a.corners, strict=True))
        B = dict(zip(b.ids.tolist(), b.corners, strict=True))
        clean = {m for m in A if m in f.truth.visible}  # nothing hides corners or centre
        since = {m: since.get(m, f.index) for m in clean}
        must = {m for m in clean if f.index == 0 or f.index - since[m] >= due}
        assert must <= set(B), f"frame {f.index}: tracking lost {sorted(must - set(B))}"
        for m in clean & set(B):
            true = f.truth.corners[m]
            ef = np.linalg.norm(A[m] - true, axis=1).max()
            et = np.linalg.norm(B[m] - true, axis=1).max()
            # Full detection itself jumps by up to ~1 px between frames on some 30 px
            # markers; a floor marker keeps the corners of the detection it was found by.
            assert et <= ef + 1.0, (f.index, m, ef, et)
            err_full.append(ef)
            err_tracked.append(et)
            diff.append(np.abs(A[m] - B[m]).max())
        # Nothing reported that is not in the frame.
        assert set(B) <= set(f.truth.corners), (f.index, sorted(set(B) - set(f.truth.corners)))
    assert np.mean(err_tracked) <= np.mean(err_full) + 0.05, (np.mean(err_tracked),
                                                              np.mean(err_full))
    assert np.median(diff) < 0.2
    assert modes[0] == "full" and modes[1:].count("followed") >= len(frames) - 3, modes
    assert tracker.background >= 2  # the periodic background discovery ran


def _robot_corner_gaps(spec: str, n: int, width: int, **kw
                       ) -> tuple[list[float], FixedCameraDetector]:
    """Per robot marker look of a tracker over ``n`` frames of ``spec``: the largest corner
    gap (px) to a full detection of the same frame."""
    frames, src = _frames(spec, n, width)
    robot_ids = {m for r in src.scene.robot_specs() for m in r.markers}
    full = MarkerDetector(DetectorConfig(src.world_map.dictionary))
    tracker = _tracker(src, **kw)
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
    from kmea.vision.fixed_camera_detector import CodeSampler, _homographies

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


def test_marker_entering_the_view_is_reported_within_0_3_s():
    fps = 30.0
    frames, src = _frames("sim:default?enter_at=0.6", 60)
    tracker = _tracker(src)
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


def test_bumped_camera_restarts_detection_and_estimation_with_an_event():
    fps = 30.0
    frames, src = _frames("sim:default?bump_at=0.4&bump_deg=1.5", 30)
    bump_frame = math.ceil(0.4 * fps)
    p = Pipeline(src.camera, src.world_map, PipelineSettings(
        robots=tuple(src.scene.robot_specs()), fixed_camera=True))
    p.observer.detector.close()
    p.observer.detector = _tracker(src)
    full = MarkerDetector(DetectorConfig(src.world_map.dictionary))
    results = [p.process(FrameInput(f.index, f.timestamp, f.image)) for f in frames]
    restarts = [r.index for r in results if r.restart]
    assert restarts == [bump_frame], restarts
    r = results[bump_frame]
    assert r.detect_mode == "full" and any("camera moved" in e for e in r.events), r.events
    assert r.loo_fresh  # statistics recomputed at once
    # Recovered within 0.5 s: from the bump on, every frame is estimated and its markers
    # match a full detection of the bumped view.
    at_bump = set(r.ids.tolist())
    for f, res in zip(frames[bump_frame:], results[bump_frame:], strict=True):
        assert res.ok, (f.index, res.estimate.reason)
        a = full.detect(f.image)
        # Markers found at the restart and not hidden since stay reported (a marker that
        # full detection finds only now and then waits for a background detection).
        clean = {m for m in a.ids.tolist() if m in f.truth.visible} & at_bump
        assert clean <= set(res.ids.tolist()), (f.index, sorted(clean - set(res.ids.tolist())))
    before = np.mean([e for x in results[2:bump_frame] for e in x.loo.values()])
    after = np.mean([e for x in results[bump_frame:] for e in x.loo.values()])
    assert after < 2.0 * before + 1e-3, (before, after)  # metres: the estimate is sane again


def test_robots_at_speed_keep_their_pose_every_frame():
    # 1.5 m/s along the default loops (their curves turn the robots at up to several rad/s).
    frames, src = _frames("sim:default?speed=1.5", 30)
    specs = tuple(src.scene.robot_specs())
    p = Pipeline(src.camera, src.world_map, PipelineSettings(robots=specs, fixed_camera=True))
    p.observer.detector.close()
    p.observer.detector = _tracker(src)
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


def test_incremental_poses_and_leave_one_out_match_recomputation(default_frames):
    frames, src = default_frames
    specs = tuple(src.scene.robot_specs())
    inc = _tracked_pipeline(src)
    ref = Pipeline(src.camera, src.world_map, PipelineSettings(robots=specs))
    reused = 0
    for f in frames[:12]:
        r = inc.process(FrameInput(f.index, f.timestamp, f.image))
        # The same detections, everything recomputed from scratch.
        s = ref.process(FrameInput(f.index, f.timestamp, f.image,
                                   ids=r.ids, corners=r.corners,
                                   observations=ref.poses(r.ids, r.corners)[0]))
        assert r.loo.keys() == s.loo.keys()
        for m in r.loo:
            assert abs(r.loo[m] - s.loo[m]) < 1e-5, (f.index, m)  # 10 um
        reused += not r.loo_fresh
        for name, fix in r.robots.items():
            other = s.robots[name]
            assert math.hypot(fix.x - other.x, fix.y - other.y) < 1e-3, (f.index, name)
    assert reused >= 5
    assert inc.session.poses.reused > inc.session.poses.posed


def test_robots_are_sent_before_the_floor_is_refitted(default_frames):
    # Every background detection at full resolution: each one averages the floor's
    # reference corners, so the floor's poses and the camera fit change in those frames.
    frames, src = default_frames
    specs = tuple(src.scene.robot_specs())
    p = _tracked_pipeline(src, "corner-pnp", full_res_every=1)
    ref = Pipeline(src.camera, src.world_map, PipelineSettings(robots=specs,
                                                               algorithm="corner-pnp"))
    early = 0
    for f in frames:
        det = p.detector.detect(f.image)
        sent: list[tuple[bool, dict]] = []
        # When the relay runs: is the floor of this frame still waiting to be posed?
        def relay(t, fx, sent=sent, det=det):
            sent.append((p.session.poses.fixed_changed(det.ids, det.corners), dict(fx)))

        r = p.process(FrameInput(f.index, f.timestamp, f.image, detections=det),
                      on_robots=relay)
        assert len(sent) == 1, f.index  # one relay call per frame
        pending, fixes = sent[0]
        assert fixes.keys() == r.robots.keys()
        early += pending
        s = ref.process(FrameInput(f.index, f.timestamp, f.image, ids=r.ids,
                                   corners=r.corners,
                                   observations=ref.poses(r.ids, r.corners)[0]))
        for name, fix in fixes.items():
            other = s.robots[name]
            assert math.hypot(fix.x - other.x, fix.y - other.y) < 1e-3, (f.index, name)
    assert early >= 2  # the floor changed in some frames, and the robots went first


def test_corner_pnp_warm_start_gives_the_fresh_solve(default_frames):
    from kmea.estimators.corner_pnp import CornerPnP

    frames, src = default_frames
    p = _tracked_pipeline(src, "corner-pnp")
    assert p.estimator.warm_start
    fresh = CornerPnP()
    intr = p.camera.intrinsics
    heights = p.plane_heights
    warm_used = 0
    for f in frames[:10]:
        before = p.estimator._warm
        r = p.process(FrameInput(f.index, f.timestamp, f.image))
        # Started from the previous fit: the same fit returned (the floor unchanged) or a
        # warm solve that replaced it.
        warm_used += before is not None and (p.estimator._warm is not before
                                             or p.estimator._warm.fit is before.fit)
        s = fresh.estimate(r.observations, src.world_map, camera=intr, plane_heights=heights)
        assert r.estimate.ok and s.ok
        assert set(r.estimate.references) == set(s.references)
        for mid, me in s.markers.items():
            d = np.linalg.norm(r.estimate.markers[mid].position - me.position)
            assert d < 2e-5, (f.index, mid, d)  # 20 um: the same optimum
            a, b = r.estimate.markers[mid].sigma, me.sigma
            assert (a is None) == (b is None) and (a is None or abs(a - b) < 1e-6), (mid, a, b)
    assert warm_used >= 1  # some frames started from the previous fit


def _refits(src, frames, **settings) -> tuple[list[int], list]:
    """Frames at which a tracking pipeline (corner-pnp) refitted the floor's camera, and
    its results."""
    from dataclasses import replace

    p = _tracked_pipeline(src, "corner-pnp")
    p.settings = replace(p.settings, **settings)
    refits, results, fit = [], [], None
    for f in frames:
        results.append(p.process(FrameInput(f.index, f.timestamp, f.image)))
        if p.estimator._warm.fit is not fit:
            fit = p.estimator._warm.fit
            refits.append(f.index)
    p.close()
    return refits, results


def test_floor_refits_are_paced_and_new_floor_markers_placed_meanwhile():
    from kmea.estimators.corner_pnp import CornerPnP

    frames, src = _frames("sim:default", 46)
    every, paced = _refits(src, frames, refit_every=1)
    refits, results = _refits(src, frames, refit_every=20)
    assert len(refits) < len(every), (refits, every)
    # after the first frame's fit, at most one refit per 20 frames
    assert all(b - a >= 20 for a, b in itertools.pairwise(refits[1:])), refits
    fresh = CornerPnP()
    deferred = 0
    for r in results:
        for m in r.deferred:  # a fixed marker new to the floor: reported, not a reference
            deferred += 1
            assert m in r.estimate.markers and m not in r.estimate.references
        if r.deferred:
            # The same as a solve told to leave them out (the last fit, to micrometres).
            s = fresh.estimate(r.observations, src.world_map, exclude=r.deferred,
                               camera=src.camera.intrinsics, plane_heights={})
            for m in r.deferred:
                d = np.linalg.norm(r.estimate.markers[m].position - s.markers[m].position)
                assert d < 2e-4, (r.index, m, d)
    assert deferred >= 1
    # Every frame's robots and markers agree with refitting at every change within 1 mm.
    for a, b in zip(results, paced, strict=True):
        for m, me in b.estimate.markers.items():
            if m in a.estimate.markers:
                d = np.linalg.norm(a.estimate.markers[m].position - me.position)
                assert d < 1e-3, (a.index, m, d)


def test_live_daemon_tracks_and_reports_a_bumped_camera():
    import logging
    import threading

    from kmea.sim.scenes import scene_from_spec
    from kmea.sources.registry import register_source
    from kmead.config.layers import load_config
    from kmead.run.daemon import Daemon

    scene = scene_from_spec("sim:default", width=WIDTH)
    # The bump at 0.8 s of the scene's 30 frames/s: frame 24.
    src = SimSource("sim:default?bump_at=0.8&bump_deg=1.5", width=WIDTH, frames=36)
    frames = [src.read() for _ in range(36)]
    results = []
    taken = threading.Event()  # the last frame served went through the pipeline
    taken.set()

    class Lockstep(SimSource):
        """A live source (the daemon tracks) from frames rendered beforehand that serves the
        next frame only once the last one was processed: no frame dropped, whatever the
        machine's load, so what the test sees does not depend on scheduling."""

        def read(self):
            assert taken.wait(DEADLINE), "the daemon did not process a frame"
            taken.clear()
            return super().read()

    register_source("tracktest", lambda rest, **o: Lockstep(scene, realtime=True,
                                                            rendered=frames, fps=1000))
    cfg = load_config(None, ["source.spec=tracktest", 'network.telemetry=""',
                             'network.control=""'])
    d = Daemon(cfg)
    assert d.live and d.pipeline.settings.fixed_camera
    orig = d._outputs

    def keep(res):
        results.append(res)
        orig(res)
        taken.set()

    d._outputs = keep

    class Keep(logging.Handler):  # on kmead's logger itself (another test may stop it
        def __init__(self) -> None:  # propagating to pytest's capture)
            super().__init__(logging.WARNING)
            self.records: list[logging.LogRecord] = []

        def emit(self, record: logging.LogRecord) -> None:
            self.records.append(record)

    caught = Keep()
    logging.getLogger("kmead").addHandler(caught)
    runner = threading.Thread(target=d.run)
    try:
        runner.start()
        runner.join(timeout=DEADLINE)
    finally:
        d.stop()
        runner.join(timeout=JOIN)
        d.close()
        logging.getLogger("kmead").removeHandler(caught)
    assert [r.index for r in results] == list(range(36))  # every frame, in order
    assert sum(r.detect_mode == "followed" for r in results) >= len(results) // 2
    moved = [r for r in caught.records if "camera moved" in r.getMessage()]
    assert len(moved) == 1, [r.getMessage() for r in caught.records]
    bumped = [r for r in results if r.restart]
    assert len(bumped) == 1 and bumped[0].index >= 24
    assert all(r.ok for r in results if r.index >= bumped[0].index)


def test_live_frame_time_is_the_sensor_timestamp():
    """A live frame with a sensor timestamp (picamera2's SensorTimestamp, as unix time) keeps
    that instant as its time and the latency is counted from it."""
    import threading

    from kmea.sources.base import Frame, FrameSource
    from kmea.sources.registry import register_source
    from kmead.config.layers import load_config
    from kmead.run.daemon import Daemon

    scene_src = SimSource("sim:default", width=WIDTH, frames=1)
    image = scene_src.read().image
    expected: dict[int, float] = {}

    class Sensor(FrameSource):
        live = True

        def __init__(self) -> None:
            super().__init__()
            self.n = 0
            self.spec = "sensortest"

        def read(self):
            if self.n >= 12:
                return None
            time.sleep(1 / 30)
            # The readout began 40 ms before the frame reached Python (the picamera source
            # gives it as unix time, the raw CLOCK_MONOTONIC value in the meta).
            ns = time.monotonic_ns() - 40_000_000
            expected[self.n] = time.time() - 0.040
            self.n += 1
            return Frame(self.n - 1, expected[self.n - 1], image, {"sensor_timestamp_ns": ns})

    register_source("sensortest", lambda rest, **o: Sensor())
    cfg = load_config(None, ["source.spec=sensortest", 'network.telemetry=""',
                             'network.control=""'])
    d = Daemon(cfg)
    d.pipeline.base_camera = scene_src.camera
    d.pipeline.camera = scene_src.camera
    d.pipeline.observer.camera = scene_src.camera
    results = []
    orig = d._outputs
    d._outputs = lambda res: (results.append(res), orig(res))
    runner = threading.Thread(target=d.run)
    try:
        runner.start()
        runner.join(timeout=60)
    finally:
        d.stop()
        runner.join(timeout=JOIN)
        d.close()
    assert results
    for r in results:
        assert abs(r.timestamp - expected[r.index]) < 0.005, (r.index, r.timestamp)
    assert min(d.totals.latency_ms) >= 40.0  # counted from the exposure, not the receipt


def test_tracking_is_on_for_live_sources_only_and_can_be_switched_off():
    from kmead.config.layers import load_config

    on = load_config(None, use_local=False).data
    assert on["detector"]["fixed_camera"] is True  # the default
    assert PipelineSettings.from_config(on, live=True).fixed_camera
    assert not PipelineSettings.from_config(on, live=False).fixed_camera  # frame-exact files
    off = load_config(None, sets=["detector.fixed_camera=false"], use_local=False).data
    assert not PipelineSettings.from_config(off, live=True).fixed_camera


def test_refit_pacing_is_a_detector_setting():
    from kmead.config.layers import ConfigError, load_config

    cfg = load_config(None, sets=["detector.fixed_refit_every=7"], use_local=False)
    assert PipelineSettings.from_config(cfg.data, live=True).refit_every == 7
    assert PipelineSettings.from_config(load_config(None, use_local=False).data).refit_every == 30
    with pytest.raises(ConfigError, match=r"detector\.fixed_refit_every"):
        load_config(None, sets=["detector.fixed_refit_every=0"], use_local=False)


def test_half_resolution_discovery_uses_one_window_sized_for_the_markers(pi_frames):
    """Background discovery at half resolution thresholds with one window (a fifth of the
    markers' side there) and still finds what the full parameters find there."""
    frames, src = pi_frames
    tracker = _tracker(src)
    used: list[int] = []
    orig = tracker._tuned_detector

    def spy(cache, win):
        used.append(win)
        return orig(cache, win)

    tracker._tuned_detector = spy
    for f in frames:
        tracker.detect(f.image)
    assert used and all(3 <= w <= 15 and w % 2 == 1 for w in used), used
    full = MarkerDetector(DetectorConfig(src.world_map.dictionary))
    one = orig({}, used[0])
    seen = lost = 0
    for f in frames[::3]:
        a = FixedCameraDetector._discover(full, f.image, True).ids.tolist()
        b = FixedCameraDetector._discover(one, f.image, True).ids.tolist()
        seen += len(a)
        lost += len(set(a) - set(b))
    assert seen >= 100 and lost <= 0.02 * seen, (seen, lost)


def test_a_refit_keeps_the_intrinsics_model_unless_the_references_changed_much(pi_frames,
                                                                               monkeypatch):
    from dataclasses import replace

    from kmea.estimators.corner_pnp import CornerPnP
    from kmea.estimators.corner_pnp import estimator as estimator_mod

    frames, src = pi_frames
    p = Pipeline(src.camera, src.world_map, PipelineSettings(robots=(), fixed_camera=False))
    r = p.process(FrameInput(0, 0.0, frames[0].image))
    p.close()
    floor = [o for o in r.observations if o.id in src.world_map]
    assert len(floor) >= 20
    est = CornerPnP()
    est.warm_start = True
    tested = []
    orig = estimator_mod.select_model
    monkeypatch.setattr(estimator_mod, "select_model",
                        lambda *a, **k: (tested.append(1), orig(*a, **k))[1])
    intr = src.camera.intrinsics

    def nudged(obs):  # one more averaged look: every reference's corners move a little
        return [replace(o, corners=np.asarray(o.corners) + 0.02) for o in obs]

    assert est.estimate(floor, src.world_map, camera=intr).ok and tested  # cold: tested
    tested.clear()
    assert est.estimate(nudged(floor[1:]), src.world_map, camera=intr).ok
    assert not tested  # one reference fewer, corners moved: the model choice stands
    keep = floor[: len(floor) // 2]
    assert est.estimate(nudged(keep), src.world_map, camera=intr).ok
    assert tested  # half the references gone: tested again


def test_background_detection_waits_for_the_frames_robots(default_frames, monkeypatch):
    """The background detection of a frame starts once the pipeline says the frame's robots
    were sent (its gate), so it does not share the cores with the frame path."""
    import threading

    from kmea.vision import fixed_camera_detector

    monkeypatch.setattr(fixed_camera_detector, "GATE_WAIT_S", 60.0)  # a slow machine: no timeout
    frames, src = default_frames
    gate = threading.Event()
    pool = ThreadPoolExecutor(1, thread_name_prefix="test-discover")
    tracker = FixedCameraDetector(DetectorConfig(src.world_map.dictionary),
                               FixedCameraConfig(static_ids=_static_ids(src)), executor=pool,
                               gate=gate)
    try:
        for f in frames:
            tracker.detect(f.image)  # clears the gate: this frame's path is running
            if tracker._draining:
                break
        assert tracker._draining and not gate.is_set()
        time.sleep(0.1)
        assert tracker._draining and tracker._result is None  # held back by the gate
        gate.set()
        t0 = time.monotonic()
        while tracker._draining and time.monotonic() - t0 < DEADLINE:
            time.sleep(0.01)
        assert not tracker._draining and tracker._result is not None
    finally:
        tracker.close()
        pool.shutdown(wait=True)


def test_the_library_starts_no_thread(default_frames):
    """Without an executor the background detection runs in the calling thread: a tracked
    pipeline over frames with discoveries leaves the process's threads as they were."""
    frames, src = default_frames
    before = set(threading.enumerate())
    p = Pipeline(src.camera, src.world_map, PipelineSettings(
        robots=tuple(src.scene.robot_specs()), fixed_camera=True))
    try:
        for f in frames[:8]:
            p.process(FrameInput(f.index, f.timestamp, f.image))
        assert p.detector.background >= 1  # a background detection ran, in this thread
        assert set(threading.enumerate()) == before
    finally:
        p.close()


def test_the_pipeline_opens_the_gate_once_the_robots_are_known(default_frames):
    frames, src = default_frames
    p = Pipeline(src.camera, src.world_map, PipelineSettings(
        robots=tuple(src.scene.robot_specs()), fixed_camera=True))
    seen = []
    try:
        assert p.detector.gate is p.robots_sent
        for f in frames[:3]:
            det = p.detector.detect(f.image)
            seen.append(p.robots_sent.is_set())  # cleared by the detection
            p.process(FrameInput(f.index, f.timestamp, f.image, detections=det),
                      on_robots=lambda t, fixes: seen.append(p.robots_sent.is_set()))
            seen.append(p.robots_sent.is_set())
    finally:
        p.close()
    assert seen == [False, False, True] * 3, seen


def test_kmea_warm_start_gives_the_cold_estimate(default_frames, monkeypatch):
    """KMEA on a fixed camera: while the references are the very observations of the last
    frame their alignment is reused (fewer alignments than frames), with the estimate of a
    cold KMEA, bit for bit."""
    from kmea.estimators import kmea as kmea_mod

    frames, src = default_frames
    p = _tracked_pipeline(src, "kmea")
    assert p.estimator.warm_start
    aligned = []
    orig = kmea_mod.kmea_align
    monkeypatch.setattr(kmea_mod, "kmea_align", lambda *a: (aligned.append(1), orig(*a))[1])
    cold = kmea_mod.KMEA(unknown_plane=p.settings.unknown_plane)
    n = 0
    for f in frames[:12]:
        before = len(aligned)
        r = p.process(FrameInput(f.index, f.timestamp, f.image))
        n += len(aligned) > before
        s = cold.estimate(r.observations, src.world_map, camera=p.camera.intrinsics,
                          plane_heights=p.plane_heights)
        assert r.estimate.ok and s.ok and r.estimate.references == s.references
        assert np.array_equal(r.estimate.cam2world, s.cam2world)
        for mid, me in s.markers.items():
            assert np.array_equal(r.estimate.markers[mid].position, me.position), (f.index, mid)
    p.close()
    assert n < 12  # some frames reused the alignment


def test_robots_are_placed_from_their_corners_before_any_pose(default_frames, monkeypatch):
    """With the floor of the last camera fit, corner-pnp places the robots from their corners
    and the relay runs before the frame's markers are posed; the fixes equal those of the
    full path (placements from the same fit) to 1e-9."""
    from kmea.estimators.corner_pnp import CornerPnP

    frames, src = default_frames

    def run(early: bool):
        p = _tracked_pipeline(src, "corner-pnp")
        if not early:
            monkeypatch.setattr(p.estimator, "place_on_planes", lambda *a, **k: None)
        out, before_pose = [], 0
        for f in frames[:16]:
            posed = p.session.poses.posed
            got = []

            def relay(t, fixes, got=got, posed=posed):
                got.append(({n: (x.x, x.y, x.theta, x.sigma) for n, x in fixes.items()},
                            p.session.poses.posed == posed))

            p.process(FrameInput(f.index, f.timestamp, f.image), on_robots=relay)
            assert len(got) == 1
            out.append(got[0][0])
            before_pose += got[0][1]
        p.close()
        return out, before_pose

    fast, n_fast = run(True)
    slow, n_slow = run(False)
    assert n_fast >= 10 and n_slow == 0, (n_fast, n_slow)
    assert isinstance(CornerPnP().place_on_planes([40], np.zeros((1, 4, 2)), [0.06],
                                                  src.world_map, {40: 0.1}), type(None))
    for a, b in zip(fast, slow, strict=True):
        assert a.keys() == b.keys()
        for name in a:
            np.testing.assert_allclose(a[name], b[name], rtol=0, atol=1e-9)


def test_the_robots_placed_early_are_not_placed_again(default_frames, monkeypatch):
    """The frame's estimate takes the placements made from the robots' corners before the
    relay (same fit, same corners): one placement of the robots per frame, not two."""
    from kmea.estimators.corner_pnp import estimator as estimator_mod

    frames, src = default_frames
    p = _tracked_pipeline(src, "corner-pnp")
    calls: list[set] = []
    orig = estimator_mod.place_markers

    def spy(s, planes, fit, obs, *a, only=None, **k):
        calls.append(set(obs if only is None else only))
        return orig(s, planes, fit, obs, *a, only=only, **k)

    monkeypatch.setattr(estimator_mod, "place_markers", spy)
    once = 0
    for f in frames[:16]:
        calls.clear()
        p.process(FrameInput(f.index, f.timestamp, f.image), on_robots=lambda t, fixes: None)
        robots = [c for c in calls if c & {40, 41, 42}]
        once += len(robots) == 1
    p.close()
    assert once >= 10, once


def test_robot_observations_come_from_their_placements_not_a_pose(default_frames, monkeypatch):
    """With the floor of the last camera fit, the robots' markers are not posed (no IPPE):
    their observations are their placements seen from the fit's camera, within a few mm and
    degrees of IPPE's pose of the same corners (whose depth scatters by ~1 % at 30 px), with a
    sub-pixel reprojection error; and the
    frame's result is the same with and without a relay."""
    frames, src = default_frames
    robot_ids = {m for r in src.scene.robot_specs() for m in r.markers}

    def run(relay: bool):
        p = _tracked_pipeline(src, "corner-pnp")
        posed_robots, placed, results = 0, [], []
        orig = p.observer.poses

        def spy(ids, corners, *a, **k):
            nonlocal posed_robots
            posed_robots += len(robot_ids & set(np.asarray(ids).tolist()))
            return orig(ids, corners, *a, **k)

        monkeypatch.setattr(p.observer, "poses", spy)
        for f in frames[:16]:
            before = posed_robots
            res = p.process(FrameInput(f.index, f.timestamp, f.image),
                            on_robots=(lambda t, fixes: None) if relay else None)
            results.append(res)
            if f.index >= 4 and posed_robots == before:
                placed += [o for o in res.observations if o.id in robot_ids]
        ref = {}
        for o in placed:  # IPPE of the very corners, for comparison
            got, _ = orig(np.array([o.id]), o.corners[None])
            ref[id(o)] = got[0]
        p.close()
        return placed, ref, results

    placed, ref, with_relay = run(True)
    assert len(placed) >= 20, len(placed)
    for o in placed:
        r = ref[id(o)]
        assert np.linalg.norm(o.marker2cam_t - r.marker2cam_t) < 0.02 * np.linalg.norm(
            r.marker2cam_t)
        cos = (np.trace(o.marker2cam_R.T @ r.marker2cam_R) - 1.0) / 2.0
        assert math.degrees(math.acos(min(1.0, cos))) < 5.0
        assert 0.0 <= o.reproj_error < 0.5 and not o.ambiguous and o.alt_R is None
    _, _, without = run(False)
    for a, b in zip(with_relay, without, strict=True):
        assert a.robots.keys() == b.robots.keys()
        for name in a.robots:
            assert (a.robots[name].x, a.robots[name].y) == (b.robots[name].x, b.robots[name].y)


def test_code_sampler_homographies_are_opencvs_and_a_degenerate_quad_spoils_only_itself():
    """The closed-form square-to-quad homographies equal ``cv2.getPerspectiveTransform``;
    a degenerate quad (corners on a line) scores 0 without zeroing the other quads' scores
    (a batched linear solve used to fail for all of them)."""
    import cv2

    from kmea.vision.fixed_camera_detector import CodeSampler, _homographies

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


def test_a_small_bump_is_noticed_in_its_frame_by_the_rotating_drift_check():
    # 0.1 degrees moves the floor by about a pixel: every code still reads, only the drift
    # shows it; the drift of a third of the markers is measured per frame.
    fps = 30.0
    frames, src = _frames("sim:default?bump_at=0.4&bump_deg=0.1", 16)
    tracker = _tracker(src)
    modes = [(f.index, d.mode, d.events) for f in frames for d in [tracker.detect(f.image)]]
    bump_frame = math.ceil(0.4 * fps)
    bumped = [i for i, _, ev in modes if any("camera moved" in e for e in ev)]
    assert bumped == [bump_frame], modes
    assert modes[bump_frame][1] == "full"


def test_a_floor_marker_pushed_by_two_pixels_is_noticed_within_the_drift_rotation():
    frames, src = _frames("sim:default", 14)
    tracker = _tracker(src)
    every = tracker.settings.drift_every
    for f in frames[:6]:
        tracker.detect(f.image)
    static = sorted(m for m, t in tracker.known.items() if t.static)
    assert len(static) > 3 * tracker.settings.drift_min  # a share, not all, per frame
    mid = static[len(static) // 2]
    c = tracker.known[mid].corners
    x0, y0 = (np.floor(c.min(axis=0)) - 6).astype(int)
    x1, y1 = (np.ceil(c.max(axis=0)) + 6).astype(int)
    events = []
    for f in frames[6:6 + every]:
        img = f.image.copy()
        # The marker's patch moved 2 px right (its surroundings are the plain floor).
        img[y0:y1, x0 + 2:x1 + 2] = f.image[y0:y1, x0:x1]
        d = tracker.detect(img)
        events += [e for e in d.events if e.startswith("floor marker")]
        assert not d.restart
    assert any(str(mid) in e.split("moved")[0] for e in events), events


def test_a_floor_reference_averaged_once_more_keeps_its_pose_for_corner_fits(default_frames):
    from kmea.fixed_camera import IncrementalPoses

    frames, src = default_frames
    p = _tracked_pipeline(src, algorithm="corner-pnp")
    det = p.detector.detect(frames[0].image)
    ids, corners = det.ids, det.corners
    posed: list[list[int]] = []

    def pose(i, c, w2c=None):
        posed.append([int(m) for m in i])
        return p.poses(i, c, w2c)

    fixed = [m for m in ids.tolist() if m in p.session.poses.fixed]
    for reuse_px in (0.1, 0.0):
        inc = IncrementalPoses(p.session.poses.fixed, reuse_px=reuse_px)
        first, _ = inc.poses(pose, ids, corners)
        nudged = corners.copy()
        a, b = (ids.tolist().index(m) for m in fixed[:2])
        nudged[a] += 0.04   # one more averaged look
        nudged[b] += 0.3    # a reference that really changed
        posed.clear()
        second, _ = inc.poses(pose, ids, nudged)
        by_id = {o.id: o for o in second}
        old = {o.id: o for o in first}
        assert np.array_equal(by_id[fixed[0]].corners, nudged[a])
        assert np.array_equal(by_id[fixed[1]].corners, nudged[b])
        repose = {m for call in posed for m in call}
        assert fixed[1] in repose
        if reuse_px:
            assert fixed[0] not in repose and inc.refreshed == 1
            assert by_id[fixed[0]].marker2cam_t is old[fixed[0]].marker2cam_t
        else:
            assert fixed[0] in repose and inc.refreshed == 0
    assert p.session.poses.reuse_px == 0.1  # on for corner-pnp
    p.set_algorithm("kmea")
    assert p.session.poses.reuse_px == 0.0  # off for estimators that read the poses
    p.close()


def test_leave_one_out_is_reused_for_the_same_floor_in_another_order(default_frames):
    # A full detection lists markers in its own order, a tracked frame by id: the same
    # observations must not recompute the errors (2-3 ms at 1640x1232).
    from kmea.fixed_camera import IncrementalLoo

    frames, src = default_frames
    p = _tracked_pipeline(src)
    r = p.process(FrameInput(frames[0].index, frames[0].timestamp, frames[0].image))
    p.close()
    obs = list(r.observations)
    calls = []

    def compute():
        calls.append(1)
        return {o.id: float(len(calls)) for o in obs}

    loo = IncrementalLoo(every=30)
    first, fresh = loo.get(obs, src.world_map.markers, compute)
    assert fresh and len(calls) == 1
    again, fresh = loo.get(obs[::-1], src.world_map.markers, compute)
    assert not fresh and again == first and len(calls) == 1
    in_map = [k for k, o in enumerate(obs) if o.id in src.world_map.markers]
    changed = list(obs)
    changed[in_map[0]] = replace(obs[in_map[0]], corners=obs[in_map[0]].corners + 0.1)
    _, fresh = loo.get(changed, src.world_map.markers, compute)
    assert fresh and len(calls) == 2
