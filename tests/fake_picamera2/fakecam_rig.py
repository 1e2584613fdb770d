"""The fake Pi camera's hardware and system: what is attached, what it sees, how it fails.

``tests/fake_picamera2`` holds test doubles of ``picamera2``, ``libcamera`` (its Python
bindings) and ``simplejpeg``, put first on ``sys.path`` by :func:`fakepi.install` so that
``import picamera2`` really runs their module code (import failures happen where they do on a
Pi). Their signatures and behaviours are picamera2's own (raspberrypi/picamera2, the calls
KMEA makes are unchanged since v0.3.12); each behaviour's comment says where it comes from.
This module is the "rig" the tests turn: reset it with :func:`reset` before each test.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

# IMX219 (Pi Camera v2) as libcamera reports it (CameraManager.cameras[i].properties and id).
IMX219 = {"Model": "imx219", "Location": 2, "Rotation": 180,
          "Id": "/base/soc/i2c0mux/i2c@1/imx219@10"}

# The IMX219's raw modes as `rpicam-hello --list-cameras` lists them on a Pi 4 (10-bit).
IMX219_MODES = [
    {"format": "SRGGB10_CSI2P", "size": (640, 480), "fps": 206.65, "bit_depth": 10,
     "crop_limits": (1000, 752, 1280, 960)},
    {"format": "SRGGB10_CSI2P", "size": (1640, 1232), "fps": 41.85, "bit_depth": 10,
     "crop_limits": (0, 0, 3280, 2464)},
    {"format": "SRGGB10_CSI2P", "size": (1920, 1080), "fps": 47.57, "bit_depth": 10,
     "crop_limits": (680, 692, 1920, 1080)},
    {"format": "SRGGB10_CSI2P", "size": (3280, 2464), "fps": 21.19, "bit_depth": 10,
     "crop_limits": (0, 0, 3280, 2464)},
]


# The other camera modules, as libcamera names them (camera_properties["Model"]: the names
# raspberrypi/libcamera's camera helpers register, cam_helper_imx708.cpp, _imx296.cpp,
# _imx477.cpp) with their sensor modes as picamera2 lists them on a Pi 4: size, the fastest
# frame rate (one over rows + minimum vertical blanking line times, the kernel drivers'
# figures, kmea.timing.SENSORS) and crop_limits (x, y, w, h) on the pixel array.
IMX708 = {"Model": "imx708", "Location": 2, "Rotation": 180,
          "Id": "/base/soc/i2c0mux/i2c@1/imx708@1a"}
IMX708_WIDE = {**IMX708, "Model": "imx708_wide"}
IMX296 = {"Model": "imx296", "Location": 2, "Rotation": 180,
          "Id": "/base/soc/i2c0mux/i2c@1/imx296@1a"}
IMX477 = {"Model": "imx477", "Location": 2, "Rotation": 180,
          "Id": "/base/soc/i2c0mux/i2c@1/imx477@1a"}

IMX708_MODES = [
    {"format": "SRGGB10_CSI2P", "size": (1536, 864), "fps": 120.12, "bit_depth": 10,
     "crop_limits": (768, 432, 3072, 1728)},
    {"format": "SRGGB10_CSI2P", "size": (2304, 1296), "fps": 56.02, "bit_depth": 10,
     "crop_limits": (0, 0, 4608, 2592)},
    {"format": "SRGGB10_CSI2P", "size": (4608, 2592), "fps": 14.35, "bit_depth": 10,
     "crop_limits": (0, 0, 4608, 2592)},
]
IMX296_MODES = [
    {"format": "SBGGR10_CSI2P", "size": (1456, 1088), "fps": 60.38, "bit_depth": 10,
     "crop_limits": (0, 0, 1456, 1088)},
]
IMX477_MODES = [
    {"format": "SRGGB10_CSI2P", "size": (1332, 990), "fps": 120.05, "bit_depth": 10,
     "crop_limits": (696, 528, 2664, 1980)},
    {"format": "SRGGB12_CSI2P", "size": (2028, 1080), "fps": 50.03, "bit_depth": 12,
     "crop_limits": (0, 440, 4056, 2160)},
    {"format": "SRGGB12_CSI2P", "size": (2028, 1520), "fps": 40.01, "bit_depth": 12,
     "crop_limits": (0, 0, 4056, 3040)},
    {"format": "SRGGB12_CSI2P", "size": (4056, 3040), "fps": 10.0, "bit_depth": 12,
     "crop_limits": (0, 0, 4056, 3040)},
]
MODES = {"imx219": IMX219_MODES, "imx708": IMX708_MODES, "imx708_wide": IMX708_MODES,
         "imx296": IMX296_MODES, "imx477": IMX477_MODES}

# camera_controls (name -> (min, max, default)), the ones KMEA sets. Every camera has the
# exposure and frame controls; only a camera with a lens driver (the IMX708's) has the
# autofocus ones: raspberrypi/libcamera ipa_base.cpp adds defaultAfControls (AfMode
# 0..2, LensPosition 0.0..32.0 dioptres, default 1.0) when a lens is present.
BASE_CONTROLS = {"ExposureTime": (1, 66666, 20000), "AnalogueGain": (1.0, 16.0, 1.0),
                 "FrameDurationLimits": (4000, 1000000, 33333)}
AF_CONTROLS = {"AfMode": (0, 2, 0), "LensPosition": (0.0, 32.0, 1.0)}


def controls_of(model: str) -> dict:
    return {**BASE_CONTROLS, **(AF_CONTROLS if model.startswith("imx708") else {})}


def gradient(n: int, w: int, h: int) -> np.ndarray:
    """Default scene: full-range luma 0..255 across the image, shifted by the frame number."""
    x = (np.arange(w)[None, :] * 256 // max(w, 1) + np.zeros((h, 1), int) + n) % 256
    x[0, 0], x[-1, -1] = 0, 255  # both ends of the range in every frame
    return x.astype(np.uint8)


@dataclass
class Rig:
    cameras: list[dict] = field(default_factory=lambda: [dict(IMX219)])
    busy: bool = False                     # another process has acquired the camera
    libcamera_installed: bool = True       # apt python3-libcamera present
    simplejpeg_numpy_major: int | None = None  # numpy major simplejpeg was built for (None: same)
    scene: Callable[[int, int, int], np.ndarray] = gradient  # (n, w, h) -> (h, w) uint8
    # Auto exposure's choice (us) when the application sets no ExposureTime: indoors the
    # AGC picks 10-30 ms at low gain. With ExposureTime set, the AGC keeps it and varies
    # only the analogue gain to make up the light (RPi AGC, fixed shutter): the gain is
    # light_exposure_us / ExposureTime within the IMX219's 1.0-10.667 (imx219.c: register
    # 0..232, gain = 256 / (256 - reg)).
    exposure_us: int = 8000
    light_exposure_us: int = 16000
    # Arrival of the frame - the instant its first row is read out (SensorTimestamp,
    # picamera2 examples/timestamp_capture.py). None: the sensor's readout of all its rows,
    # rows x 18.90 us (IMX219 line time, kmea.timing) - 23.3 ms for 1232 rows - plus 1 ms
    # through the ISP.
    readout_s: float | None = None
    # Stalls: the k-th open of a camera (0-based) hands stall_after[k] frames to the
    # application and then completes no more; opens past the list deliver forever. (Counted
    # in delivered frames, not sensor frames, so a slow test machine sees the same story.)
    stall_after: list[int] = field(default_factory=list)
    # Where an autofocus lens really is, dioptres (None: where it was asked to go, or the
    # LensPosition default 1.0): a lens knocked or driven elsewhere reports this.
    lens_at: float | None = None
    opens: int = 0                         # Picamera2 instances that acquired the camera
    instances: list = field(default_factory=list)


rig = Rig()


def reset() -> Rig:
    """A fresh rig: one IMX219, free, nothing broken."""
    global rig
    rig = Rig()
    return rig


def numpy_major() -> int:
    return int(np.__version__.split(".")[0])
