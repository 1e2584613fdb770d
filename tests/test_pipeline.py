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
