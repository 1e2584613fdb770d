"""Marker maps: surveyed 6-DoF poses of ArUco markers in the world frame.

A map is loaded from TOML (full description) or CSV (marker table only; the dictionary
and default length then come from the configuration). See ``docs/maps.md``.
"""

from __future__ import annotations

import csv
import math
import sys
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np

from kmea.transforms import euler_zyx_fixed_deg, marker_corners_local

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

__all__ = ["Marker", "MarkerMap", "MapError", "default_map", "load_map", "save_map_toml"]


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
    """

    id: int
    position: np.ndarray
    rotation: np.ndarray
    length: float

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
    the diagonal of the floor markers' extent.
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
        return float(p[:, 0].min()), float(p[:, 0].max()), float(p[:, 1].min()), float(p[:, 1].max())

    def ref_length(self) -> float:
        """Reference length for the MRE, metres."""
        if self.reference_length is not None:
            return self.reference_length
        x0, x1, y0, y1 = self.floor_extent()
        return math.hypot(x1 - x0, y1 - y0)


# ---------------------------------------------------------------------------- loading

_MAP_KEYS = {"name", "dictionary", "default_length", "origin_id", "x_id", "y_id",
             "reference_length", "markers"}
_MARKER_KEYS = {"id", "x", "y", "z", "rx_deg", "ry_deg", "rz_deg", "length"}


def _num(value: object, where: str) -> float:
    if isinstance(value, bool):
        raise MapError(f"{where}: expected a number, got {value!r}")
    try:
        v = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise MapError(f"{where}: expected a number, got {value!r}") from None
    if not math.isfinite(v):
        raise MapError(f"{where}: value must be finite, got {value!r}")
    return v


def _int(value: object, where: str) -> int:
    v = _num(value, where)
    if v != int(v) or v < 0:
        raise MapError(f"{where}: expected a non-negative integer id, got {value!r}")
    return int(v)


def _make_marker(row: dict, where: str, default_length: float) -> Marker:
    mid = _int(row.get("id"), f"{where}: id")
    pos = np.array([_num(row.get(k), f"{where}: {k}") for k in ("x", "y", "z")])
    angles = [_num(row.get(k, 0.0) if row.get(k, "") != "" else 0.0, f"{where}: {k}")
              for k in ("rx_deg", "ry_deg", "rz_deg")]
    raw_len = row.get("length", "")
    length = default_length if raw_len in ("", None) else _num(raw_len, f"{where}: length")
    if length <= 0:
        raise MapError(f"{where}: length must be > 0 m, got {length}")
    return Marker(mid, pos, euler_zyx_fixed_deg(*angles), float(length))


def _add(markers: dict[int, Marker], m: Marker, where: str) -> None:
    if m.id in markers:
        raise MapError(f"{where}: duplicate marker id {m.id}")
    markers[m.id] = m


def load_csv_markers(path: Path, default_length: float) -> dict[int, Marker]:
    """Read ``id,x,y,z[,rx_deg,ry_deg,rz_deg][,length]`` (metres, degrees)."""
    markers: dict[int, Marker] = {}
    try:
        with open(path, newline="") as f:
            reader = csv.DictReader(f)
            header = [h.strip() for h in (reader.fieldnames or [])]
            for col in ("id", "x", "y", "z"):
                if col not in header:
                    raise MapError(f"{path}: line 1: missing column {col!r}")
            unknown = set(header) - _MARKER_KEYS
            if unknown:
                raise MapError(f"{path}: line 1: unknown column(s) {sorted(unknown)}")
            reader.fieldnames = header
            for row in reader:
                where = f"{path}: line {reader.line_num}"
                if None in row:
                    raise MapError(f"{where}: more values than columns")
                row = {k: (v.strip() if isinstance(v, str) else v) for k, v in row.items()}
                if all(v in ("", None) for v in row.values()):
                    continue
                _add(markers, _make_marker(row, where, default_length), where)
    except OSError as e:
        raise MapError(f"{path}: cannot read: {e.strerror or e}") from None
    except UnicodeDecodeError:
        raise MapError(f"{path}: not a text file") from None
    if not markers:
        raise MapError(f"{path}: no markers")
    return markers


def load_map(path: str | Path, dictionary: str = "DICT_5X5_50",
             default_length: float = 0.06) -> MarkerMap:
    """Load a map from ``.toml`` or ``.csv``.

    A CSV map takes ``dictionary`` and ``default_length`` (m) from the caller (the
    configuration); the anchors default to the RobotAtFactory ids 13, 16, 4.
    """
    path = Path(path)
    if path.suffix.lower() == ".csv":
        markers = load_csv_markers(path, default_length)
        return MarkerMap(markers, dictionary=dictionary, default_length=default_length,
                         name=path.stem, source=str(path))
    if path.suffix.lower() == ".toml":
        try:
            data = tomllib.loads(path.read_text())
        except OSError as e:
            raise MapError(f"{path}: cannot read: {e.strerror or e}") from None
        except tomllib.TOMLDecodeError as e:
            raise MapError(f"{path}: invalid TOML: {e}") from None
        return map_from_dict(data, str(path))
    raise MapError(f"{path}: unknown map format {path.suffix!r} (use .toml or .csv)")


def map_from_dict(data: dict, source: str) -> MarkerMap:
    """Build a map from a parsed TOML document (see ``docs/maps.md``)."""
    unknown = set(data) - _MAP_KEYS
    if unknown:
        raise MapError(f"{source}: unknown key(s) {sorted(unknown)}")
    default_length = _num(data.get("default_length", 0.06), f"{source}: default_length")
    if default_length <= 0:
        raise MapError(f"{source}: default_length must be > 0 m")
    dictionary = data.get("dictionary", "DICT_5X5_50")
    if not isinstance(dictionary, str) or not dictionary:
        raise MapError(f"{source}: dictionary must be a non-empty string")
    rows = data.get("markers")
    if not isinstance(rows, list) or not rows:
        raise MapError(f"{source}: markers: expected a non-empty array of tables [[markers]]")
    markers: dict[int, Marker] = {}
    for i, row in enumerate(rows):
        where = f"{source}: markers[{i}]"
        if not isinstance(row, dict):
            raise MapError(f"{where}: expected a table")
        bad = set(row) - _MARKER_KEYS
        if bad:
            raise MapError(f"{where}: unknown key(s) {sorted(bad)}")
        for k in ("id", "x", "y", "z"):
            if k not in row:
                raise MapError(f"{where}: missing key {k!r}")
        _add(markers, _make_marker(row, where, default_length), where)
    ref = data.get("reference_length")
    m = MarkerMap(
        markers,
        dictionary=dictionary,
        default_length=default_length,
        origin_id=_int(data.get("origin_id", 13), f"{source}: origin_id"),
        x_id=_int(data.get("x_id", 16), f"{source}: x_id"),
        y_id=_int(data.get("y_id", 4), f"{source}: y_id"),
        reference_length=None if ref is None else _num(ref, f"{source}: reference_length"),
        name=str(data.get("name", Path(source).stem)),
        source=source,
    )
    if m.reference_length is not None and m.reference_length <= 0:
        raise MapError(f"{source}: reference_length must be > 0 m")
    return m


def _angles_deg(R: np.ndarray) -> tuple[float, float, float]:
    """Inverse of ``euler_zyx_fixed_deg``: R = Rx(a) Ry(b) Rz(c) -> (a, b, c) degrees."""
    b = math.asin(max(-1.0, min(1.0, R[0, 2])))
    if abs(R[0, 2]) < 1.0 - 1e-9:
        a = math.atan2(-R[1, 2], R[2, 2])
        c = math.atan2(-R[0, 1], R[0, 0])
    else:  # gimbal lock: put everything in c
        a = 0.0
        c = math.atan2(R[1, 0], R[1, 1])
    return tuple(round(math.degrees(v), 9) + 0.0 for v in (a, b, c))  # type: ignore[return-value]


def map_to_dict(m: MarkerMap) -> dict:
    """The TOML document of a map (angles in degrees: the file is meant for people)."""
    doc: dict = {
        "name": m.name,
        "dictionary": m.dictionary,
        "default_length": m.default_length,
        "origin_id": m.origin_id,
        "x_id": m.x_id,
        "y_id": m.y_id,
    }
    if m.reference_length is not None:
        doc["reference_length"] = m.reference_length
    rows = []
    for mid in m.ids:
        mk = m.markers[mid]
        rx, ry, rz = _angles_deg(mk.rotation)
        row = {"id": mid, "x": float(mk.position[0]), "y": float(mk.position[1]),
               "z": float(mk.position[2])}
        if (rx, ry, rz) != (0.0, 0.0, 0.0):
            row.update(rx_deg=rx, ry_deg=ry, rz_deg=rz)
        row["length"] = mk.length
        rows.append(row)
    doc["markers"] = rows
    return doc


def save_map_toml(m: MarkerMap, path: str | Path) -> None:
    """Write ``m`` as TOML (round-trips through :func:`load_map`)."""
    import tomli_w

    Path(path).write_text(tomli_w.dumps(map_to_dict(m)))


def default_map() -> MarkerMap:
    """The official RobotAtFactory 4.0 map, shipped in the package.

    33 floor markers (60 mm) and 16 wall markers (40 mm). The rules' floor dictionary is
    DICT_5X5_50, but the wall markers have ids 50-65, beyond it; DICT_5X5_100 holds the
    same first 50 codes, so the built-in map names DICT_5X5_100 and every marker is found.
    """
    pkg = resources.files("kmea") / "data"
    with resources.as_file(pkg / "raf4_floor_markers.csv") as floor_csv, \
            resources.as_file(pkg / "raf4_wall_markers.csv") as wall_csv:
        markers = load_csv_markers(Path(floor_csv), 0.06)
        for mid, mk in load_csv_markers(Path(wall_csv), 0.04).items():
            _add(markers, mk, str(wall_csv))
    return MarkerMap(markers, dictionary="DICT_5X5_100", default_length=0.06, origin_id=13,
                     x_id=16, y_id=4, reference_length=2.081, name="RobotAtFactory 4.0",
                     source="<built-in RobotAtFactory 4.0>")
