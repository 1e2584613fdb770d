"""The ``picamera`` source against a fake picamera2 built from the real one's behaviour.

The fake lives in tests/fake_picamera2 (picamera2, libcamera, simplejpeg and the rig that
controls them); each behaviour below names where in raspberrypi/picamera2 it comes from.
"""

from __future__ import annotations

import concurrent.futures
import sys
import time

import numpy as np
import pytest
from deadlines import JOIN
from fakepi import forget, install

from kmea.sources.base import SourceError
from kmea.sources.registry import open_source


@pytest.fixture
def rig(monkeypatch: pytest.MonkeyPatch):
    yield install(monkeypatch).rig
    forget()


# ---------------------------------------------------------------------------- the fake itself


def test_fake_capture_request_blocks_forever_without_timeout(rig) -> None:
    """picamera2.py dispatch_functions: capture_request() waits on a Future with no timeout,
    so a camera that stops delivering hangs the caller (what the old source did)."""
    from picamera2 import Picamera2
    from picamera2.picamera2 import HangsForever

    rig.stall_after = [1]
    cam = Picamera2()
    cam.configure(cam.create_video_configuration(main={"size": (64, 48), "format": "YUV420"},
                                                 controls={"FrameRate": 200.0}))
    cam.start()
    cam.capture_request().release()
    with pytest.raises(HangsForever):
        cam.capture_request()
    # with wait=seconds: concurrent.futures' TimeoutError (job.py: Future.result(timeout))
    t0 = time.monotonic()
    with pytest.raises(concurrent.futures.TimeoutError):
        cam.capture_request(wait=0.05)
    assert time.monotonic() - t0 >= 0.05  # it did wait the timeout
    cam.close()


def test_fake_timed_out_job_swallows_the_next_frame(rig) -> None:
    """A timed-out job stays in the job list and takes the next frame, which nobody releases:
    why the source reopens the camera instead of asking again."""
    from picamera2 import Picamera2

    rig.stall_after = [0]
    cam = Picamera2()
    cam.configure(cam.create_video_configuration(main={"size": (64, 48), "format": "YUV420"},
                                                 controls={"FrameRate": 200.0}))
    cam.start()
    with pytest.raises(TimeoutError):
        cam.capture_request(wait=0.02)
    cam._limit = None  # the camera recovers
    req = cam.capture_request(wait=1.0)
    assert cam._held == 2  # the orphaned request still holds a buffer
    req.release()
    assert cam._held == 1
    cam.close()


# ---------------------------------------------------------------------------- frames


def test_yuv420_stride_at_1640x1232_only_y_copied_full_range(rig) -> None:
    """1640 wide YUV420 has a 1664-byte stride on the Pi 4 ISP (raspberrypi/linux PR 4419);
    MappedArray gives (1232 * 3/2, 1664) (request.py); the frame must be exactly the
    1640x1232 Y plane, full range (Sycc asked for; Rec709 would be 16..235)."""
    scene = rig.scene(7, 1640, 1232)
    rig.scene = lambda n, w, h: scene
    with open_source("picamera?fps=100") as src:
        cam = rig.instances[0]
        main = cam.stream_configuration("main")
        assert main["size"] == (1640, 1232) and main["stride"] == 1664
        assert src.size == (1640, 1232) and src.stride == 1664
        assert cam.camera_config["colour_space"].name == "sYCC"
        assert cam.camera_config["queue"] is False
        frames = [src.read() for _ in range(2)]
    for f in frames:
        assert f is not None and f.image.shape == (1232, 1640) and f.image.dtype == np.uint8
        assert f.image.flags.c_contiguous and f.image.flags.writeable
        # the padding (0x5A) and the chroma (128) must not leak in; the range is 0..255
        np.testing.assert_array_equal(f.image, scene)
        assert f.image.min() == 0 and f.image.max() == 255
    assert cam._held == 0  # every request released
    assert not cam.is_open


def test_default_colour_space_would_be_limited_range(rig) -> None:
    """The counterfactual of the test above: without colour_space, picamera2 picks Rec709 at
    this size and Y spans 16..235 (create_video_configuration)."""
    from picamera2 import Picamera2

    cam = Picamera2()
    cam.configure(cam.create_video_configuration(main={"size": (1640, 1232),
                                                       "format": "YUV420"}))
    cam.start()
    req = cam.capture_request(wait=1.0)
    y = req.make_array("main")[:1232, :1640]
    req.release()
    cam.close()
    assert (int(y.min()), int(y.max())) == (16, 235)


def test_sensor_timestamp_becomes_unix_time_of_readout_start(rig) -> None:
    """SensorTimestamp: ns on CLOCK_MONOTONIC at the start of readout
    (examples/timestamp_capture.py compares it with time.monotonic_ns())."""
    rig.readout_s = 0.010
    with open_source("picamera?width=320&height=240&fps=100") as src:
        f = src.read()
        now_unix, now_mono = time.time(), time.monotonic()
    ts = f.meta["sensor_timestamp_ns"]
    assert f.timestamp == pytest.approx(now_unix - (now_mono - ts * 1e-9), abs=2e-3)
    assert f.timestamp <= now_unix - 0.009  # readout began before the frame arrived
    assert f.meta["exposure_time_us"] == rig.exposure_us
    assert f.meta["frame_duration_us"] == 10000


def test_frame_timing_from_the_request_metadata(rig) -> None:
    """meta["timing"]: row 0 read out at SensorTimestamp after ExposureTime us of exposure
    (picamera2 examples/timestamp_capture.py: exposure start = SensorTimestamp - 1000 *
    ExposureTime), one IMX219 line (3448 / 182.4 MHz, imx219.c) per sensor row: two per row
    of 820x616 from the 1640x1232 mode. max_exposure_ms is asked as ExposureTime; the AGC
    makes up the light with analogue gain."""
    from kmea.timing import IMX219_LINE_S, imx219_line_time

    with open_source("picamera?width=820&height=616&fps=30&max_exposure_ms=2") as src:
        f = src.read()
    assert rig.instances[-1].camera_config["controls"]["ExposureTime"] == 2000
    tm = f.meta["timing"]
    assert (tm.t_read0, tm.exposure_s, tm.exact) == (f.timestamp, 0.002, False)
    assert tm.line_s == pytest.approx(2 * IMX219_LINE_S, rel=1e-3)
    assert imx219_line_time(1640, 1232) == pytest.approx(IMX219_LINE_S, rel=1e-3)
    # kmea.timing's mode figures are the ones the camera lists (kmea doctor shows them)
    import fakecam_rig

    from kmea.timing import IMX219_MODES

    listed = {m["size"]: (m["fps"], *m["crop_limits"][2:]) for m in fakecam_rig.IMX219_MODES}
    assert listed == IMX219_MODES
    for (w, h), (fps, _, _) in IMX219_MODES.items():
        if (w, h) != (640, 480):  # its own line length: not a full-field mode
            assert 1 / (fps * (h + 32)) == pytest.approx(IMX219_LINE_S, rel=2e-3)
    assert tm.row_time(308) == pytest.approx(f.timestamp + 308 * tm.line_s - 0.001)
    assert f.meta["exposure_time_us"] == 2000
    assert f.meta["analogue_gain"] == pytest.approx(rig.light_exposure_us / 2000)
    # the whole readout (1232 sensor rows) lies between the timestamp and the arrival
    assert time.time() - f.timestamp > 1232 * IMX219_LINE_S


def test_auto_exposure_and_bad_exposure(rig) -> None:
    """0 (the default) leaves the exposure to the AGC: no ExposureTime control, the frame
    says what it used; an exposure longer than a frame is refused in one line."""
    with open_source("picamera?width=320&height=240&fps=30") as src:
        f = src.read()
    assert "ExposureTime" not in rig.instances[-1].camera_config["controls"]
    assert f.meta["timing"].exposure_s == pytest.approx(rig.exposure_us * 1e-6)
    with pytest.raises(SourceError, match=r"^picamera: max_exposure_ms must be in \[0, "
                                          r"33.3333\] ms .*got 40"):
        open_source("picamera?fps=30&max_exposure_ms=40")


def test_monotonic_to_unix_conversion() -> None:
    from kmea.sources.picamera import monotonic_to_unix_ns

    m, w = time.monotonic_ns(), time.time_ns()
    assert abs(monotonic_to_unix_ns(m) - w) < 2_000_000  # 2 ms
    assert monotonic_to_unix_ns(m + 5_000_000_000) - monotonic_to_unix_ns(m) == \
        pytest.approx(5_000_000_000, abs=2_000_000)


# ---------------------------------------------------------------------------- failures


def test_stall_reopens_the_camera_then_frames_go_on(rig, caplog) -> None:
    rig.stall_after = [3]  # the first open delivers 3 frames, the next ones never stall
    with open_source("picamera?width=320&height=240&fps=200&timeout=0.05") as src:
        frames = [src.read() for _ in range(6)]
        assert src.reopened == 1
    assert [f.index for f in frames] == list(range(6))
    assert len(rig.instances) == 2 and not any(c.is_open for c in rig.instances)
    assert "no frame for 0.05 s; reopening the camera (1 of 3)" in caplog.text


def test_stall_after_reopens_ends_with_one_line(rig) -> None:
    rig.stall_after = [2, 0, 0, 0]  # first open: 2 frames; each reopen: none
    with open_source("picamera?width=320&height=240&fps=200&timeout=0.03&reopen=3") as src:
        assert src.read() is not None and src.read() is not None
        with pytest.raises(SourceError) as e:
            src.read()
    msg = str(e.value)
    assert "\n" not in msg
    assert "no frame for 0.03 s, 4 times in a row (camera reopened 3 times)" in msg
    assert "exiting so the service restarts" in msg
    assert len(rig.instances) == 4 and not any(c.is_open for c in rig.instances)


def test_camera_missing(rig) -> None:
    """No camera: global_camera_info() is empty (Picamera2() itself would say only "Camera
    __init__ sequence did not complete.", or IndexError on old versions)."""
    rig.cameras = []
    with pytest.raises(SourceError) as e:
        open_source("picamera")
    assert "no camera found by libcamera" in str(e.value)
    assert "rpicam-hello --list-cameras" in str(e.value)
    assert rig.instances == []


def test_camera_number_past_the_cameras(rig) -> None:
    with pytest.raises(SourceError, match=r"camera 1 asked for, libcamera sees 1"):
        open_source("picamera?camera=1")


def test_camera_busy(rig) -> None:
    """Busy: the reason is only in the chain of "Camera __init__ sequence did not complete."
    (Picamera2.__init__ re-raises inside its except block)."""
    from picamera2 import Picamera2

    rig.busy = True
    with pytest.raises(RuntimeError) as raw:
        Picamera2()
    assert str(raw.value) == "Camera __init__ sequence did not complete."
    assert "Device or resource busy" in str(raw.value.__context__)
    with pytest.raises(SourceError) as e:
        open_source("picamera")
    assert str(e.value).startswith("picamera: camera 0 is busy: another program holds it")


def test_second_source_on_the_same_camera_is_busy(rig) -> None:
    with open_source("picamera?width=320&height=240"), pytest.raises(SourceError, match="busy"):
        open_source("picamera?width=320&height=240")


def test_import_value_error_numpy_mismatch(rig) -> None:
    """picamera2 imports the apt simplejpeg, built for the other numpy major: ValueError at
    import (issues 1088, 1211), not ImportError."""
    rig.simplejpeg_numpy_major = 2 if np.__version__.startswith("1.") else 1
    with pytest.raises(ValueError, match=r"numpy\.dtype size changed"):
        import picamera2  # noqa: F401
    forget_only_picamera2()
    with pytest.raises(SourceError) as e:
        open_source("picamera")
    msg = str(e.value)
    assert "\n" not in msg
    assert f"cannot be imported with numpy {np.__version__}" in msg
    assert "numpy.dtype size changed" in msg
    assert "pip uninstall -y numpy" in msg and "-c constraints/" in msg


def forget_only_picamera2() -> None:
    for name in list(sys.modules):
        if name.split(".")[0] in ("picamera2", "simplejpeg"):
            del sys.modules[name]


def test_import_libcamera_missing(rig) -> None:
    rig.libcamera_installed = False
    with pytest.raises(SourceError) as e:
        open_source("picamera")
    assert "libcamera's Python bindings are not" in str(e.value)
    assert "sudo apt install python3-picamera2 python3-libcamera" in str(e.value)


def test_picamera2_not_installed(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "picamera2", None)  # import now raises ImportError
    with pytest.raises(SourceError) as e:
        open_source("picamera")
    assert "sudo apt install python3-picamera2" in str(e.value)
    assert "--system-site-packages" in str(e.value)


def test_bad_options(rig) -> None:
    with pytest.raises(SourceError, match="takes no argument"):
        open_source("picamera:0")
    with pytest.raises(SourceError, match="timeout must be > 0"):
        open_source("picamera?timeout=0")
    with pytest.raises(SourceError, match="option 'gain' is not supported"):
        open_source("picamera?gain=2")


def test_describe_open_error_old_versions() -> None:
    """Older picamera2 wordings of the same failures (issues 399, 587, 909)."""
    from kmea.sources.picamera import describe_open_error

    for inner in (RuntimeError("Failed to acquire camera"),
                  RuntimeError("camera.acquire() returned unexpected code: -16")):
        try:
            try:
                raise inner
            except RuntimeError:
                raise RuntimeError("Camera __init__ sequence did not complete.")  # noqa: B904
        except RuntimeError as outer:
            assert describe_open_error(outer).startswith("camera 0 is busy")
    assert describe_open_error(IndexError("list index out of range")).startswith(
        "no camera 0 found")
    assert "kmea doctor" in describe_open_error(OSError("something else"))


def test_close_from_another_thread_while_a_read_waits(rig) -> None:
    """The daemon closes the source from its main thread while the capture thread waits in
    capture_request: the read ends with None, and the camera is not opened again."""
    import threading

    rig.stall_after = [1]
    src = open_source("picamera?width=320&height=240&fps=200&timeout=0.2")
    assert src.read() is not None
    out: list = []
    t = threading.Thread(target=lambda: out.append(src.read()))
    t.start()
    time.sleep(0.05)
    src.close()
    t.join(timeout=JOIN)
    assert not t.is_alive() and out == [None]
    assert len(rig.instances) == 1 and not rig.instances[0].is_open


def test_camera_busy_because_kmead_holds_it_says_how_to_stop_it(rig, tmp_path) -> None:
    """kmea calibrate / kmea map survey on a Pi whose service holds the camera: the line says
    the running kmead holds it and how to stop it, or to take its frames instead."""
    import subprocess
    import sys

    from deadlines import JOIN

    program = tmp_path / "kmead"  # a kmead as the service runs it: .../bin/kmead --source picamera
    program.write_text("import sys\nsys.stdin.read()\n")
    holder = subprocess.Popen([sys.executable, str(program), "--headless", "--source",
                               "picamera"], stdin=subprocess.PIPE)
    try:
        rig.busy = True
        with pytest.raises(SourceError) as e:
            open_source("picamera")
        msg = str(e.value)
        assert msg.startswith(f"picamera: camera 0 is busy: kmead (pid {holder.pid}")
        assert "sudo systemctl stop kmead" in msg and "kmea snapshot" in msg
        assert "\n" not in msg
    finally:
        holder.communicate(timeout=JOIN)


# ---------------------------------------------------------------------------- camera modules


@pytest.mark.parametrize(("camera", "size", "line_s"), [
    # Camera Module 3 (wide): 1152x648 from the 2304x1296 binned mode, two rows per row.
    ("IMX708_WIDE", (1152, 648), 2 * 0x1E90 / 585.6e6),
    # HQ Camera: 1014x760 from the 2028x1520 binned mode.
    ("IMX477", (1014, 760), 2 * 0x31C4 / 840e6),
    # Global Shutter Camera: every row exposed at once, no skew.
    ("IMX296", (1456, 1088), 0.0),
])
def test_each_module_gets_its_sensors_line_time(rig, camera: str, size: tuple[int, int],
                                                line_s: float) -> None:
    import fakecam_rig

    rig.cameras = [dict(getattr(fakecam_rig, camera))]
    with open_source(f"picamera?width={size[0]}&height={size[1]}&fps=30") as src:
        f = src.read()
    assert f.meta["timing"].line_s == pytest.approx(line_s, rel=1e-12, abs=0.0)
    assert ("AfMode" in rig.instances[-1].camera_config["controls"]) == camera.startswith(
        "IMX708")


def test_unknown_sensor_gets_no_correction_and_says_so(rig, caplog) -> None:
    import fakecam_rig

    rig.cameras = [{**fakecam_rig.IMX219, "Model": "ov5647"}]
    fakecam_rig.MODES["ov5647"] = fakecam_rig.IMX219_MODES
    try:
        with open_source("picamera?width=320&height=240&fps=30") as src:
            f = src.read()
    finally:
        del fakecam_rig.MODES["ov5647"]
    assert f.meta["timing"].line_s == 0.0
    assert "no timing table for the sensor 'ov5647'" in caplog.text


def test_autofocus_lens_locked_at_the_calibrations_position(rig, caplog) -> None:
    """AfMode manual and the camera file's LensPosition on the IMX708; the lens reports
    its position in the metadata; another position is warned about once."""
    import fakecam_rig

    rig.cameras = [dict(fakecam_rig.IMX708)]
    with open_source("picamera?width=1152&height=648&fps=30&lens_position=0.6") as src:
        f = src.read()
        controls = rig.instances[-1].camera_config["controls"]
        assert (controls["AfMode"], controls["LensPosition"]) == (0, 0.6)
        assert f.meta["lens_position"] == 0.6
        assert "lens is at" not in caplog.text
        rig.lens_at = 0.9  # knocked, or moved by another program
        src.read()
        src.read()
    assert caplog.text.count("the lens is at 0.900 dioptres, the calibration (camera file "
                             "lens_position) at 0.600") == 1


def test_fixed_focus_camera_gets_no_autofocus_controls(rig, caplog) -> None:
    """picamera2 refuses a control the camera does not advertise: the IMX219 gets none of
    the autofocus ones, even with a lens position in its camera file."""
    with open_source("picamera?width=320&height=240&fps=30&lens_position=0.6") as src:
        f = src.read()
    controls = rig.instances[-1].camera_config["controls"]
    assert "AfMode" not in controls and "LensPosition" not in controls
    assert "lens_position" not in f.meta
    assert "the imx219 has a fixed focus: ignored" in caplog.text
    # and the fake refuses them as picamera2 does
    cam = rig.instances[-1]
    cam.close()
    from picamera2 import Picamera2

    other = Picamera2(0)
    cfg = other.create_video_configuration(main={"size": (320, 240), "format": "YUV420"},
                                           controls={"AfMode": 0})
    with pytest.raises(RuntimeError, match="Control AfMode is not advertised by libcamera"):
        other.configure(cfg)
    other.close()
    with pytest.raises(SourceError, match=r"lens_position must be in \[0, 32\] dioptres"):
        open_source("picamera?lens_position=40")


def test_the_full_field_mode_is_asked_for_not_a_crop_of_the_same_size(rig) -> None:
    """1536x864 on a Camera Module 3 is the size of its cropped 120 fps mode: the source
    asks for the full-field 2304x1296 mode, whose line time kmea.timing gives."""
    import fakecam_rig

    rig.cameras = [dict(fakecam_rig.IMX708)]
    with open_source("picamera?width=1536&height=864&fps=30") as src:
        f = src.read()
    assert rig.instances[-1].camera_config["sensor"] == {"output_size": (2304, 1296),
                                                         "bit_depth": 10}
    assert f.meta["timing"].line_s == pytest.approx(0x1E90 / 585.6e6 * 1296 / 864, rel=1e-12)
