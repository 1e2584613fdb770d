"""The Raspberry Pi camera through picamera2, as picamera2 really behaves.

Imported only when a ``picamera`` source is opened (``open_source("picamera")``); picamera2
itself is imported inside :func:`import_picamera2`, so this module loads anywhere.

What picamera2 does that this module handles (references are to raspberrypi/picamera2):

- **Import failures are not only ImportError.** ``from picamera2 import Picamera2`` imports the
  apt ``simplejpeg`` (picamera2/encoders/jpeg_encoder.py); built against Raspberry Pi OS's
  numpy, it raises ``ValueError: numpy.dtype size changed`` when a venv's numpy of the other
  major version shadows it (issues 1088, 1211). PyPI's picamera2 without the apt libcamera
  bindings fails on ``import libcamera``. Each becomes one line naming the cause and the fix.
- **Camera missing or busy.** ``Picamera2()`` turns every failure into
  ``RuntimeError("Camera __init__ sequence did not complete.")`` raised inside its ``except``
  block, so the reason ("Device or resource busy", "Camera(s) not found") is only in the
  exception chain; old versions give ``IndexError`` for no camera. The cameras are counted
  first with ``Picamera2.global_camera_info()`` and the chain is read for "busy".
- **capture_request() waits forever by default** (``dispatch_functions``: ``wait=None`` means
  ``job.get_result(timeout=None)``). It is called with ``wait=<seconds>``, which raises
  ``TimeoutError`` (``concurrent.futures``) after that long. The timed-out job stays in the
  camera's job list and would swallow (and never release) the next frame, so a stalled camera
  is closed and opened again rather than asked again; after ``reopen`` consecutive stalls the
  source raises :class:`SourceError` and the daemon exits non-zero so systemd restarts it.
- **The Y plane, full range, copied alone.** YUV420 is mapped as a (H * 3/2, stride) array
  (request.py, ``MappedArray``); the stride is the width rounded up to 64 bytes on the Pi 4 ISP
  (1640 -> 1664), so only ``[:H, :W]`` is copied. ``create_video_configuration`` picks Rec709
  (limited range, Y in 16..235) at 1280x720 and above; ``colour_space=Sycc`` asks for full range.
- **Timestamps.** ``SensorTimestamp`` is nanoseconds on CLOCK_MONOTONIC at the start of the
  frame's readout (examples/timestamp_capture.py compares it with ``time.monotonic_ns()``).
  :attr:`Frame.timestamp` is that instant as unix time (seconds); ``meta`` keeps the raw value,
  ``exposure_time_us`` and ``frame_duration_us``, ``analogue_gain``.
- **When each row was seen.** Row 0 is read out at ``SensorTimestamp`` after ``ExposureTime``
  us of exposure (picamera2 computes the exposure start as ``SensorTimestamp - 1000 *
  ExposureTime``); each later row ends one line time later (:mod:`kmea.timing`: 18.90 us
  per IMX219 sensor row; each model's mode table in :data:`kmea.timing.SENSORS`, 0 for the
  IMX296's global shutter). ``meta["timing"]`` is that :class:`kmea.timing.FrameTiming`; for
  a sensor without a table the line time is left 0 (no rolling-shutter correction) and the
  source says so once.
- **Autofocus.** A camera with a lens driver (Camera Module 3) advertises ``AfMode`` and
  ``LensPosition`` in ``camera_controls``; picamera2 refuses a control the camera does not
  advertise ("Control AfMode is not advertised by libcamera"), so they are set only there:
  ``AfMode`` manual (libcamera's AfModeManual, 0) and ``LensPosition`` (dioptres) from the
  camera file (:mod:`kmea.vision.lens`). The lens reports its position in each request's
  metadata (``LensPosition``): ``meta["lens_position"]``; a position other than the
  calibration's is warned about once.
- **Exposure.** ``max_exposure_ms`` > 0 sets ``ExposureTime`` to it: libcamera's Raspberry Pi
  AGC then keeps that exposure and makes up the light with analogue gain (and noise). The
  AGC has no "longest exposure" control short of a custom exposure mode in the tuning file,
  so the exposure is that figure, not at most it; 0 leaves exposure and gain to the AGC
  (indoors 10-30 ms: a robot at 1.5 m/s smears by 15-45 mm). The frame rate is asked as
  ``FrameRate`` (picamera2 turns it into ``FrameDurationLimits``), which bounds the
  exposure too.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import importlib
import inspect
import logging
import os
import re
import time
from pathlib import Path
from typing import Any

import numpy as np

from kmea.sources.base import Frame, FrameSource, SourceError
from kmea.timing import FrameTiming, line_time, sensor_for
from kmea.vision.lens import lens_differs

__all__ = [
    "PICAMERA2_MISSING",
    "PiCameraSource",
    "describe_open_error",
    "import_picamera2",
    "monotonic_to_unix_ns",
    "os_codename",
    "system_numpy_version",
]

log = logging.getLogger(__name__)

PICAMERA2_MISSING = ("picamera2 is not installed: on Raspberry Pi OS run `sudo apt install "
                     "python3-picamera2` and create the venv with --system-site-packages")

#: What ``capture_request`` may raise on timeout: the built-in on Python >= 3.11, a separate
#: class in concurrent.futures on 3.10.
_TIMEOUTS = (TimeoutError, concurrent.futures.TimeoutError)

_SYSTEM_SITE = Path("/usr/lib/python3/dist-packages")

#: The default stall timeout is the larger of this and 10 frame periods (seconds).
MIN_STALL_TIMEOUT_S = 1.0


def os_codename(os_release: Path = Path("/etc/os-release")) -> str | None:
    """Debian codename (``bookworm``, ``trixie``) from os-release, or None when unknown."""
    try:
        text = os_release.read_text(encoding="utf-8", errors="replace")
    except OSError:
        return None
    m = re.search(r'^VERSION_CODENAME="?([a-z]+)"?\s*$', text, re.M)
    return m.group(1) if m else None


def system_numpy_version(site: Path = _SYSTEM_SITE) -> str | None:
    """Version of the apt numpy (``python3-numpy``) in ``site``, or None when there is none."""
    for info in sorted(site.glob("numpy-*.*-info")):
        m = re.match(r"numpy-([0-9][^-]*?)(?:\.dist-info|\.egg-info)$", info.name)
        if m:
            return m.group(1)
    return None


def _constraints_hint() -> str:
    name = os_codename()
    return f"constraints/{name if name in ('bookworm', 'trixie') else 'bookworm'}.txt"


def import_picamera2() -> tuple[Any, Any, Any]:
    """``(Picamera2, MappedArray, libcamera)``, or :class:`SourceError` with one line.

    The line names the cause and the fix; the original exception is not chained (it would
    only repeat a traceback through picamera2's imports).
    """
    try:
        # picamera2 first: with neither installed, the missing one to name is picamera2.
        picamera2 = importlib.import_module("picamera2")
        libcamera = importlib.import_module("libcamera")
        Picamera2, MappedArray = picamera2.Picamera2, picamera2.MappedArray
    except ModuleNotFoundError as e:
        if e.name == "libcamera":
            msg = ("picamera2 is installed but libcamera's Python bindings are not (picamera2 "
                   "from PyPI?): `sudo apt install python3-picamera2 python3-libcamera`, "
                   "`.venv/bin/pip uninstall -y picamera2`, and create the venv with "
                   "--system-site-packages")
        elif e.name and e.name.split(".")[0] == "picamera2":
            msg = PICAMERA2_MISSING
        else:
            msg = (f"picamera2 cannot be imported: module {e.name!r} is missing ({e}); "
                   f"`sudo apt install --reinstall python3-picamera2`, then `kmea doctor`")
        raise SourceError(f"picamera: {msg}") from None
    except ValueError as e:
        if "size changed" in str(e):
            sys_np = system_numpy_version()
            raise SourceError(
                f"picamera: picamera2 cannot be imported with numpy {np.__version__} "
                f"({e}): Raspberry Pi OS's picamera2/simplejpeg are built for its own numpy "
                f"{sys_np or '(python3-numpy)'}; fix: `.venv/bin/pip uninstall -y numpy && "
                f".venv/bin/pip install -c {_constraints_hint()} -e .` (README, On the "
                f"Raspberry Pi)") from None
        raise SourceError(f"picamera: picamera2 cannot be imported: ValueError: {e}; "
                          f"run `kmea doctor`") from None
    except Exception as e:  # picamera2's imports run native code: any error can come out
        raise SourceError(f"picamera: picamera2 cannot be imported: {type(e).__name__}: {e}; "
                          f"run `kmea doctor`") from None
    return Picamera2, MappedArray, libcamera


def _parameters(cls: Any) -> set[str]:
    try:
        return set(inspect.signature(cls).parameters)
    except (TypeError, ValueError):
        return set()


def _chain_text(exc: BaseException) -> str:
    """The messages of ``exc`` and of every exception it was raised from or during."""
    parts, seen = [], set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        parts.append(f"{type(e).__name__}: {e}")
        e = e.__cause__ or e.__context__
    return " <- ".join(parts)


_BUSY_RE = re.compile(r"busy|EBUSY|code: -16|failed to acquire|in use by another", re.I)
_MISSING_RE = re.compile(r"not found|list index out of range|no camera", re.I)

_BUSY_FIX = ("another program holds it (a second kmead, rpicam-hello/rpicam-vid, a Python "
             "session); `sudo fuser -v /dev/media* /dev/video*` names it: stop it, then "
             "start again")
_MISSING_FIX = ("check the ribbon cable (both ends, contacts the right way round), "
                "`camera_auto_detect=1` in /boot/firmware/config.txt, reboot, then "
                "`rpicam-hello --list-cameras`")


def kmead_holding_camera(proc: Path = Path("/proc")) -> int | None:
    """The pid of a running ``kmead`` on a Pi camera (the service, or one by hand), else
    None: from the processes' command lines (Linux)."""
    try:
        entries = [p for p in proc.iterdir() if p.name.isdigit() and int(p.name) != os.getpid()]
    except OSError:
        return None
    for p in entries:
        try:
            argv = (p / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        # The program: kmead itself (/opt/kmea/bin/kmead), a Python running it, or -m
        # kmead.cli; behind an emulator too (qemu-user's binfmt with P shows
        # [qemu, /usr/bin/python3, python3, /path/kmead, ...]).
        program = argv[:4] + ([argv[argv.index(b"-m") + 1]] if b"-m" in argv[:-1] else [])
        if (any(a.endswith(b"/kmead") or a in (b"kmead", b"kmead.cli") for a in program)
                and any(a.startswith(b"picamera") for a in argv)):
            return int(p.name)
    return None


def describe_open_error(exc: BaseException, camera: int = 0) -> str:
    """One line for an exception out of ``Picamera2(camera)``: busy, missing or other."""
    text = _chain_text(exc)
    if _BUSY_RE.search(text):
        pid = kmead_holding_camera()
        if pid is not None:
            return (f"camera {camera} is busy: kmead (pid {pid}, the service when installed) "
                    "holds it; `sudo systemctl stop kmead` first (`sudo systemctl start kmead` "
                    "after), or take the running kmead's frames without stopping it: "
                    "`kmea snapshot`, the terminal UI's Camera tab")
        return f"camera {camera} is busy: {_BUSY_FIX}"
    if isinstance(exc, IndexError) or _MISSING_RE.search(text):
        return f"no camera {camera} found by libcamera: {_MISSING_FIX}"
    return f"cannot open camera {camera}: {text}; run `kmea doctor`"


def monotonic_to_unix_ns(t_mono_ns: int) -> int:
    """A CLOCK_MONOTONIC instant (ns) as unix time (ns), by the clocks' offset now.

    The offset is read between two monotonic readings; the pair closest together of three
    bounds the error to the time between them (~1 us). A wall-clock step (NTP) moves the
    result by that step, which is what a receiver comparing with its own clock wants.
    """
    best: tuple[int, int] | None = None
    for _ in range(3):
        m0 = time.monotonic_ns()
        w = time.time_ns()
        m1 = time.monotonic_ns()
        if best is None or m1 - m0 < best[0]:
            best = (m1 - m0, w - (m0 + m1) // 2)
    assert best is not None
    return int(t_mono_ns) + best[1]


class PiCameraSource(FrameSource):
    """The Raspberry Pi camera through picamera2, greyscale (the Y plane of YUV420, full range).

    Options: ``width``, ``height`` (default 1640x1232, the IMX219 full-field binned mode),
    ``fps`` (default 30), ``buffer_count`` (default 4), ``camera`` (libcamera's camera number,
    default 0), ``timeout`` (seconds without a frame that count as a stall; default the larger
    of 1 s and 10 frame periods), ``reopen`` (consecutive stalls survived by closing and
    opening the camera again before the source gives up; default 3), ``max_exposure_ms``
    (0: the AGC's own exposure; > 0: that exposure, gain making up the light),
    ``lens_position`` (dioptres: the calibration's focus; autofocus cameras only; None: the
    lens is locked where libcamera puts it).

    Frame: image (H, W) uint8, full-range luma; timestamp: unix time (s) of the start of the
    frame's readout (sensor timestamp); meta: ``sensor_timestamp_ns`` (CLOCK_MONOTONIC),
    ``exposure_time_us``, ``frame_duration_us``, ``analogue_gain`` when the camera reports
    them, ``lens_position`` (dioptres) from an autofocus camera, and ``timing``
    (:class:`kmea.timing.FrameTiming`) with the sensor timestamp.
    Raises :class:`SourceError` (one line) when picamera2 cannot be imported, the camera is
    missing or busy, or it stalled ``reopen + 1`` times in a row.
    """

    live = True

    def __init__(self, width: int = 1640, height: int = 1232, fps: float = 30.0,
                 buffer_count: int = 4, camera: int = 0, timeout: float | None = None,
                 reopen: int = 3, max_exposure_ms: float = 0.0,
                 lens_position: float | None = None) -> None:
        super().__init__()
        self.spec = "picamera"
        if fps <= 0:
            raise SourceError(f"picamera: fps must be > 0, got {fps}")
        if not (0 <= max_exposure_ms <= 1e3 / fps):
            raise SourceError(f"picamera: max_exposure_ms must be in [0, {1e3 / fps:g}] ms "
                              f"(one frame at {fps:g} frames/s), got {max_exposure_ms}")
        self.max_exposure_ms = float(max_exposure_ms)
        if lens_position is not None and not (0.0 <= float(lens_position) <= 32.0):
            raise SourceError(f"picamera: lens_position must be in [0, 32] dioptres, got "
                              f"{lens_position}")
        self.lens_position = None if lens_position is None else float(lens_position)
        self.autofocus = False  # the camera advertises AfMode (set when opened)
        self._lens_warned = False
        if timeout is not None and timeout <= 0:
            raise SourceError(f"picamera: timeout must be > 0 s, got {timeout}")
        if int(reopen) < 0:
            raise SourceError(f"picamera: reopen must be >= 0, got {reopen}")
        self.fps = float(fps)
        self.camera = int(camera)
        self.timeout = (float(timeout) if timeout is not None
                        else max(MIN_STALL_TIMEOUT_S, 10.0 / self.fps))
        self.reopen = int(reopen)
        self.requested = (int(width), int(height))
        self.buffer_count = int(buffer_count)
        self.reopened = 0  # times the camera was opened again after a stall (whole run)
        self.stride: int | None = None
        self._Picamera2, self._MappedArray, self._libcamera = import_picamera2()
        # write=False (no cache flush back to the buffer) exists in newer picamera2 only.
        self._map_kw = ({"write": False} if "write" in _parameters(self._MappedArray)
                        else {})
        self._check_present()
        self._cam: Any = None
        self._open()
        self._index = 0
        w, h = self.size or self.requested
        line = line_time(self.model, w, h)
        if line is None:
            log.warning("picamera: no timing table for the sensor %r: poses are stamped "
                        "without the rolling-shutter correction (kmea.timing.SENSORS)",
                        self.model)
        self.line_s = line or 0.0

    # ------------------------------------------------------------------ opening
    def _check_present(self) -> None:
        try:
            cams = list(self._Picamera2.global_camera_info())
        except Exception as e:  # libcamera's camera manager itself failed to start
            raise SourceError(f"picamera: libcamera cannot list cameras ({type(e).__name__}: "
                              f"{e}); run `kmea doctor`") from None
        if not cams:
            raise SourceError(f"picamera: no camera found by libcamera: {_MISSING_FIX}")
        if self.camera >= len(cams) or self.camera < 0:
            raise SourceError(f"picamera: camera {self.camera} asked for, libcamera sees "
                              f"{len(cams)} (numbers 0..{len(cams) - 1}); use "
                              f"picamera?camera=N")
        self.model = str(cams[self.camera].get("Model", "camera"))

    def _open(self) -> None:
        w, h = self.requested
        try:
            cam = self._Picamera2(self.camera)
        except Exception as e:
            raise SourceError(f"picamera: {describe_open_error(e, self.camera)}") from None
        try:
            self.autofocus = "AfMode" in dict(cam.camera_controls)
        except Exception:  # an old picamera2 without camera_controls: no autofocus to set
            self.autofocus = False
        if self.lens_position is not None and not self.autofocus:
            log.warning("picamera: the camera file stores a lens position (%g dioptres) but "
                        "the %s has a fixed focus: ignored", self.lens_position, self.model)
        # The sensor mode is asked for by name when kmea.timing knows the sensor: libcamera
        # would otherwise take a cropped mode of the output's exact size (the IMX708's
        # 1536x864), whose field and line time are not the full-field mode's.
        sensor = sensor_for(self.model)
        pinned = {}
        if sensor is not None:
            mode = sensor.mode_for(w, h)
            pinned = {"sensor": {"output_size": mode.size, "bit_depth": mode.bit_depth}}
        try:
            config = cam.create_video_configuration(
                main={"size": (w, h), "format": "YUV420"}, **pinned,
                colour_space=self._libcamera.ColorSpace.Sycc(),  # full-range Y
                controls=self._controls(), buffer_count=self.buffer_count,
                # queue=False: every capture_request waits for a frame that completes after
                # it is asked for, never one held from earlier (lowest latency).
                queue=False)
            cam.configure(config)
            main = cam.stream_configuration("main")
            self.size = (int(main["size"][0]), int(main["size"][1]))
            self.stride = int(main["stride"])
            cam.start()
        except Exception as e:
            with contextlib.suppress(Exception):
                cam.close()
            raise SourceError(f"picamera: cannot start {w}x{h} YUV420 at {self.fps:g} fps: "
                              f"{type(e).__name__}: {e}") from None
        if self.size != self.requested:
            log.warning("picamera: asked for %dx%d, the camera delivers %dx%d", w, h,
                        *self.size)
        self._cam = cam

    def _controls(self) -> dict[str, Any]:
        """FrameRate, and ExposureTime (us) when an exposure is set (the AGC then varies the
        analogue gain only)."""
        out: dict[str, Any] = {"FrameRate": self.fps}
        if self.max_exposure_ms > 0:
            out["ExposureTime"] = round(self.max_exposure_ms * 1e3)
        if self.autofocus:
            # The calibration holds at one focus: never let the lens hunt (AfModeManual).
            out["AfMode"] = 0
            if self.lens_position is not None:
                out["LensPosition"] = self.lens_position
        return out

    def _close_cam(self) -> None:
        cam, self._cam = self._cam, None
        if cam is None:
            return
        with contextlib.suppress(Exception):  # a stalled camera may fail to stop: close anyway
            cam.stop()
        with contextlib.suppress(Exception):
            cam.close()

    # ------------------------------------------------------------------ frames
    def read(self) -> Frame | None:
        if self._closed:
            return None
        stalls = 0
        while True:
            try:
                request = self._cam.capture_request(wait=self.timeout)
            except _TIMEOUTS:
                stalls += 1
                what = f"no frame for {self.timeout:g} s"
            except Exception as e:
                stalls += 1
                what = f"capture failed ({type(e).__name__}: {e})"
            else:
                return self._frame_from(request)
            if self._closed:  # closed from another thread while this one waited
                return None
            if stalls > self.reopen:
                raise SourceError(f"picamera: {what}, {stalls} times in a row (camera reopened "
                                  f"{stalls - 1} times): the camera stalled; exiting so the "
                                  f"service restarts (check the ribbon cable, `dmesg | grep "
                                  f"-i -e unicam -e {self.model}`)")
            log.warning("picamera: %s; reopening the camera (%d of %d)", what, stalls,
                        self.reopen)
            self._close_cam()
            self._open()
            self.reopened += 1

    def _frame_from(self, request: Any) -> Frame:
        w, h = self.size or self.requested
        try:
            # Only the Y rows and columns are copied, straight out of the mapped buffer.
            with self._MappedArray(request, "main", **self._map_kw) as m:
                gray = np.array(m.array[:h, :w], dtype=np.uint8, copy=True, order="C")
            md = request.get_metadata() or {}
        finally:
            request.release()  # the buffer goes back to libcamera as soon as possible
        meta: dict[str, Any] = {}
        ts_ns = md.get("SensorTimestamp")
        if ts_ns is not None:
            meta["sensor_timestamp_ns"] = int(ts_ns)
            t = monotonic_to_unix_ns(int(ts_ns)) * 1e-9
        else:
            t = time.time()
        if "ExposureTime" in md:
            meta["exposure_time_us"] = md["ExposureTime"]
        if "FrameDuration" in md:
            meta["frame_duration_us"] = md["FrameDuration"]
        if "AnalogueGain" in md:
            meta["analogue_gain"] = md["AnalogueGain"]
        if "LensPosition" in md:
            meta["lens_position"] = md["LensPosition"]
            if not self._lens_warned and lens_differs(self.lens_position, md["LensPosition"]):
                self._lens_warned = True
                log.warning("picamera: the lens is at %.3f dioptres, the calibration (camera "
                            "file lens_position) at %.3f: positions are off until they agree; "
                            "calibrate again at this focus or fix the lens", md["LensPosition"],
                            self.lens_position)
        if ts_ns is not None:
            exp = md.get("ExposureTime")
            meta["timing"] = FrameTiming(t, self.line_s,
                                         0.0 if exp is None else float(exp) * 1e-6)
        i = self._index
        self._index += 1
        return Frame(i, t, gray, meta)

    def close(self) -> None:
        if not self._closed:
            super().close()  # first: a read() waiting in another thread must not reopen
            self._close_cam()

