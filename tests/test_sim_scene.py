"""Scenes, paths, cameras, the lens model and the sim frame source."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from kmea.maps.files import default_map
from kmea.sim import (
    CrossingPath,
    LoopPath,
    Occluder,
    Renderer,
    Scene,
    SimFrame,
    SimRobot,
    Stationary,
    available_scenes,
    get_scene,
    scenario1_camera,
    scenario2_camera,
    scene_from_spec,
)
from kmea.sim.lens import distort, project, ray_map, undistort_pixels
from kmea.sources.sim import SimSource
from kmea.vision.camera import CameraModel, pi_camera_v2


def test_loop_path_is_continuous_and_heads_along_travel():
    p = LoopPath([(0, 0), (1, 0), (1, 1), (0, 1)], speed=0.2)
    assert p.length > 3.0  # the smooth curve is at least as long as the chord polygon
    ts = np.arange(0, p.period, 0.05)
    poses = np.array([p.pose(t) for t in ts])
    steps = np.hypot(*np.diff(poses[:, :2], axis=0).T)
    assert np.allclose(steps, 0.2 * 0.05, rtol=0.05)  # constant speed, no jumps
    travel = np.arctan2(*np.diff(poses[:, :2], axis=0).T[::-1])
    dh = np.angle(np.exp(1j * (travel - poses[:-1, 2])))
    assert np.abs(dh).max() < 0.05
    assert np.allclose(p.pose(0.0)[:2], p.pose(p.period)[:2], atol=1e-9)  # closed loop
    assert np.allclose(p.pose(0.0)[:2], (0.0, 0.0), atol=1e-9)  # passes its waypoints
    back = LoopPath([(0, 0), (1, 0), (1, 1)], speed=-0.2, smooth=False)
    x, y, th = back.pose(1.0)  # 0.2 m backwards from (0, 0) along the edge (1, 1) -> (0, 0)
    assert np.allclose((x, y), (0.2 / math.sqrt(2), 0.2 / math.sqrt(2)))
    assert math.isclose(th, math.atan2(1, 1))  # facing along its (reversed) travel
    with pytest.raises(ValueError, match="waypoints"):
        LoopPath([(0, 0)])


def test_crossing_path_present_only_while_crossing():
    c = CrossingPath((-1, 0), (1, 0), t0=2.0, duration=4.0, period=10.0)
    assert c.pose(1.9) is None and c.pose(6.1) is None
    assert np.allclose(c.pose(4.0), (0.0, 0.0, 0.0))
    assert np.allclose(c.pose(14.0), (0.0, 0.0, 0.0))  # repeats
    with pytest.raises(ValueError, match="period"):
        CrossingPath((0, 0), (1, 0), duration=3.0, period=1.0)


def test_scenario_cameras():
    T1 = scenario1_camera(1.35)
    assert np.allclose(T1[:3, 3], (0, 0, 1.35))
    assert np.allclose(T1[:3, 2], (0, 0, -1))  # optical axis down
    assert np.allclose(T1[:3, 0], (1, 0, 0))  # image x = world x: the image is the plan
    # the lowest height that sees the whole 1.7 x 1.2 m floor, and it does see its corners
    T = scenario1_camera(None)
    cam = pi_camera_v2()
    uv, z = project(np.array([[x, y, 0.0] for x in (-0.85, 0.85) for y in (-0.6, 0.6)]),
                    np.linalg.inv(T), cam)
    assert np.all(z > 0)
    assert np.all((uv >= 0) & (uv <= [cam.width - 1, cam.height - 1]))
    T2 = scenario2_camera()
    assert T2[0, 3] < 0 < T2[1, 3] and T2[2, 3] > 0.8  # above the top-left part
    origin_cam = np.linalg.inv(T2) @ np.array([0, 0, 0, 1.0])
    uv0, _ = project(np.zeros((1, 3)), np.linalg.inv(T2), cam)
    assert origin_cam[2] > 0
    assert np.linalg.norm(uv0 - [cam.cx, cam.cy]) < 150  # looking at the origin
    angle = math.degrees(math.acos(-T2[2, 2]))
    assert 30 < angle < 60  # oblique


def test_named_scenes_and_options():
    names = available_scenes()
    assert {"default", "scenario1", "scenario2"} <= set(names)
    d = get_scene()
    assert d.size == (1640, 1232) and d.fps == 30
    assert [(r.name, r.markers) for r in d.robots] == [("amr1", (40, 41)), ("amr2", (42,))]
    assert all(r.height == 0.20 and r.length == 0.06 for r in d.robots)
    assert d.robots[0].separation == pytest.approx(0.10)
    assert get_scene("scenario1").robots == []
    s = get_scene("scenario2", width=640, height=480, noise=4, blur=0, seed=3)
    assert s.size == (640, 480) and s.effects.noise_sigma == 4 and s.seed == 3
    assert get_scene("default", width=640).size == (640, 481)  # 1640x1232 is not exactly 4:3
    with pytest.raises(ValueError, match="unknown scene"):
        get_scene("nope")
    with pytest.raises(ValueError, match="unknown option"):
        get_scene("default", colour="red")


def test_scene_from_spec():
    s = scene_from_spec("sim:scenario2?width=320&height=240&noise=0&covered=4,13")
    assert s.name == "scenario2" and s.size == (320, 240) and s.effects.noise_sigma == 0
    assert [o.name for o in s.effects.occluders] == ["sheet over 4", "sheet over 13"]
    assert scene_from_spec("sim").name == "default"
    assert scene_from_spec("sim:", robots=False).robots == []
    with pytest.raises(ValueError, match="key=value"):
        scene_from_spec("sim:default?noise")


def test_scene_validation_names_the_problem():
    m = default_map()
    cam = pi_camera_v2(320, 240)
    T = scenario1_camera()
    with pytest.raises(ValueError, match="carries map marker 13"):
        Scene(m, cam, T, [SimRobot("r", (13,))])
    with pytest.raises(ValueError, match="misplaced marker 99"):
        Scene(m, cam, T, misplaced={99: (0.01, 0, 0)})
    with pytest.raises(ValueError, match=r"overrides\[99\]"):
        Scene(m, cam, T, overrides={99: np.eye(4)})
    with pytest.raises(ValueError, match="duplicate robot names"):
        Scene(m, cam, T, [SimRobot("r", (40,)), SimRobot("r", (41,))])
    with pytest.raises(ValueError, match="height"):
        SimRobot("r", (40,), height=-1)
    with pytest.raises(ValueError, match="not in dictionary"):
        Renderer(Scene(m, cam, T, [SimRobot("r", (140,))]))


def test_lens_model_matches_opencv_and_inverts():
    # a camera with every coefficient the simulator supports (rational + thin prism)
    K = np.array([[600.0, 0.5, 330.0], [0, 610.0, 242.0], [0, 0, 1]])
    d = np.array([0.08, -0.12, 0.001, -0.0015, 0.03, 0.01, -0.02, 0.005, 0.001, -0.0005,
                  0.0008, 0.0002])
    cam = CameraModel(K, d, 640, 480)
    rng = np.random.default_rng(1)
    P = np.column_stack([rng.uniform(-0.5, 0.5, (200, 2)), rng.uniform(1.0, 2.0, 200)])
    T = np.eye(4)
    uv, z = project(P, T, cam)
    assert np.allclose(z, P[:, 2])
    ref, _ = cv2.projectPoints(P, np.zeros(3), np.zeros(3), K, d)
    assert np.abs(uv - ref.reshape(-1, 2)).max() < 1e-9
    x, y = undistort_pixels(uv[:, 0], uv[:, 1], cam)
    assert np.allclose(x, P[:, 0] / P[:, 2], atol=1e-11)
    assert np.allclose(y, P[:, 1] / P[:, 2], atol=1e-11)
    rm = ray_map(pi_camera_v2(320, 240))
    u, v = distort(rm.x, rm.y, pi_camera_v2(320, 240))
    assert np.abs(u - np.arange(320)).max() < 1e-8
    assert np.abs(v - np.arange(240)[:, None]).max() < 1e-8


def test_sim_source_frames_and_open_source():
    from kmea.sources.registry import open_source

    with SimSource(get_scene("default", width=160, height=120), start=5, frames=3) as src:
        frames = list(src)
    assert [f.index for f in frames] == [5, 6, 7]
    assert all(isinstance(f, SimFrame) and f.image.shape == (120, 160) for f in frames)
    assert frames[1].t == pytest.approx(6 / 30) == frames[1].timestamp
    assert frames[0].meta["truth"] is frames[0].truth
    src = open_source("sim:scenario1?width=160&height=120&fps=10&noise=0")
    f = src.read()
    assert f.image.shape == (120, 160) and f.timestamp == 0.0
    assert src.read().timestamp == pytest.approx(0.1)
    src.close()
    assert src.read() is None
    bgr = SimSource("sim:scenario1?width=160&height=120", gray=False).read()
    assert bgr.image.shape == (120, 160, 3)


def test_static_occluder_and_moving_occluder_in_truth():
    sc = get_scene("scenario1", width=320, height=240,
                   occluders=[Occluder((0.3, 0.3), (0.0, 0.3), Stationary(0.695, 0.355))])
    tr = Renderer(sc).truth(0)
    assert 5 not in tr.visible and 4 in tr.visible  # (0.695, 0.355) hidden, its neighbour not
    sc = get_scene("scenario1", width=320, height=240, occluders=["person"])
    r = Renderer(sc)
    seen = [len(r.truth(i).visible) for i in range(0, 300, 15)]
    assert min(seen) < max(seen)  # someone walked past and hid some markers for a while


def test_image_effects():
    def canvas_mean(img: np.ndarray, truth, x: float, y: float) -> float:
        # a 10 x 10 px patch of bare canvas at world (x, y) (between marker rows)
        from kmea.sim.lens import project

        uv, _ = project(np.array([[x, y, 0.0]]), np.linalg.inv(truth.cam2world),
                        pi_camera_v2(320, 240))
        u, v = np.round(uv[0]).astype(int)
        return float(img[v - 5:v + 5, u - 5:u + 5].mean())

    plain = {"width": 320, "height": 240, "noise": 0, "blur": 0, "vignetting": 0}
    base = Renderer(get_scene("scenario1", **plain)).render(0)
    c0 = canvas_mean(base.image, base.truth, 0.1, 0.075)
    assert abs(c0 - 0.74 * 255) < 1.0  # the canvas albedo
    dark = Renderer(get_scene("scenario1", **{**plain, "exposure": 0.5})).render(0)
    assert abs(canvas_mean(dark.image, dark.truth, 0.1, 0.075) - c0 / 2) < 1.0
    lit = Renderer(get_scene("scenario1", **{**plain, "gradient": (0.5, 0.0)})).render(0)
    left = canvas_mean(lit.image, lit.truth, -0.6, 0.075)
    right = canvas_mean(lit.image, lit.truth, 0.6, 0.075)
    assert abs(left - c0 * 0.7) < 1.5 and abs(right - c0 * 1.3) < 1.5
    vig = Renderer(get_scene("scenario1", **{**plain, "vignetting": 0.3})).render(0)
    centre = canvas_mean(vig.image, vig.truth, 0.1, 0.075)
    corner = canvas_mean(vig.image, vig.truth, -0.6, 0.075)  # far from the image centre
    assert corner < centre - 10
    with pytest.raises(ValueError, match="frame index"):
        Renderer(get_scene("scenario1", **plain)).render(-1)


def test_write_frames_and_truth(tmp_path, capsys):
    import json

    from kmea.sim.__main__ import main

    assert main(["sim:default?width=160&height=120", "--frames", "2", "--start", "30",
                 "--step", "15", "--out", str(tmp_path)]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "frame_000030.png", "frame_000045.png", "truth.jsonl"]
    img = cv2.imread(str(tmp_path / "frame_000045.png"), cv2.IMREAD_UNCHANGED)
    ref = Renderer(get_scene("default", width=160, height=120)).render(45)
    assert np.array_equal(img, ref.image)
    lines = [json.loads(s) for s in (tmp_path / "truth.jsonl").read_text().splitlines()]
    assert [d["index"] for d in lines] == [30, 45]
    assert lines[1]["t"] == pytest.approx(1.5)
    assert np.allclose(lines[1]["robots"]["amr1"], ref.truth.robots["amr1"])
    assert set(lines[1]["visible"]) == ref.truth.visible
    assert np.allclose(lines[1]["corners"]["13"], ref.truth.corners[13])
    assert main(["sim:nope", "--out", str(tmp_path)]) == 2
    assert "unknown scene" in capsys.readouterr().err
