"""``kmea map survey``: measure every marker a camera sees against a (possibly partial) map.

The technician's check of a floor. Each frame: detect, estimate every marker's camera-frame
pose, then estimate world poses with the chosen estimator (default ``corner-pnp``):

- a marker **in the map** is measured with its own map entry left out entirely (not a
  reference, and not even its plane: a moved marker must not be pulled back onto its own
  survey), i.e. as if it were a new marker;
- a marker **not in the map** is measured from the map's markers (its plane inferred, see
  :mod:`kmea.estimators.unknown_plane`).

Over N frames each marker's position is the coordinate-wise median (robust to a frame with
a hidden corner); its yaw the circular mean. Its standard error is ``1.2533 * 1.4826 * MAD /
sqrt(n)`` per axis (the median's efficiency on Gaussian noise).

**Disagreement with the map** (map markers): ``d`` = distance in the marker's map plane
between measured and surveyed position. Per-frame noise averages out but systematic errors
(calibration, camera pose, corner bias) do not, and they grow with the marker's footprint
in metres per pixel: ``g`` = its side (m) / its shortest side in the image (px), large for
a far or oblique marker (a wall seen from above). So the per-axis uncertainty is ``sigma =
sqrt(se^2 + (s_px g)^2)``, with ``s_px`` the systematic level in pixels the map markers
themselves show: ``median(d / g) / 1.1774`` over the measured map markers of its group (the
median of a 2-D Gaussian's norm is 1.1774 sigma; robust to a few moved markers): markers
facing up (the floor) and the others (walls, seen edge-on, with larger corner biases) each
have their own level, a group of fewer than 3 takes the larger one; 0 with fewer than 5 map
markers measured. The disagreement is significant when ``(d / sigma)^2`` exceeds the
chi-square (2 dof) quantile at ``level`` (default 0.9999, about 4.3 sigma: on a 40-marker
floor the chance of one false alarm is 0.4 %). Thresholds thus scale with the noise, the
marker's size in pixels and the systematic level the survey itself measures. A marker
estimated *free* (no plane of the map fits it, e.g. alone on its wall) has a single-marker
depth: its depth uncertainty, the references' robust relative spread of PnP distance against
the fitted camera, times the ratio of their size in pixels to its own, times its distance,
projected on its map plane, adds in quadrature.

The output CSV has the map CSV columns ``id,x,y,z,rx_deg,ry_deg,rz_deg,length`` (metres,
degrees, ``R = Rx @ Ry @ Rz``), in the given map's frame (its origin and axes), for every
marker seen.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from kmea.estimators import DEFAULT_ALGORITHM, get
from kmea.estimators.base import MarkerObservation
from kmea.geometry.camera import CameraIntrinsics
from kmea.maps.files import MarkerMap, _angles_deg

__all__ = ["MarkerSurvey", "Survey", "format_report", "survey_frames", "write_csv"]


@dataclass
class MarkerSurvey:
    """One marker's survey result (metres, radians).

    position (3,) robust mean; rotation (3, 3) marker2world; stderr (3,) per axis; n frames
    measured; in_map; map_position (3,) or None; disagreement m (in the map plane) and its
    significance (z, in sigmas) for map markers; significant: flagged.
    """

    id: int
    position: np.ndarray
    rotation: np.ndarray
    stderr: np.ndarray
    n: int
    length: float
    in_map: bool
    map_position: np.ndarray | None = None
    disagreement: float = math.nan
    sigma: float = math.nan
    z: float = math.nan
    significant: bool = False
    plane: str = ""
    footprint: float = math.nan  # g: metres per pixel along the marker's shortest image side
    free_sigma: float = 0.0  # in-plane depth uncertainty of a free estimate, m


@dataclass
class Survey:
    """All markers measured, the map ids never seen, frames used, the systematic level."""

    markers: dict[int, MarkerSurvey] = field(default_factory=dict)
    never_seen: list[int] = field(default_factory=list)
    frames: int = 0
    frames_failed: int = 0
    systematic_px: float = 0.0
    systematic_levels: dict = field(default_factory=dict)
    level: float = 0.9999


def _shortest_side(o: MarkerObservation) -> float:
    """Shortest side of the marker's detected quadrilateral, px (NaN without corners)."""
    if o.corners is None:
        return math.nan
    c = np.asarray(o.corners, float).reshape(4, 2)
    return float(np.min(np.linalg.norm(c - np.roll(c, 1, axis=0), axis=1)))


def _depth_spread(est, obs: list[MarkerObservation], world_map: MarkerMap,
                  marker: MarkerObservation) -> float:
    """Relative 1-sigma of ``marker``'s single-marker PnP depth: the references' robust
    spread of PnP distance against the fitted camera's, scaled by how much smaller the
    marker looks than they do (the relative depth error of a PnP goes as corner noise over
    size in pixels)."""
    if est.cam2world is None or len(est.references) < 3:
        return math.nan
    C = est.cam2world[:3, 3]
    by_id = {o.id: o for o in obs}
    refs = [i for i in est.references if i in by_id]
    r = np.array([np.linalg.norm(world_map[i].position - C)
                  / max(float(np.linalg.norm(by_id[i].marker2cam_t)), 1e-9) for i in refs])
    spread = float(1.4826 * np.median(np.abs(r - np.median(r))))
    size = _shortest_side(marker)
    ref_size = float(np.nanmedian([_shortest_side(by_id[i]) for i in refs]))
    if math.isfinite(size) and size > 0 and math.isfinite(ref_size):
        spread *= max(1.0, ref_size / size)
    return spread


def _free_sigma(position: np.ndarray, camera_centre: np.ndarray, normal: np.ndarray | None,
                spread: float) -> float:
    """In-plane 1-sigma (m) of a free estimate: its depth uncertainty along the camera ray,
    projected on the plane of normal ``normal`` (the whole of it without one)."""
    ray = position - camera_centre
    dist = float(np.linalg.norm(ray))
    if not (dist > 0 and math.isfinite(spread)):
        return 0.0
    cos = abs(float(ray @ normal)) / dist if normal is not None else 0.0
    return spread * dist * math.sqrt(max(0.0, 1.0 - cos * cos))


def _measure_frame(estimator, obs: list[MarkerObservation], world_map: MarkerMap,
                   camera: CameraIntrinsics
                   ) -> dict[int, tuple[np.ndarray, np.ndarray, str, float]]:
    """id -> (position (3,), rotation (3, 3), plane label, free-depth sigma m) of every
    marker of one frame, map markers each with its own entry removed from the map."""
    out: dict[int, tuple[np.ndarray, np.ndarray, str, float]] = {}
    by_id = {o.id: o for o in obs}

    def record(i: int, e) -> None:
        me = e.markers[i]
        plane = e.info.get("unknown_planes", {}).get(i, "")
        fs = 0.0
        if plane == "free" and e.cam2world is not None:
            n = world_map[i].normal if i in world_map else None
            fs = _free_sigma(me.position, e.cam2world[:3, 3], n,
                             _depth_spread(e, obs, world_map, by_id[i]))
        out[i] = (me.position, me.rotation, plane, fs)

    full = estimator.estimate(obs, world_map, camera=camera)
    if full.ok:
        for i in full.markers:
            if i not in world_map:
                record(i, full)
    for o in obs:
        if o.id not in world_map:
            continue
        without = replace(world_map, markers={i: m for i, m in world_map.markers.items()
                                              if i != o.id}, extra=dict(world_map.extra))
        e = estimator.estimate(obs, without, camera=camera)
        if e.ok and o.id in e.markers:
            record(o.id, e)
    return out


def survey_frames(frames: Iterable[np.ndarray], world_map: MarkerMap, camera,
                  algorithm: str = DEFAULT_ALGORITHM, level: float = 0.9999,
                  default_length: float | None = None,
                  progress: Callable[[int, int], None] | None = None) -> Survey:
    """Survey grey images ``frames`` seen by ``camera`` (a :class:`CameraModel`).

    progress(frame index, markers seen so far) is called after each frame.
    """
    from kmea.stats.chi2 import chi2_quantile
    from kmea.vision.detection import DetectorConfig, MarkerDetector
    from kmea.vision.marker_pose import estimate_marker_poses

    estimator = get(algorithm)
    detector = MarkerDetector(DetectorConfig(dictionary=world_map.dictionary))
    dl = world_map.default_length if default_length is None else float(default_length)
    lengths = {i: m.length for i, m in world_map.markers.items()}
    samples: dict[int, list[tuple[np.ndarray, np.ndarray, str, float]]] = {}
    lens: dict[int, float] = {}
    sides: dict[int, list[float]] = {}
    res = Survey(level=level)
    for k, image in enumerate(frames):
        res.frames += 1
        det = detector.detect(image)
        obs, _ = estimate_marker_poses(det.ids, det.corners, camera, lengths, world_map,
                                       default_length=dl)
        got = _measure_frame(estimator, obs, world_map, camera.intrinsics) if obs else {}
        if not got:
            res.frames_failed += 1
        for o in obs:
            lens[o.id] = o.length
            if o.corners is not None:
                sides.setdefault(o.id, []).append(_shortest_side(o))
        for i, v in got.items():
            samples.setdefault(i, []).append(v)
        if progress:
            progress(k, len(samples))
    for i, vals in sorted(samples.items()):
        P = np.array([v[0] for v in vals])
        med = np.median(P, axis=0)
        mad = np.median(np.abs(P - med), axis=0)
        se = 1.2533 * 1.4826 * mad / math.sqrt(len(P))
        Rs = np.array([v[1] for v in vals])
        R = _mean_rotation(Rs)
        planes = [v[2] for v in vals if v[2]]
        plane = max(set(planes), key=planes.count) if planes else ""
        ms = MarkerSurvey(i, med, R, se, len(P), lens.get(i, dl), i in world_map, plane=plane,
                          free_sigma=float(np.median([v[3] for v in vals])))
        if sides.get(i):
            ms.footprint = ms.length / max(float(np.median(sides[i])), 1e-9)
        if i in world_map:
            ms.map_position = world_map[i].position.copy()
        res.markers[i] = ms
    _significance(res, world_map, chi2_quantile(level, 2))
    res.never_seen = [i for i in world_map.ids if i not in res.markers]
    return res


def _mean_rotation(Rs: np.ndarray) -> np.ndarray:
    """Chordal mean of rotations (N, 3, 3): the SO(3) projection of their sum."""
    U, _, Vt = np.linalg.svd(Rs.sum(axis=0))
    D = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(U @ Vt))) or 1.0])
    return U @ D @ Vt


def _in_plane(world_map: MarkerMap, i: int, delta: np.ndarray) -> np.ndarray:
    """The component of ``delta`` (3,) in marker i's map plane, in its plane axes (2,)."""
    F = world_map[i].rotation
    return (F.T @ delta)[:2]


def _group(world_map: MarkerMap, i: int) -> str:
    """"floor" for markers facing up (normal within 25 degrees of +z), else "walls"."""
    return "floor" if world_map[i].normal[2] > 0.9 else "walls"


def _significance(res: Survey, world_map: MarkerMap, threshold: float) -> None:
    mapped = [m for m in res.markers.values() if m.in_map]
    ds = []
    for m in mapped:
        d2 = _in_plane(world_map, m.id, m.position - m.map_position)
        m.disagreement = float(np.hypot(*d2))
        ds.append(m.disagreement)
    # Systematic level (px) from the bulk of the map markers (robust: a few moved markers do
    # not inflate it): median of a 2-D Gaussian's norm = sqrt(2 ln 2) sigma = 1.1774 sigma.
    # Markers facing the camera's way (the floor) and markers seen edge-on (walls) have
    # different corner biases: one level per group, the larger one for a group too small.
    groups: dict[str, list[float]] = {}
    for m in mapped:
        if m.footprint > 0:
            groups.setdefault(_group(world_map, m.id), []).append(m.disagreement / m.footprint)
    levels = {g: float(np.median(v) / 1.1774) for g, v in groups.items() if len(v) >= 3}
    if sum(len(v) for v in groups.values()) < 5:
        levels = {}
    fallback = max(levels.values(), default=0.0)
    res.systematic_px = levels.get("floor", fallback)
    res.systematic_levels = dict(levels)
    for m in mapped:
        se = float(np.sqrt(np.mean(_in_plane(world_map, m.id, m.stderr) ** 2)))
        g = m.footprint if m.footprint > 0 else 0.0
        level = levels.get(_group(world_map, m.id), fallback)
        m.sigma = math.sqrt(se ** 2 + (level * g) ** 2 + m.free_sigma ** 2)
        m.z = m.disagreement / m.sigma if m.sigma > 0 else math.inf
        m.significant = m.z ** 2 > threshold


def write_csv(survey: Survey, path: str | Path) -> None:
    """The map CSV format: id,x,y,z,rx_deg,ry_deg,rz_deg,length (m, degrees)."""
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(["id", "x", "y", "z", "rx_deg", "ry_deg", "rz_deg", "length"])
        for i, m in sorted(survey.markers.items()):
            rx, ry, rz = _angles_deg(m.rotation)
            w.writerow([i, f"{m.position[0]:.5f}", f"{m.position[1]:.5f}",
                        f"{m.position[2]:.5f}", f"{rx:.3f}", f"{ry:.3f}", f"{rz:.3f}",
                        f"{m.length:.4f}"])


def format_report(survey: Survey) -> str:
    """For people: millimetres."""
    lines = [f"survey: {survey.frames} frames ({survey.frames_failed} without an estimate), "
             f"{len(survey.markers)} markers seen, systematic level per axis "
             + (", ".join(f"{g} {v:.3f} px" for g, v in sorted(survey.systematic_levels.items()))
                or "0 (fewer than 5 map markers)")
             + f", significance level {survey.level}"]
    bad = [m for m in survey.markers.values() if m.significant]
    if bad:
        lines.append("markers that disagree with the map:")
        for m in sorted(bad, key=lambda m: -m.z):
            dx, dy, dz = m.position - m.map_position
            lines.append(f"  {m.id:>4}: moved {m.disagreement * 1e3:.1f} mm (dx {dx * 1e3:+.1f}, "
                         f"dy {dy * 1e3:+.1f}, dz {dz * 1e3:+.1f} mm), {m.z:.1f} sigma (sigma "
                         f"{m.sigma * 1e3:.2f} mm, {m.n} frames)")
    else:
        lines.append("no marker disagrees significantly with the map")
    new = [m for m in survey.markers.values() if not m.in_map]
    if new:
        lines.append("markers not in the map: " + ", ".join(
            f"{m.id} ({m.position[0]:+.4f}, {m.position[1]:+.4f}, {m.position[2]:+.4f}) m"
            + (f" [{m.plane}]" if m.plane else "") for m in sorted(new, key=lambda m: m.id)))
    if survey.never_seen:
        lines.append("map markers never seen: " + ", ".join(map(str, survey.never_seen)))
    return "\n".join(lines)
