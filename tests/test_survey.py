"""``kmea map survey`` on rendered floors (real rendering and detection)."""

from __future__ import annotations

import csv
from dataclasses import replace

import numpy as np
import pytest

from kmea.cli import main
from kmea.maps.files import default_map, load_map
from kmea.survey import survey_frames

# Displaced on the floor (dx, dy metres; yaw degrees), unknown to the map.
MOVED = {9: (0.015, -0.010, 0.0), 24: (-0.008, 0.012, 4.0), 31: (0.025, 0.0, 0.0)}


def _scene(width=1640, height=1232):
    from kmea.sim import get_scene

    return get_scene("scenario1", width=width, height=height, seed=21,
                     misplaced={i: ((dx, dy, 0.0), (0.0, 0.0, yaw))
                                for i, (dx, dy, yaw) in MOVED.items()})


def _frames(scene, n):
    from kmea.sim import Renderer

    r = Renderer(scene)
    return (r.render_image(k) for k in range(n))


def test_survey_finds_the_displaced_markers_where_they_are_and_nothing_else():
    scene = _scene()
    truth = scene.static_markers()
    sv = survey_frames(_frames(scene, 2), scene.world_map, scene.camera)
    flagged = {i for i, m in sv.markers.items() if m.significant}
    assert flagged == set(MOVED), {i: (m.disagreement, m.z) for i, m in sv.markers.items()
                                   if m.significant}
    for i in MOVED:
        err = np.hypot(*(sv.markers[i].position[:2] - truth[i].position[:2]))
        assert err < 0.5e-3, (i, err)
        assert sv.markers[i].disagreement == pytest.approx(np.hypot(*MOVED[i][:2]), abs=0.5e-3)
    # Every floor marker seen, none far from the truth.
    floor = [i for i in scene.world_map.ids if scene.world_map[i].on_floor]
    assert set(floor) <= set(sv.markers)
    errs = [np.hypot(*(sv.markers[i].position[:2] - truth[i].position[:2])) for i in floor]
    assert max(errs) < 1e-3


def test_survey_with_a_partial_map_measures_the_new_markers(tmp_path):
    scene = _scene(820, 616)
    full = scene.world_map
    keep = {4, 13, 16, 0, 10, 21, 26, 35, 9}  # a few surveyed markers, one of them moved
    partial = replace(full, markers={i: m for i, m in full.markers.items() if i in keep},
                      extra=dict(full.extra))
    sv = survey_frames(_frames(scene, 2), partial, scene.camera)
    truth = scene.static_markers()
    new = [i for i, m in sv.markers.items() if not m.in_map and full[i].on_floor]
    assert len(new) >= 20
    for i in new:
        assert sv.markers[i].plane == "floor"
        assert np.hypot(*(sv.markers[i].position[:2] - truth[i].position[:2])) < 1.5e-3, i
    assert sv.markers[9].significant
    assert not any(m.significant for i, m in sv.markers.items() if i != 9)


def test_cli_writes_a_map_csv_and_reports(tmp_path, capsys):
    from kmea.vision.camera import pi_camera_v2, save_camera

    cam = tmp_path / "cam.toml"
    save_camera(pi_camera_v2(), cam)
    out = tmp_path / "survey.csv"
    rc = main(["map", "survey", "--source", "sim:misplaced?width=820", "--camera", str(cam),
               "--out", str(out), "--frames", "2"])
    assert rc == 0
    text = capsys.readouterr()
    # A progress bar with its estimate, one plain line per tenth when not a terminal.
    lines = [ln for ln in text.err.splitlines() if ln.startswith("kmea map survey [")]
    assert lines and "\r" not in text.err
    assert "2/2 frames" in lines[-1] and "ETA" in lines[-1] and "markers seen" in lines[-1]
    assert "7: moved 2" in text.out  # the scene moves marker 7 by +2 cm in x
    flagged = [ln.split(":")[0].strip() for ln in text.out.splitlines()
               if ln.startswith("  ") and "moved" in ln]
    assert flagged == ["7"], text.out  # no false alarm (walls included)
    assert "map markers never seen" in text.out
    with open(out, newline="") as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0]) == ["id", "x", "y", "z", "rx_deg", "ry_deg", "rz_deg", "length"]
    back = load_map(out)  # the written file is a map
    assert 7 in back and abs(back[7].position[0] - (default_map()[7].position[0] + 0.02)) < 1e-3


def test_cli_bad_inputs_are_one_line(tmp_path, capsys):
    assert main(["map", "survey", "--camera", "x.toml", "--out", str(tmp_path / "o.csv")]) == 2
    assert "--source" in capsys.readouterr().err
    (tmp_path / "frames").mkdir()
    rc = main(["map", "survey", "--source", f"images:{tmp_path / 'frames'}",
               "--out", str(tmp_path / "o.csv")])
    assert rc != 0 and "kmea map survey" in capsys.readouterr().err
    rc = main(["map", "survey", "--source", "sim", "--camera", str(tmp_path / "none.toml"),
               "--out", str(tmp_path / "o.csv")])
    assert rc == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "none.toml" in err[0]
