"""The marker map model: surveyed 6-DoF poses of ArUco markers in the world frame (numpy only).

Positions are metres; ``Marker.rotation`` is marker2world. The file formats (TOML, CSV) and
the built-in RobotAtFactory map are in :mod:`kmea.maps.files`. See ``docs/maps.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from kmea.geometry import marker_corners_local
from kmea.maps.aruco_names import MAX_MARKER_ID, PREDEFINED, is_dictionary_file

__all__ = ["DEFAULT_DICTIONARY", "MAX_COORDINATE", "MAX_LENGTH", "MAX_MARKER_ID", "MIN_LENGTH",
           "MapError", "Marker", "MarkerMap", "check_map", "check_spread"]

#: The dictionary of a map that names none. RobotAtFactory 4.0's floor markers are
#: DICT_5X5_50 codes (ids 0-49); DICT_5X5_100's first 50 codes are the same, and its wall
#: markers (ids 50-65) need the larger dictionary, so every map reads DICT_5X5_100 unless
#: it says otherwise.
DEFAULT_DICTIONARY = "DICT_5X5_100"

# Marker centres lie within 10 km of the world origin (m). The world frame is a venue's
# (its origin a marker of the map), and no camera finds a marker that far: at the longest
# focal length a camera file may have (100 image widths) a 6 cm marker is 10 px wide at
# 1 km for a 1640 px image, a few km for the largest sensors. Beyond is a slip (1e308,
# or metres scaled by 1e200: the squares overflow and every frame warns); a survey grid
# (UTM) is to be shifted to the venue.
MAX_COORDINATE = 1e4
# A marker's side (m): the range of the configuration's detector.marker_length, from a
# 0.1 mm print to a 10 m banner; 1e-300 or 1e300 leaves no pose to compute.
MIN_LENGTH = 1e-4
MAX_LENGTH = 10.0

# A camera of this many pixels across that sees the whole map images each marker at
# width * side / extent pixels; ArUco needs some 10 px, so a map spanning more than this
# many marker sides is not one floor in metres (a map in millimetres spans ~30,000).
MAX_SIDES_SPANNED = 1000
# A marker whose nearest neighbour is this many times farther than the map's median
# spacing, and farther than twice the rest of the map is wide, is a typing slip
# (7,227,150,0 for 7,0.227,0.150,0).
FAR_SPACINGS = 20.0
MAX_OVERLAPS_SHOWN = 10


class MapError(ValueError):
    """A map file or map value is invalid; the message names the file, line or key."""


@dataclass(frozen=True)
class Marker:
    """One surveyed marker.

    Attributes:
        id: ArUco id.
        position: (3,) centre in the world frame, metres.
        rotation: (3, 3) marker2world rotation.
        length: side of the black square, metres.

    Lists are accepted and stored as float arrays; an id beyond MAX_MARKER_ID, a bad shape,
    a non-finite value, a coordinate beyond MAX_COORDINATE, a rotation that is not proper
    or a length outside MIN_LENGTH-MAX_LENGTH raises :class:`MapError`.
    """

    id: int
    position: np.ndarray
    rotation: np.ndarray
    length: float

    def __post_init__(self) -> None:
        where = f"marker {self.id}"
        if isinstance(self.id, bool) or not isinstance(self.id, (int, np.integer)) \
                or not 0 <= self.id <= MAX_MARKER_ID:
            raise MapError(f"marker id must be an integer 0-{MAX_MARKER_ID}, got {self.id!r}")
        p = np.array(self.position, dtype=float)
        R = np.array(self.rotation, dtype=float)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise MapError(f"{where}: position must be 3 finite numbers (m)")
        if np.abs(p).max() > MAX_COORDINATE:
            raise MapError(f"{where}: position {p.tolist()} m is beyond +-{MAX_COORDINATE:g} m "
                           "of the origin (map positions are metres)")
        if R.shape != (3, 3) or not np.all(np.isfinite(R)) \
                or np.abs(R @ R.T - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0:
            raise MapError(f"{where}: rotation must be a proper 3x3 rotation matrix")
        if isinstance(self.length, bool) or not (math.isfinite(self.length)
                                                 and MIN_LENGTH <= self.length <= MAX_LENGTH):
            raise MapError(f"{where}: length must be {MIN_LENGTH:g}-{MAX_LENGTH:g} m, "
                           f"got {self.length!r}")
        p.setflags(write=False)
        R.setflags(write=False)
        object.__setattr__(self, "id", int(self.id))
        object.__setattr__(self, "position", p)
        object.__setattr__(self, "rotation", R)
        object.__setattr__(self, "length", float(self.length))

    @property
    def on_floor(self) -> bool:
        """Lies flat on the floor plane z = 0 facing up."""
        return abs(self.position[2]) < 1e-9 and self.rotation[2, 2] > 1.0 - 1e-9

    @property
    def normal(self) -> np.ndarray:
        """(3,) unit normal of the printed face in the world frame."""
        return self.rotation[:, 2].copy()

    def corners_world(self) -> np.ndarray:
        """(4, 3) world corners in OpenCV ArUco order (TL, TR, BR, BL)."""
        return marker_corners_local(self.length) @ self.rotation.T + self.position


@dataclass
class MarkerMap:
    """A set of surveyed markers and the metadata the estimators need.

    ``origin_id``, ``x_id`` and ``y_id`` are the anchors of LMEA and of KMEA's scale step.
    ``reference_length`` (m) is the denominator of the mean relative error; ``None`` means
    the diagonal of the floor markers' extent. ``extra["where"]``: id -> where the marker
    was read ("FILE: line N"), to name it in warnings.
    """

    markers: dict[int, Marker]
    dictionary: str = "DICT_5X5_50"
    default_length: float = 0.06
    origin_id: int = 13
    x_id: int = 16
    y_id: int = 4
    reference_length: float | None = None
    name: str = "map"
    source: str = "<memory>"
    extra: dict = field(default_factory=dict)

    def __contains__(self, marker_id: object) -> bool:
        return marker_id in self.markers

    def __getitem__(self, marker_id: int) -> Marker:
        return self.markers[marker_id]

    def __len__(self) -> int:
        return len(self.markers)

    @property
    def ids(self) -> list[int]:
        return sorted(self.markers)

    def positions(self, ids: list[int] | None = None) -> np.ndarray:
        """(N, 3) world positions of ``ids`` (default: all, sorted by id)."""
        ids = self.ids if ids is None else ids
        return np.array([self.markers[i].position for i in ids], dtype=float).reshape(-1, 3)

    def floor_extent(self) -> tuple[float, float, float, float]:
        """(xmin, xmax, ymin, ymax) of the floor markers' centres, metres (all markers if none)."""
        ms = [m for m in self.markers.values() if m.on_floor] or list(self.markers.values())
        p = np.array([m.position for m in ms])
        return (float(p[:, 0].min()), float(p[:, 0].max()),
                float(p[:, 1].min()), float(p[:, 1].max()))

    def extent(self) -> tuple[float, float, float, float]:
        """(xmin, xmax, ymin, ymax) of every marker's centre, metres."""
        p = self.positions()
        return (float(p[:, 0].min()), float(p[:, 0].max()),
                float(p[:, 1].min()), float(p[:, 1].max()))

    def ref_length(self) -> float:
        """Reference length for the MRE, metres."""
        if self.reference_length is not None:
            return self.reference_length
        x0, x1, y0, y1 = self.floor_extent()
        return math.hypot(x1 - x0, y1 - y0)


def check_spread(m: MarkerMap) -> None:
    """:class:`MapError` for a map whose markers do not span a length (all at one point,
    or one marker): no estimator can scale to it and no error can be relative to it."""
    ref = m.ref_length()
    if not (math.isfinite(ref) and ref > 0):
        raise MapError(f"{m.source}: the markers' centres span {ref:g} m: a map needs "
                       "markers at different places (at least three, apart)")


def check_map(m: MarkerMap) -> list[str]:
    """Warnings about a loaded map that is usable but probably not what was meant.

    Anchors missing from the map (LMEA then never estimates; KMEA's scale step uses the
    centroid), ids the dictionary cannot encode, an unknown dictionary, overlapping markers,
    positions that look like millimetres and a marker far from all others (a typing slip).
    """
    out: list[str] = []
    for label, mid in (("origin_id", m.origin_id), ("x_id", m.x_id), ("y_id", m.y_id)):
        if mid not in m:
            out.append(f"{label} {mid} is not in the map (LMEA cannot run)")
    if len({m.origin_id, m.x_id, m.y_id}) < 3:
        out.append("origin_id, x_id and y_id are not three different markers")
    size = PREDEFINED.get(m.dictionary)
    if size is None and not is_dictionary_file(m.dictionary):
        out.append(f"unknown ArUco dictionary {m.dictionary!r}")
    elif size is not None:
        big = [i for i in m.ids if i >= size]
        if big:
            out.append(f"{m.dictionary} has ids 0-{size - 1}; ids {big} can never be detected")
    # Markers facing the same way closer than their mean side overlap (back-to-back wall
    # markers, facing opposite ways, are fine).
    ids = m.ids
    P = m.positions(ids)
    N = np.array([m[i].normal for i in ids])
    L = np.array([m[i].length for i in ids])
    overlaps = []
    for a in range(len(ids)):
        d = np.linalg.norm(P[a + 1:] - P[a], axis=1)
        same = N[a + 1:] @ N[a] > 0.9
        overlaps += [f"markers {ids[a]} and {ids[a + 1 + j]} overlap (centres {d[j]:.4f} m "
                     "apart)" for j in np.nonzero(same & (d < (L[a + 1:] + L[a]) / 2))[0]]
    if len(overlaps) > MAX_OVERLAPS_SHOWN:
        overlaps = [*overlaps[:MAX_OVERLAPS_SHOWN - 1],
                    f"... and {len(overlaps) - MAX_OVERLAPS_SHOWN + 1} more overlapping pairs"]
    return out + overlaps + _implausible(m, ids, P, L)


def _implausible(m: MarkerMap, ids: list[int], P: np.ndarray, L: np.ndarray) -> list[str]:
    """Positions that are not metres of one floor: an extent of thousands of marker sides,
    and single markers far from all the others."""
    if len(ids) < 3:
        return []
    out: list[str] = []
    where = m.extra.get("where", {})
    side = float(np.median(L))
    D = np.linalg.norm(P[:, None, :] - P[None, :, :], axis=2)
    np.fill_diagonal(D, np.inf)
    nearest = D.min(1)
    spacing = float(np.median(nearest))
    slips = []
    for a in np.nonzero(nearest > FAR_SPACINGS * max(spacing, side))[0]:
        rest = np.delete(P, a, axis=0)
        if nearest[a] > 2 * np.linalg.norm(rest.max(0) - rest.min(0)):
            slips.append(a)
            p = ", ".join(f"{v:g}" for v in P[a])
            out.append(f"{where.get(ids[a], f'marker {ids[a]}')}: marker {ids[a]} at "
                       f"({p}) m is {nearest[a]:.4g} m from the nearest other marker "
                       f"(median spacing {spacing:.3g} m): a typing slip?")
    kept = np.delete(P, slips, axis=0)
    span = float(np.linalg.norm(kept.max(0) - kept.min(0)))
    if span > MAX_SIDES_SPANNED * side:
        out.insert(0, f"the markers span {span:.4g} m, {span / side:.0f} times their "
                      f"{side:g} m side: map positions are metres (are these millimetres?); "
                      "a camera seeing it all would image each marker at under 2 px")
    return out
