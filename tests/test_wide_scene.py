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
    pa, pb = a.robot_poses(0.0)["amr1"], b.robot_poses(123.0)["amr1"]
    assert np.allclose(pa[:2], pb[:2], atol=0.01)  # frame times do not matter, Unix time does
    frame = scene_from_spec("sim:wide?speed=0.02").robot_poses(10.0)["amr1"]
    assert np.allclose(pa[:2], frame[:2], atol=0.01)


@pytest.mark.parametrize("spec, match", [("sim:wide?camera=2", "camera must be 0 or 1"),
                                         ("sim:wide?clock=gps", "clock must be"),
                                         ("sim:wide?bogus=1", "unknown option")])
def test_bad_options_name_the_problem(spec: str, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        scene_from_spec(spec)
