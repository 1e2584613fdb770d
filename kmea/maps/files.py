"""Marker map files: TOML (full description) and CSV (marker table only), and the built-in
RobotAtFactory 4.0 map. The model itself (:class:`Marker`, :class:`MarkerMap`,
:func:`check_map`) is :mod:`kmea.maps.model`, re-exported here.

A CSV map takes the dictionary and default length from the configuration. Positions are
metres; rotations are given in the files as degrees ``rx_deg, ry_deg, rz_deg``: fixed-frame
rotations applied first about Z, then Y, then X, i.e. ``R = Rx @ Ry @ Rz`` (marker2world).
The dictionary is any name the configuration accepts (:mod:`kmea.maps.aruco_names`): a
predefined one or a custom dictionary file, relative to the map file. See ``docs/maps.md``.

Every problem with a file raises :class:`MapError` with one line naming the file, the line
(CSV, and TOML ``[[markers]]`` tables) or the key, and the problem.
"""

from __future__ import annotations

import csv
import math
import re
from importlib import resources
from pathlib import Path

import numpy as np
import tomli_w

from kmea.geometry import euler_zyx_fixed_deg
from kmea.maps.aruco_names import check_dictionary_name, is_dictionary_file
from kmea.maps.model import (
    DEFAULT_DICTIONARY,
    MAX_COORDINATE,
    MAX_LENGTH,
    MAX_MARKER_ID,
    MIN_LENGTH,
    MapError,
    Marker,
    MarkerMap,
    check_map,
    check_spread,
)
from kmea.wire import tomlvalue as toml

__all__ = [
    "DEFAULT_DICTIONARY",
    "MapError",
    "Marker",
    "MarkerMap",
    "check_map",
    "check_spread",
    "default_map",
    "dumps_map_toml",
    "load_csv_markers",
    "load_map",
    "map_digest",
    "map_from_dict",
    "map_to_dict",
    "save_map_toml",
]


def _check_dictionary(name: object, where: str, relative_to: Path | None = None) -> str:
    """A dictionary name the configuration accepts; a relative dictionary file is taken
    relative to the map file's folder (``relative_to``)."""
    try:
        out = check_dictionary_name(name, where)
    except ValueError as e:
        raise MapError(str(e)) from None
    if relative_to is not None and is_dictionary_file(out) and not Path(out).is_absolute():
        out = str(relative_to / out)
    return out


# ---------------------------------------------------------------------------- loading

_MAP_KEYS = {"name", "dictionary", "default_length", "origin_id", "x_id", "y_id",
             "reference_length", "markers"}
_MARKER_KEYS = {"id", "x", "y", "z", "rx_deg", "ry_deg", "rz_deg", "length"}
# Rotations in files are degrees within one turn either way: that reaches every
# orientation in both conventions people use ([0, 360) and (-180, 180]), and an angle
# beyond is a slip (900 for 90.0) or garbage (1e300, which has no angle left in it).
MAX_ANGLE_DEG = 360.0
# The longest reference length a map can need: the diagonal of the cube of positions.
MAX_REFERENCE_LENGTH = 2 * math.sqrt(3) * MAX_COORDINATE


def _num(value: object, where: str, strict: bool = False) -> float:
    """A finite float; ``strict`` (TOML) refuses strings, CSV cells are strings."""
    if value is None or value == "":
        raise MapError(f"{where}: missing value")
    if isinstance(value, bool) or (strict and not isinstance(value, (int, float))):
        what = (f"the string {value!r} (a number is written without quotes)"
                if isinstance(value, str) else repr(value))
        raise MapError(f"{where}: expected a number, got {what}")
    try:
        v = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise MapError(f"{where}: expected a number, got {_short(value)}") from None
    except OverflowError:  # a TOML integer of hundreds of digits
        raise MapError(f"{where}: value too large, got {_short(value)}") from None
    if not math.isfinite(v):
        raise MapError(f"{where}: value must be finite, got {_short(value)}")
    return v


def _short(value: object) -> str:
    """``repr`` cut to a line (a cell or a TOML integer can be thousands of characters)."""
    r = repr(value) if not isinstance(value, int) or value.bit_length() < 200 else "<huge int>"
    return r if len(r) <= 40 else r[:37] + "..."


def _within(v: float, lo: float, hi: float, where: str, unit: str, why: str = "") -> float:
    if not lo <= v <= hi:
        raise MapError(f"{where}: {v:g}{unit} is outside [{lo:g}, {hi:g}]{unit}{why}")
    return v


def _int(value: object, where: str, strict: bool = False) -> int:
    if strict and isinstance(value, float):
        raise MapError(f"{where}: expected an integer id, got {value!r}")
    v = _num(value, where, strict)
    if v != int(v) or v < 0:
        raise MapError(f"{where}: expected a non-negative integer id, got {_short(value)}")
    if v > MAX_MARKER_ID:
        shown = str(value) if isinstance(value, int) else f"{v:g}"  # (a huge int: _num refused it)
        raise MapError(f"{where}: {shown} is beyond {MAX_MARKER_ID}, more markers than any "
                       "ArUco dictionary has")
    return int(v)


def _make_marker(row: dict, where: str, default_length: float, strict: bool = False) -> Marker:
    mid = _int(row.get("id"), f"{where}: id", strict)
    pos = np.array([_within(_num(row.get(k), f"{where}: {k}", strict), -MAX_COORDINATE,
                            MAX_COORDINATE, f"{where}: {k}", " m",
                            " (positions are metres from the venue's origin)")
                    for k in ("x", "y", "z")])
    angles = [0.0 if row.get(k) in (None, "") else
              _within(_num(row[k], f"{where}: {k}", strict), -MAX_ANGLE_DEG, MAX_ANGLE_DEG,
                      f"{where}: {k}", " degrees", " (one turn either way)")
              for k in ("rx_deg", "ry_deg", "rz_deg")]
    raw_len = row.get("length")
    length = default_length if raw_len in ("", None) else _num(raw_len, f"{where}: length",
                                                               strict)
    _within(length, MIN_LENGTH, MAX_LENGTH, f"{where}: length", " m")
    return Marker(mid, pos, euler_zyx_fixed_deg(*angles), float(length))


def _add(markers: dict[int, Marker], m: Marker, where: str) -> None:
    if m.id in markers:
        raise MapError(f"{where}: duplicate marker id {m.id}")
    markers[m.id] = m


def load_csv_markers(path: Path, default_length: float) -> dict[int, Marker]:
    """Read ``id,x,y,z[,rx_deg,ry_deg,rz_deg][,length]`` (metres, degrees); blank lines are
    skipped. ``default_length`` (m) is used where ``length`` is absent or empty."""
    return _read_csv(Path(path), default_length)[0]


def _read_csv(path: Path, default_length: float) -> tuple[dict[int, Marker], dict[int, str]]:
    """The markers of a CSV map and where each was read (id -> "FILE: line N")."""
    markers: dict[int, Marker] = {}
    wheres: dict[int, str] = {}
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            reader = csv.DictReader(f)
            header = [h.strip() for h in (reader.fieldnames or [])]
            for col in ("id", "x", "y", "z"):
                if col not in header:
                    raise MapError(f"{path}: line 1: missing column {col!r}")
            unknown = set(header) - _MARKER_KEYS
            if unknown:
                raise MapError(f"{path}: line 1: unknown column(s) {sorted(unknown)}")
            dup = sorted({h for h in header if header.count(h) > 1})
            if dup:
                raise MapError(f"{path}: line 1: duplicate column(s) {dup}")
            reader.fieldnames = header
            for row in reader:
                where = f"{path}: line {reader.line_num}"
                if None in row:
                    raise MapError(f"{where}: more values than columns")
                row = {k: (v.strip() if isinstance(v, str) else v) for k, v in row.items()}
                if all(v in ("", None) for v in row.values()):
                    continue
                _add(markers, _make_marker(row, where, default_length), where)
                wheres[next(reversed(markers))] = f"line {reader.line_num}"
    except OSError as e:
        raise MapError(f"{path}: cannot read: {e.strerror or e}") from None
    except UnicodeDecodeError:
        raise MapError(f"{path}: not a UTF-8 text file") from None
    except csv.Error as e:
        raise MapError(f"{path}: bad CSV: {e}") from None
    if not markers:
        raise MapError(f"{path}: no markers")
    return markers, wheres


def load_map(path: str | Path, dictionary: str = DEFAULT_DICTIONARY,
             default_length: float = 0.06) -> MarkerMap:
    """Load a map from ``.toml`` or ``.csv``.

    A CSV map takes ``dictionary`` and ``default_length`` (m) from the caller (the
    configuration); the anchors default to the RobotAtFactory ids 13, 16, 4 and the
    reference length to the diagonal of the floor markers' extent.
    """
    path = Path(path)
    if path.suffix.lower() == ".csv":
        dictionary = _check_dictionary(dictionary, f"{path}: dictionary")
        if isinstance(default_length, bool) or not (math.isfinite(default_length)
                                                    and MIN_LENGTH <= default_length
                                                    <= MAX_LENGTH):
            raise MapError(f"{path}: default marker length must be {MIN_LENGTH:g}-"
                           f"{MAX_LENGTH:g} m, got {default_length!r}")
        markers, wheres = _read_csv(path, default_length)
        return MarkerMap(markers, dictionary=dictionary, default_length=default_length,
                         name=path.stem, source=str(path), extra={"where": wheres})
    if path.suffix.lower() == ".toml":
        try:
            text = path.read_text(encoding="utf-8")
            data = toml.loads(text)
        except OSError as e:
            raise MapError(f"{path}: cannot read: {e.strerror or e}") from None
        except UnicodeDecodeError:
            raise MapError(f"{path}: not a UTF-8 text file") from None
        except (toml.TOMLDecodeError, toml.TooDeep) as e:
            raise MapError(f"{path}: invalid TOML: {e}") from None
        return map_from_dict(data, str(path), _table_lines(text))
    raise MapError(f"{path}: unknown map format {path.suffix!r} (use .toml or .csv)")


_TABLE_RE = re.compile(r"^\s*\[\[\s*markers\s*\]\]")


def _table_lines(text: str) -> list[int]:
    """Line numbers (1-based) of the ``[[markers]]`` headers, in order."""
    return [i + 1 for i, line in enumerate(text.splitlines()) if _TABLE_RE.match(line)]


def map_from_dict(data: dict, source: str, lines: list[int] | None = None) -> MarkerMap:
    """Build a map from a parsed TOML document (see ``docs/maps.md``).

    ``lines``: line numbers of the ``[[markers]]`` tables, to name them in errors.
    """
    unknown = set(data) - _MAP_KEYS
    if unknown:
        raise MapError(f"{source}: unknown key(s) {sorted(unknown)}")
    default_length = _within(_num(data.get("default_length", 0.06),
                                  f"{source}: default_length", True),
                             MIN_LENGTH, MAX_LENGTH, f"{source}: default_length", " m")
    folder = Path(source).parent if Path(source).is_file() else None
    dictionary = _check_dictionary(data.get("dictionary", DEFAULT_DICTIONARY),
                                   f"{source}: dictionary", folder)
    name = data.get("name", Path(source).stem)
    if not isinstance(name, str):
        raise MapError(f"{source}: name must be a string, got {name!r}")
    rows = data.get("markers")
    if not isinstance(rows, list) or not rows:
        raise MapError(f"{source}: markers: expected a non-empty array of tables [[markers]]")
    row_lines = lines if lines is not None and len(lines) == len(rows) else None
    markers: dict[int, Marker] = {}
    wheres: dict[int, str] = {}
    for i, row in enumerate(rows):
        where = f"{source}: markers[{i}]" + (
            f" (line {row_lines[i]})" if row_lines is not None else "")
        if not isinstance(row, dict):
            raise MapError(f"{where}: expected a table")
        bad = set(row) - _MARKER_KEYS
        if bad:
            raise MapError(f"{where}: unknown key(s) {sorted(bad)}")
        for k in ("id", "x", "y", "z"):
            if k not in row:
                raise MapError(f"{where}: missing key {k!r}")
        _add(markers, _make_marker(row, where, default_length, strict=True), where)
        wheres[next(reversed(markers))] = where.removeprefix(f"{source}: ")
    anchors = {}
    for key, default in (("origin_id", 13), ("x_id", 16), ("y_id", 4)):
        anchors[key] = _int(data.get(key, default), f"{source}: {key}", strict=True)
        if key in data and anchors[key] not in markers:
            raise MapError(f"{source}: {key}: marker {anchors[key]} is not in the map")
    if len(set(anchors.values())) < 3 and any(k in data for k in anchors):
        raise MapError(f"{source}: origin_id, x_id and y_id must be three different markers")
    ref = data.get("reference_length")
    if ref is not None:
        ref = _within(_num(ref, f"{source}: reference_length", True), MIN_LENGTH,
                      MAX_REFERENCE_LENGTH, f"{source}: reference_length", " m")
    return MarkerMap(markers, dictionary=dictionary, default_length=default_length,
                     reference_length=ref, name=name, source=source, extra={"where": wheres},
                     **anchors)


# ---------------------------------------------------------------------------- saving

def _angles_deg(R: np.ndarray) -> tuple[float, float, float]:
    """Inverse of ``euler_zyx_fixed_deg``: R = Rx(a) Ry(b) Rz(c) -> (a, b, c) degrees."""
    b = math.asin(max(-1.0, min(1.0, R[0, 2])))
    if abs(R[0, 2]) < 1.0 - 1e-9:
        a = math.atan2(-R[1, 2], R[2, 2])
        c = math.atan2(-R[0, 1], R[0, 0])
    else:  # gimbal lock: put everything in c
        a = 0.0
        c = math.atan2(R[1, 0], R[1, 1])
    return tuple(_tidy(math.degrees(v)) for v in (a, b, c))  # type: ignore[return-value]


def _tidy(deg: float) -> float:
    """90.00000000000001 -> 90.0 (for people), other angles kept to full precision."""
    r = round(deg, 6)
    return (r if abs(deg - r) < 1e-9 else deg) + 0.0  # + 0.0 turns -0.0 into 0.0


def map_to_dict(m: MarkerMap) -> dict:
    """The TOML document of a map (angles in degrees: the file is meant for people)."""
    doc: dict = {
        "name": m.name,
        "dictionary": m.dictionary,
        "default_length": float(m.default_length),
        "origin_id": int(m.origin_id),
        "x_id": int(m.x_id),
        "y_id": int(m.y_id),
    }
    if m.reference_length is not None:
        doc["reference_length"] = float(m.reference_length)
    rows = []
    for mid in m.ids:
        mk = m.markers[mid]
        rx, ry, rz = _angles_deg(mk.rotation)
        row = {"id": int(mid), "x": float(mk.position[0]), "y": float(mk.position[1]),
               "z": float(mk.position[2])}
        if (rx, ry, rz) != (0.0, 0.0, 0.0):
            row.update(rx_deg=rx, ry_deg=ry, rz_deg=rz)
        row["length"] = float(mk.length)
        rows.append(row)
    doc["markers"] = rows
    return doc


def map_digest(m: MarkerMap) -> str:
    """A short digest (16 hex digits) of what the poses depend on: dictionary, marker ids,
    poses and sizes, the axes' markers; not the map's name or file. Two cameras estimate in
    the same world frame only if their maps' digests agree (the fusion node checks)."""
    import hashlib
    import json

    doc = map_to_dict(m)
    doc.pop("name", None)
    text = json.dumps(doc, sort_keys=True, separators=(",", ":"), allow_nan=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def dumps_map_toml(m: MarkerMap) -> str:
    """The TOML text of ``m`` (``tomli_w`` on :func:`map_to_dict`, under a units comment)."""
    doc = map_to_dict(m)
    for k, v in [*doc.items(), *((k, v) for row in doc["markers"] for k, v in row.items())]:
        if isinstance(v, float) and not math.isfinite(v):
            raise MapError(f"cannot write non-finite value {v!r} ({k})")
    head = ("# KMEA marker map: metres; rotations in degrees, fixed frame Z then Y then X\n"
            "# (R = Rx @ Ry @ Rz, marker2world). See docs/maps.md.\n")
    return head + tomli_w.dumps(doc)


def save_map_toml(m: MarkerMap, path: str | Path) -> None:
    """Write ``m`` as TOML (round-trips through :func:`load_map`)."""
    path = Path(path)
    try:
        path.write_text(dumps_map_toml(m), encoding="utf-8")
    except OSError as e:
        raise MapError(f"{path}: cannot write: {e.strerror or e}") from None


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
        for mk in load_csv_markers(Path(wall_csv), 0.04).values():
            _add(markers, mk, str(wall_csv))
    return MarkerMap(markers, dictionary=DEFAULT_DICTIONARY, default_length=0.06, origin_id=13,
                     x_id=16, y_id=4, reference_length=2.081, name="RobotAtFactory 4.0",
                     source="<built-in RobotAtFactory 4.0>")
