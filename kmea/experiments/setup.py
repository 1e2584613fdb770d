"""What an experiment is told: :class:`ExperimentConfig`, and the camera the estimators
believe in (:func:`miscalibrated`). Imported by the sampling loop (``run``) and the scene
builder (``simscene``), which import neither each other's internals nor this back."""

from __future__ import annotations

from dataclasses import dataclass

from kmea.experiments.parts import PartSpec

__all__ = ["MODES", "ExperimentConfig", "miscalibrated"]

#: Evaluation modes (see :mod:`kmea.experiments.run`).
MODES = ("plane-known", "off-map")


@dataclass(frozen=True)
class ExperimentConfig:
    """What to run. Picklable: it is sent to the worker processes.

    samples: frames per Part (= samples per evaluated marker and algorithm).
    width, height: rendered image size (the Pi Camera v2 model is scaled to it).
    focal_error: relative error of the focal length the estimators believe (0.02 = +2 %).
    k1_error: absolute error added to the first radial coefficient the estimators believe.
    known_heights: give the estimators Part II's support height as ``plane_heights`` (as the
        daemon does for a robot's top plate); off by default, as in the paper.
    floor_only: the estimators' map keeps the floor markers only (wall markers are still
        drawn and detected, but never references).
    modes: evaluation modes (``MODES``) computed from the same frames; the first is the
        primary one.
    iir_alpha: the paper's IIR filter weight applied to every estimator's samples (1 = off).
    """

    part: PartSpec
    algorithms: tuple[str, ...]
    baseline: str = "lmea"
    samples: int = 256
    seed: int = 0
    width: int = 1640
    height: int = 1232
    focal_error: float = 0.0
    k1_error: float = 0.0
    known_heights: bool = False
    floor_only: bool = False
    jobs: int = 1
    chunk: int = 8
    modes: tuple[str, ...] = MODES
    iir_alpha: float = 1.0


def miscalibrated(camera, focal_error: float, k1_error: float):
    """The camera the estimators believe in: focal lengths scaled by ``1 + focal_error``,
    ``k1_error`` added to k1. Returns a new ``kmea.vision.camera.CameraModel``."""
    from kmea.vision.camera import CameraModel

    K = camera.camera_matrix.copy()
    K[0, 0] *= 1.0 + focal_error
    K[1, 1] *= 1.0 + focal_error
    d = camera.dist_coeffs.copy()
    d[0] += k1_error
    return CameraModel(K, d, camera.width, camera.height)
