"""Ray-cast rendering of a :class:`~kmea.sim.scene.Scene` with exact ground truth.

How: every pixel of the image is the average of the scene over the pixel's square (a box
filter, OpenCV convention: pixel (u, v) covers [u - 0.5, u + 0.5] x [v - 0.5, v + 0.5]).
Rays come from the exact inverse of the lens model (:mod:`kmea.sim.lens`), so the image is
distorted exactly as ``cv2.projectPoints`` says. Everything is a planar quad (floor markers
and wall markers as decals, wall panels, the sides and top of robots and occluders) over the
floor plane. Uniform pixels take one ray at their centre; pixels where the one-ray image
changes (edges) take 89 rays (34 for moving objects) on a Fibonacci lattice.

The static scene is rendered once per :class:`Renderer`; each frame re-renders only the
rectangles where robots and moving occluders are, then adds the image effects.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable

import cv2
import numpy as np

from kmea.geometry import unit_rays_plane_depth, yaw_of
from kmea.maps.files import Marker
from kmea.sim import lens
from kmea.sim.quads import Quad, Rect, box_quads, grow, overlap, union
from kmea.sim.sampling import (
    DYNAMIC_SAMPLES,
    STATIC_BIT,
    STATIC_SAMPLES,
    edges,
    or_dilate,
)
from kmea.sim.scene import PALETTE, Occluder, Scene, SimRobot, pose_matrix
from kmea.sim.truth import (
    FrameTruth,
    SimFrame,
    corners_and_probes,
    hidden_markers,
    rolled_corners,
)
from kmea.timing import FrameTiming
from kmea.vision.dictionary import get_dictionary

__all__ = ["FrameTruth", "Renderer", "SimFrame"]

# ---------------------------------------------------------------------------- renderer


class Renderer:
    """Renders frames of ``scene``; frame ``i`` is at t = i / fps.

    The static part (floor, map, wall and extra markers, supports, still occluders) is
    rendered on construction (about 1 s at 1640x1232 with a new camera, 0.3 s once the
    camera's ray map is cached; 0.25 s at 640x480). Frames can be rendered in any order; the
    result depends only on the scene (seed included) and the index. Not thread-safe: use one
    renderer per thread.
    """

    def __init__(self, scene: Scene) -> None:
        self.scene = scene
        cam = scene.camera
        self.width, self.height = cam.width, cam.height
        self.cam2world = scene.cam2world.copy()
        self.world2cam = np.linalg.inv(self.cam2world)
        self.rays = lens.ray_map(cam)
        self._dictionary = get_dictionary(scene.world_map.dictionary)
        self._textures: dict[int, np.ndarray] = {}
        self._static_markers = scene.static_markers()
        self._idx = np.full((self.height, self.width), -1, dtype=np.int32)
        self._dyn_cache: tuple[float, list[list[Quad]]] | None = None
        for robot in scene.robots:
            for mid in robot.markers:
                self.texture(mid)  # unknown ids fail here, naming the marker
        self._build_static()

    # ------------------------------------------------------------ scene content
    def texture(self, mid: int) -> np.ndarray:
        """(cells, cells) albedos of marker ``mid``'s black square (border included)."""
        if mid not in self._textures:
            d = self._dictionary
            cells = d.markerSize + 2
            if mid >= d.bytesList.shape[0]:
                raise ValueError(f"marker {mid}: not in dictionary "
                                 f"{self.scene.world_map.dictionary} "
                                 f"({d.bytesList.shape[0]} markers)")
            img = cv2.aruco.generateImageMarker(d, mid, cells, borderBits=1)
            self._textures[mid] = np.where(img > 127, PALETTE["white"],
                                           PALETTE["black"]).astype(np.float32)
        return self._textures[mid]

    def _marker_quad(self, mid: int, T: np.ndarray, length: float) -> Quad:
        """A marker as a decal: its black square plus a one-cell white quiet zone."""
        tex = self.texture(mid)
        h = length / 2
        hq = h * (tex.shape[0] + 2) / tex.shape[0]
        return Quad(T[:3, 3].copy(), T[:3, 0].copy(), T[:3, 1].copy(), hq, hq,
                     PALETTE["white"], tex, h, decal=True, occludes=False)

    def _wall_panels(self, markers: list[Marker]) -> list[Quad]:
        """Two-sided panels behind groups of coplanar non-floor markers, down to the floor."""
        groups: list[list[Marker]] = []
        for m in markers:
            n = m.normal
            for g in groups:
                g0 = g[0]
                if g0.normal @ n > 1 - 1e-6 and abs(g0.normal @ (m.position - g0.position)) < 2e-3:
                    g.append(m)
                    break
            else:
                groups.append([m])
        panels = []
        for g in groups:
            n = g[0].normal
            h = np.cross([0.0, 0.0, 1.0], n)
            if np.linalg.norm(h) < 1e-6:
                h = np.array([1.0, 0.0, 0.0])
            h /= np.linalg.norm(h)
            v = np.cross(n, h)
            p0 = g[0].position
            pts = np.vstack([m.corners_world() for m in g]) - p0
            a, b = pts @ h, pts @ v
            a0, a1 = a.min() - 0.05, a.max() + 0.05
            b0, b1 = b.min() - 0.03, b.max() + 0.03
            if v[2] > 0.5:  # down to the floor
                b0 = min(b0, -p0[2] / v[2])
            c = p0 + (a0 + a1) / 2 * h + (b0 + b1) / 2 * v
            panels.append(Quad(c, h, v, (a1 - a0) / 2, (b1 - b0) / 2, PALETTE["wall"],
                                two_sided=True))
        return panels

    def _build_static(self) -> None:
        sc = self.scene
        quads: list[Quad] = []
        decals: list[Quad] = []
        wall: list[Marker] = []
        for mid, m in sorted(self._static_markers.items()):
            decals.append(self._marker_quad(mid, pose_matrix(m.rotation, m.position), m.length))
            facing_up = m.rotation[2, 2] > 0.99
            if not facing_up:
                wall.append(m)
            elif sc.supports and mid in sc.overrides and m.position[2] > 0.005:
                side = m.length * 9 / 7 + 0.03  # a 1.5 cm rim around the paper
                yaw = float(yaw_of(m.rotation))  # one matrix: a float
                quads += box_quads((m.position[0], m.position[1]), yaw, side, side, 0.0,
                                    m.position[2], PALETTE["support"], PALETTE["side"])
        quads += self._wall_panels(wall)
        decals = self._line_quads() + decals
        for occ in sc.effects.occluders:
            if not occ.moving:
                quads += self._occluder_quads(occ, 0.0)
        self.static_quads = [q.to_cam(self.world2cam) for q in quads + decals]
        self.static_rects = [self._rect(q) for q in self.static_quads]
        self._floor_setup()

        H, W = self.height, self.width
        full = (0, H, 0, W)
        t, alb, _ = self._cast_rect(full, self.static_quads, self.static_rects, floor=True)
        edge = edges(alb)
        rows, cols = np.nonzero(edge)
        if rows.size:
            alb[rows, cols] = self._supersample(rows, cols, STATIC_SAMPLES)
        self.static_edges = edge
        self.static_albedo = alb
        self.static_depth = t.astype(np.float32)
        self.light = self._light(t, full)
        cam = self.scene.camera
        uu = (np.arange(W) - cam.cx) / max(cam.cx, W - 1 - cam.cx)
        vv = (np.arange(H) - cam.cy) / max(cam.cy, H - 1 - cam.cy)
        r2 = (uu[None, :] ** 2 + vv[:, None] ** 2) / 2.0
        eff = sc.effects
        self.gain = ((1.0 - eff.vignetting * r2) * (255.0 * eff.exposure)).astype(np.float32)
        lit = alb if self.light is None else alb * self.light
        self.static_image = self._blur(lit) * self.gain
        self._noise_bank: np.ndarray | None = None
        self._static_truth()

    def _line_quads(self, half_width: float = 0.004) -> list[Quad]:
        """The faint floor lines (8 mm) as decals on the floor."""
        out = []
        for a, b in self.scene.lines():
            a, b = np.array([a[0], a[1], 0.0]), np.array([b[0], b[1], 0.0])
            d = b - a
            L = float(np.linalg.norm(d))
            if L < 1e-9:
                continue
            ex = d / L
            ey = np.array([-ex[1], ex[0], 0.0])
            out.append(Quad((a + b) / 2, ex, ey, L / 2 + half_width, half_width,
                             PALETTE["line"], decal=True, occludes=False))
        return out

    def _occluder_quads(self, occ: Occluder, t: float) -> list[Quad]:
        p = occ.path.pose(t)
        if p is None:
            return []
        return box_quads((p[0], p[1]), p[2], occ.size[0], occ.size[1], occ.z[0], occ.z[1],
                          occ.shade, occ.shade * 0.8, bottom=occ.z[0] > 1e-6)

    def _robot_quads(self, robot: SimRobot, pose: tuple[float, float, float]) -> list[Quad]:
        s = float(robot.plate)  # type: ignore[arg-type]
        quads = box_quads((pose[0], pose[1]), pose[2], s, s, 0.0, robot.height,
                           PALETTE["plate"], PALETTE["side"], front=PALETTE["side"] * 1.3)
        for mid, T in self.scene.robot_marker_poses(robot, pose).items():
            quads.append(self._marker_quad(mid, T, robot.length))
        return quads

    def _rect(self, q: Quad) -> Rect | None:
        if q.bbox is None:
            return (0, self.height, 0, self.width)
        return self.rays.pixel_rect(*q.bbox)

    # ------------------------------------------------------------ the floor
    def _floor_setup(self) -> None:
        R, t = self.world2cam[:3, :3], self.world2cam[:3, 3]
        self._fn = R[:, 2].copy()  # floor normal in the camera frame
        self._fnc = float(self._fn @ t)
        self._c2w = self.cam2world[:3, :3]
        self._o = self.cam2world[:3, 3]
        self._rect_floor = self.scene.floor_rect()

    def _floor(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t, ok = unit_rays_plane_depth(x, y, self._fn, self._fnc)
        R = [[float(v) for v in row] for row in self._c2w]
        o = [float(v) for v in self._o]
        tt = np.where(ok, t, 0.0).astype(t.dtype)
        xw = R[0][0] * x + R[0][1] * y + R[0][2]
        xw *= tt
        xw += o[0]
        yw = R[1][0] * x + R[1][1] * y + R[1][2]
        yw *= tt
        yw += o[1]
        x0, x1, y0, y1 = self._rect_floor
        inside = (xw >= x0) & (xw <= x1) & (yw >= y0) & (yw <= y1)
        alb = np.where(inside, np.float32(PALETTE["canvas"]), np.float32(PALETTE["surround"]))
        alb[~ok] = 0.0
        return t, alb

    def _light(self, t: np.ndarray, r: Rect) -> np.ndarray | None:
        gx, gy = self.scene.effects.gradient
        if gx == 0 and gy == 0:
            return None
        x = self.rays.x[r[0]:r[1], r[2]:r[3]]
        y = self.rays.y[r[0]:r[1], r[2]:r[3]]
        R, o = self._c2w, self._o
        tt = np.where(np.isfinite(t), t, 0.0)
        xw = o[0] + tt * (R[0, 0] * x + R[0, 1] * y + R[0, 2])
        yw = o[1] + tt * (R[1, 0] * x + R[1, 1] * y + R[1, 2])
        return np.clip(1.0 + gx * xw + gy * yw, 0.0, None).astype(np.float32)

    # ------------------------------------------------------------ casting
    def _cast_rect(self, r: Rect, quads: list[Quad], rects: list[Rect | None],
                   floor: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Depth, albedo and winning quad index (-1: floor or nothing) at the pixel centres
        of rectangle ``r``."""
        r0, r1, c0, c1 = r
        x = self.rays.x[r0:r1, c0:c1]
        y = self.rays.y[r0:r1, c0:c1]
        if floor:
            t, alb = self._floor(x, y)
        else:
            t = np.full(x.shape, np.inf)
            alb = np.zeros(x.shape, dtype=np.float32)
        qid = np.full(x.shape, -1, dtype=np.int64)
        for i, (q, qr) in enumerate(zip(quads, rects, strict=True)):
            if qr is None or not overlap(qr, r):
                continue
            a0, a1, b0, b1 = max(qr[0], r0), min(qr[1], r1), max(qr[2], c0), min(qr[3], c1)
            sl = (slice(a0 - r0, a1 - r0), slice(b0 - c0, b1 - c0))
            tq, aq = q.hit(x[sl], y[sl])
            tcur = t[sl]
            win = tq <= tcur * (1 + 1e-9) if q.decal else tq < tcur
            tcur[win] = tq[win]
            alb[sl][win] = aq[win]
            qid[sl][win] = i
        return t, alb, qid

    def _cast_samples(self, x: np.ndarray, y: np.ndarray,
                      ids_in: Callable[[Rect], np.ndarray], quads: list[Quad],
                      rects: list[Rect | None], floor: bool,
                      t: np.ndarray | None = None,
                      alb: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Depth and albedo of sample rays x, y (P, S) of P pixels; ``ids_in(rect)`` gives
        the indices of the pixels inside a rectangle."""
        if floor:
            t, alb = self._floor(x, y)
        elif t is None:
            t = np.full(x.shape, np.inf, dtype=x.dtype)
            alb = np.zeros(x.shape, dtype=np.float32)
        if alb is None:
            raise ValueError("_cast_samples: t and alb go together")
        for q, qr in zip(quads, rects, strict=True):
            if qr is None:
                continue
            ids = ids_in(qr)
            if ids.size == 0:
                continue
            if ids.size == x.shape[0]:  # every pixel: no gather/scatter
                tq, aq = q.hit(x, y)
                win = tq <= t * (1 + 1e-9) if q.decal else tq < t
                t[win] = tq[win]
                alb[win] = aq[win]
                continue
            xs, ys = x[ids], y[ids]
            tq, aq = q.hit(xs, ys)
            tcur = t[ids]
            win = tq <= tcur * (1 + 1e-9) if q.decal else tq < tcur
            if not win.any():
                continue
            tcur[win] = tq[win]
            acur = alb[ids]
            acur[win] = aq[win]
            t[ids] = tcur
            alb[ids] = acur
        return t, alb

    def _supersample(self, rows: np.ndarray, cols: np.ndarray,
                     pattern: tuple[np.ndarray, np.ndarray], dyn: list[Quad] | None = None,
                     dyn_rects: list[Rect | None] | None = None, static: bool = True,
                     static_sel: list[int] | None = None, chunk: int = 20000,
                     uniform: bool = False) -> np.ndarray:
        """Box-filtered albedo of pixels (rows, cols): the static scene (unless ``static`` is
        False) and the ``dyn`` quads. ``uniform``: the static scene is uniform over these
        pixels, take its value and depth at the centre instead of casting it."""
        du, dv = pattern
        out = np.empty(rows.size, dtype=np.float32)
        rm = self.rays
        sq = self.static_quads if static_sel is None else [self.static_quads[i] for i in static_sel]
        sr = self.static_rects if static_sel is None else [self.static_rects[i] for i in static_sel]
        for s in range(0, rows.size, chunk):
            r, c = rows[s:s + chunk], cols[s:s + chunk]
            # float32 rays: 4e-8 relative, i.e. ~1e-4 px and ~0.1 um on a marker
            x = (rm.x[r, c][:, None] + rm.dxdu[r, c][:, None] * du
                 + rm.dxdv[r, c][:, None] * dv).astype(np.float32)
            y = (rm.y[r, c][:, None] + rm.dydu[r, c][:, None] * du
                 + rm.dydv[r, c][:, None] * dv).astype(np.float32)
            self._idx[r, c] = np.arange(r.size, dtype=np.int32)

            rlo, rhi, clo, chi = int(r.min()), int(r.max()) + 1, int(c.min()), int(c.max()) + 1
            everyone = np.arange(r.size, dtype=np.int32)

            def ids_in(q: Rect, rlo: int = rlo, rhi: int = rhi, clo: int = clo,
                       chi: int = chi, everyone: np.ndarray = everyone) -> np.ndarray:
                if not (q[0] < rhi and rlo < q[1] and q[2] < chi and clo < q[3]):
                    return everyone[:0]
                if q[0] <= rlo and rhi <= q[1] and q[2] <= clo and chi <= q[3]:
                    return everyone
                block = self._idx[max(q[0], rlo):min(q[1], rhi), max(q[2], clo):min(q[3], chi)]
                return block[block >= 0]

            try:
                if static and uniform:
                    t = np.repeat(self.static_depth[r, c][:, None], x.shape[1], axis=1)
                    alb = np.repeat(self.static_albedo[r, c][:, None], x.shape[1], axis=1)
                elif static:
                    t, alb = self._cast_samples(x, y, ids_in, sq, sr, floor=True)
                else:
                    t = np.full(x.shape, np.inf, dtype=x.dtype)
                    alb = np.zeros(x.shape, dtype=np.float32)
                if dyn:
                    t, alb = self._cast_samples(x, y, ids_in, dyn, dyn_rects or [], False, t, alb)
            finally:
                self._idx[r, c] = -1
            out[s:s + chunk] = alb.mean(axis=1)
        return out

    def _decal_pixels(self, rows: np.ndarray, cols: np.ndarray, q: Quad) -> np.ndarray:
        """Box-filtered albedo of pixels lying wholly on the textured quad ``q``.

        The quad's plane coordinates are affine in the sub-pixel offset to ~1e-7 of a pixel,
        so each sub-sample costs a texture lookup only."""
        rm = self.rays
        x, y = rm.x[rows, cols], rm.y[rows, cols]
        xu, xv = rm.dxdu[rows, cols], rm.dxdv[rows, cols]
        yu, yv = rm.dydu[rows, cols], rm.dydv[rows, cols]
        n0, n1, n2 = q._n
        e0, e1, e2 = q._ex
        f0, f1, f2 = q._ey
        D = n0 * x + n1 * y + n2
        E = e0 * x + e1 * y + e2
        F = f0 * x + f1 * y + f2
        Du, Dv = n0 * xu + n1 * yu, n0 * xv + n1 * yv
        s = q.nc / D
        s2 = q.nc / (D * D)
        a = s * E - q.exc
        b = s * F - q.eyc
        au = s2 * ((e0 * xu + e1 * yu) * D - E * Du)
        av = s2 * ((e0 * xv + e1 * yv) * D - E * Dv)
        bu = s2 * ((f0 * xu + f1 * yu) * D - F * Du)
        bv = s2 * ((f0 * xv + f1 * yv) * D - F * Dv)
        du, dv = DYNAMIC_SAMPLES
        tex = q._padded
        if tex is None:
            raise ValueError("_decal_pixels: the quad has no texture in the camera frame")
        cells = tex.shape[0]
        k = cells / (2.0 * q.hx)
        A = ((a + q.hx) * k).astype(np.float32)[:, None] + \
            (au * k).astype(np.float32)[:, None] * du + (av * k).astype(np.float32)[:, None] * dv
        B = ((q.hy - b) * k).astype(np.float32)[:, None] - \
            (bu * k).astype(np.float32)[:, None] * du - (bv * k).astype(np.float32)[:, None] * dv
        col = np.clip(A.astype(np.int32), 0, cells - 1)
        row = np.clip(B.astype(np.int32), 0, cells - 1)
        return tex[row, col].mean(axis=1)

    # ------------------------------------------------------------ effects
    def _blur(self, img: np.ndarray) -> np.ndarray:
        s = self.scene.effects.blur_sigma
        if s <= 0:
            return img.astype(np.float32, copy=True)
        return cv2.GaussianBlur(img.astype(np.float32), (0, 0), s, borderType=cv2.BORDER_REPLICATE)

    @property
    def _blur_radius(self) -> int:
        s = self.scene.effects.blur_sigma
        return 0 if s <= 0 else math.ceil(4 * s) + 1

    def _noise(self, index: int) -> np.ndarray | None:
        """Gaussian noise for frame ``index``: a window of a seeded bank of 2 x H x W values
        at an offset drawn from (seed, index); its sigma grows with the gain a short
        exposure needs (:attr:`Effects.sensor_noise_sigma`)."""
        sigma = self.scene.effects.sensor_noise_sigma
        if sigma <= 0:
            return None
        n = self.width * self.height
        if self._noise_bank is None:
            rng = np.random.default_rng([self.scene.seed, 0x5EED])
            self._noise_bank = (rng.standard_normal(2 * n, dtype=np.float32) * np.float32(sigma))
        off = int(np.random.default_rng([self.scene.seed, index & 0xFFFFFFFF, index >> 32])
                  .integers(0, n))
        return self._noise_bank[off:off + n].reshape(self.height, self.width)

    # ------------------------------------------------------------ frames
    def dynamic_quads(self, t: float) -> list[list[Quad]]:
        """Camera-frame quads of each moving object (robots, moving occluders) at ``t``."""
        if self._dyn_cache is not None and self._dyn_cache[0] == t:
            return self._dyn_cache[1]
        objs = self._dynamic_quads(t)
        self._dyn_cache = (t, objs)
        return objs

    def _dynamic_quads(self, t: float) -> list[list[Quad]]:
        sc = self.scene
        poses = sc.robot_poses(t)
        objs = [self._robot_quads(r, poses[r.name]) for r in sc.robots]
        objs += [self._occluder_quads(o, t) for o in sc.effects.occluders if o.moving]
        return [[q.to_cam(self.world2cam) for q in obj] for obj in objs if obj]

    def frame_time(self, index: int, t: float | None = None) -> float:
        """Frame ``index``'s time, s: ``t`` when given (a wall-clock scene's Unix time),
        else index / fps."""
        return index / self.scene.fps if t is None else float(t)

    def timing(self, index: int, t: float | None = None) -> FrameTiming:
        """When frame ``index``'s rows were exposed (exact): row 0 is read out at the
        frame's time (:meth:`frame_time`)."""
        eff = self.scene.effects
        return FrameTiming(self.frame_time(index, t), eff.line_time_s, eff.exposure_time_s,
                           exact=True)

    def _regions(self, objs: list[list[Quad]]) -> list[tuple[Rect, list[Quad]]]:
        """Pixel boxes of the objects, overlapping ones merged, with their quads."""
        regions: list[tuple[Rect, list[Quad]]] = []
        for obj in objs:
            rects = [self._rect(q) for q in obj]
            rs = [r for r in rects if r is not None]
            if not rs:
                continue
            box = rs[0]
            for r in rs[1:]:
                box = union(box, r)
            box = grow(box, 1, (self.height, self.width))
            merged = [obj]
            for other in list(regions):
                if overlap(other[0], box):
                    regions.remove(other)
                    box = union(box, other[0])
                    merged.append(other[1])
            regions.append((box, [q for m in merged for q in m]))
        return regions

    def render_image(self, index: int, t: float | None = None) -> np.ndarray:
        """(H, W) uint8 image of frame ``index`` (at time ``t``: :meth:`frame_time`)."""
        if index < 0:
            raise ValueError(f"frame index must be >= 0, got {index}")
        timing = self.timing(index, t)
        t = timing.t_read0
        frame = self.static_image.copy()
        if self.scene.effects.timed and (self.scene.robots or any(
                o.moving for o in self.scene.effects.occluders)):
            self._render_timed(frame, timing)
        else:
            for box, quads in self._regions(self.dynamic_quads(t)):
                self._render_region(frame, box, quads)
        noise = self._noise(index)
        if noise is not None:
            frame += noise
        np.clip(frame, 0.0, 255.0, out=frame)
        frame += 0.5
        return frame.astype(np.uint8)

    def _render_region(self, frame: np.ndarray, box: Rect, quads: list[Quad]) -> None:
        shape = (self.height, self.width)
        rects = [self._rect(q) for q in quads]
        r0, r1, c0, c1 = box
        td, ad, qd = self._cast_rect(box, quads, rects, floor=False)
        hit = td < self.static_depth[r0:r1, c0:c1]
        if not hit.any():
            return
        comp = self.static_albedo[r0:r1, c0:c1].copy()
        comp[hit] = ad[hit]
        near = cv2.dilate(hit.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        e = (edges(comp) | edges(hit)) & near
        rows, cols = np.nonzero(e)
        if rows.size:
            sel = [i for i, qr in enumerate(self.static_rects)
                   if qr is not None and overlap(qr, box)]
            # What a pixel's square can show is what its 3 x 3 neighbours' centres show (the
            # surfaces are convex and larger than a pixel): cast only those surfaces.
            if len(quads) <= 62:
                bits = np.where(hit, np.left_shift(np.int64(1), np.maximum(qd, 0)), STATIC_BIT)
                masks = or_dilate(bits)[rows, cols]
            else:
                masks = np.full(rows.size, -1, dtype=np.int64)
            # Where the static image has no edge around a pixel, the static scene is uniform
            # over its square: its centre value and depth stand for every sub-sample.
            flat = ~self.static_edges[rows + r0, cols + c0]
            for m in np.unique(masks):
                use = [i for i in range(len(quads)) if m == -1 or (m >> i) & 1]
                static = bool(m & STATIC_BIT)
                if not static and len(use) == 1 and quads[use[0]].tex is not None:
                    k = np.flatnonzero(masks == m)
                    comp[rows[k], cols[k]] = self._decal_pixels(rows[k] + r0, cols[k] + c0,
                                                                quads[use[0]])
                    continue
                for part in ((True, False) if static else (False,)):
                    k = np.flatnonzero((masks == m) & ((flat == part) | (not static)))
                    if k.size == 0:
                        continue
                    comp[rows[k], cols[k]] = self._supersample(
                        rows[k] + r0, cols[k] + c0, DYNAMIC_SAMPLES, [quads[i] for i in use],
                        [rects[i] for i in use], static, sel, uniform=part)
        k = self._blur_radius
        out = grow(box, k, shape)
        big = grow(out, k, shape)
        lit = self.static_albedo[big[0]:big[1], big[2]:big[3]].copy()
        lit[r0 - big[0]:r1 - big[0], c0 - big[2]:c1 - big[2]] = comp
        if self.light is not None:
            dl = self._light(np.where(hit, td, self.static_depth[r0:r1, c0:c1]), box)
            light = self.light[big[0]:big[1], big[2]:big[3]].copy()
            light[r0 - big[0]:r1 - big[0], c0 - big[2]:c1 - big[2]] = dl
            lit *= light
        blurred = self._blur(lit)
        inner = blurred[out[0] - big[0]:out[1] - big[0], out[2] - big[2]:out[3] - big[2]]
        frame[out[0]:out[1], out[2]:out[3]] = inner * self.gain[out[0]:out[1], out[2]:out[3]]


    # ------------------------------------------------------------ exposure, rolling shutter
    #: Largest image motion of a moving object between two of the instants a timed frame
    #: is rendered at, pixels: the smear is a sum of copies this far apart (a box blur
    #: sampled at 0.4 px is within 1 % of the continuous one for the detector).
    TIME_STEP_PX = 0.4

    def _image_speed(self, t0: float, t1: float) -> float:
        """Largest speed of a robot marker corner or plate corner in the image between
        ``t0`` and ``t1`` s, px/s (from 9 instants; moving occluders: their centres)."""
        sc = self.scene
        ts = np.linspace(t0, t1, 9)
        pts = []
        for t in ts:
            p = []
            for r in sc.robots:
                pose = r.path.pose(float(t))
                if pose is None:
                    p.append(np.full((4, 3), np.nan))
                    continue
                x, y, th = pose
                c, s_ = math.cos(th), math.sin(th)
                h = float(r.plate) / 2  # type: ignore[arg-type]
                loc = np.array([[h, h], [h, -h], [-h, h], [-h, -h]])
                w = np.column_stack([x + c * loc[:, 0] - s_ * loc[:, 1],
                                     y + s_ * loc[:, 0] + c * loc[:, 1],
                                     np.full(4, r.height)])
                p.append(w)
            for o in sc.effects.occluders:
                if o.moving:
                    q = o.path.pose(float(t))
                    p.append(np.full((1, 3), np.nan) if q is None
                             else np.array([[q[0], q[1], o.z[1]]]))
            pts.append(np.vstack(p))
        uv = [lens.project(w, self.world2cam, sc.camera)[0] for w in pts]
        dt = (t1 - t0) / 8 if t1 > t0 else 1.0
        speed = 0.0
        for a, b in itertools.pairwise(uv):
            d = np.hypot(*(b - a).T)
            if np.isfinite(d).any():
                speed = max(speed, float(np.nanmax(d)) / dt)
        return speed

    def _render_timed(self, frame: np.ndarray, timing: FrameTiming) -> None:
        """The moving objects of one frame, each row as it was over its own exposure.

        Row r integrates the scene over [t_read0 + r line - E, t_read0 + r line]. The
        objects are rendered at instants on a grid fine enough that nothing moves more than
        :data:`TIME_STEP_PX` between two; each row averages the renders whose instant falls
        in its exposure (the nearest one when the exposure is shorter than a step)."""
        E, line = timing.exposure_s, timing.line_s
        H = self.height
        t_lo = timing.t_read0 - E
        t_hi = timing.t_read0 + (H - 1) * line
        # Where the objects can be in this frame: their boxes at the two ends and between.
        span = [self.dynamic_quads(float(t)) for t in np.linspace(t_lo, t_hi, 5)]
        boxes = self._regions([q for objs in span for q in objs])
        speed = self._image_speed(t_lo, t_hi)
        shape = (self.height, self.width)
        k = self._blur_radius
        work = self.static_image.copy()
        for box, _ in boxes:
            out = grow(box, k, shape)
            r0, r1 = out[0], out[1]
            a = timing.t_read0 + np.arange(r0, r1) * line - E  # exposure start of each row
            lo, hi = float(a[0]), float(a[-1]) + E
            step = self.TIME_STEP_PX / speed if speed > 0 else max(hi - lo, 1e-6)
            n = max(1, min(400, math.ceil((hi - lo) / step)))
            ts = lo + (np.arange(n) + 0.5) * (hi - lo) / n if hi > lo else np.array([lo])
            # weights (rows, n): the instants inside each row's exposure
            inside = (ts[None, :] >= a[:, None]) & (ts[None, :] < a[:, None] + E)
            empty = ~inside.any(axis=1)
            if empty.any():  # exposure shorter than a step: the instant nearest mid-exposure
                mid = a[empty] + E / 2
                j = np.abs(ts[None, :] - mid[:, None]).argmin(axis=1)
                inside[np.flatnonzero(empty), j] = True
            w = inside / inside.sum(axis=1, keepdims=True)
            acc = np.zeros((r1 - r0, out[3] - out[2]), dtype=np.float64)
            used = np.flatnonzero(w.any(axis=0))
            for j in used:
                t = float(ts[j])
                for sub_box, quads in self._regions(self.dynamic_quads(t)):
                    if overlap(sub_box, box):
                        self._render_region(work, sub_box, quads)
                rows = np.flatnonzero(w[:, j])
                acc[rows] += w[rows, j][:, None] * work[r0 + rows, out[2]:out[3]]
                work[out[0]:out[1], out[2]:out[3]] = self.static_image[out[0]:out[1],
                                                                       out[2]:out[3]]
            frame[out[0]:out[1], out[2]:out[3]] = acc.astype(np.float32)

    # ------------------------------------------------------------ truth
    def _static_truth(self) -> None:
        """What does not change between frames: static markers, corners, static occlusion."""
        self._truth_T = {mid: pose_matrix(m.rotation, m.position)
                         for mid, m in self._static_markers.items()}
        self._truth_len = {mid: m.length for mid, m in self._static_markers.items()}
        corners, ids, Pc = corners_and_probes(self._truth_T, self._truth_len, self.scene.camera,
                                              self.cam2world, self.world2cam)
        hidden = hidden_markers(Pc, [q for q in self.static_quads if q.occludes])
        self._truth_corners = corners
        keep = ~hidden
        self._truth_open = [m for m, k in zip(ids, keep, strict=True) if k]
        self._truth_probes = Pc.reshape(-1, 5, 3)[keep].reshape(-1, 3)

    def truth(self, index: int, t: float | None = None) -> FrameTruth:
        """Ground truth of frame ``index`` at time ``t`` (:meth:`frame_time`; cheap: no
        image)."""
        sc = self.scene
        t = self.frame_time(index, t)
        robots = sc.robot_poses(t)
        markers = {mid: T.copy() for mid, T in self._truth_T.items()}
        lengths = dict(self._truth_len)
        moving: dict[int, np.ndarray] = {}
        for r in sc.robots:
            for mid, T in sc.robot_marker_poses(r, robots[r.name]).items():
                moving[mid] = T
                lengths[mid] = r.length
        markers.update(moving)
        rc, rids, rPc = corners_and_probes(moving, lengths, sc.camera, self.cam2world,
                                           self.world2cam)
        timing = self.timing(index, t)
        if sc.effects.timed:
            rc = rolled_corners(rc, sc, timing, self.world2cam)
        corners = {m: c.copy() for m, c in self._truth_corners.items()}
        corners.update(rc)
        dyn = [q for obj in self.dynamic_quads(t) for q in obj if q.occludes]
        statics = [q for q in self.static_quads if q.occludes]
        visible = {m for m, h in zip(self._truth_open, hidden_markers(self._truth_probes, dyn),
                                     strict=True) if not h}
        visible |= {m for m, h in zip(rids, hidden_markers(rPc, statics + dyn), strict=True)
                    if not h and m in rc}
        return FrameTruth(self.cam2world.copy(), markers, lengths, corners, visible, robots, t,
                          timing, {r.name: r.path for r in sc.robots})

    def render(self, index: int, t: float | None = None) -> SimFrame:
        """Frame ``index`` at time ``t`` (:meth:`frame_time`): image and truth, both of that
        one instant, and the frame stamped with it."""
        t = self.frame_time(index, t)
        truth = self.truth(index, t)
        return SimFrame(index=index, timestamp=t, image=self.render_image(index, t),
                        meta={"truth": truth, "timing": truth.timing}, truth=truth)
