"""A marker's code read at known corners: is the marker there, and how well does it read?

A marker whose place in the image is known is checked, not searched: its module grid is
sampled at its quadrilateral and correlated with its printed code. The floor check reads
every fixed marker this way each frame (:mod:`kmea.fixed_camera.floor`), the follower reads
a moving marker at its refined corners (:mod:`kmea.fixed_camera.follow`).

- :func:`marker_codes`: the printed module grid of each id;
- :class:`CodeSampler`: the sample points of fixed quads, built once, read per frame;
- :func:`code_scores` / :func:`verify_codes`: one-off reads of quads;
- :class:`CodeBook`: the codes of one dictionary, made on first use.

Pixel convention: OpenCV's (the top-left pixel's centre is (0, 0)).
"""

from __future__ import annotations

import math
from collections.abc import Collection

import cv2
import numpy as np

__all__ = ["CodeBook", "CodeSampler", "code_scores", "marker_codes", "verify_codes"]


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




class CodeBook:
    """id -> (S+2, S+2) bool module grid of ``dictionary``'s markers, made on first use."""

    def __init__(self, dictionary: cv2.aruco.Dictionary) -> None:
        self.dictionary = dictionary
        self._codes: dict[int, np.ndarray] = {}

    def __call__(self, mid: int) -> np.ndarray:
        c = self._codes.get(mid)
        if c is None:
            c = self._codes[mid] = marker_codes(self.dictionary, [mid])[mid]
        return c
