"""The tracking detector (kmea.fixed_camera.detector) against full detection of the same
rendered frames and the simulator's truth; the daemon tracking a live source."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from deadlines import DEADLINE, JOIN
from fixed_camera_helpers import (
    WIDTH,
)
from fixed_camera_helpers import tracker as make_tracker

from kmea.pipeline import FrameInput, Pipeline, PipelineSettings
from kmea.sources.sim import SimSource
from kmea.vision.detection import DetectorConfig, MarkerDetector


def test_tracked_detection_matches_full_detection(pi_frames):
    # At the Pi's 1640x1232: floor markers 55-70 px wide.
    frames, src = pi_frames
    full = MarkerDetector(DetectorConfig(src.world_map.dictionary))
    tracker = make_tracker(src)
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
