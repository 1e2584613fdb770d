"""Tracking detection for a fixed camera: look where the markers are, detect what is new.

The camera is bolted above a static floor; only robots move. Full ``detectMarkers`` on
every 1640x1232 frame thresholds two million pixels three times to find markers whose
place is already known. :class:`FixedCameraDetector` keeps what the last frames found and,
per frame:

- **static markers** (the map's, minus robot markers): they are where they were. Their
  reference corners (from the last full detection) are checked, not searched: the marker's
  7x7 module grid is sampled at the reference quadrilateral and compared with its code
  (:func:`verify_codes`: a hidden marker fails and is not reported in that frame), and
  ``cv2.cornerSubPix`` from the reference corners measures how far each corner drifted
  (a rotating third of the markers a frame: ``drift_every``).
  A marker whose corners drifted more than ``move_px`` moved: a full detection follows.
  When most static markers drift, or fail their code, the camera was bumped: a full
  detection runs at once (in that frame), every reference is replaced and the result
  carries a ``camera moved`` event (the pipeline then restarts its estimation).
  The reported corners of a static marker stay its reference corners while it does not
  move, so the pipeline can reuse its pose (:class:`kmea.pipeline.Pipeline`).
- **moving markers** (robots, anything not in the map): predicted from their last two
  positions (constant velocity in the image). Their corners are refined from the prediction
  as the detector refines them (``cornerSubPix``) and kept when the marker's code reads at
  the refined corners and its size held; otherwise (a sharp turn, a change of speed beyond
  the refinement's reach, near the border) the marker is detected with the full parameters
  in a small region around the prediction (``cv2.aruco.ArucoDetector`` on a crop), in a
  wider one when the first misses. A moving marker lost there triggers one full detection in
  the same frame (a robot visible in the frame keeps its pose for the frame).
- **new markers**: a full detection runs in the background (on the executor the caller
  gives, e.g. the daemon's one low-priority thread; without one, in the calling thread:
  the library starts no thread) every ``full_every`` frames and whenever a tracked marker
  is lost; what it finds that is not tracked is checked in the current frame (a moving one
  detected around where it was found) and reported from then on. At 30 frames/s,
  ``full_every`` = 6 reports a marker entering the view within 0.2 s plus one background
  detection.

Stateful: one instance per live source, called on consecutive frames. For file sources
(frame-exact, reproducible results) the pipeline keeps full detection on every frame.
Pixel convention: OpenCV's (the top-left pixel's centre is (0, 0)).
"""

from __future__ import annotations

import collections
import contextlib
import math
import os
import threading
from collections.abc import Collection
from concurrent.futures import Executor
from dataclasses import dataclass, field

import cv2
import numpy as np

from kmea.vision.detection import Detections, DetectorConfig, MarkerDetector, as_gray

__all__ = ["CodeSampler", "FixedCameraConfig", "FixedCameraDetector", "code_scores", "marker_codes",
           "verify_codes"]


@dataclass
class FixedCameraConfig:
    """Tracking settings (pixels, frames).

    full_every: a background full detection every this many frames (new markers), at half
    resolution except every ``full_res_every``-th (small, far markers) and after a loss.
    move_px: a static marker whose corners drift more than this moved.
    drift_every: each static marker's drift is measured every this many frames (a
    rotating share of them a frame, at least ``drift_min``; all of them when there are no
    more); its code is checked every frame.
    bump_fraction: this share of the static markers moved or missing (at least
    ``bump_min`` of them) = the camera was bumped; counted among the markers whose drift
    was measured in the frame, and among all of them for the code check.
    min_score: a static marker is seen when its code correlates at least this much with
    the image at its reference corners (:func:`code_scores`); add_score: a static marker
    found by a background detection is taken (or replaces its reference) from this score.
    margin: search region around a moving marker's prediction, in marker sides.
    follow: a moving marker seen in the last two frames is first refined from its predicted
    corners (``cornerSubPix`` as the detector refines) and kept when its code reads at
    least ``follow_score`` there and its size held; otherwise, or with ``follow`` off, it
    is detected in a region around the prediction.
    average: a fixed marker's reference corners are the mean of up to this many
    full-resolution detections.
    """

    full_every: int = 6
    full_res_every: int = 10
    average: int = 8
    move_px: float = 1.0
    drift_every: int = 3
    drift_min: int = 8
    bump_fraction: float = 0.5
    bump_min: int = 3
    min_score: float = 0.6
    add_score: float = 0.75
    margin: float = 0.4
    follow: bool = True
    follow_score: float = 0.75
    static_ids: frozenset[int] = field(default_factory=frozenset)


def marker_codes(dictionary: cv2.aruco.Dictionary, ids: Collection[int]) -> dict[int, np.ndarray]:
    """id -> (S+2, S+2) bool module grid of the printed marker (True = white; black border
    included), S the dictionary's marker size."""
    size = int(dictionary.markerSize) + 2
    out = {}
    for mid in ids:
        img = cv2.aruco.generateImageMarker(dictionary, int(mid), size, borderBits=1)
        out[int(mid)] = img > 127
    return out


def _homographies(quads: np.ndarray, size: int) -> np.ndarray:
    """(N, 3, 3) homographies mapping module coordinates [0, size]^2 (x right, y down) to the
    image quads (N, 4, 2) TL, TR, BR, BL: the closed-form square-to-quadrilateral mapping
    (Heckbert, "Fundamentals of texture mapping", 1989); the exact homography of the four
    corners, as a direct linear solve gives it, without the solve. A degenerate quad (three
    corners on a line) gives non-finite entries. In floats, quad by quad: it runs for the
    followed markers of every frame (a few quads), where numpy's per-call cost on (N,)
    arrays was ~50 us."""
    out = []
    inf = math.inf
    for (x0, y0), (x1, y1), (x2, y2), (x3, y3) in np.asarray(quads, float).tolist():
        sx, sy = x0 - x1 + x2 - x3, y0 - y1 + y2 - y3
        dx1, dx2, dy1, dy2 = x1 - x2, x3 - x2, y1 - y2, y3 - y2
        den = dx1 * dy2 - dx2 * dy1
        if den != 0.0:
            g = (sx * dy2 - dx2 * sy) / den
            h = (dx1 * sy - sx * dy1) / den
        else:
            g = h = inf
        out.append(((x1 - x0 + g * x1) / size, (x3 - x0 + h * x3) / size, x0,
                    (y1 - y0 + g * y1) / size, (y3 - y0 + h * y3) / size, y0,
                    g / size, h / size, 1.0))
    return np.array(out, dtype=float).reshape(-1, 3, 3)


class CodeSampler:
    """Where to sample the modules of fixed quads (N, 4, 2) px with codes (N, M, M) bool.

    Built once for the static markers' reference corners (the homographies and sample
    points do not change while the references do not); :meth:`scores` then reads a frame.
    """

    _grids: dict[int, np.ndarray] = {}

    def __init__(self, quads: np.ndarray, codes: np.ndarray, shape: tuple[int, int]) -> None:
        n = len(quads)
        self.n = n
        m = codes.shape[1] if n else 0
        self.m = m
        if n == 0:
            return
        grid = self._grids.get(m)
        if grid is None:
            g = np.arange(m) + 0.5
            off = np.array([[-0.2, -0.2], [0.2, -0.2], [-0.2, 0.2], [0.2, 0.2]])
            gx, gy = np.meshgrid(g, g)                                  # (m, m), x right
            pts = np.stack([gx, gy], -1)[:, :, None, :] + off           # (m, m, 4, 2)
            grid = np.concatenate([pts.reshape(-1, 2), np.ones((m * m * 4, 1))], 1)
            self._grids[m] = grid
        H = _homographies(np.asarray(quads, float), m)
        proj = H @ grid.T                                               # (N, 3, P)
        # numpy's ufuncs directly: this runs per followed marker per frame, where the
        # method wrappers' (mean, clip) call overhead is most of the cost.
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            x = np.divide(proj[:, 0], proj[:, 2])                       # (N, P)
            y = np.divide(proj[:, 1], proj[:, 2])
        h, w = shape
        finite = np.isfinite(x)
        finite &= np.isfinite(y)
        self.finite = np.logical_and.reduce(finite, axis=1)
        if not self.finite.all():
            x = np.where(finite, x, 0.0)
            y = np.where(finite, y, 0.0)
        # Bilinear samples through cv2.remap (one C call; its weights are in 1/32 px steps,
        # and a point outside the image takes the nearest border pixel's value).
        self.map_x = np.minimum(np.maximum(x, -1.0), w).astype(np.float32)   # (N, P)
        self.map_y = np.minimum(np.maximum(y, -1.0), h).astype(np.float32)
        ref = codes.reshape(n, m * m).astype(np.float64)
        ref -= np.add.reduce(ref, axis=1, keepdims=True) / (m * m)
        self.ref = ref
        self.ref_norm = np.sqrt(np.add.reduce(ref * ref, axis=1))

    def scores(self, gray: np.ndarray) -> np.ndarray:
        """(N,) correlation of each code with the frame ``gray`` (see :func:`code_scores`)."""
        if self.n == 0:
            return np.zeros(0)
        v = cv2.remap(gray, self.map_x, self.map_y, cv2.INTER_LINEAR,
                      borderMode=cv2.BORDER_REPLICATE)
        mm = self.m * self.m
        # Module sums of the 4 samples (the correlation does not see the scale of a mean).
        vals = np.add.reduce(v.reshape(self.n, mm, 4), axis=2, dtype=np.float64)
        vals -= np.add.reduce(vals, axis=1, keepdims=True) / mm
        num = np.add.reduce(vals * self.ref, axis=1)
        den = np.sqrt(np.add.reduce(vals * vals, axis=1)) * self.ref_norm
        with np.errstate(divide="ignore", invalid="ignore"):
            score = np.where(den > 0, num / den, 0.0)
        return np.where(self.finite, score, 0.0)


def code_scores(gray: np.ndarray, quads: np.ndarray, codes: np.ndarray) -> np.ndarray:
    """(N,) correlation (-1..1) between the image at each quad (N, 4, 2) px and its code
    (N, M, M) bool modules (border included).

    Each module is sampled (bilinear, ``cv2.remap``) at 4 points around its centre and
    averaged; the score is the normalised correlation of the M*M module values with the
    code: 1 for a sharp marker, ~0.85 for a 10 px high wall marker seen edge-on, lower for a
    hidden one and 0 for a flat patch. Vectorised over the markers.
    """
    return CodeSampler(np.asarray(quads, float), codes, gray.shape[:2]).scores(gray)


def verify_codes(gray: np.ndarray, quads: np.ndarray, codes: np.ndarray,
                 min_score: float = 0.6) -> np.ndarray:
    """(N,) bool: does each quad show its code? (:func:`code_scores` >= ``min_score``)."""
    return code_scores(gray, quads, codes) >= min_score


# Longest wait (s) of a background detection for the frame path's gate.
GATE_WAIT_S = 0.25

# A followed marker's corners may leave the similarity image of its last corners by this much
# (px); see FixedCameraDetector._follow.
SHAPE_PX = 0.5


def _perimeter(c: list) -> float:
    """The perimeter (px) of a quad c (4 [x, y] pairs): corner k to corner k + 1."""
    total = 0.0
    for (x0, y0), (x1, y1) in zip(c, c[1:] + c[:1], strict=True):
        dx, dy = x1 - x0, y1 - y0
        total += math.sqrt(dx * dx + dy * dy)
    return total


def _median(v: list[float]) -> float:
    """The median of a few floats (np.median costs ~15 us a call)."""
    v = sorted(v)
    n = len(v)
    return v[n // 2] if n % 2 else 0.5 * (v[n // 2 - 1] + v[n // 2])


def _subpix_window(ref: np.ndarray) -> int:
    """The floor check's ``cornerSubPix`` half-window (px) for reference corners ref
    (N, 4, 2) px: 0.3 of the median marker's module (7 modules a side), 2 to 6 px."""
    side = np.linalg.norm(ref[:, 0] - ref[:, 2], axis=1) / np.sqrt(2.0)
    module = float(np.median(side)) / 7.0
    return int(min(6, max(2, round(0.3 * module))))


@dataclass(eq=False)
class _FloorCheck:
    """What the static markers' per-frame check needs while their references hold."""

    key: tuple                              # (ids, their tracks, image shape)
    ref: np.ndarray                         # (n, 4, 2) reference corners, px
    win: int                                # cornerSubPix half-window, px
    sampler: CodeSampler                    # their codes at the references
    sub0: np.ndarray                        # (n, 4, 2) first look's cornerSubPix; NaN: none


@dataclass(eq=False)
class _Followed:
    corners: np.ndarray                     # (4, 2) last seen
    velocity: np.ndarray                    # (4, 2) px per frame
    static: bool
    seen: int                               # frame number last seen
    looks: int = 1                          # full-resolution detections averaged (static)
    steady: bool = False                    # velocity from two consecutive frames (moving)


class FixedCameraDetector:
    """``detect(image) -> Detections`` like :class:`MarkerDetector`, tracking what it knows
    (see the module docstring). ``Detections.mode`` is "full" (a full detection answered)
    or "followed"; ``Detections.events`` carries "camera moved" and friends.

    Counters: ``tracked`` / ``full`` frames, ``background`` full detections, ``bumps``,
    ``followed`` moving markers refined from their prediction (no region detection).
    """

    def __init__(self, config: DetectorConfig, tracking: FixedCameraConfig | None = None,
                 executor: Executor | None = None, gate: threading.Event | None = None
                 ) -> None:
        """executor: where the background detection runs (one job at a time; the caller
        owns it and shuts it down); None: in the calling thread, within ``detect``."""
        self.config = config
        # Set by the pipeline once a frame's robots are sent, cleared when the next frame's
        # detection starts: the background detection waits for it (see _drain).
        self.gate = gate
        self.settings = tracking or FixedCameraConfig()
        self.full_detector = MarkerDetector(config)
        self.roi_detector = MarkerDetector(config)._detector
        self.dictionary = self.full_detector.dictionary
        self._codes: dict[int, np.ndarray] = {}
        self._floor: _FloorCheck | None = None
        self._tuned: dict[int, MarkerDetector] = {}  # the calling thread's (see _drain)
        # The executor's (one task at a time: _drain runs alone).
        self._worker_det: MarkerDetector | None = None
        self._worker_tuned: dict[int, MarkerDetector] = {}
        self._half_ok = False
        self._side = 0.0  # median marker side (px) of the last full detection
        self.known: dict[int, _Followed] = {}  # id -> what is known of its corners
        self.frame = -1
        self.followed_frames = 0
        self.full = 0
        self.background = 0
        self.bumps = 0
        self.followed = 0
        # The last followed looks' shape residuals (px; see _follow), for tests and tuning.
        self.shape_px: collections.deque[float] = collections.deque(maxlen=512)
        self._since_full = 0
        self._want_full = True
        self._executor = executor
        self._job: tuple[int, np.ndarray, bool, int] | None = None
        self._result: tuple[int, Detections, bool] | None = None
        self._draining = False  # a _drain task is queued or running on the executor
        self._cond = threading.Condition()
        self._closed = False

    # ------------------------------------------------------------------ background detection
    def _drain(self) -> None:
        """The executor's task: run the queued job, and the next one queued meanwhile, until
        none is left (newest wins: a job replaced before it started is dropped)."""
        with contextlib.suppress(OSError, AttributeError):
            # Below the frame path: on one core the tracked frames preempt discovery (nice 5:
            # a third of the frame path's share; at nice 10 a loaded machine starved it).
            # The executor's thread keeps it: the caller's executor is for this work.
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 5)
        if self._worker_det is None:
            self._worker_det = MarkerDetector(self.config)
        det, tuned = self._worker_det, self._worker_tuned
        while True:
            with self._cond:
                if self._job is None or self._closed:
                    self._draining = False
                    return
                frame_no, image, half, win = self._job
                self._job = None
            if self.gate is not None:
                # Run in the gap after the frame's robots were sent, not beside the frame
                # path: OpenCV's worker threads (not niced) would share the cores with it.
                # Never starve: after GATE_WAIT_S it runs anyway.
                self.gate.wait(GATE_WAIT_S)
            try:
                d = self._discover(self._tuned_detector(tuned, win) if half and win else det,
                                   image, half)
            except Exception:  # a frame the detector cannot digest: no result
                d = None
            with self._cond:
                if d is not None:
                    self._result = (frame_no, d, half)

    def _tuned_detector(self, cache: dict[int, MarkerDetector], win: int) -> MarkerDetector:
        """A detector with one adaptive-threshold window of ``win`` px, a fifth of the
        markers' side (a third of the full parameters' three passes), from ``cache`` (one
        per thread: the calling thread's)."""
        det = cache.get(win)
        if det is None:
            params = {**self.config.parameters, "adaptiveThreshWinSizeMin": win,
                      "adaptiveThreshWinSizeMax": win}
            det = cache[win] = MarkerDetector(DetectorConfig(
                self.config.dictionary, self.config.corner_refinement, params))
        return det

    @staticmethod
    def _discover(det: MarkerDetector, image: np.ndarray, half: bool) -> Detections:
        """Full detection of ``image``, at half resolution when ``half`` (4x fewer pixels;
        corners mapped back to full-resolution pixels, to be refined there)."""
        if not half:
            return det.detect(image)
        h, w = image.shape[:2]
        small = cv2.resize(image, (w // 2, h // 2), interpolation=cv2.INTER_AREA)
        d = det.detect(small)
        # INTER_AREA by 2: small pixel i covers full pixels 2i and 2i+1 (centre 2i + 0.5).
        return Detections(d.ids, d.corners * 2.0 + 0.5, d.rejected)

    def _submit(self, image: np.ndarray, full_res: bool = False) -> None:
        """Queue a background detection of ``image`` (one at a time; newest wins): at half
        resolution, except every ``full_res_every``-th one and when ``full_res``."""
        self.background += 1
        half = (self._half_ok and not full_res
                and self.background % max(1, self.settings.full_res_every) != 0)
        # At half resolution one threshold window sized for the markers already seen (new
        # ones are the same markers on the same floor; the full-resolution looks keep all
        # three windows for anything else).
        win = max(3, round(self._side / 10.0) | 1) if half and self._side > 0 else 0
        if self._executor is None:
            det = self._tuned_detector(self._tuned, win) if win else self.full_detector
            self._result = (self.frame, self._discover(det, image, half), half)
            return
        with self._cond:
            if self._closed:
                return
            self._job = (self.frame, image, half, win)
            if self._draining:
                return  # the running task takes it next
            self._draining = True
        try:
            self._executor.submit(self._drain)
        except RuntimeError:  # the executor was shut down (the daemon stops): no discovery
            with self._cond:
                self._draining = False

    def _take_result(self) -> tuple[int, Detections, bool] | None:
        with self._cond:
            r, self._result = self._result, None
        return r

    def close(self) -> None:
        """No more background detections (a queued one is dropped; one running finishes on
        the caller's executor, whose owner waits for it)."""
        with self._cond:
            self._closed = True
            self._job = None

    # ------------------------------------------------------------------ helpers
    def _code(self, mid: int) -> np.ndarray:
        c = self._codes.get(mid)
        if c is None:
            c = self._codes[mid] = marker_codes(self.dictionary, [mid])[mid]
        return c

    def _is_static(self, mid: int) -> bool:
        return mid in self.settings.static_ids

    def _reset_from(self, det: Detections) -> None:
        """Every track from a full detection of the current frame."""
        old = self.known
        # A static marker the detection missed (hidden now) keeps its place.
        self.known = {m: t for m, t in old.items() if t.static}
        sides = []
        for mid, c in zip(det.ids.tolist(), det.corners, strict=True):
            prev = old.get(mid)
            sides.append(float(np.linalg.norm(c[0] - c[2])) / np.sqrt(2.0))
            if prev is not None and prev.static and self._is_static(mid):
                self.known[mid] = self._averaged(prev, c)
                continue
            vel = np.zeros((4, 2))
            if prev is not None and not prev.static and self.frame > prev.seen:
                vel = (c - prev.corners) / (self.frame - prev.seen)
            self.known[mid] = _Followed(c.copy(), vel, self._is_static(mid), self.frame,
                                      steady=prev is not None and not prev.static
                                      and self.frame - prev.seen == 1)
        if sides:
            # Half-resolution discovery only when markers stay >= 20 px wide there.
            self._side = float(np.median(sides))
            self._half_ok = self._side >= 40.0
        self._since_full = 0
        self._want_full = False

    def _averaged(self, t: _Followed, c: np.ndarray) -> _Followed:
        """A fixed marker's reference with one more full-resolution look ``c`` (4, 2) px:
        the mean of up to ``average`` looks within ``move_px`` of it (single detections of
        a 30-60 px marker scatter by up to ~1 px), else ``c`` (it moved)."""
        if np.abs(c - t.corners).max() > 1.5 * self.settings.move_px:
            return _Followed(c.copy(), np.zeros((4, 2)), True, self.frame)
        if np.abs(c - t.corners).max() < 1e-9:
            return t
        n = min(t.looks + 1, self.settings.average)
        new = _Followed(t.corners + (c - t.corners) / n, np.zeros((4, 2)), True, self.frame)
        new.looks = n
        return new

    def _roi_detector(self, side: float):
        """The ArUco detector for a region: one adaptive-threshold window of a fifth of the
        marker side (the full parameters' three windows cost three times as much) when
        ``side`` > 0 px, else the configured parameters."""
        if side <= 0:
            return self.roi_detector
        return self._tuned_detector(self._tuned, max(3, round(side / 5.0) | 1))._detector

    def _detect_roi(self, gray: np.ndarray, center: np.ndarray, half: float, side: float = 0.0
                    ) -> tuple[np.ndarray, np.ndarray]:
        """(ids, corners) found in the square of half-side ``half`` px around ``center``
        (``side``: the marker's side in px, for a tuned threshold window; 0: configured)."""
        return self._detect_box(gray, (center[0] - half, center[1] - half,
                                       center[0] + half, center[1] + half), side)

    def _detect_box(self, gray: np.ndarray, box: tuple[float, float, float, float],
                    side: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """(ids, corners) found in ``box`` (x0, y0, x1, y1) px; ``side`` as in
        :meth:`_detect_roi`."""
        h, w = gray.shape
        x0, y0 = max(0, int(box[0])), max(0, int(box[1]))
        x1, y1 = min(w, int(box[2]) + 1), min(h, int(box[3]) + 1)
        if x1 - x0 < 16 or y1 - y0 < 16:
            return np.zeros(0, np.int64), np.zeros((0, 4, 2))
        corners, ids, _ = self._roi_detector(side).detectMarkers(gray[y0:y1, x0:x1])
        if ids is None or not len(corners):
            return np.zeros(0, np.int64), np.zeros((0, 4, 2))
        c = np.asarray(corners, dtype=np.float64).reshape(-1, 4, 2) + np.array([x0, y0], float)
        return np.asarray(ids, np.int64).reshape(-1), c

    def _region(self, pred: np.ndarray) -> tuple[np.ndarray, float, float]:
        """(centre (2,), half-side px of the search square, marker side px) around a
        predicted quad (4, 2) px."""
        side = float(np.linalg.norm(pred[0] - pred[2])) / np.sqrt(2.0)
        ctr = pred.mean(axis=0)
        span = float(np.max(np.abs(pred - ctr)))
        return ctr, span + self.settings.margin * side + 4.0, side

    def _groups(self, preds: dict[int, np.ndarray]
                ) -> list[tuple[tuple[float, float, float, float], float, set[int]]]:
        """Search boxes (x0, y0, x1, y1) px, mean marker side and member ids: the regions
        of ``preds`` (id -> predicted quad), overlapping ones joined when their union is
        not much larger than the two (one detection call instead of two)."""
        out: list[list] = []
        for m, q in preds.items():
            ctr, half, side = self._region(q)
            box = [ctr[0] - half, ctr[1] - half, ctr[0] + half, ctr[1] + half]
            for g in out:
                b = g[0]
                u = [min(b[0], box[0]), min(b[1], box[1]), max(b[2], box[2]),
                     max(b[3], box[3])]
                area = (u[2] - u[0]) * (u[3] - u[1])
                if area <= 1.2 * ((b[2] - b[0]) * (b[3] - b[1])
                                  + (box[2] - box[0]) * (box[3] - box[1])):
                    g[0] = u
                    g[1].append(side)
                    g[2].add(m)
                    break
            else:
                out.append([box, [side], {m}])
        return [(tuple(b), float(np.mean(sides)), ids) for b, sides, ids in out]

    def _find_moving(self, gray: np.ndarray, mid: int, pred: np.ndarray,
                     wide_only: bool = False
                     ) -> tuple[np.ndarray | None, dict[int, np.ndarray]]:
        """Corners (4, 2) of moving marker ``mid`` near its prediction (None if not there),
        and any other marker seen in the region (id -> corners). ``wide_only``: skip the
        first, tight look (done already)."""
        side = float(np.linalg.norm(pred[0] - pred[2])) / np.sqrt(2.0)
        ctr = pred.mean(axis=0)
        span = float(np.max(np.abs(pred - ctr)))
        others: dict[int, np.ndarray] = {}
        tries = ((3.0, False),) if wide_only else ((1.0, True), (3.0, False))
        for grow, tuned in tries:
            half = span + self.settings.margin * side * grow + 4.0
            ids, cs = self._detect_roi(gray, ctr, half, side if tuned else 0.0)
            found = None
            for i, c in zip(ids.tolist(), cs, strict=True):
                if i == mid:
                    found = c
                else:
                    others[i] = c
            if found is not None:
                return found, others
        return None, others

    # ------------------------------------------------------------------ per frame
    def detect(self, image: np.ndarray) -> Detections:
        """Markers in ``image`` (the next frame of the fixed camera); see the module
        docstring."""
        gray = as_gray(image)
        if self.gate is not None:
            self.gate.clear()  # this frame's path runs until the pipeline sets it again
        self.frame += 1
        self._since_full += 1
        events: list[str] = []
        if self._want_full or not self.known:
            return self._full(gray, events)
        s = self.settings
        out_ids: list[int] = []
        out_c: list[np.ndarray] = []
        lost = False
        # ---- static markers: code check and drift at the reference corners
        st = [m for m, t in self.known.items() if t.static]
        moved: list[int] = []
        if st:
            fc = self._floor_check(st, gray.shape)
            seen = fc.sampler.scores(gray) >= s.min_score
            # The drift of a rotating share of them (cornerSubPix is the floor check's
            # largest cost): a bump moves every marker, so any share shows it at once; a
            # single marker pushed by less than its code's tolerance shows within
            # drift_every frames.
            chk = self._drift_share(len(st))
            refined = self._subpix(gray, fc.ref[chk], fc.win)
            first = np.isnan(fc.sub0[chk, 0, 0])
            if first.any():  # first look since the reference
                fc.sub0[chk[first]] = refined[first]
            # Drift of the refinement from the refinement at the reference (same method on
            # both sides: the detector's own refinement differs by up to ~1 px on oblique
            # wall markers).
            # Moved: at least 3 corners drifted (a robot's plate over one corner pulls only
            # that corner; the reference stays right for a marker that did not move).
            d = refined - fc.sub0[chk]
            far = np.zeros(len(st), dtype=bool)
            far[chk] = np.add.reduce(np.add.reduce(d * d, axis=2) > s.move_px ** 2,
                                     axis=1) >= 3
            moved = [m for m, ok, f in zip(st, seen, far, strict=True) if ok and f]
            missing = int((~seen).sum())
            bad_chk = int((~seen[chk]).sum()) + len(moved)
            if len(st) >= s.bump_min and (
                    missing >= max(s.bump_min, s.bump_fraction * len(st))
                    or (len(chk) >= s.bump_min
                        and bad_chk >= max(s.bump_min, s.bump_fraction * len(chk)))):
                self.bumps += 1
                events.append(f"camera moved: {len(moved)} of {len(chk)} floor markers "
                              f"measured moved, {missing} of {len(st)} missing at their "
                              "place in the image; full detection and estimation restart")
                return self._full(gray, events)
            if moved:
                events.append("floor marker(s) " + ", ".join(map(str, moved))
                              + f" moved more than {s.move_px:g} px in the image")
            for m, ok, f in zip(st, seen, far, strict=True):
                t = self.known[m]
                if ok and not f:
                    out_ids.append(m)
                    out_c.append(t.corners)
                    t.seen = self.frame
                elif t.seen == self.frame - 1:
                    # Just hidden or moved: one background look (a hidden one keeps its
                    # place; a moved one gets its new place from the full detection).
                    lost = True
        # ---- moving markers: near their prediction, one detection per group of nearby
        # regions (a robot's two markers share one crop)
        moving = [(m, t) for m, t in self.known.items() if not t.static]
        found: dict[int, np.ndarray] = {}
        others: dict[int, np.ndarray] = {}
        preds = {m: t.corners + t.velocity * (self.frame - t.seen) for m, t in moving}
        if s.follow:
            found = self._follow(gray, {m: preds[m] for m, t in moving
                                        if t.steady and t.seen == self.frame - 1})
        for box, side, members in self._groups({m: q for m, q in preds.items()
                                                if m not in found}):
            ids, cs = self._detect_box(gray, box, side)
            for i, c in zip(ids.tolist(), cs, strict=True):
                (found if i in members else others)[i] = c
        for m, t in moving:
            c = found.get(m)
            if c is None:  # not where predicted: a wider look with the full parameters
                c, more = self._find_moving(gray, m, preds[m], wide_only=True)
                others.update(more)
            if c is None:
                if t.seen == self.frame - 1:
                    # Just lost: it may have outrun the prediction; a robot visible in the
                    # frame must keep its pose, so look at the whole frame once.
                    return self._full(gray, events)
                if self.frame - t.seen > 30:
                    del self.known[m]
                continue
            t.steady = self.frame - t.seen == 1
            t.velocity = (c - t.corners) / max(1, self.frame - t.seen)
            t.corners, t.seen = c, self.frame
            out_ids.append(m)
            out_c.append(c)
        for i, oc in others.items():
            if i not in self.known:
                self.known[i] = _Followed(oc, np.zeros((4, 2)), self._is_static(i), self.frame)
        # ---- discoveries of the background detection
        got = self._take_result()
        if got is not None:
            self._merge(gray, got, out_ids, out_c)
        if lost or self._since_full >= s.full_every:
            self._since_full = 0
            self._submit(gray, full_res=lost)
        self.followed_frames += 1
        return self._result_of(out_ids, out_c, "followed", events)

    def _follow(self, gray: np.ndarray, preds: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
        """Corners (id -> (4, 2) px) of moving markers refined from their predicted corners
        ``preds``, for those whose code reads there and whose size held (the others: {}).

        A coarse ``cornerSubPix`` (half-window 0.8 module: a prediction a few pixels off,
        from a change of speed or turn, is pulled in) then the detector's own refinement
        (OpenCV's window: ``relativeCornerRefinmentWinSize`` x the module, at most
        ``cornerRefinementWinSize``; its iterations and accuracy), so a followed marker's
        corners are those a detection would give, at ~0.1 ms for a few markers instead of
        ~0.5 ms per region detection."""
        if not preds:
            return {}
        # The per-marker glue in floats: a few quads a frame, where numpy's per-call cost
        # on (n, 4, 2) arrays was most of this method's time.
        h, w = gray.shape
        quads = {m: preds[m].tolist() for m in preds}
        # Near the border: the region detection decides.
        ids = [m for m, c in quads.items()
               if all(2 <= x <= w - 3 and 2 <= y <= h - 3 for x, y in c)]
        if not ids:
            return {}
        qs = [quads[m] for m in ids]
        p = self.full_detector.parameters
        bits = self.dictionary.markerSize + 2 * p.markerBorderBits
        coarse = int(min(8, max(2, round(0.8 * _median([_perimeter(c) / (4.0 * bits)
                                                        for c in qs])))))
        pts = np.array(qs, dtype=np.float32).reshape(-1, 1, 2)
        pts = cv2.cornerSubPix(gray, pts, (coarse, coarse), (-1, -1),
                               (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 0.05))
        # The detector's window, from the coarse corners (as it takes it from its contour's).
        rel = float(getattr(p, "relativeCornerRefinmentWinSize", 0.3))
        wins = [int(min(p.cornerRefinementWinSize, max(1, round(rel * (_perimeter(c)
                                                                      / (4.0 * bits))))))
                for c in pts.reshape(-1, 4, 2).astype(np.float64).tolist()]
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS,
                p.cornerRefinementMaxIterations, p.cornerRefinementMinAccuracy)
        fine = pts.reshape(-1, 4, 1, 2)
        for win in set(wins):
            sel = [k for k, v in enumerate(wins) if v == win]
            part = np.ascontiguousarray(fine[sel].reshape(-1, 1, 2))
            fine[sel] = cv2.cornerSubPix(gray, part, (win, win), (-1, -1), crit
                                         ).reshape(-1, 4, 1, 2)
        got = fine.reshape(-1, 4, 2).astype(np.float64)
        ok: list[bool] = []
        for m, q, g in zip(ids, qs, got.tolist(), strict=True):
            # The shape held: the last corners map onto the new ones by a similarity (a
            # frame's perspective change is far below a pixel) - a corner caught by another
            # feature (the robot's other marker, an edge) breaks it by pixels.
            z0 = [complex(x, y) for x, y in self.known[m].corners.tolist()]
            z1 = [complex(x, y) for x, y in g]
            c0, c1 = sum(z0) / 4.0, sum(z1) / 4.0
            z0 = [z - c0 for z in z0]
            z1 = [z - c1 for z in z1]
            a = sum(u.conjugate() * v for u, v in zip(z0, z1, strict=True)) / sum(
                abs(u) ** 2 for u in z0)
            shape = max(abs(v - a * u) for u, v in zip(z0, z1, strict=True))
            self.shape_px.append(shape)
            step = max(max(abs(gx - qx), abs(gy - qy)) for (gx, gy), (qx, qy)
                       in zip(g, q, strict=True))
            ok.append(step <= coarse + 2.0 and abs(abs(a) - 1.0) < 0.15 and shape <= SHAPE_PX)
        keep = [k for k, v in enumerate(ok) if v]
        if keep:
            score = code_scores(gray, got[keep], np.stack([self._code(ids[k]) for k in keep]))
            for k, sc in zip(keep, score.tolist(), strict=True):
                ok[k] = sc >= self.settings.follow_score
        self.followed += sum(ok)
        return {m: got[k] for k, m in enumerate(ids) if ok[k]}

    def _floor_check(self, st: list[int], shape: tuple[int, ...]) -> _FloorCheck:
        """The floor check of the static markers ``st`` (their tracks as they are now),
        built again when a reference changed; a marker whose track did not change keeps
        its first look's refinement."""
        key = (tuple(st), tuple(self.known[m] for m in st), shape)
        fc = self._floor
        if fc is not None and fc.key == key:
            return fc
        ref = np.stack([self.known[m].corners for m in st])
        sub0 = np.full(ref.shape, np.nan)
        if fc is not None:
            old = {t: k for k, t in enumerate(fc.key[1])}
            for k, t in enumerate(key[1]):
                j = old.get(t)
                if j is not None:
                    sub0[k] = fc.sub0[j]
        # The cornerSubPix window of these references (the same for a marker at every
        # look, whichever share is measured).
        self._floor = fc = _FloorCheck(key, ref, _subpix_window(ref), CodeSampler(
            ref, np.stack([self._code(m) for m in st]), (shape[0], shape[1])), sub0)
        return fc

    def _drift_share(self, n: int) -> np.ndarray:
        """Indices of the n static markers whose drift is measured in this frame: every
        ``drift_every``-th from a start that rotates frame by frame (all when that is
        fewer than ``drift_min``)."""
        s = self.settings
        every = max(1, int(s.drift_every))
        if every == 1 or n <= s.drift_min:
            return np.arange(n)
        chk = np.arange(self.frame % every, n, every)
        return chk if len(chk) >= s.drift_min else np.arange(n)

    @staticmethod
    def _subpix(gray: np.ndarray, ref: np.ndarray, win: int) -> np.ndarray:
        """(N, 4, 2) ``cornerSubPix`` of the reference corners (N, 4, 2) px, half-window
        ``win`` px (:func:`_subpix_window`)."""
        pts = ref.reshape(-1, 1, 2).astype(np.float32)
        crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 20, 0.01)
        refined = cv2.cornerSubPix(gray, pts, (win, win), (-1, -1), crit)
        return refined.reshape(-1, 4, 2).astype(np.float64)

    def _merge(self, gray: np.ndarray, got: tuple[int, Detections, bool],
               out_ids: list[int], out_c: list[np.ndarray]) -> None:
        """Add what the background detection found and is not tracked, detected again in
        this frame around where it was found (full resolution)."""
        frame_no, det, half = got
        have = set(out_ids)
        s = self.settings
        same_px = 2.0 if half else 0.5
        for mid, c0 in zip(det.ids.tolist(), det.corners, strict=True):
            t = self.known.get(mid)
            static = self._is_static(mid)
            if (static and not half and mid in have and t is not None
                    and np.abs(c0 - t.corners).max() < 1.5 * s.move_px):
                # Another full-resolution look at a fixed marker in place: averaged in.
                nt = self._averaged(t, c0)
                if nt is not t:
                    self.known[mid] = nt
                    out_c[out_ids.index(mid)] = nt.corners
                continue
            if t is not None and (t.seen > frame_no or mid in have) and (
                    not static or np.abs(c0 - t.corners).max() < same_px):
                continue  # tracked since, or a fixed marker at its place: nothing new
            c, _ = self._find_moving(gray, mid, c0)
            if c is None:
                continue  # not in this frame (any more)
            if static:
                if np.abs(c - c0).max() > same_px:
                    # A fixed marker found at two different places in two frames: part of
                    # it was covered in one of them (a robot passing): wait for a clean look.
                    continue
                new = float(code_scores(gray, c[None], self._code(mid)[None])[0])
                if new < s.add_score:
                    continue  # half hidden now: wait for a clean look
                if mid in have:
                    # Reported at its reference, found elsewhere (> 0.5 px) by a full
                    # detection of the whole marker that reads at least as well: the
                    # reference was taken while something covered part of the marker.
                    if t is None:  # every reported id is tracked: cannot happen
                        raise RuntimeError(f"marker {mid} reported without a track")
                    if np.abs(c - t.corners).max() < 0.5:
                        continue
                    old = float(code_scores(gray, t.corners[None], self._code(mid)[None])[0])
                    if new < old:
                        continue
                    out_c[out_ids.index(mid)] = c
                    self.known[mid] = _Followed(c.copy(), np.zeros((4, 2)), True, self.frame)
                    continue
                self.known[mid] = _Followed(c.copy(), np.zeros((4, 2)), True, self.frame)
            else:
                if mid in have:
                    continue
                vel = (c - c0) / max(1, self.frame - frame_no)
                self.known[mid] = _Followed(c, vel, False, self.frame)
            out_ids.append(mid)
            out_c.append(c)
            have.add(mid)

    def _full(self, gray: np.ndarray, events: list[str]) -> Detections:
        det = self.full_detector.detect(gray)
        self.full += 1
        bumped = any(e.startswith("camera moved") for e in events)
        if bumped:
            self._take_result()  # a background result of the old view is worthless
            self.known = {}
        self._reset_from(det)
        return Detections(det.ids, det.corners, det.rejected, mode="full",
                          events=tuple(events), restart=bumped)

    @staticmethod
    def _result_of(ids: list[int], corners: list[np.ndarray], mode: str, events: list[str]
                   ) -> Detections:
        if not ids:
            return Detections(np.zeros(0, np.int64), np.zeros((0, 4, 2)), 0, mode=mode,
                              events=tuple(events))
        order = np.argsort(ids, kind="stable")
        return Detections(np.asarray(ids, np.int64)[order], np.stack(corners)[order], 0,
                          mode=mode, events=tuple(events))
