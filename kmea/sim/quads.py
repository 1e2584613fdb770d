"""The simulator's planar quads (markers, wall panels, robot and occluder boxes) and the
pixel rectangles the renderer works on. A quad is intersected with the camera rays in the
camera frame (:meth:`Quad.hit`)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from kmea.geometry import rot_z

__all__ = ["Quad", "Rect", "box_quads", "grow", "overlap", "union"]

Rect = tuple[int, int, int, int]  # r0, r1, c0, c1 (half-open)


@dataclass
class Quad:
    """A planar rectangle in the world: centre c, unit axes ex, ey (normal ex x ey),
    half sizes hx, hy. A marker texture (cells x cells albedos) covers |a|, |b| < hl; the
    rest is ``albedo``. decal: drawn over coplanar surfaces. occludes: hides markers."""

    c: np.ndarray
    ex: np.ndarray
    ey: np.ndarray
    hx: float
    hy: float
    albedo: float
    tex: np.ndarray | None = None
    hl: float = 0.0
    two_sided: bool = False
    decal: bool = False
    occludes: bool = True
    # camera-frame copies, filled by to_cam
    n: np.ndarray = field(default_factory=lambda: np.zeros(3))
    nc: float = 0.0
    exc: float = 0.0
    eyc: float = 0.0
    bbox: tuple[float, float, float, float] | None = None
    _n: tuple[float, float, float] = (0.0, 0.0, 0.0)
    _ex: tuple[float, float, float] = (0.0, 0.0, 0.0)
    _ey: tuple[float, float, float] = (0.0, 0.0, 0.0)
    _padded: np.ndarray | None = None  # texture with its quiet-zone ring

    def corners(self) -> np.ndarray:
        s = np.array([[-1, 1], [1, 1], [1, -1], [-1, -1]], dtype=float)
        return self.c + (s[:, :1] * self.hx) * self.ex + (s[:, 1:] * self.hy) * self.ey

    def to_cam(self, w2c: np.ndarray) -> Quad:
        R, t = w2c[:3, :3], w2c[:3, 3]
        c = R @ self.c + t
        ex, ey = R @ self.ex, R @ self.ey
        q = Quad(c, self.ex, self.ey, self.hx, self.hy, self.albedo, self.tex, self.hl,
                  self.two_sided, self.decal, self.occludes)
        q.n = np.cross(ex, ey)
        q.nc = float(q.n @ c)
        q.exc, q.eyc = float(ex @ c), float(ey @ c)
        q._n, q._ex, q._ey = _floats3(q.n), _floats3(ex), _floats3(ey)
        if self.tex is not None:
            if abs(self.hx - self.hl * (self.tex.shape[0] + 2) / self.tex.shape[0]) > 1e-12:
                raise ValueError("marker quad: the quiet zone must be one cell wide")
            q._padded = np.pad(self.tex, 1, constant_values=np.float32(self.albedo))
        P = self.corners() @ R.T + t
        if np.all(P[:, 2] > 1e-6):
            x, y = P[:, 0] / P[:, 2], P[:, 1] / P[:, 2]
            q.bbox = (float(x.min()), float(x.max()), float(y.min()), float(y.max()))
        return q

    def hit(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Depth z of the hit (inf where none) and albedo, for normalised rays (x, y, 1).

        Works in the dtype of ``x`` (float32 rays: ~1e-7 m in a marker's plane)."""
        n0, n1, n2 = self._n
        e0, e1, e2 = self._ex
        f0, f1, f2 = self._ey
        nd = n0 * x + n1 * y + n2
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            t = self.nc / nd
            a = e0 * x
            a += e1 * y
            a += e2
            a *= t
            a -= self.exc
            b = f0 * x
            b += f1 * y
            b += f2
            b *= t
            b -= self.eyc
        ok = t > 1e-9
        if not self.two_sided:
            ok &= nd < 0
        ok &= np.abs(a) <= self.hx
        ok &= np.abs(b) <= self.hy
        t[~ok] = np.inf
        if self.tex is None:
            return t, np.full(np.shape(x), self.albedo, dtype=np.float32)
        # The texture with its one-cell quiet zone maps uniformly onto the whole quad.
        tex = self._padded
        if tex is None:
            raise ValueError("Quad.hit: a textured quad is hit in the camera frame (to_cam)")
        cells = tex.shape[0]
        k = cells / (2.0 * self.hx)
        a += self.hx
        a *= k
        b -= self.hy
        b *= -k
        col = np.clip(a.astype(np.int32), 0, cells - 1)
        row = np.clip(b.astype(np.int32), 0, cells - 1)
        return t, tex[row, col]


def _floats3(v: np.ndarray) -> tuple[float, float, float]:
    """A (3,) vector as three Python floats."""
    return float(v[0]), float(v[1]), float(v[2])


def box_quads(center_xy: tuple[float, float], yaw: float, lx: float, ly: float,
               z0: float, z1: float, top: float, side: float, front: float | None = None,
               bottom: bool = False) -> list[Quad]:
    """The faces of an upright box (outward normals, one-sided)."""
    R = rot_z(yaw)
    fx, fy, fz = R[:, 0], R[:, 1], np.array([0.0, 0.0, 1.0])
    c = np.array([center_xy[0], center_xy[1], (z0 + z1) / 2])
    hz = (z1 - z0) / 2
    quads = [Quad(c + hz * fz, fx, fy, lx / 2, ly / 2, top)]
    if bottom:
        quads.append(Quad(c - hz * fz, fx, -fy, lx / 2, ly / 2, side))
    # side faces: ex horizontal, ey up, normal = ex x ey outward
    quads.append(Quad(c + lx / 2 * fx, fy, fz, ly / 2, hz, side if front is None else front))
    quads.append(Quad(c - lx / 2 * fx, -fy, fz, ly / 2, hz, side))
    quads.append(Quad(c + ly / 2 * fy, -fx, fz, lx / 2, hz, side))
    quads.append(Quad(c - ly / 2 * fy, fx, fz, lx / 2, hz, side))
    return quads


def overlap(a: Rect, b: Rect) -> bool:
    return a[0] < b[1] and b[0] < a[1] and a[2] < b[3] and b[2] < a[3]


def grow(r: Rect, k: int, shape: tuple[int, int]) -> Rect:
    return (max(r[0] - k, 0), min(r[1] + k, shape[0]), max(r[2] - k, 0), min(r[3] + k, shape[1]))


def union(a: Rect, b: Rect) -> Rect:
    return (min(a[0], b[0]), max(a[1], b[1]), min(a[2], b[2]), max(a[3], b[3]))
