"""What a technician needs on top of a camera frame: map markers the camera should see,
a focus figure, a drawn overlay and a thumbnail.

Pixel coordinates follow OpenCV (x right, y down, pixel centres at integer coordinates).
``cam2world`` is the estimator's (4, 4) similarity ``world = scale * R @ cam + t``.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from kmea.geometry import check_distortion, project
from kmea.maps.files import MarkerMap
from kmea.vision.camera import CameraModel

__all__ = [
    "OverlayMarker",
    "draw_overlay",
    "expected_marker_corners",
    "focus_measure",
    "thumbnail",
]

# BGR colours of the drawn overlay (OpenCV order).
COLOR_DETECTED = (0, 200, 0)
COLOR_SUSPECT = (0, 215, 255)
COLOR_REJECTED = (0, 0, 230)
COLOR_EXPECTED = (255, 160, 0)


@dataclass(frozen=True)
class OverlayMarker:
    """One marker outline in image pixels: corners (4, 2) TL, TR, BR, BL.

    kind: ``detected``, ``suspect`` (detected, corners not trusted), ``rejected`` (a
    reference the robust estimator rejected) or ``expected`` (a map marker that should be
    in view but was not detected).
    """

    id: int
    corners: np.ndarray
    kind: str = "detected"


def expected_marker_corners(cam2world: np.ndarray, camera: CameraModel, world_map: MarkerMap,
                            exclude: Iterable[int] = (), margin: float = 0.0
                            ) -> dict[int, np.ndarray]:
    """Map markers that project fully inside the image, as pixel corners (4, 2).

    cam2world: (4, 4) similarity (see the module docstring). exclude: ids to leave out
    (those detected). margin: pixels every corner must keep from the border. Markers
    behind the camera or whose face points away from it are left out.
    """
    T = np.asarray(cam2world, dtype=float)
    A = T[:3, :3]
    s = float(np.cbrt(np.linalg.det(A)))
    if not math.isfinite(s) or s <= 0:
        return {}
    R = A / s
    t = T[:3, 3]
    skip = {int(i) for i in exclude}
    ids = [mid for mid in world_map.markers if mid not in skip]
    if not ids:
        return {}
    mks = [world_map.markers[mid] for mid in ids]
    # All markers at once (one projection call): this runs every frame Foxglove is on.
    cw = np.stack([mk.corners_world() for mk in mks])  # (M, 4, 3)
    centres = np.array([mk.position for mk in mks])
    normals = np.array([mk.normal for mk in mks])
    facing = np.einsum("ij,ij->i", t - centres, normals) > 0  # seen from the front
    pc = (cw.reshape(-1, 3) - t) @ R / s  # world -> camera: R^T (p - t) / s
    in_front = (pc[:, 2] > 1e-6).reshape(-1, 4).all(axis=1)
    pc[:, 2] = np.where(pc[:, 2] > 1e-6, pc[:, 2], 1.0)  # keep the division finite
    uv = project(pc, camera.camera_matrix, check_distortion(camera.dist_coeffs)).reshape(-1, 4, 2)
    inside = (np.isfinite(uv).all(axis=(1, 2))
              & (uv[..., 0] >= margin).all(axis=1) & (uv[..., 1] >= margin).all(axis=1)
              & (uv[..., 0] <= camera.width - 1 - margin).all(axis=1)
              & (uv[..., 1] <= camera.height - 1 - margin).all(axis=1))
    keep = facing & in_front & inside
    return {int(mid): uv[k] for k, mid in enumerate(ids) if keep[k]}


def focus_measure(gray: np.ndarray, quads: Sequence[np.ndarray], pad: float = 0.25
                  ) -> float | None:
    """Sharpness of the marker regions: variance of the Laplacian over their bounding
    boxes (grown by ``pad`` of their size), pooled; None without a usable region.

    gray: (H, W) uint8. quads: pixel corners (4, 2) each. Larger is sharper; the figure
    depends on the scene, so compare it while turning the lens, not between venues.
    """
    if gray is None or gray.ndim != 2 or not len(quads):
        return None
    h, w = gray.shape
    total, n = 0.0, 0
    for q in quads:
        q = np.asarray(q, dtype=float).reshape(4, 2)
        if not np.all(np.isfinite(q)):
            continue
        lo, hi = q.min(axis=0), q.max(axis=0)
        grow = (hi - lo) * pad
        x0, y0 = np.maximum(np.floor(lo - grow), 0).astype(int)
        x1, y1 = np.minimum(np.ceil(hi + grow) + 1, [w, h]).astype(int)
        if x1 - x0 < 5 or y1 - y0 < 5:
            continue
        lap = cv2.Laplacian(gray[y0:y1, x0:x1], cv2.CV_64F, ksize=3)
        inner = lap[1:-1, 1:-1]  # the border rows see the padding, not the image
        total += float(((inner - inner.mean()) ** 2).sum())
        n += inner.size
    return total / n if n else None


def thumbnail(gray: np.ndarray, max_width: int, max_height: int) -> tuple[np.ndarray, float]:
    """The frame shrunk (area average) to fit max_width x max_height, keeping its aspect.

    Returns (thumb (h, w) uint8, scale) with thumb pixel = scale * frame pixel. Never
    enlarges (scale <= 1).
    """
    if gray.ndim == 3:
        gray = cv2.cvtColor(gray, cv2.COLOR_BGR2GRAY)
    h, w = gray.shape
    scale = min(1.0, max_width / w, max_height / h)
    if scale >= 1.0:
        return np.ascontiguousarray(gray), 1.0
    tw, th = max(1, round(w * scale)), max(1, round(h * scale))
    return cv2.resize(gray, (tw, th), interpolation=cv2.INTER_AREA), tw / w


def draw_overlay(image: np.ndarray, markers: Sequence[OverlayMarker],
                 focus: float | None = None) -> np.ndarray:
    """A BGR copy of ``image`` with the marker outlines, ids and the focus figure drawn.

    Expected-but-unseen markers are drawn dashed-looking (thin) with their id in brackets;
    suspect ones get a ``?`` after the id.
    """
    out = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image.copy()
    h = out.shape[0]
    thick = max(1, round(h / 400))
    font = max(0.4, h / 1000)
    colors = {"detected": COLOR_DETECTED, "suspect": COLOR_SUSPECT,
              "rejected": COLOR_REJECTED, "expected": COLOR_EXPECTED}
    for m in markers:
        q = np.asarray(m.corners, dtype=float).reshape(4, 2)
        c = colors.get(m.kind, COLOR_DETECTED)
        pts = np.round(q).astype(np.int32).reshape(-1, 1, 2)
        cv2.polylines(out, [pts], True, c, 1 if m.kind == "expected" else thick, cv2.LINE_AA)
        if m.kind != "expected":
            cv2.circle(out, tuple(int(v) for v in np.round(q[0])), thick + 1, c, -1)
        label = {"expected": f"({m.id})", "suspect": f"{m.id}?"}.get(m.kind, str(m.id))
        shift = np.array([-4 * font * len(label), 4])  # roughly centred on the marker
        org = tuple(int(v) for v in np.round(q.mean(axis=0) + shift))
        cv2.putText(out, label, org, cv2.FONT_HERSHEY_SIMPLEX, font, c, thick, cv2.LINE_AA)
    if focus is not None:
        cv2.putText(out, f"focus {focus:.0f}", (10, int(30 * font + 10)),
                    cv2.FONT_HERSHEY_SIMPLEX, font, (255, 255, 255), thick, cv2.LINE_AA)
    return out
