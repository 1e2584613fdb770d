"""``kmea doctor``: what a technician runs first on a new Raspberry Pi.

One line per check, ``OK`` or ``FIX`` followed by what to do; exit 0 when every line is OK,
1 otherwise. Checks, in order: Python and whether the venv sees the apt packages; numpy
(against the apt numpy picamera2 was built for), OpenCV, picamera2 and whether they import
together; the camera as libcamera sees it, with its modes; permissions (group video, the
camera device nodes); the configured telemetry/control ports; the configuration, map and
camera files (as ``kmead --check``); the sensor mode the configured size reads (line time,
readout skew, aspect ratio, CPU a frame on this Pi 4 or Pi 5) and an autofocus camera's lens
position in the camera file; free disk space for logs.

Nothing here starts the camera: it is opened only to read its modes, and closed.
"""

from __future__ import annotations

import argparse
import contextlib
import grp
import os
import shutil
import socket
import sys
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any

from kmea.wire.destinations import THIS_MACHINE_ONLY, this_machine_only
from kmead.outputs.retention import usage

__all__ = ["Check", "Doctor", "add_arguments", "run"]

SERVICE_CONFIG = Path("/etc/kmead/kmead.toml")
STATE_DIR = Path("/var/lib/kmea")
SYSTEM_SITE = Path("/usr/lib/python3/dist-packages")
# Python of each Raspberry Pi OS release: the apt picamera2 is built for it alone.
OS_PYTHON = {"bookworm": (3, 11), "trixie": (3, 13)}
MIN_FREE_BYTES = 1 << 30
BOARD_MODEL = Path("/proc/device-tree/model")


@dataclass
class Check:
    """One line: ``ok`` and the text (for a FIX: what is wrong, then what to do)."""

    ok: bool
    name: str
    text: str

    def line(self) -> str:
        return f"{'OK ' if self.ok else 'FIX'}  {self.name}: {self.text}"


@dataclass
class Doctor:
    """The checks, with the system's paths and lookups injectable for tests."""

    config: str | None = None
    sets: list[str] = field(default_factory=list)
    dev: Path = Path("/dev")
    system_site: Path = SYSTEM_SITE
    codename: str | None = None
    groups: Callable[[], Iterable[int]] = os.getgroups
    min_free_bytes: int = MIN_FREE_BYTES
    board: str | None = None  # the device tree's model; None: read from BOARD_MODEL
    results: list[Check] = field(default_factory=list)
    # What check_camera saw: (camera number, model, advertises AfMode) per camera.
    sensors: list[tuple[int, str, bool]] = field(default_factory=list)

    def add(self, ok: bool, name: str, text: str) -> Check:
        c = Check(ok, name, text)
        self.results.append(c)
        return c

    # ------------------------------------------------------------------ software
    def check_python(self, pi: bool = True) -> None:
        v = sys.version_info
        ver = f"{v.major}.{v.minor}.{v.micro}"
        want = OS_PYTHON.get(self.codename or "")
        if want and (v.major, v.minor) != want:
            self.add(False, "python", f"{ver} ({sys.executable}), but Raspberry Pi OS "
                     f"{self.codename}'s picamera2 is for Python {want[0]}.{want[1]}: make the "
                     f"venv with the system python: `/usr/bin/python3 -m venv "
                     f"--system-site-packages .venv`")
        elif v < (3, 10):
            self.add(False, "python", f"{ver}: kmea needs Python 3.10 or later")
        else:
            self.add(True, "python", f"{ver} ({sys.executable})")
        in_venv = sys.prefix != sys.base_prefix
        if pi and in_venv and self.system_site.is_dir():
            sees = any(Path(p) == self.system_site for p in sys.path)
            if sees:
                self.add(True, "venv", f"{sys.prefix} sees the apt packages ({self.system_site})")
            else:
                self.add(False, "venv", f"{sys.prefix} does not see the apt packages (picamera2"
                         f", libcamera): make it again with `python3 -m venv "
                         f"--system-site-packages {sys.prefix}` and reinstall "
                         f"(README, On the Raspberry Pi)")

    def check_numpy_opencv(self) -> bool:
        from kmea.sources.picamera import system_numpy_version

        try:
            import numpy as np
        except Exception as e:
            self.add(False, "numpy", f"cannot be imported: {type(e).__name__}: {e}")
            return False
        where = "apt" if Path(np.__file__).is_relative_to(self.system_site) else "venv"
        apt = system_numpy_version(self.system_site)
        if apt and where == "venv" and apt.split(".")[0] != np.__version__.split(".")[0]:
            self.add(False, "numpy", f"{np.__version__} from the venv hides the apt numpy {apt} "
                     f"that picamera2's simplejpeg is built for (import fails: numpy.dtype size "
                     f"changed): `.venv/bin/pip uninstall -y numpy && .venv/bin/pip install -c "
                     f"constraints/{self.codename or 'bookworm'}.txt -e .`")
        else:
            extra = f"; apt numpy {apt}" if apt and where == "venv" else ""
            self.add(True, "numpy", f"{np.__version__} ({where}{extra})")
        try:
            import cv2
        except Exception as e:
            self.add(False, "opencv", f"cannot be imported with numpy {np.__version__}: "
                     f"{type(e).__name__}: {e}: `.venv/bin/pip install -c "
                     f"constraints/{self.codename or 'bookworm'}.txt -e .`")
            return False
        from kmea.vision.cvcompat import MIN_CV_VERSION, cv_version

        ver = cv_version()
        if ver < MIN_CV_VERSION:
            self.add(False, "opencv", f"{cv2.__version__} is older than 4.8 (the ArUco API kmea "
                     f"uses): `.venv/bin/pip install 'opencv-python-headless>=4.8'` (not the apt "
                     f"python3-opencv)")
            return False
        self.add(True, "opencv", f"{cv2.__version__}")
        return True

    def check_picamera2(self) -> Any:
        """The picamera2 module trio, or None (with a FIX line)."""
        from kmea.sources.base import SourceError
        from kmea.sources.picamera import import_picamera2

        try:
            mods = import_picamera2()
        except SourceError as e:
            self.add(False, "picamera2", str(e).removeprefix("picamera: "))
            return None
        try:
            ver = metadata.version("picamera2")
        except metadata.PackageNotFoundError:
            ver = "version unknown"
        import cv2
        import numpy as np

        self.add(True, "picamera2", f"{ver}; numpy {np.__version__}, OpenCV {cv2.__version__} "
                 f"and picamera2 import together")
        return mods

    # ------------------------------------------------------------------ camera
    def _device_nodes(self) -> list[Path]:
        nodes: list[Path] = []
        for pattern in ("media*", "video*", "dma_heap/*"):
            nodes += sorted(self.dev.glob(pattern))
        return nodes

    def check_camera(self, mods: Any) -> None:
        from kmea.sources.picamera import describe_open_error

        media = sorted(self.dev.glob("media*")) + sorted(self.dev.glob("video*"))
        if mods is None:
            if not media:
                self.add(False, "camera", f"no camera device ({self.dev}/media*, "
                         f"{self.dev}/video*): connect the camera (ribbon contacts the right way "
                         f"round), `camera_auto_detect=1` in /boot/firmware/config.txt, reboot; "
                         f"and install picamera2 (above)")
            else:
                self.add(False, "camera", "cannot ask libcamera without picamera2: fix the "
                         "picamera2 line above, then run kmea doctor again")
            return
        Picamera2 = mods[0]
        try:
            cams = list(Picamera2.global_camera_info())
        except Exception as e:
            self.add(False, "camera", f"libcamera cannot list cameras ({type(e).__name__}: {e})"
                     f": `rpicam-hello --list-cameras` says why")
            return
        if not cams:
            self.add(False, "camera", "libcamera sees no camera: check the ribbon cable (both "
                     "ends, contacts the right way round), `camera_auto_detect=1` in "
                     "/boot/firmware/config.txt, reboot, then `rpicam-hello --list-cameras`")
            return
        for i, info in enumerate(cams):
            name = f"camera {i}"
            what = f"{info.get('Model', '?')} ({info.get('Id', '?')})"
            try:
                cam = Picamera2(i)
            except Exception as e:
                self.add(False, name, f"{what}: {describe_open_error(e, i)} (a running kmead "
                         f"holds it: `sudo systemctl stop kmead` to read its modes)")
                continue
            try:
                modes = cam.sensor_modes
                try:
                    af = "AfMode" in dict(cam.camera_controls)
                except Exception:  # an old picamera2: no autofocus to lock
                    af = False
                self.sensors.append((i, str(info.get("Model", "?")), af))
            except Exception as e:
                modes = None
                err = f"{type(e).__name__}: {e}"
            finally:
                with contextlib.suppress(Exception):
                    cam.close()
            if modes is None:
                self.add(False, name, f"{what}: cannot read its modes ({err})")
                continue
            listed = ", ".join(f"{m['size'][0]}x{m['size'][1]}@{m.get('fps', 0):.0f}"
                               for m in modes if "size" in m)
            self.add(True, name, f"{what}, modes {listed}")

    def check_permissions(self) -> None:
        if os.geteuid() == 0:
            self.add(True, "permissions", "root (the service runs as kmead: `sudo -u kmead "
                     ".../kmea doctor` checks as it)")
        else:
            try:
                video = grp.getgrnam("video").gr_gid
            except KeyError:
                video = None
            user = _user()
            if video is None:
                self.add(False, "permissions", "no group video on this system: not Raspberry "
                         "Pi OS?")
            elif video not in set(self.groups()):
                self.add(False, "permissions", f"{user} is not in the group video (camera "
                         f"devices): `sudo usermod -aG video {user}`, then log in again")
            else:
                self.add(True, "permissions", f"{user} is in the group video")
        denied = [str(n) for n in self._device_nodes()
                  if n.exists() and not os.access(n, os.R_OK | os.W_OK)]
        if denied:
            self.add(False, "devices", f"no read/write access to {', '.join(denied)}: add the "
                     f"user to the owning group (`ls -l {denied[0]}`)")

    # ------------------------------------------------------------------ configuration
    def load(self) -> Any:
        from kmead.config.layers import ConfigError, load_config

        path = self.config
        try:
            cfg = load_config(path, sets=self.sets)
        except (ConfigError, OSError) as e:
            self.add(False, "configuration", f"{e}: fix the file, then `kmead --check`")
            return None
        spec = cfg["source"]["spec"]
        where = path or "the built-in default"
        note = ("" if spec.split("?")[0].split(":")[0] in ("picamera", "camera") else
                " (not the camera: the service's ExecStart says --source picamera)")
        self.add(True, "configuration", f"{where}: source {spec}{note}")
        return cfg

    def check_files(self, cfg: Any) -> None:
        """The checks of start-up and ``kmead --check`` (:func:`kmead.config.plan.plan_startup`),
        one line each for the map and the camera file."""
        from kmea.vision.camera import load_camera
        from kmead.config.plan import plan_startup
        from kmead.config.startup import StartupError

        try:
            warnings = plan_startup(cfg).warnings
        except StartupError as e:
            what, _, why = str(e).partition(": ")
            name, fix = (("map", "fix the file (`kmea map check FILE`)") if what == "map" else
                         ("camera file", "calibrate again (`kmea calibrate`) or fix camera.file")
                         if what == "camera" else ("files", "fix it, then `kmead --check`"))
            self.add(False, name, f"{why or e}: {fix}")
            return
        for w in warnings:
            if "not opened by --check" not in w:
                self.add(False, "files", w)
        self.add(True, "map", cfg["map"]["file"] or "the built-in RobotAtFactory 4.0 map")
        cam = cfg["camera"]["file"]
        live = cfg["source"]["spec"].split("?")[0].split(":")[0] in ("picamera", "camera")
        if not cam and not live:
            self.add(True, "camera file", f"none needed for the source "
                     f"{cfg['source']['spec']} (it brings its camera model or uses a nominal "
                     "one)")
            return
        if not cam:
            self.add(False, "camera file", "none configured: a nominal Pi Camera v2 model is "
                     "used; calibrate (`kmea calibrate --source picamera ... --out "
                     "/etc/kmead/camera.yml`) and set camera.file")
            return
        model = load_camera(cam)  # the plan has loaded it once already: it loads
        self.add(True, "camera file", f"{cam} ({model.width}x{model.height}, "
                 f"fx {model.fx:.0f} px)")

    def check_motion(self, cfg: Any) -> None:
        """The smear of a robot at 1.5 m/s at the configured exposure (kmea.timing)."""
        from kmea.timing import BLUR_WARN_M, blur_m

        ms = float(cfg["camera"]["max_exposure_ms"])
        fps = float(cfg["source"]["fps"]) or 30.0
        if ms > 0:
            exp, what = min(ms * 1e-3, 1.0 / fps), f"camera.max_exposure_ms = {ms:g}"
        else:
            exp, what = 1.0 / fps, "camera.max_exposure_ms = 0: auto exposure, up to a frame"
        b = blur_m(1.5, exp)
        pi = cfg["source"]["spec"].split("?")[0].split(":")[0] == "picamera"
        text = (f"exposure {exp * 1e3:.1f} ms ({what}): a robot at 1.5 m/s smears by "
                f"{b * 1e3:.1f} mm")
        if b <= BLUR_WARN_M:
            self.add(True, "motion blur", text)
        elif not pi:
            self.add(True, "motion blur", f"{text} (applies to the picamera source only)")
        else:
            self.add(False, "motion blur", f"{text}, more than {BLUR_WARN_M * 1e3:g} mm: markers "
                     f"of moving robots blur and are lost; set camera.max_exposure_ms = 2 "
                     f"(docs/motion.md)")

    def check_sensor(self, cfg: Any) -> None:
        """Per camera: the mode the configured size reads, its timing, the aspect ratio,
        CPU a frame on this board (kmea.camera_advice); the autofocus lens position."""
        from kmea.camera_advice import BOARD_NAME, advise, board_of
        from kmea.vision.camera import CameraError
        from kmea.vision.lens import load_lens_position

        w, h = int(cfg["source"]["width"] or 1640), int(cfg["source"]["height"] or 1232)
        board = board_of(self.board or "")
        for i, model, af in self.sensors:
            name = f"sensor {i}"
            adv = advise(model, w, h)
            if adv is None:
                self.add(True, name, f"{model}: no timing table in kmea.timing: poses are "
                         "stamped without the rolling-shutter correction")
                continue
            m, rw, rh = adv.mode, *adv.recommended()
            shutter = ("global shutter: no skew" if adv.sensor.global_shutter else
                       f"rolling shutter {m.line_s * 1e6:.2f} us a row, readout "
                       f"{adv.readout_s * 1e3:.1f} ms (a robot at 1.5 m/s moves "
                       f"{adv.skew_m(1.5) * 1e3:.0f} mm meanwhile; each pose is stamped at "
                       f"its rows' time)")
            cpu = ""
            if board is not None:
                tracked, full = adv.cpu_ms(board)
                cpu = (f"; on this {BOARD_NAME[board]} about {tracked:.0f} ms CPU a tracked "
                       f"frame, {full:.0f} ms a full detection (estimate, docs/pi.md)")
            text = (f"{adv.sensor.product} ({model}) at {w}x{h} (source.width/height): the "
                    f"{m.width}x{m.height} mode, up to {m.fps:.0f} fps, {shutter}{cpu}")
            if not adv.aspect_ok:
                self.add(False, name, f"{text}; {w}x{h} is not the mode's aspect ratio (the "
                         f"ISP crops the field): set source.width/height to {rw}x{rh} "
                         f"(docs/pi.md, sensor modes)")
            else:
                self.add(True, name, text)
            if not af:
                continue
            cam_file = cfg["camera"]["file"]
            try:
                lens = load_lens_position(cam_file) if cam_file else None
            except CameraError as e:
                self.add(False, "lens", f"{e}: calibrate again (kmea calibrate)")
                continue
            if lens is None:
                self.add(False, "lens", f"camera {i} ({model}) has autofocus and "
                         f"{cam_file or 'no camera file'} stores no lens_position: the "
                         f"calibration holds at one focus only; calibrate with the lens "
                         f"fixed, `kmea calibrate --source 'picamera?lens_position=D' ...` "
                         f"(D = 1 / the camera's height above the floor in m), which stores "
                         f"it (docs/camera.md, autofocus)")
            else:
                self.add(True, "lens", f"camera {i} ({model}) has autofocus: kmead locks "
                         f"the lens at {lens:g} dioptres ({1 / lens:.2f} m; the camera "
                         f"file's lens_position) and warns if it reports another position"
                         if lens > 0 else f"camera {i} ({model}) has autofocus: kmead locks "
                         f"the lens at infinity (the camera file's lens_position 0)")

    def check_ports(self, cfg: Any) -> None:
        for key in ("telemetry", "control"):
            ep = cfg["network"][key]
            name = f"port {key}"
            if not ep:
                self.add(True, name, "off")
                continue
            if not ep.startswith("tcp://"):
                self.add(True, name, f"{ep} (not TCP: not checked)")
                continue
            host, _, port = ep[len("tcp://"):].rpartition(":")
            if port in ("*", "0", ""):
                self.add(True, name, f"{ep} (any free port)")
                continue
            host = {"*": "0.0.0.0", "localhost": "127.0.0.1"}.get(host, host)
            err = _bind_error((host or "").strip("[]"), int(port))
            if err is None:
                self.add(True, name, f"{ep} is free")
            else:
                self.add(False, name, f"{ep}: {err} (a kmead already running? `ss -ltnp "
                         f"'sport = :{port}'`): stop it, or choose another port with --set "
                         f"network.{key}=tcp://127.0.0.1:PORT")

    def check_robots(self, cfg: Any, pi: bool) -> None:
        """Where the robots' datagrams go: nowhere but this machine is a FIX on a Pi (the
        built-in robots' destinations), fine for the simulator elsewhere."""
        robots = cfg["robots"]
        dests = ", ".join(d for r in robots for d in r["destinations"]) or "none"
        if this_machine_only(robots):
            fix = ("set each [[robots]] destinations in the configuration to its robot's "
                   "address, e.g. [\"udp:192.168.1.21:9001\"] (docs/pi.md, Robots)")
            self.add(not pi, "robots", f"{THIS_MACHINE_ONLY} ({dests})"
                     + (f": {fix}" if pi else "; on the Pi: " + fix))
        else:
            self.add(True, "robots", f"{len(robots)} robots; UDP poses to {dests}")

    def check_retention(self, cfg: Any, pi: bool) -> None:
        """What kmead's files take where it writes them, and what retention keeps."""
        lg = cfg["log"]
        dirs = {Path(lg["dir"] or (STATE_DIR if STATE_DIR.is_dir() else Path.cwd()))}
        dirs |= {Path(p).parent for p in (lg["csv"], lg["record"]) if p}
        if (STATE_DIR / "logs").is_dir():
            dirs.add(STATE_DIR / "logs")
        u = usage(dirs)
        where = ", ".join(sorted(str(d) for d in dirs))
        held = (f"{u.files} of kmead's files, {u.bytes / 1e6:.0f} MB"
                + (f", the oldest {u.oldest_days:.1f} days old" if u.oldest_days is not None
                   else ""))
        rule = (f"kept: {lg['keep_days']:g} days and {lg['keep_mb']:g} MB at most, parts of "
                f"{lg['part_mb']:g} MB / {lg['part_min']:g} min")
        if not (lg["keep_days"] or lg["keep_mb"]):
            self.add(not pi, "retention", f"{where}: {held}; nothing is ever removed "
                     "(log.keep_days = log.keep_mb = 0): a service logging every frame "
                     "fills an SD card in days; set log.keep_days and log.keep_mb")
        else:
            self.add(True, "retention", f"{where}: {held}; {rule}")

    def check_disk(self, cfg: Any) -> None:
        target = Path(cfg["log"]["csv"]).parent if cfg and cfg["log"]["csv"] else (
            STATE_DIR if STATE_DIR.is_dir() else Path.cwd())
        probe = target
        while not probe.exists() and probe != probe.parent:
            probe = probe.parent
        free = shutil.disk_usage(probe).free
        text = f"{free / (1 << 30):.1f} GiB free for logs in {target}"
        if free < self.min_free_bytes:
            self.add(False, "disk", f"{text}, under {self.min_free_bytes / (1 << 30):.1f} GiB: "
                     f"delete old logs (/var/lib/kmea/logs), `sudo journalctl --vacuum-size=100M`")
        else:
            self.add(True, "disk", text)

    # ------------------------------------------------------------------ all
    def on_pi(self) -> bool:
        if self.board is None:
            try:
                self.board = BOARD_MODEL.read_bytes().rstrip(b"\0").decode("ascii", "replace")
            except OSError:
                self.board = ""
        return "Raspberry Pi" in self.board

    def run_all(self) -> list[Check]:
        pi = self.on_pi()
        if not pi:
            # A laptop or CI machine: no apt picamera2, camera or video group to look for,
            # and nothing to rebuild for them.
            self.codename = None
            board = self.board or "no device-tree model"
            self.add(True, "machine", f"not a Raspberry Pi ({board}): the Pi checks (apt "
                     "packages, picamera2, camera, video group) skipped; Python, numpy, "
                     "OpenCV, configuration, ports, files and disk checked")
        self.check_python(pi)
        numpy_ok = self.check_numpy_opencv()
        if pi:
            self.check_camera(self.check_picamera2() if numpy_ok else None)
            self.check_permissions()
        cfg = self.load()
        if cfg is not None:
            self.check_ports(cfg)
            self.check_files(cfg)
            if pi:
                self.check_sensor(cfg)
            self.check_motion(cfg)
            self.check_robots(cfg, pi)
            self.check_retention(cfg, pi)
        self.check_disk(cfg)
        return self.results


def _user() -> str:
    try:
        import pwd

        return pwd.getpwuid(os.geteuid()).pw_name
    except (KeyError, ImportError):
        return str(os.geteuid())


def _bind_error(host: str, port: int) -> str | None:
    """Why a TCP listener cannot bind ``host:port`` now, or None (bound and closed at once).

    SO_REUSEADDR as ZeroMQ sets it, so a closing connection's TIME_WAIT does not count."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
            s.listen(1)
        except OSError as e:
            return e.strerror or str(e)
    return None


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.description = ("Check this machine for kmead: Python, numpy, OpenCV and picamera2, the "
                     "camera and its modes, permissions, ports, the configuration, map and "
                     "camera files, disk space. Each line is OK or says what to fix.")
    p.add_argument("--config", metavar="FILE",
                   help=f"the configuration kmead runs with (default: {SERVICE_CONFIG} when it "
                        f"exists, else the built-in default)")
    p.add_argument("--set", metavar="SECTION.KEY=VALUE", action="append", default=[],
                   help="override one key, as for kmead")


def run(args: argparse.Namespace) -> int:
    from kmea.sources.picamera import os_codename

    config = args.config
    if config is None and SERVICE_CONFIG.is_file():
        config = str(SERVICE_CONFIG)
    doc = Doctor(config=config, sets=list(args.set), codename=os_codename())
    for c in doc.run_all():
        print(c.line(), flush=True)
    bad = sum(not c.ok for c in doc.results)
    print(f"kmea doctor: {len(doc.results) - bad} OK, {bad} to fix")
    return 1 if bad else 0
