"""picamera2/picamera2.py: the Picamera2 class, the calls KMEA makes and how they behave.

Time is real: frames "arrive" every frame duration after ``start()`` and ``capture_request``
sleeps until one does (or until its timeout), as the real one blocks on a Future that the
camera's event loop completes. No thread: a frame is delivered when a caller waits for it.
"""

from __future__ import annotations

import time
from typing import Any

import fakecam_rig
import libcamera
import numpy as np

from .job import Job
from .request import CompletedRequest


class HangsForever(AssertionError):
    """The real call would block forever here (no frame will come and no timeout was given)."""


class Picamera2:
    def __init__(self, camera_num: int = 0, verbose_console: Any = None,
                 tuning: Any = None) -> None:
        rig = fakecam_rig.rig
        self.camera_idx = camera_num
        self.is_open = False
        self.started = False
        self.camera_config: dict | None = None
        self._job_list: list[Job] = []
        self._held = 0  # requests handed out and not yet released
        self._completed: CompletedRequest | None = None
        try:
            self._open_camera()
        except Exception:
            # Picamera2.__init__: `except Exception: _log.error(...); raise RuntimeError("Camera
            # __init__ sequence did not complete.")` - raised inside the except block, so the
            # reason is only in __context__.
            raise RuntimeError("Camera __init__ sequence did not complete.")  # noqa: B904
        self._open_index = rig.opens
        rig.opens += 1
        rig.instances.append(self)

    def _open_camera(self) -> None:
        rig = fakecam_rig.rig
        try:
            cams = libcamera.CameraManager.singleton().cameras
            if not cams:
                # _initialize_camera (picamera2 >= 0.3.17); older versions index the empty
                # list and raise IndexError "list index out of range" instead.
                raise RuntimeError("Camera(s) not found (Do not forget to disable legacy "
                                   "camera with raspi-config).")
            self.camera = cams[self.camera_idx]  # _grab_camera: IndexError past the list
        except RuntimeError:
            raise RuntimeError("Failed to initialize camera")  # noqa: B904 - _open_camera
        if rig.busy or any(p.is_open for p in rig.instances):
            # camera.acquire(): libcamera returns -EBUSY when another process (or another
            # Picamera2 in this one) holds the camera; the bindings raise it as this.
            raise RuntimeError("Failed to acquire camera: Device or resource busy")
        self.is_open = True

    @staticmethod
    def global_camera_info() -> list[dict]:
        """One dict per attached camera (Model, Location, Rotation, Id), in camera order."""
        return [{**c.properties, "Id": c.id}
                for c in libcamera.CameraManager.singleton().cameras]

    @property
    def camera_properties(self) -> dict:
        return dict(self.camera.properties) if self.is_open else {}

    @property
    def sensor_modes(self) -> list[dict]:
        return [dict(m) for m in fakecam_rig.MODES[self.camera.properties["Model"]]]

    @property
    def camera_controls(self) -> dict:
        """name -> (min, max, default) of every control libcamera advertises for this camera
        (picamera2: ``camera_controls``, from ``camera.controls``)."""
        return fakecam_rig.controls_of(self.camera.properties["Model"])

    # ------------------------------------------------------------------ configuration
    def create_video_configuration(self, main: dict | None = None, lores: dict | None = None,
                                   raw: dict | None = None, transform: Any = None,
                                   colour_space: Any = None, buffer_count: int = 6,
                                   controls: dict | None = None, display: str | None = "main",
                                   encode: str | None = "main", queue: bool = True,
                                   sensor: dict | None = None, use_case: str = "video") -> dict:
        if not self.is_open:
            raise RuntimeError("Camera not opened")
        stream = {"format": "XBGR8888", "size": (1280, 720), "preserve_ar": True}
        for key, value in (main or {}).items():
            # _make_initial_stream_config: other keys are a ValueError.
            if key not in ("format", "size", "stride", "preserve_ar"):
                raise ValueError(f"Bad key {key!r}: valid stream configuration keys are "
                                 f"('format', 'size', 'stride', 'preserve_ar')")
            stream[key] = value
        w, h = stream["size"]
        stream["size"] = (w - w % 2, h - h % 2)  # align_stream(optimal=False): even sizes
        if colour_space is None:
            # create_video_configuration: Smpte170m below 1280x720, else Rec709 - both
            # limited range (Y 16..235).
            small = stream["size"][0] < 1280 or stream["size"][1] < 720
            colour_space = (libcamera.ColorSpace.Smpte170m() if small
                            else libcamera.ColorSpace.Rec709())
        controls = {"FrameDurationLimits": (33333, 33333)} | dict(controls or {})
        return {"use_case": use_case, "transform": transform or libcamera.Transform(),
                "colour_space": colour_space, "buffer_count": buffer_count, "queue": queue,
                "main": stream, "lores": lores, "raw": raw, "controls": controls,
                "sensor": sensor, "display": display, "encode": encode}

    def configure(self, camera_config: dict) -> None:
        if self.started:
            raise RuntimeError("Camera must be stopped before configuring")
        config = {k: (dict(v) if isinstance(v, dict) else v) for k, v in camera_config.items()}
        # check_camera_config / check_stream_config
        if not isinstance(config["colour_space"], libcamera.ColorSpace):
            raise RuntimeError("Colour space has incorrect type")
        main = config["main"]
        if type(main["size"]) is not tuple or len(main["size"]) != 2:
            raise RuntimeError("size in main stream should be (width, height)")
        if main["size"][0] % 2 or main["size"][1] % 2:
            raise RuntimeError("width and height should be even")
        if main["format"] not in ("YUV420", "YVU420"):
            raise RuntimeError(f"the fake camera delivers YUV420 only, not {main['format']}")
        # libcamera's validate() fills the stride: the bcm2835 ISP aligns the Y stride of
        # YUV420 to 64 bytes (raspberrypi/linux PR 4419), so 1640 wide -> 1664 bytes a row.
        w, h = main["size"]
        main["stride"] = (w + 63) // 64 * 64
        main["framesize"] = main["stride"] * h * 3 // 2
        if config.get("sensor"):
            # _update_libcamera_sensor_config / libcamera validate(): the output size and
            # bit depth must be one of the sensor's modes.
            want = (tuple(config["sensor"]["output_size"]), config["sensor"].get("bit_depth"))
            if not any((m["size"], m["bit_depth"]) == want if want[1] else m["size"] == want[0]
                       for m in self.sensor_modes):
                raise RuntimeError(f"sensor mode {want} is not one of the camera's")
        controls = config["controls"]
        for name in controls:
            # picamera2 Controls.__setattr__: a control the camera does not advertise is an
            # error, not ignored (FrameRate is picamera2's own, mapped below).
            if name != "FrameRate" and name not in self.camera_controls:
                raise RuntimeError(f"Control {name} is not advertised by libcamera")
        if "FrameRate" in controls:  # picamera2 Controls: FrameRate -> FrameDurationLimits
            d = round(1e6 / controls["FrameRate"])
            controls["FrameDurationLimits"] = (d, d)
        self.camera_config = config

    def camera_configuration(self) -> dict:
        return self.camera_config

    def stream_configuration(self, name: str = "main") -> dict:
        return self.camera_config[name]

    # ------------------------------------------------------------------ running
    def start(self, config: Any = None, show_preview: bool = False) -> None:
        if config is not None:
            self.configure(config)
        if self.camera_config is None:
            raise RuntimeError("Camera has not been configured")
        rig = fakecam_rig.rig
        self.started = True
        self._t0 = time.monotonic()
        self._made = 0  # frames the sensor has produced since start()
        self._delivered = 0  # of which handed to the application
        self._period = self.camera_config["controls"]["FrameDurationLimits"][0] * 1e-6
        k = self._open_index
        self._limit = rig.stall_after[k] if k < len(rig.stall_after) else None

    def stop(self) -> None:
        self.started = False

    def close(self) -> None:
        if not self.is_open:
            return
        self.stop()
        self.is_open = False

    def _next_arrival(self) -> float | None:
        """When the next frame completes, or None when none will (stalled or stopped)."""
        if not self.started or (self._limit is not None and self._delivered >= self._limit):
            return None
        return self._t0 + (self._made + 1) * self._period

    def _pump(self) -> None:
        """Complete every frame whose time has come: to the oldest waiting job, else hold it
        (queue=True keeps the newest, _max_queue_len = 1) or recycle it (queue=False)."""
        now = time.monotonic()
        while (t := self._next_arrival()) is not None and t <= now:
            n = self._made
            self._made += 1
            if self._held >= self.camera_config["buffer_count"]:
                continue  # every buffer is held by the application: nothing to fill
            req = self._make_request(n, t)
            if self._job_list:
                self._held += 1
                self._delivered += 1
                self._job_list.pop(0).signal(req)
            elif self.camera_config["queue"] and self.camera_config["buffer_count"] > 1:
                self._completed = req
            # else recycled straight back to the camera

    def _make_request(self, n: int, t_arrival: float) -> CompletedRequest:
        rig = fakecam_rig.rig
        main = self.camera_config["main"]
        w, h = main["size"]
        stride = main["stride"]
        buf = np.full((h * 3 // 2, stride), 128, np.uint8)  # U and V planes: neutral grey
        y = rig.scene(n, w, h).astype(np.float64)
        if not self.camera_config["colour_space"].full_range:
            y = 16.0 + y * (219.0 / 255.0)  # limited ("video") range
        buf[:h, :w] = np.round(y).astype(np.uint8)
        buf[:h, w:] = 0x5A  # row padding: whatever the ISP left there
        controls = self.camera_config["controls"]
        # libcamera: ExposureTime is the exposure this frame used (us, every row); it is
        # capped by the frame duration (exposure <= frame length - 4 lines, imx219.c).
        frame_us = round(self._period * 1e6)
        exposure = int(controls.get("ExposureTime") or rig.exposure_us)
        exposure = min(exposure, frame_us - 4 * 19)
        gain = min(max(rig.light_exposure_us / exposure, 1.0), 256 / (256 - 232))
        readout = rig.readout_s
        if readout is None:  # the sensor mode's rows (2 per output row below 1640x1232)
            rows = 1232 if h <= 1232 else 2464
            readout = rows * 3448 / 182.4e6 + 0.001
        md = {"SensorTimestamp": int((t_arrival - readout) * 1e9),
              "ExposureTime": exposure, "FrameDuration": frame_us,
              "AnalogueGain": round(gain, 3), "DigitalGain": 1.0}
        if "LensPosition" in self.camera_controls:
            # The lens driver reports where the lens is in every request's metadata.
            asked = controls.get("LensPosition", self.camera_controls["LensPosition"][2])
            md["LensPosition"] = float(asked if rig.lens_at is None else rig.lens_at)
        return CompletedRequest(self, buf, md)

    def _returned(self, req: CompletedRequest) -> None:
        self._held -= 1

    def capture_request(self, wait: Any = None, signal_function: Any = None,
                        flush: Any = None) -> Any:
        """dispatch_functions: wait None -> wait forever unless a signal_function is given;
        True -> forever; False -> return the Job; a number -> that many seconds, then
        TimeoutError. A timed-out job stays queued and takes the next frame."""
        job = Job(signal_function=signal_function)
        if self._completed is not None:
            self._held += 1
            req, self._completed = self._completed, None
            self._delivered += 1
            job.signal(req)
        else:
            self._job_list.append(job)
        if wait is None:
            wait = signal_function is None
        timeout = None if wait is True else wait
        return self.wait(job, timeout) if wait else job

    def wait(self, job: Job, timeout: float | None = None) -> Any:
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            self._pump()
            if job.done():
                return job.get_result()
            nxt = self._next_arrival()
            if nxt is None and deadline is None:
                raise HangsForever("capture_request() without a timeout on a camera that "
                                   "delivers no more frames blocks forever (dispatch_functions: "
                                   "job.get_result(timeout=None))")
            now = time.monotonic()
            if deadline is not None and now >= deadline:
                return job.get_result(timeout=0)  # concurrent.futures.TimeoutError
            until = min(t for t in (nxt, deadline) if t is not None)
            time.sleep(max(0.0, until - now))
