"""When each row of a frame was seen: the rolling shutter and the exposure (pure Python).

A rolling-shutter sensor exposes and reads its rows one after another. What a source knows
about a frame is a :class:`FrameTiming`: the instant row 0 is read out (the end of its
exposure), the time from one image row to the next, and the exposure. Row ``v`` (image
pixels, fractional) was exposed over ``[t_read0 + v * line_s - exposure_s, t_read0 + v *
line_s]``; the instant an observation stands for is the middle of that window
(:meth:`FrameTiming.row_time`): what a moving marker's blurred image averages.

The Pi camera's figures (picamera2 request metadata, libcamera and the IMX219 driver):

- ``SensorTimestamp`` (ns, CLOCK_MONOTONIC on the Pi): the instant the first row is read
  out. picamera2's examples/timestamp_capture.py: "'SensorTimestamp' is when the first pixel
  was read out, so it started being exposed 'ExposureTime' earlier", and
  ``Picamera2.wait_for_timestamp_`` computes the exposure start as ``SensorTimestamp - 1000 *
  ExposureTime``. (libcamera's control_ids_core.yaml words it as "the time when the first
  row of the image sensor active array is exposed"; on the Pi the value is the unicam
  buffer's frame-start time, src/libcamera/pipeline/rpi/vc4/vc4.cpp, which picamera2 reads
  as above. This module follows picamera2.)
- ``ExposureTime`` (us): the exposure of this frame, every row the same.
- Line time: the IMX219 driver's line length (``IMX219_PPL_DEFAULT`` / ``IMX219_LLP_MIN``
  3448 pixel clocks) over its pixel rate (``IMX219_PIXEL_RATE`` 182.4 MHz): 18.90 us per
  sensor row. The same figure follows from the mode list ``kmea doctor`` reads (fps at the
  shortest frame = 1 / ((rows + 32 rows of minimum vertical blanking) x line time):
  1640x1232 at 41.85 fps, 1920x1080 at 47.57, 3280x2464 at 21.19 all give 18.90 us).
  The ISP scales the sensor mode to the output: 820x616 from the 1640x1232 mode has two
  sensor rows per image row, 37.81 us.

The other camera modules (:data:`SENSORS`, keyed by the model name picamera2 reports in
``camera_properties["Model"]``; libcamera's camera helpers register ``imx708``,
``imx708_wide``, ``imx708_noir``, ``imx708_wide_noir``, ``imx296``, ``imx477``): each mode's
line time is its line length over its pixel rate in the Raspberry Pi kernel's sensor driver
(drivers/media/i2c/imx708.c, imx296.c, imx477.c), and its fastest frame rate one over (rows
+ minimum vertical blanking) line times. The IMX296 (Global Shutter Camera) exposes every
row at once: its rows are read out one after another, but what they saw is one instant, so
its line time for the pose-time model is 0. The modes are the sensor's own, the same on a
Pi 4 and a Pi 5 (the boards differ in the raw formats they carry them in, not in timing).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["BLUR_WARN_M", "IMX219_LINE_S", "IMX219_MODES", "IMX219_VBLANK_MIN", "SENSORS",
           "FrameTiming", "Sensor", "SensorMode", "blur_m", "blur_warning", "imx219_line_time",
           "imx219_mode_for", "line_time", "sensor_for"]

#: IMX219 line length (pixel clocks) and pixel rate (Hz), Linux drivers/media/i2c/imx219.c.
IMX219_LINE_PCLK = 3448
IMX219_PIXEL_RATE = 182.4e6
#: Seconds per sensor row.
IMX219_LINE_S = IMX219_LINE_PCLK / IMX219_PIXEL_RATE
#: Minimum vertical blanking, rows (imx219.c ``IMX219_VBLANK_MIN``).
IMX219_VBLANK_MIN = 32

#: The IMX219's raw modes as ``rpicam-hello --list-cameras`` lists them on a Pi 4 (10-bit):
#: (width, height) -> (fastest fps, crop width, crop height) - the figures the fake Pi
#: camera of the tests and ``kmea doctor`` see.
IMX219_MODES: dict[tuple[int, int], tuple[float, int, int]] = {
    (640, 480): (206.65, 1280, 960),
    (1640, 1232): (41.85, 3280, 2464),
    (1920, 1080): (47.57, 1920, 1080),
    (3280, 2464): (21.19, 3280, 2464),
}


def imx219_mode_for(width: int, height: int) -> tuple[int, int]:
    """The sensor mode libcamera picks for a ``width`` x ``height`` output of the full
    field: the smallest full-field mode at least as large (1640x1232 for 820x616 and
    1640x1232; 3280x2464 above)."""
    for size in ((1640, 1232), (3280, 2464)):
        if width <= size[0] and height <= size[1]:
            return size
    return (3280, 2464)


def imx219_line_time(width: int, height: int) -> float:
    """Seconds from one output image row to the next on the IMX219 at ``width`` x
    ``height`` (full field): the sensor line time times the sensor rows per output row."""
    mode = imx219_mode_for(width, height)
    fps = IMX219_MODES[mode][0]
    line = 1.0 / (fps * (mode[1] + IMX219_VBLANK_MIN))  # = IMX219_LINE_S within 0.01 %
    return line * mode[1] / float(height)


@dataclass(frozen=True)
class SensorMode:
    """One raw mode of a sensor: output size (px), seconds per row, the shortest frame in
    rows (rows + minimum vertical blanking), the crop on the pixel array (x, y, w, h) and
    the bit depth."""

    width: int
    height: int
    line_s: float
    frame_rows_min: int
    crop: tuple[int, int, int, int]
    bit_depth: int = 10

    @property
    def size(self) -> tuple[int, int]:
        return (self.width, self.height)

    @property
    def fps(self) -> float:
        """Fastest frame rate, frames/s."""
        return 1.0 / (self.frame_rows_min * self.line_s)

    @property
    def readout_s(self) -> float:
        """Time from the first row's readout to the last's, s."""
        return self.height * self.line_s


@dataclass(frozen=True)
class Sensor:
    """A camera module's sensor: its pixel array, shutter, lens and raw modes."""

    model: str  # picamera2's camera_properties["Model"], without a variant suffix
    product: str
    array: tuple[int, int]  # active pixel array, px
    modes: tuple[SensorMode, ...]
    global_shutter: bool = False
    autofocus: bool = False

    def full_field(self, mode: SensorMode) -> bool:
        """The mode sees the whole pixel array (binned or not), not a crop of it."""
        return (mode.crop[2], mode.crop[3]) == self.array

    def mode(self, size: tuple[int, int]) -> SensorMode | None:
        return next((m for m in self.modes if m.size == tuple(size)), None)

    def mode_for(self, width: int, height: int) -> SensorMode:
        """The mode libcamera picks for a ``width`` x ``height`` output of the whole field:
        the smallest full-field mode at least as large, else the largest."""
        full = sorted((m for m in self.modes if self.full_field(m)),
                      key=lambda m: m.width * m.height)
        for m in full:
            if width <= m.width and height <= m.height:
                return m
        return full[-1]


def _pclk(line_pclk: int, pixel_rate_hz: float) -> float:
    return line_pclk / pixel_rate_hz


def _imx219_modes() -> tuple[SensorMode, ...]:
    # The line time that reproduces the listed frame rate (rows + IMX219_VBLANK_MIN), as
    # imx219_line_time computes it.
    return tuple(SensorMode(w, h, 1.0 / (fps * (h + IMX219_VBLANK_MIN)), h + IMX219_VBLANK_MIN,
                            ((3280 - cw) // 2, (2464 - ch) // 2, cw, ch))
                 for (w, h), (fps, cw, ch) in IMX219_MODES.items())


#: The sensors kmead knows, by picamera2's model name. Figures: the Raspberry Pi kernel's
#: drivers (raspberrypi/linux drivers/media/i2c): imx708.c ``supported_modes_10bit_no_hdr``
#: (line_length_pix, pixel_rate, vblank_min), imx477.c ``supported_modes_12bit`` /
#: ``_10bit`` (line_length_pix at IMX477_PIXEL_RATE 840 MHz; the shortest frame is
#: floor(timeperframe_min x pixel rate / line length) rows, imx477_get_frame_length),
#: imx296.c (HMAX 1100 at the fixed 74.25 MHz INCK, VBLANK minimum 30; libcamera's
#: cam_helper_imx296.cpp: timePerLine = 550 / 37.125 MHz, the same 14.81 us). docs/pi.md
#: has the table.
SENSORS: dict[str, Sensor] = {
    "imx219": Sensor("imx219", "Camera Module v2", (3280, 2464), _imx219_modes()),
    "imx708": Sensor("imx708", "Camera Module 3", (4608, 2592), (
        SensorMode(1536, 864, _pclk(0x1460, 566.4e6), 864 + 40, (768, 432, 3072, 1728)),
        SensorMode(2304, 1296, _pclk(0x1E90, 585.6e6), 1296 + 40, (0, 0, 4608, 2592)),
        SensorMode(4608, 2592, _pclk(0x3D20, 595.2e6), 2592 + 58, (0, 0, 4608, 2592)),
    ), autofocus=True),
    "imx296": Sensor("imx296", "Global Shutter Camera", (1456, 1088), (
        SensorMode(1456, 1088, 1100 / 74.25e6, 1088 + 30, (0, 0, 1456, 1088)),
    ), global_shutter=True),
    "imx477": Sensor("imx477", "HQ Camera", (4056, 3040), (
        SensorMode(1332, 990, _pclk(6664, 840e6), 1050, (696, 528, 2664, 1980)),
        SensorMode(2028, 1080, _pclk(0x31C4, 840e6), 1318, (0, 440, 4056, 2160), 12),
        SensorMode(2028, 1520, _pclk(0x31C4, 840e6), 1648, (0, 0, 4056, 3040), 12),
        SensorMode(4056, 3040, _pclk(0x5DC0, 840e6), 3500, (0, 0, 4056, 3040), 12),
    )),
}

#: The IMX708's HDR mode (imx708.c ``supported_modes_10bit_hdr``): 2304x1296, line length
#: 0x1460 at 777.6 MHz, vertical blanking 3673 rows: 30 frames/s at most. Not used for
#: detection (docs/camera.md): kmead never turns HDR on.
IMX708_HDR_MODE = SensorMode(2304, 1296, _pclk(0x1460, 777.6e6), 1296 + 3673,
                             (0, 0, 4608, 2592))

#: Model-name suffixes of the same sensor in another module (lens, IR filter, colour).
_VARIANTS = ("_wide_noir", "_wide", "_noir", "_mono")


def sensor_for(model: str) -> Sensor | None:
    """The :class:`Sensor` of a picamera2 model name (``imx708_wide`` -> the IMX708), or
    None for a sensor kmead has no table for."""
    name = str(model).strip().lower()
    for suffix in _VARIANTS:
        if name.endswith(suffix):
            name = name[: -len(suffix)]
            break
    return SENSORS.get(name)


def line_time(model: str, width: int, height: int) -> float | None:
    """Seconds from one output image row to the next on ``model`` at ``width`` x
    ``height`` (full field, the mode libcamera picks): 0 for a global shutter, None for an
    unknown sensor. The IMX219's figure is :func:`imx219_line_time`'s."""
    sensor = sensor_for(model)
    if sensor is None:
        return None
    if sensor.global_shutter:
        return 0.0
    if sensor.model == "imx219":
        return imx219_line_time(width, height)
    mode = sensor.mode_for(width, height)
    return mode.line_s * mode.height / float(height)


@dataclass(frozen=True)
class FrameTiming:
    """What a source knows about the timing of one frame (seconds).

    t_read0: the instant row 0 is read out (end of its exposure), on the frame timestamps'
    clock. line_s: time from one image row to the next (0: a global shutter). exposure_s:
    the exposure of every row (0: unknown or instantaneous). exact: the figures are known
    exactly (the simulator), not reported by a camera.
    """

    t_read0: float
    line_s: float = 0.0
    exposure_s: float = 0.0
    exact: bool = False

    def __post_init__(self) -> None:
        for k in ("t_read0", "line_s", "exposure_s"):
            v = getattr(self, k)
            if not (isinstance(v, (int, float)) and math.isfinite(v)):
                raise ValueError(f"frame timing: {k} must be a finite number of seconds, "
                                 f"got {v!r}")
        if self.line_s < 0 or self.exposure_s < 0:
            raise ValueError(f"frame timing: line_s and exposure_s must be >= 0 s, got "
                             f"{self.line_s!r}, {self.exposure_s!r}")

    def row_time(self, v: float) -> float:
        """Mid-exposure instant of image row ``v`` (pixels, fractional), seconds."""
        return self.t_read0 + self.row_offset(v)

    def row_offset(self, v: float) -> float:
        """Mid-exposure of image row ``v`` after ``t_read0``, s (exactly 0 without a
        rolling shutter and exposure)."""
        return v * self.line_s - 0.5 * self.exposure_s

    def rows_time(self, vs: list[float] | tuple[float, ...]) -> float:
        """Mid-exposure instant of a set of rows (their mean row), seconds."""
        return self.row_time(sum(vs) / len(vs)) if vs else self.row_time(0.0)

    @classmethod
    def from_picamera(cls, t_read0: float, exposure_us: float | None, width: int,
                      height: int) -> FrameTiming:
        """The IMX219's timing for a frame whose ``SensorTimestamp`` is ``t_read0`` (s)
        with metadata ``ExposureTime`` (us; None: unknown, taken as 0)."""
        exp = 0.0 if exposure_us is None else float(exposure_us) * 1e-6
        return cls(float(t_read0), imx219_line_time(width, height), exp)


def blur_m(speed_m_s: float, exposure_s: float) -> float:
    """How far a marker moving at ``speed_m_s`` travels during ``exposure_s``: the length
    of its smear, metres."""
    return abs(speed_m_s) * max(exposure_s, 0.0)


#: Smear (m) of a robot at its top speed above which kmead warns and ``kmea doctor`` says
#: FIX: on the tuning motion scenes (docs/motion.md) 60 mm markers at 1.5 m/s are found in
#: every frame up to 3 ms of exposure (4.5 mm), and start to be lost beyond.
BLUR_WARN_M = 0.0045


def blur_warning(exposure_s: float, speed_m_s: float) -> str | None:
    """One line when an exposure of ``exposure_s`` smears a robot at ``speed_m_s`` by more
    than :data:`BLUR_WARN_M`, else None."""
    b = blur_m(speed_m_s, exposure_s)
    if b <= BLUR_WARN_M:
        return None
    return (f"camera exposure {exposure_s * 1e3:.1f} ms: a robot at {speed_m_s:g} m/s "
            f"(filter.max_speed) smears by {b * 1e3:.1f} mm, more than "
            f"{BLUR_WARN_M * 1e3:g} mm: moving robots' markers blur and may be lost; set "
            f"camera.max_exposure_ms to at most {BLUR_WARN_M / speed_m_s * 1e3:.1f} "
            f"(docs/motion.md)")
