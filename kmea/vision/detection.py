"""ArUco marker detection with ``cv2.aruco.ArucoDetector``.

Defaults are tuned for the RobotAtFactory setup: 60 mm floor markers (40 mm on the walls)
seen from 1.2 to 1.5 m by a Pi Camera v2 at 1640x1232, i.e. markers 55-70 px wide (wall
markers ~35 px, often oblique). See ``docs/vision.md`` for the reasoning.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from kmea.vision.dictionary import get_dictionary

__all__ = ["DEFAULT_PARAMETERS", "DETECTOR_PARAMETERS", "Detections", "DetectorConfig",
           "DetectorParam", "MarkerDetector", "as_gray", "check_parameters"]

_REFINEMENT = {
    "none": cv2.aruco.CORNER_REFINE_NONE,
    "subpix": cv2.aruco.CORNER_REFINE_SUBPIX,
    "contour": cv2.aruco.CORNER_REFINE_CONTOUR,
    "apriltag": cv2.aruco.CORNER_REFINE_APRILTAG,
}

# Our defaults over OpenCV's (attribute name -> value); every other parameter keeps OpenCV's.
# Measured on rendered RobotAtFactory frames (kmea.sim) and the real tutorial photo; see
# docs/vision.md. OpenCV's adaptive-threshold windows (3, 13, 23 px) stay: dropping the 3 px
# pass or the 23 px one lost far, oblique markers in the scenario-2 view.
DEFAULT_PARAMETERS: dict[str, float | int | bool] = {
    # A 5x5 marker needs >= ~1 px per module (7 modules incl. border), i.e. >= 7 px sides,
    # perimeter 28 px = 0.044 of a 640 px frame: 0.04 (OpenCV 0.03) skips only contours
    # too small to decode, so fewer candidates are warped and read.
    "minMarkerPerimeterRate": 0.04,
    # OpenCV drops candidates with a corner closer than 3 px to the image border; at 1 px
    # the robot markers passing near the top of the 1640x1232 view are found (rendered
    # frames: +3 markers over 12 frames, no false id; at 0 px a false id appeared).
    "minDistanceToBorder": 1,
    # Sub-pixel search half-window = min(6 px, 0.3 module): 3 px for 60 mm markers at
    # 1640x1232 (8-10 px modules), inside the one-module black border so the inner bits
    # never pull the corner. 0.7 module halves the inward bias of blurred corners on
    # rendered frames but moves the real tutorial photo's corners ~1.1 px from OpenCV's
    # reference, so the relative size stays OpenCV's 0.3.
    "cornerRefinementWinSize": 6,
    # Iterate to 0.01 px (OpenCV: 0.1 px, 30 iterations): no measurable time cost.
    "cornerRefinementMaxIterations": 50,
    "cornerRefinementMinAccuracy": 0.01,
}

Scalar = float | int | bool


@dataclass(frozen=True)
class DetectorParam:
    """One ``cv2.aruco.DetectorParameters`` attribute: kind ("int", "float", "bool") and
    the closed range that has a meaning in OpenCV's detector (``lo_open``: lo excluded)."""

    kind: str
    lo: float = 0
    hi: float = 0
    lo_open: bool = False


# OpenCV's meaning of each parameter (docs of cv::aruco::DetectorParameters). Upper bounds
# are where a value stops making sense for markers in an image: a window larger than any
# frame, more iterations than sub-pixel refinement ever needs, more pixels per bit cell than
# a marker has (perspectiveRemovePixelPerCell = 2000 allocates a 14000 px square per
# candidate).
DETECTOR_PARAMETERS: dict[str, DetectorParam] = {
    "adaptiveThreshWinSizeMin": DetectorParam("int", 3, 255),
    "adaptiveThreshWinSizeMax": DetectorParam("int", 3, 255),
    "adaptiveThreshWinSizeStep": DetectorParam("int", 1, 255),
    "adaptiveThreshConstant": DetectorParam("float", -255, 255),
    "minMarkerPerimeterRate": DetectorParam("float", 0, 4, lo_open=True),
    "maxMarkerPerimeterRate": DetectorParam("float", 0, 4, lo_open=True),
    "polygonalApproxAccuracyRate": DetectorParam("float", 0, 0.5, lo_open=True),
    "minCornerDistanceRate": DetectorParam("float", 0, 1),
    "minDistanceToBorder": DetectorParam("int", 0, 1000),
    "minMarkerDistanceRate": DetectorParam("float", 0, 1),
    "minGroupDistance": DetectorParam("float", 0, 1),
    "cornerRefinementWinSize": DetectorParam("int", 1, 50),
    "relativeCornerRefinmentWinSize": DetectorParam("float", 0, 1, lo_open=True),
    "cornerRefinementMaxIterations": DetectorParam("int", 1, 1000),
    "cornerRefinementMinAccuracy": DetectorParam("float", 0, 10, lo_open=True),
    # The printed markers have a one-bit border; 0 bits is no marker at all.
    "markerBorderBits": DetectorParam("int", 1, 4),
    "perspectiveRemovePixelPerCell": DetectorParam("int", 1, 32),
    "perspectiveRemoveIgnoredMarginPerCell": DetectorParam("float", 0, 0.49),
    "maxErroneousBitsInBorderRate": DetectorParam("float", 0, 1),
    "minOtsuStdDev": DetectorParam("float", 0, 255),
    "errorCorrectionRate": DetectorParam("float", 0, 1),
    "validBitIdThreshold": DetectorParam("float", 0, 1),
    "aprilTagQuadDecimate": DetectorParam("float", 0, 16),
    "aprilTagQuadSigma": DetectorParam("float", 0, 10),
    "aprilTagMinClusterPixels": DetectorParam("int", 0, 100000),
    "aprilTagMaxNmaxima": DetectorParam("int", 1, 100),
    "aprilTagCriticalRad": DetectorParam("float", 0, math.pi),
    "aprilTagMaxLineFitMse": DetectorParam("float", 0, 1000),
    "aprilTagMinWhiteBlackDiff": DetectorParam("int", 0, 255),
    "aprilTagDeglitch": DetectorParam("int", 0, 1),
    "detectInvertedMarker": DetectorParam("bool"),
    "useAruco3Detection": DetectorParam("bool"),
    "minSideLengthCanonicalImg": DetectorParam("int", 1, 1024),
    "minMarkerLengthRatioOriginalImg": DetectorParam("float", 0, 1),
}


# Adaptive-threshold windows a frame, at most: each is one thresholding pass over the whole
# frame (OpenCV's default: 3), so 250 would make a frame 80 times slower.
MAX_THRESHOLD_PASSES = 12


def _bad(v: object) -> str:
    return f"{type(v).__name__} {v!r}"[:80]


def _check_one(name: str, spec: DetectorParam, value: object, where: str) -> Scalar:
    if spec.kind == "bool":
        if not isinstance(value, bool):
            raise ValueError(f"{where}: expected true or false, got {_bad(value)}")
        return value
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        kind = "an integer" if spec.kind == "int" else "a number"
        raise ValueError(f"{where}: expected {kind}, got {_bad(value)}")
    if spec.kind == "int":
        if not isinstance(value, (int, np.integer)):
            raise ValueError(f"{where}: expected an integer, got {_bad(value)}")
        if not spec.lo <= value <= spec.hi:
            raise ValueError(f"{where}: must be an integer in [{spec.lo:g}, {spec.hi:g}], "
                             f"got {str(value)[:40]}")
        return int(value)
    try:
        x = float(value)
    except OverflowError:
        raise ValueError(f"{where}: number out of range, got {str(value)[:40]}") from None
    if not math.isfinite(x):
        raise ValueError(f"{where}: expected a finite number, got {x}")
    if (x <= spec.lo if spec.lo_open else x < spec.lo) or x > spec.hi:
        left = "(" if spec.lo_open else "["
        raise ValueError(f"{where}: must be in {left}{spec.lo:g}, {spec.hi:g}], got {x:g}")
    return x


def check_parameters(parameters: object, where: str = "detector parameters") -> dict[str, Scalar]:
    """The one rule on ``cv2.aruco.DetectorParameters`` overrides: each name known (to
    :data:`DETECTOR_PARAMETERS` and this OpenCV), of its kind and in its range, and together
    with :data:`DEFAULT_PARAMETERS` and OpenCV's defaults a window range of at most
    :data:`MAX_THRESHOLD_PASSES` passes and a perimeter range that is not empty. Returns the
    overrides as their kinds; ``ValueError`` naming ``where`` and the key otherwise."""
    if not isinstance(parameters, dict):
        raise ValueError(f"{where}: expected a table of OpenCV DetectorParameters names")
    known = set(_parameter_names())
    out: dict[str, Scalar] = {}
    for name, value in parameters.items():
        w = f"{where}.{name}" if isinstance(name, str) and len(name) < 64 else where
        if name == "cornerRefinementMethod":
            raise ValueError(f"{w}: set it through corner_refinement "
                             "(none, subpix, contour, apriltag)")
        spec = DETECTOR_PARAMETERS.get(name) if isinstance(name, str) else None
        if spec is None or name not in known:
            close = [n for n in sorted(DETECTOR_PARAMETERS)
                     if isinstance(name, str) and name.lower()[:6] in n.lower()]
            hint = f"; did you mean {', '.join(close[:4])}?" if close else ""
            raise ValueError(f"{where}: unknown detector parameter {str(name)[:64]!r}{hint}")
        out[name] = _check_one(name, spec, value, w)
    opencv = cv2.aruco.DetectorParameters()
    merged = {**DEFAULT_PARAMETERS, **out}

    def value(key: str) -> float:
        return float(merged[key]) if key in merged else float(getattr(opencv, key))

    lo, hi = value("adaptiveThreshWinSizeMin"), value("adaptiveThreshWinSizeMax")
    step = value("adaptiveThreshWinSizeStep")
    if hi < lo:
        raise ValueError(f"{where}: adaptiveThreshWinSizeMax {hi:g} is below "
                         f"adaptiveThreshWinSizeMin {lo:g}")
    passes = int((hi - lo) // step) + 1
    if passes > MAX_THRESHOLD_PASSES:
        raise ValueError(f"{where}: adaptiveThreshWinSizeMin/Max/Step give {passes} "
                         f"thresholding passes a frame, at most {MAX_THRESHOLD_PASSES}")
    pmin, pmax = value("minMarkerPerimeterRate"), value("maxMarkerPerimeterRate")
    if not pmin < pmax:
        raise ValueError(f"{where}: minMarkerPerimeterRate {pmin:g} must be below "
                         f"maxMarkerPerimeterRate {pmax:g}")
    return out


@dataclass
class DetectorConfig:
    """What the detector needs.

    dictionary: predefined name (``DICT_5X5_100``) or a custom dictionary file path.
    corner_refinement: ``"subpix"`` (default), ``"none"``, ``"contour"`` or ``"apriltag"``.
    parameters: ``cv2.aruco.DetectorParameters`` overrides by attribute name, applied over
        :data:`DEFAULT_PARAMETERS` (``cornerRefinementMethod`` is set by ``corner_refinement``).
    """

    dictionary: str | Path = "DICT_5X5_100"
    corner_refinement: str = "subpix"
    parameters: dict[str, Scalar] = field(default_factory=dict)

    def detector_parameters(self) -> cv2.aruco.DetectorParameters:
        """The validated OpenCV parameters; ``ValueError`` naming the bad key or value."""
        method = _REFINEMENT.get(str(self.corner_refinement).lower())
        if method is None:
            raise ValueError(f"detector corner_refinement: {self.corner_refinement!r} is not one "
                             f"of {', '.join(_REFINEMENT)}")
        overrides = check_parameters(self.parameters)
        p = cv2.aruco.DetectorParameters()
        for key, value in {**DEFAULT_PARAMETERS, **overrides}.items():
            setattr(p, key, value)
        p.cornerRefinementMethod = method
        return p


def _parameter_names() -> list[str]:
    p = cv2.aruco.DetectorParameters()
    return sorted(a for a in dir(p) if not a.startswith("_")
                  and not callable(getattr(p, a)))



@dataclass(frozen=True)
class Detections:
    """Markers found in one frame.

    ids: (N,) int64. corners: (N, 4, 2) float64 pixels, TL, TR, BR, BL (OpenCV order and
    pixel convention: the top-left pixel's centre is (0, 0)). rejected: number of
    candidate squares that did not decode. mode: "full" (the whole frame was searched) or
    "followed" (:mod:`kmea.fixed_camera.detector`); events: what a tracking detector
    noticed (e.g. the camera moved); restart: the view changed, estimation must restart.
    """

    ids: np.ndarray
    corners: np.ndarray
    rejected: int = 0
    mode: str = "full"
    events: tuple[str, ...] = ()
    restart: bool = False

    def __len__(self) -> int:
        return int(self.ids.shape[0])


def as_gray(frame: object) -> np.ndarray:
    """A validated uint8 (H, W) image; BGR/BGRA (OpenCV order) colour frames are converted.

    Raises ``ValueError`` on anything else (not an array, empty, wrong dtype or shape).
    """
    if not isinstance(frame, np.ndarray):
        raise ValueError(f"frame: expected a numpy array, got {type(frame).__name__}")
    if frame.size == 0:
        raise ValueError(f"frame: empty image (shape {frame.shape})")
    if frame.dtype != np.uint8:
        raise ValueError(f"frame: expected dtype uint8, got {frame.dtype}")
    if frame.ndim == 3 and frame.shape[2] == 1:
        frame = frame[:, :, 0]
    if frame.ndim == 2:
        gray = frame
    elif frame.ndim == 3 and frame.shape[2] == 3:
        gray = cv2.cvtColor(np.ascontiguousarray(frame), cv2.COLOR_BGR2GRAY)
    elif frame.ndim == 3 and frame.shape[2] == 4:
        gray = cv2.cvtColor(np.ascontiguousarray(frame), cv2.COLOR_BGRA2GRAY)
    else:
        raise ValueError(f"frame: expected shape (H, W), (H, W, 1), (H, W, 3) or (H, W, 4), "
                         f"got {frame.shape}")
    if min(gray.shape) < 8:
        raise ValueError(f"frame: image too small ({gray.shape[1]}x{gray.shape[0]})")
    return np.ascontiguousarray(gray)


class MarkerDetector:
    """Detects ArUco markers; build once, call :meth:`detect` every frame.

    dictionary: a ready ``cv2.aruco.Dictionary`` instead of ``config.dictionary`` (e.g. one
    with its own error-correction budget).
    """

    def __init__(self, config: DetectorConfig | None = None,
                 dictionary: cv2.aruco.Dictionary | None = None) -> None:
        self.config = config or DetectorConfig()
        self.dictionary = dictionary if dictionary is not None else get_dictionary(
            self.config.dictionary)
        self.parameters = self.config.detector_parameters()
        self._detector = cv2.aruco.ArucoDetector(self.dictionary, self.parameters)

    def detect(self, gray: np.ndarray) -> Detections:
        """Detect markers in a uint8 grey (or BGR/BGRA) frame; see :class:`Detections`."""
        img = as_gray(gray)
        corners, ids, rejected = self._detector.detectMarkers(img)
        n_rej = len(rejected) if rejected is not None else 0
        if ids is None or len(corners) == 0:
            return Detections(np.zeros(0, dtype=np.int64), np.zeros((0, 4, 2)), n_rej)
        c = np.asarray(corners, dtype=np.float64).reshape(-1, 4, 2)
        return Detections(np.asarray(ids, dtype=np.int64).reshape(-1), c, n_rej)
