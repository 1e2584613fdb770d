"""The calibration's lens position: stored in the camera file, read back, checked, and
passed by kmead to the Pi camera (the autofocus lock)."""

from __future__ import annotations

from pathlib import Path

import pytest

from kmea.vision.camera import CameraError, pi_camera_v2, save_camera
from kmea.vision.lens import lens_differs, load_lens_position
from kmead.config.layers import load_config
from kmead.config.plan import plan_startup
from kmead.config.startup import StartupError, source_options


@pytest.mark.parametrize("suffix", [".yml", ".json", ".toml"])
def test_lens_position_round_trips_through_every_format(tmp_path: Path, suffix: str) -> None:
    path = tmp_path / f"cam{suffix}"
    save_camera(pi_camera_v2(), path, meta={"rms": 0.2, "lens_position": 0.45})
    assert load_lens_position(path) == 0.45
    save_camera(pi_camera_v2(), path, meta={"rms": 0.2})
    assert load_lens_position(path) is None


@pytest.mark.parametrize(("value", "why"), [(-1.0, "outside 0..32"), (40, "outside 0..32"),
                                            ("far", "expected a number")])
def test_bad_lens_position_is_one_line_naming_file_and_key(tmp_path: Path, value: object,
                                                           why: str) -> None:
    path = tmp_path / "cam.toml"
    save_camera(pi_camera_v2(), path, meta={"lens_position": value})  # type: ignore[dict-item]
    with pytest.raises(CameraError, match=rf"^{path}: meta.lens_position: .*{why}"):
        load_lens_position(path)
    yml = tmp_path / "cam.yml"
    save_camera(pi_camera_v2(), yml, meta={"lens_position": value})  # type: ignore[dict-item]
    with pytest.raises(CameraError, match=rf"^{yml}: lens_position: "):
        load_lens_position(yml)
    cfg = load_config(None, sets=[f'camera.file="{yml}"', 'source.spec="picamera"'])
    with pytest.raises(StartupError, match=rf"^camera: {yml}: lens_position: "):
        plan_startup(cfg)


def test_kmead_gives_the_pi_camera_the_calibrations_lens_position(tmp_path: Path) -> None:
    path = tmp_path / "cam.yml"
    save_camera(pi_camera_v2(), path, meta={"lens_position": 0.5})
    cfg = load_config(None, sets=[f'camera.file="{path}"', 'source.spec="picamera"'])
    assert source_options(cfg, "picamera")["lens_position"] == 0.5
    assert "lens_position" not in source_options(cfg, "sim")
    save_camera(pi_camera_v2(), path)
    assert "lens_position" not in source_options(cfg, "picamera")


def test_lens_differs_beyond_the_tolerance() -> None:
    assert not lens_differs(0.5, 0.54) and lens_differs(0.5, 0.56)
    assert not lens_differs(None, 3.0) and not lens_differs(0.5, None)
