"""Camera calibration from views of a chessboard or a ChArUco board.

Board specs (lengths in metres):

- ``chessboard:COLSxROWS:SQUARE_M``: COLS x ROWS *inner* corners (OpenCV's pattern size);
- ``charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT``: COLS x ROWS *squares*, ArUco markers of side
  MARKER_M from the predefined dictionary DICT (``DICT_5X5_100``), OpenCV 4.6+ layout.

:class:`Calibrator` takes frames one by one, keeps the sharp and new views (variance of the
Laplacian over the board's bounding box; mean corner displacement to every kept view) and
calibrates with ``cv2.calibrateCamera`` (k1, k2, p1, p2, k3). The square size only scales the
board poses (extrinsics); the intrinsics do not depend on it.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import cv2
import numpy as np

from kmea.vision.camera import CameraModel

__all__ = ["Board", "BoardError", "CalibrationResult", "Calibrator", "ViewCheck", "parse_board"]


class BoardError(ValueError):
    """A board spec is invalid; the message names the spec and the field."""


@dataclass(frozen=True)
class Board:
    """A calibration board. ``cols`` x ``rows``: inner corners (chessboard) or squares
    (charuco). ``square``, ``marker``: side lengths, metres."""

    kind: str
    cols: int
    rows: int
    square: float
    marker: float | None = None
    dictionary: str | None = None

    @property
    def spec(self) -> str:
        s = f"{self.kind}:{self.cols}x{self.rows}:{self.square:g}"
        if self.kind == "charuco":
            s += f":{self.marker:g}:{self.dictionary}"
        return s

    def chessboard_points(self) -> np.ndarray:
        """(cols * rows, 3) float32 object points of the inner corners, row by row, metres."""
        g = np.mgrid[0:self.cols, 0:self.rows].T.reshape(-1, 2)
        return np.hstack([g * self.square, np.zeros((len(g), 1))]).astype(np.float32)

    def cv_charuco(self) -> cv2.aruco.CharucoBoard:
        if self.marker is None:
            raise BoardError(f"{self.kind}:{self.cols}x{self.rows}: a ChArUco board needs "
                             "its marker size")
        return cv2.aruco.CharucoBoard((self.cols, self.rows), float(self.square),
                                      float(self.marker), aruco_dictionary(self.dictionary or ""))


def aruco_dictionary(name: str) -> cv2.aruco.Dictionary:
    """A predefined ArUco dictionary by name (``DICT_5X5_100``, ``5X5_100`` also accepted)."""
    key = name.upper()
    if not key.startswith("DICT_"):
        key = "DICT_" + key
    value = getattr(cv2.aruco, key, None)
    if not isinstance(value, int):
        raise BoardError(f"unknown ArUco dictionary {name!r} (e.g. DICT_5X5_100, DICT_4X4_50)")
    return cv2.aruco.getPredefinedDictionary(value)


def _length(text: str, spec: str, what: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise BoardError(f"{spec}: {what}: expected a length in metres, got {text!r}") from None
    if not (v > 0 and np.isfinite(v)):
        raise BoardError(f"{spec}: {what}: must be > 0 m, got {text!r}")
    if v > 1.0:
        raise BoardError(f"{spec}: {what}: {v} m is not a board square; lengths are in metres "
                         f"(25 mm = 0.025)")
    return v


def parse_board(spec: str) -> Board:
    """Parse ``chessboard:COLSxROWS:SQUARE_M`` or ``charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT``."""
    parts = spec.split(":")
    kind = parts[0].lower()
    if kind not in ("chessboard", "charuco"):
        raise BoardError(f"{spec}: unknown board {parts[0]!r} (chessboard:COLSxROWS:SQUARE_M or "
                         f"charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT)")
    expected = 3 if kind == "chessboard" else 5
    if len(parts) != expected:
        form = ("chessboard:COLSxROWS:SQUARE_M" if kind == "chessboard"
                else "charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT")
        raise BoardError(f"{spec}: expected {form}")
    m = re.fullmatch(r"(\d+)[xX](\d+)", parts[1])
    if not m:
        raise BoardError(f"{spec}: size {parts[1]!r}: expected COLSxROWS, e.g. 9x7")
    cols, rows = int(m.group(1)), int(m.group(2))
    smallest = 2 if kind == "chessboard" else 3
    if cols < smallest or rows < smallest:
        raise BoardError(f"{spec}: size {parts[1]!r}: at least {smallest}x{smallest}")
    square = _length(parts[2], spec, "square size")
    if kind == "chessboard":
        return Board("chessboard", cols, rows, square)
    marker = _length(parts[3], spec, "marker size")
    if marker >= square:
        raise BoardError(f"{spec}: marker size {marker} m must be smaller than the square "
                         f"{square} m")
    aruco_dictionary(parts[4])
    dict_name = parts[4].upper()
    if not dict_name.startswith("DICT_"):
        dict_name = "DICT_" + dict_name
    return Board("charuco", cols, rows, square, marker, dict_name)


# ---------------------------------------------------------------------------- detection

def _gray(image: np.ndarray) -> np.ndarray:
    if image.ndim == 2:
        return image
    code = cv2.COLOR_BGRA2GRAY if image.shape[2] == 4 else cv2.COLOR_BGR2GRAY
    return cv2.cvtColor(image, code)


class BoardDetector:
    """Finds a board in a greyscale image: (image points (N, 2), object points (N, 3), ids).

    subpix_window: half-size of the chessboard ``cornerSubPix`` window in pixels; None picks
    half the smallest corner spacing (at most 11). A window reaching past the neighbouring
    corners biases the corners badly: 11 on 384x288 views of a 9x7 board gives RMS 3.7 px and a
    focal length 38 % short.
    """

    def __init__(self, board: Board, subpix_window: int | None = None) -> None:
        self.board = board
        self.subpix_window = subpix_window
        if board.kind == "charuco":
            self._cv_board = board.cv_charuco()
            self._detector = cv2.aruco.CharucoDetector(self._cv_board)

    def detect(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray | None] | None:
        if self.board.kind == "chessboard":
            return self._chessboard(gray)
        return self._charuco(gray)

    def _chessboard(self, gray: np.ndarray):
        b = self.board
        flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
        found, corners = cv2.findChessboardCorners(gray, (b.cols, b.rows), flags=flags)
        if not found:
            return None
        pts = corners.reshape(-1, 2)
        # Half the smallest corner spacing, so the search window never reaches a neighbour.
        grid = pts.reshape(b.rows, b.cols, 2)
        spacing = min(np.linalg.norm(np.diff(grid, axis=1), axis=2).min(),
                      np.linalg.norm(np.diff(grid, axis=0), axis=2).min())
        win = self.subpix_window or int(np.clip(spacing / 2 - 1, 2, 11))
        crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 0.001)
        refined = cv2.cornerSubPix(gray, corners.astype(np.float32), (win, win), (-1, -1), crit)
        return refined.reshape(-1, 2).astype(np.float32), b.chessboard_points(), None

    def _charuco(self, gray: np.ndarray):
        ch_corners, ch_ids, _mc, _mi = self._detector.detectBoard(gray)
        if ch_ids is None or len(ch_ids) < 6:
            return None
        # The stubs type detectedCorners as Sequence[MatLike] (the generic Board's); for a
        # ChArUco board it is detectBoard's (N, 1, 2) array, which OpenCV takes.
        obj, img = self._cv_board.matchImagePoints(  # pyright: ignore[reportCallIssue]
            ch_corners, ch_ids)  # pyright: ignore[reportArgumentType]
        if obj is None or len(obj) < 6:
            return None
        return (img.reshape(-1, 2).astype(np.float32), obj.reshape(-1, 3).astype(np.float32),
                ch_ids.reshape(-1).astype(int))


# ---------------------------------------------------------------------------- calibrator

@dataclass
class View:
    """An accepted view: image points (N, 2) px, object points (N, 3) m, ids (charuco)."""

    name: str
    image_points: np.ndarray
    object_points: np.ndarray
    ids: np.ndarray | None
    sharpness: float


@dataclass
class ViewCheck:
    """What happened to one frame: ``status`` is accepted, no board, blurred, duplicate,
    size mismatch or unreadable."""

    name: str
    status: str
    sharpness: float | None = None
    corners: int = 0
    detail: str = ""

    @property
    def accepted(self) -> bool:
        return self.status == "accepted"


@dataclass
class CalibrationResult:
    """model: the camera (image size = the views'). rms: overall RMS reprojection error, px.
    view_errors: (name, RMS px) per view used, worst first. dropped: (name, RMS px) of the
    views removed as outliers; rms_all: the RMS before dropping them."""

    model: CameraModel
    rms: float
    view_errors: list[tuple[str, float]]
    dropped: list[tuple[str, float]] = field(default_factory=list)
    rms_all: float | None = None

    @property
    def n_views(self) -> int:
        return len(self.view_errors)


class Calibrator:
    """Accumulates board views and calibrates.

    blur_threshold: minimum variance of the Laplacian over the board's bounding box (0: off);
    blurred views give poor corners even when the board is found. min_move_px: a view whose
    corners moved less than this on average from an accepted view is a near-duplicate (None:
    2 % of the image diagonal). subpix_window: see :class:`BoardDetector`.
    """

    def __init__(self, board: Board, blur_threshold: float = 30.0,
                 min_move_px: float | None = None, subpix_window: int | None = None) -> None:
        self.board = board
        self.detector = BoardDetector(board, subpix_window)
        self.blur_threshold = float(blur_threshold)
        self.min_move_px = min_move_px
        self.views: list[View] = []
        self.image_size: tuple[int, int] | None = None
        self.seen = 0
        self.counts: dict[str, int] = {}
        self._mask: np.ndarray | None = None
        self._mask_scale = 1.0

    # -- views
    def add(self, image: np.ndarray | None, name: str) -> ViewCheck:
        """Try one frame (greyscale or BGR); keeps it when it is a good new view."""
        self.seen += 1
        check = self._check(image, name)
        self.counts[check.status] = self.counts.get(check.status, 0) + 1
        return check

    def _check(self, image: np.ndarray | None, name: str) -> ViewCheck:
        if image is None:
            return ViewCheck(name, "unreadable")
        gray = _gray(image)
        size = (int(gray.shape[1]), int(gray.shape[0]))
        if self.image_size is None:
            self.image_size = size
            diag = float(np.hypot(*size))
            self._mask_scale = min(1.0, 256.0 / max(size))
            self._mask = np.zeros((max(1, round(size[1] * self._mask_scale)),
                                   max(1, round(size[0] * self._mask_scale))), np.uint8)
            if self.min_move_px is None:
                self.min_move_px = 0.02 * diag
        elif size != self.image_size:
            return ViewCheck(name, "size mismatch",
                             detail=f"{size[0]}x{size[1]}, expected "
                                    f"{self.image_size[0]}x{self.image_size[1]}")
        found = self.detector.detect(gray)
        if found is None:
            return ViewCheck(name, "no board")
        img_pts, obj_pts, ids = found
        x, y, w, h = cv2.boundingRect(img_pts.reshape(-1, 1, 2))
        roi = gray[max(y, 0):y + h, max(x, 0):x + w]
        sharpness = float(cv2.Laplacian(roi, cv2.CV_64F).var()) if roi.size else 0.0
        if sharpness < self.blur_threshold:
            return ViewCheck(name, "blurred", sharpness, len(img_pts),
                             f"sharpness {sharpness:.0f} < {self.blur_threshold:g}")
        dup = self._duplicate_of(img_pts, ids)
        if dup is not None:
            return ViewCheck(name, "duplicate", sharpness, len(img_pts), f"close to {dup}")
        self.views.append(View(name, img_pts, obj_pts, ids, sharpness))
        self._cover(img_pts)
        return ViewCheck(name, "accepted", sharpness, len(img_pts))

    def _duplicate_of(self, pts: np.ndarray, ids: np.ndarray | None) -> str | None:
        limit = float(self.min_move_px or 0.0)
        for v in self.views:
            if ids is None:
                if v.ids is not None or len(v.image_points) != len(pts):
                    continue
                # A symmetric chessboard can be found in either corner order.
                d = min(np.linalg.norm(v.image_points - pts, axis=1).mean(),
                        np.linalg.norm(v.image_points[::-1] - pts, axis=1).mean())
            else:
                if v.ids is None:
                    continue
                common, ia, ib = np.intersect1d(v.ids, ids, return_indices=True)
                if len(common) < 0.8 * max(len(ids), len(v.ids)):
                    continue
                d = np.linalg.norm(v.image_points[ia] - pts[ib], axis=1).mean()
            if d < limit:
                return v.name
        return None

    def _cover(self, pts: np.ndarray) -> None:
        assert self._mask is not None
        hull = cv2.convexHull((pts * self._mask_scale).astype(np.float32))
        cv2.fillConvexPoly(self._mask, np.round(hull).astype(np.int32).reshape(-1, 2), 1)

    def coverage(self) -> float:
        """Fraction of the image area inside the board outline of at least one accepted view."""
        return 0.0 if self._mask is None else float(self._mask.mean())

    # -- calibration
    def _run(self, views: list[View]) -> tuple[float, np.ndarray, np.ndarray, list[float]]:
        assert self.image_size is not None
        obj = [v.object_points.reshape(-1, 1, 3) for v in views]
        img = [v.image_points.reshape(-1, 1, 2) for v in views]
        rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(obj, img, self.image_size, None, None)
        errs = []
        for o, i, r, t in zip(obj, img, rvecs, tvecs, strict=True):
            proj, _ = cv2.projectPoints(o, r, t, K, dist)
            errs.append(float(np.sqrt(np.mean(np.sum((proj - i).reshape(-1, 2) ** 2, axis=1)))))
        return float(rms), K, dist.reshape(-1), errs

    def calibrate(self, drop_outliers: bool = False, min_views: int = 5,
                  outlier_factor: float = 2.0) -> CalibrationResult:
        """Calibrate on the accepted views.

        With ``drop_outliers``, views whose RMS error exceeds ``outlier_factor`` x the median
        view error are removed (never below ``min_views`` views) and the camera recalibrated.
        Raises ``ValueError`` with fewer than ``min_views`` views.
        """
        if len(self.views) < max(min_views, 3):
            raise ValueError(f"only {len(self.views)} usable views; need at least "
                             f"{max(min_views, 3)}")
        rms, K, dist, errs = self._run(self.views)
        used = list(self.views)
        dropped: list[tuple[str, float]] = []
        rms_all = rms
        if drop_outliers:
            med = float(np.median(errs))
            order = np.argsort(errs)[::-1]
            bad = [int(i) for i in order if errs[i] > outlier_factor * med]
            bad = bad[:max(0, len(used) - min_views)]
            if bad:
                dropped = [(used[i].name, errs[i]) for i in bad]
                used = [v for i, v in enumerate(used) if i not in set(bad)]
                rms, K, dist, errs = self._run(used)
        assert self.image_size is not None
        model = CameraModel(K, dist, self.image_size[0], self.image_size[1])
        view_errors = sorted(((v.name, e) for v, e in zip(used, errs, strict=True)),
                             key=lambda p: -p[1])
        return CalibrationResult(model, rms, view_errors, dropped,
                                 rms_all if dropped else None)
