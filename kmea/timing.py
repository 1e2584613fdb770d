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
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["BLUR_WARN_M", "IMX219_LINE_S", "IMX219_MODES", "IMX219_VBLANK_MIN", "FrameTiming",
           "blur_m", "blur_warning", "imx219_line_time", "imx219_mode_for"]

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
