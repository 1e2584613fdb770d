"""kmea.timing's sensor tables against the kernel drivers' own figures, and the pose-time
model they give (line time per image row, 0 for the global shutter)."""

from __future__ import annotations

import pytest

from kmea.timing import (
    IMX219_MODES,
    IMX708_HDR_MODE,
    SENSORS,
    imx219_line_time,
    line_time,
    sensor_for,
)


def test_imx219_is_the_table_it_always_was() -> None:
    s = SENSORS["imx219"]
    assert {m.size: round(m.fps, 2) for m in s.modes} == {k: v[0] for k, v in IMX219_MODES.items()}
    for w, h in ((1640, 1232), (820, 616), (3280, 2464), (1920, 1080), (640, 480)):
        assert line_time("imx219", w, h) == imx219_line_time(w, h)


@pytest.mark.parametrize(("model", "size", "fps", "line_us"), [
    # raspberrypi/linux drivers/media/i2c/imx708.c: line_length_pix / pixel_rate, rows +
    # vblank_min rows a frame.
    ("imx708", (1536, 864), 120.12, 0x1460 / 566.4),
    ("imx708", (2304, 1296), 56.02, 0x1E90 / 585.6),
    ("imx708", (4608, 2592), 14.35, 0x3D20 / 595.2),
    # imx477.c: 840 MHz, frame length floor(1 / max fps x 840 MHz / line length).
    ("imx477", (1332, 990), 120.05, 6664 / 840.0),
    ("imx477", (2028, 1080), 50.03, 12740 / 840.0),
    ("imx477", (2028, 1520), 40.01, 12740 / 840.0),
    ("imx477", (4056, 3040), 10.0, 24000 / 840.0),
    # imx296.c: HMAX 1100 at 74.25 MHz, 1088 + 30 rows.
    ("imx296", (1456, 1088), 60.38, 1100 / 74.25),
])
def test_modes_are_the_drivers(model: str, size: tuple[int, int], fps: float,
                               line_us: float) -> None:
    mode = SENSORS[model].mode(size)
    assert mode is not None
    assert mode.fps == pytest.approx(fps, abs=0.015)
    assert mode.line_s * 1e6 == pytest.approx(line_us, rel=1e-12)


def test_variants_share_the_sensor_and_unknown_has_none() -> None:
    for name in ("imx708", "IMX708_wide", "imx708_noir", "imx708_wide_noir"):
        assert sensor_for(name) is SENSORS["imx708"]
    assert sensor_for("ov5647") is None and line_time("ov5647", 640, 480) is None


def test_global_shutter_has_no_skew_and_rolling_shutters_scale_with_the_output() -> None:
    assert line_time("imx296", 1456, 1088) == 0.0
    assert line_time("imx296", 728, 544) == 0.0
    # 1152x648 from the IMX708's 2304x1296 binned mode: two sensor rows per image row.
    assert line_time("imx708", 1152, 648) == pytest.approx(2 * 0x1E90 / 585.6e6, rel=1e-12)
    # Above the binned mode's size libcamera takes the full-resolution mode.
    assert line_time("imx708", 2560, 1440) == pytest.approx(
        0x3D20 / 595.2e6 * 2592 / 1440, rel=1e-12)
    # The cropped 1536x864 mode is never picked for the whole field.
    assert SENSORS["imx708"].mode_for(1536, 864).size == (2304, 1296)
    assert SENSORS["imx477"].mode_for(2028, 1080).size == (2028, 1520)


def test_hdr_mode_is_30_fps_at_most() -> None:
    assert IMX708_HDR_MODE.fps == pytest.approx(30.0, abs=0.01)
    assert all(m.size != IMX708_HDR_MODE.size or m.fps > 50 for m in SENSORS["imx708"].modes)


def test_simulated_floor_takes_a_modules_shutter() -> None:
    from kmea.experiments.motion import MotionCase, motion_scene
    from kmea.sim.scenes import get_scene

    sc = get_scene("scenario1", sensor="imx296")
    assert sc.effects.line_time_s == 0.0
    sc = get_scene("scenario1", width=820, height=616, sensor="imx219")
    assert sc.effects.line_time_s == imx219_line_time(820, 616)
    with pytest.raises(ValueError, match="scene option sensor: no timing table for 'ov5647'"):
        get_scene("scenario1", sensor="ov5647")
    case = MotionCase(1.5, width=1536, sensor="imx708")
    sc = motion_scene(case)
    assert (sc.camera.width, sc.camera.height) == (1536, 864)
    assert sc.effects.line_time_s == line_time("imx708", 1536, 864)
    assert motion_scene(case, line_time=False).effects.line_time_s == 0.0
    # the Camera Module v2's horizontal field of view at every width
    assert sc.camera.fx / 1536 == pytest.approx(motion_scene(MotionCase(1.5)).camera.fx / 1640)
