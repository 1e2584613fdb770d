"""Camera models: pinhole intrinsics with OpenCV distortion coefficients.

Pixel convention is OpenCV's: the centre of the top-left pixel is (0, 0).
File reading and writing (OpenCV FileStorage YAML/XML/JSON and TOML) live here too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from kmea.estimators.base import CameraIntrinsics

__all__ = ["CameraError", "CameraModel", "pi_camera_v2"]


class CameraError(ValueError):
    """A camera file or model is invalid; the message names the file and key."""


@dataclass(frozen=True)
class CameraModel:
    """Pinhole camera with OpenCV distortion.

    camera_matrix: (3, 3) K, pixels. dist_coeffs: (n,) with n in {4, 5, 8, 12, 14}, OpenCV
    order (k1, k2, p1, p2[, k3[, k4, k5, k6[, s1..s4[, tx, ty]]]]). width, height: pixels.
    """

    camera_matrix: np.ndarray
    dist_coeffs: np.ndarray
    width: int
    height: int

    def __post_init__(self) -> None:
        K = np.asarray(self.camera_matrix, dtype=float)
        d = np.asarray(self.dist_coeffs, dtype=float).reshape(-1)
        if K.shape != (3, 3):
            raise CameraError(f"camera_matrix: expected shape (3, 3), got {K.shape}")
        if d.size not in (0, 4, 5, 8, 12, 14):
            raise CameraError(f"distortion_coefficients: expected 4, 5, 8, 12 or 14 values, got {d.size}")
        if not (np.all(np.isfinite(K)) and np.all(np.isfinite(d))):
            raise CameraError("camera_matrix/distortion_coefficients: non-finite value")
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise CameraError("camera_matrix: focal lengths must be > 0")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise CameraError(f"image size must be positive, got {self.width}x{self.height}")
        object.__setattr__(self, "camera_matrix", K)
        object.__setattr__(self, "dist_coeffs", d if d.size else np.zeros(5))
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    @property
    def fx(self) -> float:
        return float(self.camera_matrix[0, 0])

    @property
    def fy(self) -> float:
        return float(self.camera_matrix[1, 1])

    @property
    def cx(self) -> float:
        return float(self.camera_matrix[0, 2])

    @property
    def cy(self) -> float:
        return float(self.camera_matrix[1, 2])

    @property
    def intrinsics(self) -> CameraIntrinsics:
        """The numpy-only view the estimators take."""
        return CameraIntrinsics(self.camera_matrix, self.dist_coeffs, self.width, self.height)

    def scaled_to(self, width: int, height: int) -> CameraModel:
        """The same camera at another resolution with the same aspect ratio.

        Sensor modes that bin or scale keep the field of view, so K scales with the image
        (pixel centres: x' + 0.5 = s (x + 0.5)). Distortion is in normalized coordinates and
        does not change. Another aspect ratio is a crop we cannot know: ``CameraError``.
        """
        if (width, height) == (self.width, self.height):
            return self
        sx, sy = width / self.width, height / self.height
        if not math.isclose(sx, sy, rel_tol=2e-3):
            raise CameraError(
                f"frame size {width}x{height} has another aspect ratio than the calibration "
                f"{self.width}x{self.height}; recalibrate at this resolution")
        K = self.camera_matrix.copy()
        K[0, 0] *= sx
        K[1, 1] *= sy
        K[0, 1] *= sx
        K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
        K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
        return CameraModel(K, self.dist_coeffs.copy(), width, height)


def pi_camera_v2(width: int = 1640, height: int = 1232) -> CameraModel:
    """A nominal Raspberry Pi Camera Module v2 (Sony IMX219) in its binned 1640x1232 mode.

    3.04 mm lens, 1.12 um pixels binned 2x2 -> f = 3.04 / 0.00224 = 1357 px; mild barrel
    distortion typical of the module. Scaled to (width, height) if they differ (4:3 only).
    """
    K = np.array([[1357.0, 0.0, 819.5], [0.0, 1357.0, 615.5], [0.0, 0.0, 1.0]])
    dist = np.array([0.12, -0.25, 0.0, 0.0, 0.10])
    return CameraModel(K, dist, 1640, 1232).scaled_to(width, height)
