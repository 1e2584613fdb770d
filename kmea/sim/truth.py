"""What the simulator knows about a frame (the exact marker poses and corners, robots), and
how the renderer projects it: marker corners, occlusion probes, rolling-shutter corners."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from kmea.frame import Frame
from kmea.sim import lens
from kmea.sim.quads import Quad
from kmea.sim.scene import Scene, SimRobot
from kmea.timing import FrameTiming
from kmea.vision.camera import CameraModel

__all__ = ["FrameTruth", "SimFrame", "corners_and_probes", "hidden_markers", "rolled_corners",
           "rolling_corners"]


@dataclass
class FrameTruth:
    """Ground truth of one frame.

    cam2world: (4, 4). markers: id -> (4, 4) true marker2world of every marker in the scene
    (map markers as placed, i.e. displaced when misplaced; extra markers; robot markers).
    lengths: id -> marker side, m. corners: id -> (4, 2) exact pixel corners (TL, TR, BR, BL,
    lens distortion included) of the markers in front of the camera, facing it, whose four
    corners lie inside the image. visible: ids of ``corners`` that nothing hides (corners and
    centre unoccluded). robots: name -> true (x, y, theta), m and rad, at ``t``. t: seconds
    (the frame's timestamp: the instant row 0 is read out). timing: when each row was
    exposed (:class:`kmea.timing.FrameTiming`, exact). paths: robot name -> its path, so
    :meth:`robot_at` gives the truth at any instant (a pose's own time). With exposure or a
    rolling shutter the ``corners`` of robot markers are where each corner was at its own
    row's mid-exposure (what a perfect detector of the smeared image would find).
    """

    cam2world: np.ndarray
    markers: dict[int, np.ndarray]
    lengths: dict[int, float]
    corners: dict[int, np.ndarray]
    visible: set[int]
    robots: dict[str, tuple[float, float, float]]
    t: float = 0.0
    timing: FrameTiming | None = None
    paths: Mapping[str, object] = field(default_factory=dict, repr=False)

    def robot_at(self, name: str, t: float) -> tuple[float, float, float]:
        """True (x, y, theta) of robot ``name`` at ``t`` seconds (m, rad)."""
        p = self.paths[name].pose(t)  # type: ignore[attr-defined]
        if p is None:
            raise ValueError(f"robot {name!r}: absent at t = {t} s")
        return (float(p[0]), float(p[1]), float(p[2]))

    def marker2cam(self, mid: int) -> np.ndarray:
        """(4, 4) true marker2cam of marker ``mid`` (what a perfect PnP would give)."""
        return np.linalg.inv(self.cam2world) @ self.markers[mid]


@dataclass
class SimFrame(Frame):
    """A rendered frame: a :class:`kmea.frame.Frame` with its truth.

    index; timestamp = index / fps seconds (also ``t``); image: (H, W) uint8 greyscale
    (never None: :attr:`pixels` is the same array, typed so); truth: :class:`FrameTruth`
    (also in ``meta["truth"]``), a required keyword.
    """

    truth: FrameTruth = field(kw_only=True)

    @property
    def t(self) -> float:
        return self.timestamp

    @property
    def pixels(self) -> np.ndarray:
        """``image``, which a rendered frame always has."""
        if self.image is None:
            raise ValueError(f"simulated frame {self.index} has no image")
        return self.image


def rolling_corners(scene: Scene, robot: SimRobot, timing: FrameTiming,
                    world2cam: np.ndarray) -> dict[int, np.ndarray]:
    """(4, 2) pixel corners of ``robot``'s markers, each corner where it was at its own
    row's mid-exposure (a fixed point: the row depends on the time and back; three
    steps, each shrinking the error by the image speed times the line time, ~0.03)."""
    sc = scene
    half = robot.length / 2
    local = np.array([[-half, half, 0], [half, half, 0], [half, -half, 0],
                      [-half, -half, 0]], dtype=float)
    out: dict[int, np.ndarray] = {}
    for mid in robot.markers:
        uv = np.zeros((4, 2))
        for c in range(4):
            t = timing.row_time(sc.camera.height / 2)
            for _ in range(4):
                pose = robot.path.pose(t)
                if pose is None:
                    break
                T = sc.robot_marker_poses(robot, pose)[mid]
                w = T[:3, :3] @ local[c] + T[:3, 3]
                uv[c] = lens.project(w[None], world2cam, sc.camera)[0][0]
                t = timing.row_time(float(uv[c, 1]))
        out[mid] = uv
    return out

def corners_and_probes(markers: dict[int, np.ndarray], lengths: dict[int, float],
                       camera: CameraModel, cam2world: np.ndarray, world2cam: np.ndarray
                       ) -> tuple[dict[int, np.ndarray], list[int], np.ndarray]:
    """Projected corners (by ``camera`` at ``cam2world``, 4x4, and its inverse ``world2cam``)
    of the markers (``markers``: id -> 4x4 marker2world, ``lengths`` m) facing the camera
    with all corners in the image,
    their ids, and their occlusion probes (5 per marker: corners 2 % inside and the
    centre) in the camera frame, (5 N, 3)."""
    ids = sorted(markers)
    if not ids:
        return {}, [], np.zeros((0, 3))
    T = np.stack([markers[m] for m in ids])  # (N, 4, 4)
    half = np.array([lengths[m] / 2 for m in ids])
    s = np.array([[-1, 1], [1, 1], [1, -1], [-1, -1], [0, 0]], dtype=float)
    local = np.zeros((len(ids), 5, 3))
    local[:, :, :2] = s[None] * half[:, None, None]
    world = np.einsum("nij,nkj->nki", T[:, :3, :3], local) + T[:, None, :3, 3]
    uv, z = lens.project(world[:, :4].reshape(-1, 3), world2cam, camera)
    uv, z = uv.reshape(-1, 4, 2), z.reshape(-1, 4)
    cam = cam2world[:3, 3]
    facing = np.einsum("ni,ni->n", T[:, :3, 2], cam - T[:, :3, 3]) > 0
    W, H = camera.width, camera.height
    with np.errstate(invalid="ignore"):
        inside = ((uv >= -0.5).all(axis=(1, 2)) & (uv[..., 0] <= W - 0.5).all(axis=1)
                  & (uv[..., 1] <= H - 0.5).all(axis=1))
    keep = np.flatnonzero(facing & inside & (z > 1e-6).all(axis=1))
    corners = {ids[i]: uv[i] for i in keep}
    probes = world[keep].copy()
    probes[:, :4] = probes[:, 4:5] + 0.98 * (probes[:, :4] - probes[:, 4:5])
    Pc = probes.reshape(-1, 3) @ world2cam[:3, :3].T + world2cam[:3, 3]
    return corners, [ids[i] for i in keep], Pc

def hidden_markers(Pc: np.ndarray, occluders: list[Quad]) -> np.ndarray:
    """(N,) whether each marker (5 probes each) is hidden by one of ``occluders``."""
    hidden = np.zeros(len(Pc), dtype=bool)
    if len(Pc) == 0:
        return hidden
    x, y, zc = Pc[:, 0] / Pc[:, 2], Pc[:, 1] / Pc[:, 2], Pc[:, 2]
    x0, x1, y0, y1 = x.min(), x.max(), y.min(), y.max()
    for q in occluders:
        b = q.bbox
        if b is not None and (b[1] < x0 or b[0] > x1 or b[3] < y0 or b[2] > y1):
            continue
        tq, _ = q.hit(x, y)
        hidden |= tq < zc * (1 - 1e-7)
    return np.any(hidden.reshape(-1, 5), axis=1)


def rolled_corners(corners: dict[int, np.ndarray], scene: Scene, timing: FrameTiming,
                   world2cam: np.ndarray) -> dict[int, np.ndarray]:
    """``corners`` (robot marker id -> (4, 2) px at the frame's instant) with each robot
    marker's corners where its rows saw them (:func:`rolling_corners`); a marker that then
    lies across the image's edge is left out."""
    out = dict(corners)
    W, H = scene.camera.width, scene.camera.height
    for r in scene.robots:
        if not any(m in out for m in r.markers):
            continue
        for m, c in rolling_corners(scene, r, timing, world2cam).items():
            if m not in out:
                continue
            if ((c >= -0.5).all() and (c[:, 0] <= W - 0.5).all()
                    and (c[:, 1] <= H - 0.5).all()):
                out[m] = c
            else:
                del out[m]
    return out
