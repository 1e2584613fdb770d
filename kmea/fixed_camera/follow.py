"""The moving markers: followed from their prediction, or detected around it.

A moving marker (a robot's, anything not in the map) is predicted from its last two
positions (constant velocity in the image). :class:`Follower` then

- refines its corners from the prediction as the detector refines them (``cornerSubPix``,
  :meth:`Follower.follow`) and keeps them when the marker's code reads at the refined
  corners and its shape held;
- otherwise (a sharp turn, a change of speed beyond the refinement's reach, near the
  border) detects it with the full parameters in a small region around the prediction
  (``cv2.aruco.ArucoDetector`` on a crop, :meth:`Follower.detect_box`), in a wider one when
  the first misses (:meth:`Follower.find_moving`).

Regions that overlap are joined into one detection (:meth:`Follower.groups`: a robot's two
markers share one crop).
"""

from __future__ import annotations

import collections
import math

import cv2
import numpy as np

from kmea.fixed_camera.codes import CodeBook, code_scores
from kmea.fixed_camera.discovery import TunedDetectors
from kmea.fixed_camera.tracks import FixedCameraConfig

__all__ = ["SHAPE_PX", "Follower"]

# A followed marker's corners may leave the similarity image of its last corners by this much
# (px); see Follower.follow.
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


class Follower:
    """Finds the moving markers of a frame near their predictions (see the module
    docstring). ``detectors``: the calling thread's; ``codes``: the dictionary's.

    ``followed`` counts markers refined from their prediction (no region detection);
    ``shape_px`` keeps the last looks' shape residuals (px), for tests and tuning.
    """

    def __init__(self, settings: FixedCameraConfig, detectors: TunedDetectors,
                 codes: CodeBook) -> None:
        self.settings = settings
        self.detectors = detectors
        self.codes = codes
        self.roi_detector = TunedDetectors(detectors.config).full._detector
        self.followed = 0
        self.shape_px: collections.deque[float] = collections.deque(maxlen=512)

    def _roi_detector(self, side: float):
        """The ArUco detector for a region: one adaptive-threshold window of a fifth of the
        marker side (the full parameters' three windows cost three times as much) when
        ``side`` > 0 px, else the configured parameters."""
        if side <= 0:
            return self.roi_detector
        return self.detectors.window(max(3, round(side / 5.0) | 1))._detector

    def detect_roi(self, gray: np.ndarray, center: np.ndarray, half: float, side: float = 0.0
                    ) -> tuple[np.ndarray, np.ndarray]:
        """(ids, corners) found in the square of half-side ``half`` px around ``center``
        (``side``: the marker's side in px, for a tuned threshold window; 0: configured)."""
        return self.detect_box(gray, (center[0] - half, center[1] - half,
                                       center[0] + half, center[1] + half), side)

    def detect_box(self, gray: np.ndarray, box: tuple[float, float, float, float],
                    side: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """(ids, corners) found in ``box`` (x0, y0, x1, y1) px; ``side`` as in
        :meth:`detect_roi`."""
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

    def region(self, pred: np.ndarray) -> tuple[np.ndarray, float, float]:
        """(centre (2,), half-side px of the search square, marker side px) around a
        predicted quad (4, 2) px."""
        side = float(np.linalg.norm(pred[0] - pred[2])) / np.sqrt(2.0)
        ctr = pred.mean(axis=0)
        span = float(np.max(np.abs(pred - ctr)))
        return ctr, span + self.settings.margin * side + 4.0, side

    def groups(self, preds: dict[int, np.ndarray]
                ) -> list[tuple[tuple[float, float, float, float], float, set[int]]]:
        """Search boxes (x0, y0, x1, y1) px, mean marker side and member ids: the regions
        of ``preds`` (id -> predicted quad), overlapping ones joined when their union is
        not much larger than the two (one detection call instead of two)."""
        out: list[list] = []
        for m, q in preds.items():
            ctr, half, side = self.region(q)
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

    def find_moving(self, gray: np.ndarray, mid: int, pred: np.ndarray,
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
            ids, cs = self.detect_roi(gray, ctr, half, side if tuned else 0.0)
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

    def follow(self, gray: np.ndarray, preds: dict[int, np.ndarray],
               last: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
        """Corners (id -> (4, 2) px) of moving markers refined from their predicted corners
        ``preds``, for those whose code reads there and whose size held (the others: {});
        ``last``: id -> the corners it was last seen with.

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
        p = self.detectors.full.parameters
        bits = self.codes.dictionary.markerSize + 2 * p.markerBorderBits
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
            z0 = [complex(x, y) for x, y in last[m].tolist()]
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
            score = code_scores(gray, got[keep], np.stack([self.codes(ids[k]) for k in keep]))
            for k, sc in zip(keep, score.tolist(), strict=True):
                ok[k] = sc >= self.settings.follow_score
        self.followed += sum(ok)
        return {m: got[k] for k, m in enumerate(ids) if ok[k]}

