"""``kmea doctor``: on this machine for real (no camera), and on the fake picamera2."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from fakepi import forget, install

from kmea.vision.camera import pi_camera_v2, save_camera
from kmead.tools.doctor import Doctor

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def rig(monkeypatch: pytest.MonkeyPatch):
    yield install(monkeypatch).rig
    forget()


def _lines(doc: Doctor, name: str) -> list[str]:
    return [c.line() for c in doc.results if c.name == name]


def _config(tmp_path: Path, body: str) -> str:
    p = tmp_path / "kmead.toml"
    p.write_text(body)
    return str(p)


PI4 = "Raspberry Pi 4 Model B Rev 1.5"  # /proc/device-tree/model on the reference board
NET_ANY = '[network]\ntelemetry = "tcp://127.0.0.1:*"\ncontrol = "tcp://127.0.0.1:*"\n'


def test_doctor_off_a_pi_says_so_and_checks_the_rest(tmp_path: Path) -> None:
    """The real command, on this machine (no Pi, no camera, no picamera2): it says it is
    not a Pi, gives no Pi-only advice, and checks what applies."""
    if "Raspberry Pi" in (Path("/proc/device-tree/model").read_text(errors="replace")
                          if Path("/proc/device-tree/model").exists() else ""):
        pytest.skip("this test is for machines that are not a Raspberry Pi")
    cfg = _config(tmp_path, NET_ANY)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    r = subprocess.run([sys.executable, "-m", "kmead.tools.kmea_cli", "doctor", "--config", cfg],
                       capture_output=True, text=True, timeout=120, env=env, cwd=tmp_path)
    out = r.stdout
    assert r.returncode == 0, out + r.stderr
    assert r.stderr == ""
    lines = out.splitlines()
    assert all(line.startswith(("OK   ", "FIX  ")) for line in lines[:-1]), out
    assert lines[0].startswith("OK   machine: not a Raspberry Pi")
    assert lines[-1].startswith("kmea doctor: ") and lines[-1].endswith(" 0 to fix")
    assert f"OK   numpy: {np.__version__}" in out
    import cv2

    assert f"OK   opencv: {cv2.__version__}" in out
    assert "system-site-packages" not in out and "picamera2" not in out.split("\n", 1)[1]
    assert f"OK   configuration: {cfg}: source sim" in out


def test_doctor_on_a_pi_without_camera_says_what_to_fix(tmp_path: Path) -> None:
    """On a Pi (the board's model given) without picamera2 or a camera device."""
    doc = Doctor(config=_config(tmp_path, NET_ANY), dev=tmp_path, board=PI4)
    doc.run_all()
    assert not _lines(doc, "machine")
    assert _lines(doc, "camera")[0].startswith(
        f"FIX  camera: no camera device ({tmp_path}/media*, {tmp_path}/video*): connect")
    assert _lines(doc, "picamera2")[0].startswith("FIX  picamera2: picamera2 is not installed")


def test_doctor_with_the_fake_camera_lists_modes(rig, tmp_path: Path) -> None:
    cam = tmp_path / "camera.yml"
    save_camera(pi_camera_v2(), cam)
    cfg = _config(tmp_path, f'[source]\nspec = "picamera"\n[camera]\nfile = "{cam}"\n'
                            + NET_ANY)
    doc = Doctor(config=cfg, codename=None, groups=lambda: [44], dev=tmp_path, board=PI4)
    doc.run_all()
    assert _lines(doc, "camera 0") == [
        "OK   camera 0: imx219 (/base/soc/i2c0mux/i2c@1/imx219@10), modes 640x480@207, "
        "1640x1232@42, 1920x1080@48, 3280x2464@21"]
    assert _lines(doc, "picamera2")[0].startswith("OK   picamera2: ")
    assert "import together" in _lines(doc, "picamera2")[0]
    assert _lines(doc, "camera file") == [f"OK   camera file: {cam} (1640x1232, fx 1357 px)"]
    assert not any(i.is_open for i in rig.instances)  # opened for the modes, then closed


def test_doctor_reports_the_blur_at_1_5_m_s(rig, tmp_path: Path) -> None:
    """The smear of a robot at 1.5 m/s for the configured exposure: OK at the default
    2 ms, FIX with the camera's auto exposure (up to a frame, 33 ms at 30 frames/s)."""
    body = '[source]\nspec = "picamera"\n' + NET_ANY
    doc = Doctor(config=_config(tmp_path, body), codename=None, groups=lambda: [44],
                 dev=tmp_path, board=PI4)
    doc.run_all()
    assert _lines(doc, "motion blur") == [
        "OK   motion blur: exposure 2.0 ms (camera.max_exposure_ms = 2): a robot at 1.5 m/s "
        "smears by 3.0 mm"]
    body = '[source]\nspec = "picamera"\n[camera]\nmax_exposure_ms = 0\n' + NET_ANY
    doc = Doctor(config=_config(tmp_path, body), codename=None, groups=lambda: [44],
                 dev=tmp_path, board=PI4)
    doc.run_all()
    assert _lines(doc, "motion blur") == [
        "FIX  motion blur: exposure 33.3 ms (camera.max_exposure_ms = 0: auto exposure, up to "
        "a frame): a robot at 1.5 m/s smears by 50.0 mm, more than 4.5 mm: markers of moving "
        "robots blur and are lost; set camera.max_exposure_ms = 2 (docs/motion.md)"]


def test_doctor_camera_busy_and_missing(rig, tmp_path: Path) -> None:
    cfg = _config(tmp_path, NET_ANY)
    rig.busy = True
    doc = Doctor(config=cfg, dev=tmp_path, board=PI4)
    doc.run_all()
    (line,) = _lines(doc, "camera 0")
    assert line.startswith("FIX  camera 0: imx219 (/base/soc/i2c0mux/i2c@1/imx219@10): camera 0 "
                           "is busy: another program holds it")
    rig.busy, rig.cameras = False, []
    doc = Doctor(config=cfg, dev=tmp_path, board=PI4)
    doc.run_all()
    assert _lines(doc, "camera")[0].startswith("FIX  camera: libcamera sees no camera: check the "
                                               "ribbon cable")


def test_doctor_numpy_mismatch_is_a_fix(rig, tmp_path: Path) -> None:
    rig.simplejpeg_numpy_major = 2 if np.__version__.startswith("1.") else 1
    doc = Doctor(config=_config(tmp_path, NET_ANY), codename="bookworm", dev=tmp_path,
                 board=PI4)
    doc.run_all()
    (line,) = _lines(doc, "picamera2")
    assert line.startswith(f"FIX  picamera2: picamera2 cannot be imported with numpy "
                           f"{np.__version__}")
    assert "constraints/" in line


def test_doctor_numpy_shadowing_the_apt_numpy(tmp_path: Path) -> None:
    """A venv numpy of another major than the apt one: the fix before picamera2 even fails."""
    other = "1.24.2" if not np.__version__.startswith("1.") else "2.2.4"
    site = tmp_path / "dist-packages"
    (site / f"numpy-{other}.dist-info").mkdir(parents=True)
    doc = Doctor(system_site=site, codename="bookworm")
    doc.check_numpy_opencv()
    (line,) = _lines(doc, "numpy")
    assert line.startswith(f"FIX  numpy: {np.__version__} from the venv hides the apt numpy "
                           f"{other}")
    assert "pip uninstall -y numpy" in line and "constraints/bookworm.txt" in line


def test_doctor_python_of_another_release(tmp_path: Path) -> None:
    doc = Doctor(codename="trixie" if sys.version_info[:2] != (3, 13) else "bookworm",
                 system_site=tmp_path)
    doc.check_python()
    assert _lines(doc, "python")[0].startswith("FIX  python: ")
    assert "/usr/bin/python3 -m venv --system-site-packages" in _lines(doc, "python")[0]


def test_doctor_port_in_use_and_group(tmp_path: Path) -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(1)
        port = s.getsockname()[1]
        cfg = _config(tmp_path, f'[network]\ntelemetry = "tcp://127.0.0.1:{port}"\n'
                                'control = ""\n')
        doc = Doctor(config=cfg, groups=lambda: [], dev=tmp_path)
        loaded = doc.load()
        doc.check_ports(loaded)
    (tele,) = _lines(doc, "port telemetry")
    assert tele.startswith(f"FIX  port telemetry: tcp://127.0.0.1:{port}: Address already in use")
    assert "--set network.telemetry=tcp://127.0.0.1:PORT" in tele
    assert _lines(doc, "port control") == ["OK   port control: off"]
    if os.geteuid() != 0:
        doc.check_permissions()
        assert "is not in the group video" in _lines(doc, "permissions")[0]


def test_doctor_bad_files_and_disk(tmp_path: Path) -> None:
    bad = tmp_path / "cam.yml"
    bad.write_text("not a camera\n")
    cfg = _config(tmp_path, f'[camera]\nfile = "{bad}"\n' + NET_ANY)
    doc = Doctor(config=cfg, min_free_bytes=1 << 60)
    loaded = doc.load()
    doc.check_files(loaded)
    doc.check_disk(loaded)
    (cam,) = _lines(doc, "camera file")
    assert cam.startswith("FIX  camera file: ") and str(bad) in cam
    assert _lines(doc, "disk")[0].startswith("FIX  disk: ")
    broken = _config(tmp_path, "[source]\nfps = -1\n")
    doc = Doctor(config=broken)
    assert doc.load() is None
    (line,) = _lines(doc, "configuration")
    assert line.startswith("FIX  configuration: ") and "source.fps" in line


def test_doctor_says_when_the_robots_poses_go_to_this_machine_only(tmp_path: Path) -> None:
    """The built-in robots send to 127.0.0.1: a FIX on a Pi (the installed service reaches
    no robot), fine off a Pi (the simulator); robots with addresses are OK."""
    on_pi = Doctor(config=_config(tmp_path, NET_ANY), dev=tmp_path, board=PI4)
    on_pi.run_all()
    (line,) = _lines(on_pi, "robots")
    assert line.startswith("FIX  robots: robots' UDP poses go to this machine only "
                           "(udp:127.0.0.1:9001, udp:127.0.0.1:9002): set each [[robots]]")
    off_pi = Doctor(config=_config(tmp_path, NET_ANY), dev=tmp_path, board="")
    off_pi.run_all()
    assert _lines(off_pi, "robots")[0].startswith("OK   robots: robots' UDP poses go to this")
    robots = ('[[robots]]\nname = "amr1"\nmarkers = [40, 41]\nheight = 0.2\n'
              'destinations = ["udp:192.168.1.21:9001"]\n')
    fixed = Doctor(config=_config(tmp_path, NET_ANY + robots), dev=tmp_path, board=PI4)
    fixed.run_all()
    assert _lines(fixed, "robots") == ["OK   robots: 1 robots; UDP poses to udp:192.168.1.21:9001"]


def test_doctor_says_what_the_configured_size_reads_on_each_module(rig, tmp_path: Path) -> None:
    """The sensor line: the mode, its line time and readout skew (0 for the global
    shutter), the CPU estimate for this board; the aspect ratio of another mode is a FIX."""
    import fakecam_rig

    def sensor(camera: dict, size: str, board: str) -> str:
        rig.cameras = [dict(camera)]
        body = f'[source]\nspec = "picamera"\n{size}' + NET_ANY
        doc = Doctor(config=_config(tmp_path, body), codename=None, groups=lambda: [44],
                     dev=tmp_path, board=board)
        doc.run_all()
        (line,) = _lines(doc, "sensor 0")
        return line

    pi5 = "Raspberry Pi 5 Model B Rev 1.0"
    line = sensor(fakecam_rig.IMX219, "", PI4)
    assert line.startswith("OK   sensor 0: Camera Module v2 (imx219) at 1640x1232 "
                           "(source.width/height): the 1640x1232 mode, up to 42 fps, rolling "
                           "shutter 18.90 us a row, readout 23.3 ms (a robot at 1.5 m/s moves "
                           "35 mm meanwhile")
    assert line.endswith("on this Pi 4 about 9 ms CPU a tracked frame, 88 ms a full "
                         "detection (estimate, docs/pi.md)")
    line = sensor(fakecam_rig.IMX296, "width = 1456\nheight = 1088\n", pi5)
    assert "the 1456x1088 mode, up to 60 fps, global shutter: no skew; on this Pi 5" in line
    line = sensor(fakecam_rig.IMX708_WIDE, "", pi5)  # 4:3 asked of a 16:9 sensor
    assert line.startswith("FIX  sensor 0: Camera Module 3 (imx708_wide) at 1640x1232")
    assert line.endswith("set source.width/height to 1536x864 (docs/pi.md, sensor modes)")
    line = sensor(fakecam_rig.IMX708, "width = 1536\nheight = 864\n", pi5)
    assert line.startswith("OK   sensor 0: Camera Module 3 (imx708) at 1536x864 "
                           "(source.width/height): the 2304x1296 mode, up to 56 fps")


def test_doctor_checks_the_autofocus_lens_position(rig, tmp_path: Path) -> None:
    import fakecam_rig

    rig.cameras = [dict(fakecam_rig.IMX708)]
    cam = tmp_path / "camera.yml"

    def lens() -> list[str]:
        body = (f'[source]\nspec = "picamera"\nwidth = 1536\nheight = 864\n[camera]\n'
                f'file = "{cam}"\n' + NET_ANY)
        doc = Doctor(config=_config(tmp_path, body), codename=None, groups=lambda: [44],
                     dev=tmp_path, board=PI4)
        doc.run_all()
        return _lines(doc, "lens")

    from kmea.vision.camera import CameraModel

    wide = CameraModel(np.array([[1200.0, 0, 767.5], [0, 1200.0, 431.5], [0, 0, 1]]),
                       np.zeros(5), 1536, 864)
    save_camera(wide, cam)
    (line,) = lens()
    assert line.startswith(f"FIX  lens: camera 0 (imx708) has autofocus and {cam} stores no "
                           "lens_position")
    save_camera(wide, cam, meta={"lens_position": 0.5})
    assert lens() == ["OK   lens: camera 0 (imx708) has autofocus: kmead locks the lens at "
                      "0.5 dioptres (2.00 m; the camera file's lens_position) and warns if it "
                      "reports another position"]
    rig.cameras = [dict(fakecam_rig.IMX219)]  # fixed focus: no lens line
    assert lens() == []
