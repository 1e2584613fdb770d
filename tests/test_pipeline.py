"""kmea.pipeline: the library's per-frame computation on real rendered frames, and its replay."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from kmea.pipeline import FrameInput, MarkerObserver, Pipeline, PipelineSettings
from kmea.recordings.format import Recorder
from kmea.sources.registry import open_source


def _frames(n: int):
    with open_source("sim:default?width=800&height=600", frames=n) as src:
        return list(src), src


def test_one_frame_detect_to_robots_against_the_truth() -> None:
    frames, src = _frames(1)
    scene = src.scene
    p = Pipeline(src.camera, src.world_map, PipelineSettings(robots=tuple(scene.robot_specs())))
    f = frames[0]
    res = p.process(FrameInput(f.index, f.timestamp, f.image))
    assert res.ok and len(res.estimate.references) >= 10
    found = set(res.ids.tolist())
    assert len(found & f.truth.visible) >= 0.8 * len(f.truth.visible)
    assert found <= set(f.truth.corners)  # no false ids
    # Leave-one-out errors of the map markers: a few millimetres at 800x600.
    assert len(res.loo) >= 10 and np.median(list(res.loo.values())) < 0.005
    assert set(res.robots) == set(f.truth.robots)
    for name, fix in res.robots.items():
        x, y, _ = f.truth.robots[name]
        assert np.hypot(fix.x - x, fix.y - y) < 0.01, name
    assert {"detect", "pose", "estimate", "loo", "robots"} <= set(res.timings)
    # Detect-then-pose is one object: the observer alone gives the pipeline's observations.
    obs = MarkerObserver(p.new_detector(), p.camera, p.world_map, p.robot_lengths,
                         p.settings.marker_length).observe(f.image)
    assert [o.id for o in obs] == [o.id for o in res.observations]


def test_replay_of_a_recording_gives_the_same_estimates(tmp_path: Path) -> None:
    frames, src = _frames(3)
    settings = PipelineSettings(robots=tuple(src.scene.robot_specs()))
    live = Pipeline(src.camera, src.world_map, settings)
    path = tmp_path / "run.jsonl"
    rec = Recorder(path, src.camera, src.world_map, "sim:default", {"robots": []})
    first = []
    for f in frames:
        res = live.process(FrameInput(f.index, f.timestamp, f.image))
        rec.write_frame(res.index, res.timestamp, res.ids, res.corners, res.observations,
                        res.diagnostics)
        first.append(res)
    rec.close()
    with open_source(f"replay:{path}") as rsrc:
        again = Pipeline(rsrc.camera, rsrc.world_map, settings)
        for before, fr in zip(first, rsrc, strict=True):
            ids, corners, obs, diag = fr.meta["replay"]
            res = again.process(FrameInput(fr.index, fr.timestamp, None, ids, corners, obs, diag))
            assert res.loo == before.loo
            assert res.markers.keys() == before.markers.keys()
            for mid, (pos, yaw) in res.markers.items():
                assert np.array_equal(pos, before.markers[mid][0]) and yaw == before.markers[mid][1]


class _Background:
    """A caller's scheduler that runs the discoveries at once and records the calls."""

    def __init__(self, log: list) -> None:
        self.log = log

    def jobs(self):
        from kmea.fixed_camera import Inline

        self.log.append("jobs")
        return Inline()

    def robots_sent(self) -> None:
        self.log.append("robots_sent")


def _counting(p: Pipeline) -> list:
    """Frame by frame, how often ``p`` made robot fixes (robot_fixes: its filters' updates)."""
    calls: list = []
    orig = p.robot_fixes

    def spy(*a, **k):
        calls.append(1)
        return orig(*a, **k)

    p.robot_fixes = spy  # type: ignore[method-assign]
    return calls


def test_robot_fixes_are_made_and_sent_once_a_frame_on_both_paths(default_frames) -> None:
    """Full detection and the fixed camera's path (robots placed before the poses, or with
    the frame's estimate): one set of robot fixes a frame, sent once, the very fixes of the
    result; the caller's background hears after each frame's robots were sent."""
    frames, src = default_frames
    specs = tuple(src.scene.robot_specs())
    for fixed in (False, True):
        log: list = []
        p = Pipeline(src.camera, src.world_map, PipelineSettings(
            robots=specs, fixed_camera=fixed, algorithm="corner-pnp"),
            background=_Background(log))
        calls = _counting(p)
        found = 0
        for f in frames[:12]:
            sent: list = []
            calls.clear()
            log.clear()
            r = p.process(FrameInput(f.index, f.timestamp, f.image),
                          on_robots=lambda t, fixes, sent=sent, log=log: (
                              sent.append(fixes), log.append("relay")))
            assert len(calls) == 1 and len(sent) == 1, (fixed, f.index, calls, sent)
            assert sent[0] is r.robots
            assert log == ["relay", "robots_sent"], (fixed, f.index, log)
            found += len(r.robots)
        assert found >= 12, (fixed, found)  # the two robots in most frames
        p.close()
        assert log[-1] == "robots_sent"  # a waiting discovery goes at once


def test_the_fixed_camera_path_agrees_with_full_detection(default_frames) -> None:
    """The same rendered frames through full detection of every frame and through the
    fixed camera's path: the same robots within 2 mm and 3 degrees, markers within 2 mm,
    every frame estimated (tracked corners are a full detection's to ~0.1 px and the
    floor's fit is refreshed at most every 30 frames: 0.3 mm seen; 3 degrees for the robot
    with one 30 px marker, whose yaw comes from that marker alone: 1.7 degrees seen)."""
    frames, src = default_frames
    specs = tuple(src.scene.robot_specs())
    full = Pipeline(src.camera, src.world_map, PipelineSettings(robots=specs))
    fast = Pipeline(src.camera, src.world_map, PipelineSettings(robots=specs,
                                                                fixed_camera=True))
    followed = 0
    for f in frames:
        a = full.process(FrameInput(f.index, f.timestamp, f.image))
        b = fast.process(FrameInput(f.index, f.timestamp, f.image))
        assert a.ok and b.ok, f.index
        followed += b.detect_mode == "followed"
        assert b.robots.keys() <= a.robots.keys()
        assert len(b.robots) >= len(a.robots) - (f.index < 3), (f.index, a.robots.keys())
        for name, fb in b.robots.items():
            fa = a.robots[name]
            assert np.hypot(fa.x - fb.x, fa.y - fb.y) < 0.002, (f.index, name)
            dth = abs(np.angle(np.exp(1j * (fa.theta - fb.theta))))
            assert dth < np.radians(3.0), (f.index, name, np.degrees(dth))
        for m in a.markers.keys() & b.markers.keys():
            assert np.linalg.norm(a.markers[m][0] - b.markers[m][0]) < 0.002, (f.index, m)
    assert followed >= len(frames) - 3
    fast.close()
