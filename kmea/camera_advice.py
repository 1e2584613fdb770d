"""Which sensor mode for which camera module and board: what ``kmea doctor`` and
docs/pi.md say.

The modes and line times are :data:`kmea.timing.SENSORS`' (the kernel drivers' figures).
CPU a frame is an estimate, not a measurement on a Pi: this development machine's figures
(docs/speed.md: ``kmea bench frame-path``, a tracked frame, 2.23 ms CPU median at
1640x1232; a full detection, bare ``detectMarkers``, 22.1 ms CPU) scaled by the image's
pixels and by a factor per board: a Pi 4 (Cortex-A72 at 1.5-1.8 GHz) 4x this machine, the
middle of the 3-5x docs/speed.md states; a Pi 5 (Cortex-A76 at 2.4 GHz) 2.5 times faster
than a Pi 4, the middle of Raspberry Pi's "2-3x" for the Pi 5's CPU, so 1.6x this machine.
"""

from __future__ import annotations

from dataclasses import dataclass

from kmea.timing import Sensor, SensorMode, sensor_for

__all__ = ["BOARD_FACTOR", "RECOMMENDED", "ModeAdvice", "advise", "board_of"]

#: CPU time a frame on each board relative to this development machine (see above).
BOARD_FACTOR = {"pi4": 4.0, "pi5": 1.6}
BOARD_NAME = {"pi4": "Pi 4", "pi5": "Pi 5"}
#: This machine's CPU a frame at 1640x1232 (docs/speed.md), ms: tracked frame path, full
#: detection.
TRACKED_MS, FULL_MS = 2.23, 22.1
_REF_PIXELS = 1640 * 1232

#: The output size kmead should ask for per sensor: a full-field mode at its own aspect
#: ratio (the ISP crops another), 60 mm markers at least ~40 px across from 1.35-2 m up.
RECOMMENDED: dict[str, tuple[int, int]] = {
    "imx219": (1640, 1232),  # the 2x2 binned mode itself
    "imx708": (1536, 864),   # from the 2304x1296 binned mode (1.5 rows a row)
    "imx296": (1456, 1088),  # the only mode
    "imx477": (1352, 1014),  # from the 2028x1520 binned mode (1.5 rows a row)
}


def board_of(model: str) -> str | None:
    """``pi4`` / ``pi5`` from the device tree's model string, else None."""
    if "Raspberry Pi 5" in model or "Compute Module 5" in model:
        return "pi5"
    if "Raspberry Pi 4" in model or "Compute Module 4" in model or "Raspberry Pi 400" in model:
        return "pi4"
    return None


@dataclass(frozen=True)
class ModeAdvice:
    """What a sensor does at an output size."""

    sensor: Sensor
    mode: SensorMode
    width: int
    height: int

    @property
    def readout_s(self) -> float:
        """The time the pose-time model spreads over the image's rows (0: global shutter)."""
        return 0.0 if self.sensor.global_shutter else self.mode.readout_s

    def skew_m(self, speed_m_s: float) -> float:
        """How far a robot moves between the top row and the bottom row, m."""
        return speed_m_s * self.readout_s

    @property
    def aspect_ok(self) -> bool:
        """The output has the mode's aspect ratio (within 1 %): no crop by the ISP."""
        return abs(self.width * self.mode.height / (self.height * self.mode.width) - 1) < 0.01

    def cpu_ms(self, board: str) -> tuple[float, float]:
        """Estimated CPU a frame on ``board``, ms: (tracked frame, full detection)."""
        k = BOARD_FACTOR[board] * self.width * self.height / _REF_PIXELS
        return TRACKED_MS * k, FULL_MS * k

    def recommended(self) -> tuple[int, int]:
        return RECOMMENDED[self.sensor.model]


def advise(model: str, width: int, height: int) -> ModeAdvice | None:
    """The mode ``model`` reads for a ``width`` x ``height`` output, or None for a sensor
    without a table."""
    sensor = sensor_for(model)
    if sensor is None:
        return None
    return ModeAdvice(sensor, sensor.mode_for(width, height), int(width), int(height))
