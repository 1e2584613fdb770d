"""The simulator's wide scene: two floors, two cameras, an overlap, the default robots."""

from __future__ import annotations

import time

import numpy as np
import pytest

from kmea.maps.files import default_map
from kmea.sim.renderer import Renderer
from kmea.sim.scenes import DEFAULT_FLEET, WIDE_DX, scene_from_spec


def test_two_floors_in_one_map_and_the_default_fleet() -> None:
    s0 = scene_from_spec("sim:wide?camera=0&width=320")
    s1 = scene_from_spec("sim:wide?camera=1&width=320")
    base = default_map()
    m = s0.world_map
    assert len(m) == len(base) + 33 and m.dictionary == "DICT_5X5_100"
    floor = [i for i in base.ids if base[i].on_floor]
    for k, mid in enumerate(floor):
        assert np.allclose(m[66 + k].position, base[mid].position + np.array([WIDE_DX, 0.0, 0.0]))
    assert [(r.name, r.markers) for r in s1.robots] == [(n, mk) for n, mk, *_ in DEFAULT_FLEET]
    assert s0.cam_position[0] < 0.85 < s1.cam_position[0]
    assert s0.name == "wide" and s1.name == "wide-cam1"


def test_the_overlap_is_seen_by_both_cameras() -> None:
    # At t = 0 amr1 is in the overlap strip, amr2 on floor B only.
    vis = [Renderer(scene_from_spec(f"sim:wide?camera={c}&width=320")).truth(0).visible
           for c in (0, 1)]
    assert {40, 41} <= vis[0] and {40, 41} <= vis[1]
    assert 42 in vis[1] and 42 not in vis[0]
    assert {13, 16, 4} <= vis[0] and not {13, 4} & vis[1] and 16 in vis[1]
    assert {66, 98} <= vis[1]


def test_wall_clock_robots_agree_across_cameras() -> None:
    epoch = time.time() - 10.0
    a = scene_from_spec(f"sim:wide?camera=0&clock=wall&epoch={epoch}&speed=0.02")
    b = scene_from_spec(f"sim:wide?camera=1&clock=wall&epoch={epoch}&speed=0.02")
    now = time.time()
    pa, pb = a.robot_poses(now)["amr1"], b.robot_poses(now)["amr1"]
    assert pa == pb  # one Unix time, one place, whichever camera draws it
    frame = scene_from_spec("sim:wide?speed=0.02").robot_poses(now - epoch)["amr1"]
    assert np.allclose(pa, frame)


def test_a_wall_clock_frame_is_stamped_at_the_instant_its_robots_are_drawn() -> None:
    from kmea.sources.sim import SimSource

    epoch = time.time() - 30.0
    src = SimSource(f"sim:wide?camera=0&clock=wall&epoch={epoch}&speed=1.5&width=320")
    before = time.time()
    f = src.read()
    after = time.time()
    assert f is not None and f.meta["unix_time"] is True
    assert before <= f.timestamp <= after
    truth = scene_from_spec("sim:wide?speed=1.5&width=320").robot_poses(f.timestamp - epoch)
    assert f.truth.robots == truth  # the drawn pose is the one at the stamped instant
    # The image shows them there too: the frame-clock scene rendered at that time.
    from kmea.sim.renderer import Renderer
    same = Renderer(scene_from_spec("sim:wide?speed=1.5&width=320")).render_image(
        0, f.timestamp - epoch)
    assert np.array_equal(same, f.image)


@pytest.mark.parametrize("spec, match", [("sim:wide?camera=2", "camera must be 0 or 1"),
                                         ("sim:wide?clock=gps", "clock must be"),
                                         ("sim:wide?bogus=1", "unknown option")])
def test_bad_options_name_the_problem(spec: str, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        scene_from_spec(spec)
