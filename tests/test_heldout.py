"""Issue 13's targets on held-out rendered scenes and real photos (real rendering, real
OpenCV detection; few frames to stay fast). ``python -m kmea.experiments.heldout`` prints
the same figures with more frames."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from kmea.experiments.heldout import (
    HELDOUT,
    TUNING,
    default_floor_loo,
    evaluate_gridboard,
    evaluate_scene,
    moved_markers,
)

GRIDBOARD = Path(__file__).resolve().parents[2] / "shared" / "data" / "opencv-gridboard"
CP = (("corner-pnp", "corner-pnp", {}, "off"),)


def test_split_is_disjoint():
    assert not set(HELDOUT) & set(TUNING)
    for h in HELDOUT.values():
        for t in TUNING.values():
            assert (h.camera, h.evaluated, h.seed) != (t.camera, t.evaluated, t.seed)


@pytest.mark.parametrize("scene,target", [
    ("centred", 0.10e-3),
    ("centred-displaced", 0.15e-3),
    ("oblique", 0.8e-3),
    ("raised", 0.10e-3),
])
def test_heldout_targets(scene, target):
    spec = HELDOUT[scene]
    (res,) = evaluate_scene(spec, frames=2, estimators=CP)
    assert res.failures == 0
    scored = set(spec.evaluated) | set(spec.robots)
    assert len(res.errors) >= len(scored) - 1  # at most one leaves the oblique view
    assert res.mae <= target, (scene, res.mae)


def test_off_the_map_floor_markers_are_put_on_the_floor():
    spec = HELDOUT["centred"]
    (res,) = evaluate_scene(spec, frames=1, estimators=CP)
    choices = res.info["unknown_planes"][0]
    assert set(choices) == set(spec.evaluated)
    assert set(choices.values()) == {"floor"}


def test_unconfigured_raised_markers_are_free_and_no_worse_than_kmea():
    spec = HELDOUT["raised-unconfigured"]
    kmea, cp = evaluate_scene(spec, frames=2, estimators=(
        ("kmea", "kmea", {}, "off"), ("corner-pnp", "corner-pnp", {}, "off")))
    for choices in cp.info["unknown_planes"]:
        assert set(choices.values()) == {"free"}, choices
    assert cp.mae <= kmea.mae


@pytest.mark.skipif(not (GRIDBOARD / "tutorial_camera_params.yml").is_file(),
                    reason="../shared/data/opencv-gridboard is absent")
def test_gridboard_photo_markers_off_the_map():
    from kmea.experiments import gridboard

    res = {}
    for image in gridboard.IMAGES:
        (r,) = evaluate_gridboard(GRIDBOARD, images=(image,), estimators=CP)
        res[image] = r
    # The unoccluded photo meets the 0.5 mm target; the occluded one (15 markers, so about
    # 11 references per fold for the intrinsics) does not: see docs/experiments.md.
    assert res["gboriginal.png"].mae <= 0.5e-3
    assert res["gbocclusion.png"].mae <= 1.5e-3


def test_default_estimator_on_the_default_floor_at_820x616():
    from kmead.config.layers import load_config

    loo = default_floor_loo(frames=3, width=820, height=616)
    errs = np.array([e for v in loo.values() for e in v])
    assert len(loo) >= 30
    assert errs.mean() <= 0.5e-3 and errs.max() <= 3e-3, (errs.mean(), errs.max())
    # Nothing looks moved to the daemon's rule with the daemon's default thresholds.
    stats = load_config(None, use_local=False)["stats"]
    assert moved_markers(loo, stats["displaced_threshold"], stats["displaced_frames"]) == set()
    # ... while the rule does see a marker whose errors are those of a moved one.
    bad = dict(loo)
    bad[7] = [0.03] * len(loo[7])
    assert moved_markers(bad, stats["displaced_threshold"], stats["displaced_frames"]) == {7}


def test_loo_on_another_scene_of_the_default_floor(capsys):
    from kmea.experiments.heldout import camera_pose, main, parse_camera

    assert parse_camera("down,1.38,0.02,-0.03,2,1.5") == ("down", 1.38, 0.02, -0.03, 2.0, 1.5)
    assert parse_camera("look_at,1,0,1.2,0,0,0") == ("look_at", (1.0, 0.0, 1.2),
                                                       (0.0, 0.0, 0.0))
    with pytest.raises(ValueError):
        parse_camera("down,1.38")
    # The default placement is the default scene's camera.
    from kmea.sim import scenario1_camera

    assert np.allclose(camera_pose(("down", 1.35, 0.0, 0.0, 0.0, 0.0)), scenario1_camera(1.35))
    assert main(["--loo", "--frames", "1", "--width", "820", "--seed", "5",
                 "--camera", "down,1.40,0.01,0.0,1,0"]) == 0
    out = capsys.readouterr().out
    assert "820x616 (seed 5, camera down,1.40,0.01,0.0,1,0), 1 frames" in out
    assert "LOO mean" in out
