"""Marker maps: the built-in default against the shared tables, TOML and CSV, bad files."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest

from kmea.cli import main as kmea_main
from kmea.maps.files import (
    MapError,
    Marker,
    MarkerMap,
    check_map,
    default_map,
    dumps_map_toml,
    load_map,
    save_map_toml,
)


def R_xyz_deg(rx: float, ry: float, rz: float) -> np.ndarray:
    """Independent R = Rx @ Ry @ Rz (degrees), written out for the test."""
    a, b, c = (math.radians(v) for v in (rx, ry, rz))
    Rx = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    Ry = np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
    Rz = np.array([[math.cos(c), -math.sin(c), 0], [math.sin(c), math.cos(c), 0], [0, 0, 1]])
    return Rx @ Ry @ Rz


# ------------------------------------------------------------------- default map

def test_default_map_equals_the_shared_tables(shared_dir: Path) -> None:
    m = default_map()
    rows = {}
    for name, length in (("floor_markers.csv", 0.06), ("wall_markers.csv", 0.04)):
        with open(shared_dir / "raf4" / name, newline="") as f:
            for r in csv.DictReader(f):
                rows[int(r["id"])] = (r, length)
    assert sorted(rows) == m.ids
    assert len(m) == 49
    for mid, (r, length) in rows.items():
        mk = m[mid]
        assert mk.position.tolist() == [float(r["x"]), float(r["y"]), float(r["z"])]
        assert mk.length == length
        R = R_xyz_deg(*(float(r.get(k, 0) or 0) for k in ("rx_deg", "ry_deg", "rz_deg")))
        assert np.allclose(mk.rotation, R, rtol=0, atol=1e-15)
    floor = [i for i in m.ids if m[i].on_floor]
    assert floor == [*range(27), 30, 31, 32, 33, 34, 35]
    assert (m.dictionary, m.origin_id, m.x_id, m.y_id) == ("DICT_5X5_100", 13, 16, 4)
    assert m.reference_length == 2.081 and m.ref_length() == 2.081
    assert m[13].position.tolist() == [0, 0, 0]
    assert m[16].position.tolist() == [0.695, 0, 0]
    assert m[4].position.tolist() == [0, 0.355, 0]
    assert check_map(m) == []


def test_default_wall_markers_face_into_the_field() -> None:
    m = default_map()
    # 50 (rx = 90) on the top wall y = 0.565: normal Rx(90) e_z = (0, -1, 0), x axis stays +x.
    assert np.allclose(m[50].normal, [0, -1, 0], atol=1e-15)
    assert np.allclose(m[50].rotation[:, 0], [1, 0, 0], atol=1e-15)
    # 62 (rx = -90, rz = 180) on the bottom wall: normal Rx(-90) e_z = (0, 1, 0), x axis -x.
    assert np.allclose(m[62].normal, [0, 1, 0], atol=1e-15)
    assert np.allclose(m[62].rotation[:, 0], [-1, 0, 0], atol=1e-15)
    # 54 (ry = -90, rz = -90) and 55 (ry = 90, rz = 90): back to back on the wall x = 0.348,
    # facing -x and +x, both upright (their y axis is world +z).
    assert np.allclose(m[54].normal, [-1, 0, 0], atol=1e-15)
    assert np.allclose(m[55].normal, [1, 0, 0], atol=1e-15)
    for i in (50, 54, 55, 62):
        assert np.allclose(m[i].rotation[:, 1], [0, 0, 1], atol=1e-15)
        assert not m[i].on_floor
    # 55's x axis is Ry(90) Rz(90) e_x = +y: a viewer at +x looking at it has +y on the
    # right, so its top-left corner (OpenCV order) is at -y, +z from the centre.
    assert np.allclose(m[55].rotation[:, 0], [0, 1, 0], atol=1e-15)
    tl = m[55].corners_world()[0]
    assert np.allclose(tl - m[55].position, [0, -0.02, 0.02], atol=1e-15)


# --------------------------------------------------------------------- TOML

def assert_same_map(a: MarkerMap, b: MarkerMap) -> None:
    assert a.ids == b.ids
    for i in a.ids:
        assert a[i].position.tolist() == b[i].position.tolist()
        assert np.allclose(a[i].rotation, b[i].rotation, rtol=0, atol=1e-12)
        assert a[i].length == b[i].length
    for k in ("dictionary", "default_length", "origin_id", "x_id", "y_id", "reference_length",
              "name"):
        assert getattr(a, k) == getattr(b, k), k


def test_toml_round_trip_of_the_default_map(tmp_path: Path) -> None:
    m = default_map()
    p = tmp_path / "raf4.toml"
    save_map_toml(m, p)
    back = load_map(p)
    assert_same_map(m, back)
    assert back.source == str(p)
    text = p.read_text()
    assert "rx_deg = 90.0" in text  # marker 50, written in degrees for people


def test_toml_round_trip_of_random_rotations_and_awkward_names(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    markers = {}
    for i in range(40):
        angles = rng.uniform(-180, 180, 3)
        if i % 5 == 0:
            angles[1] = rng.choice([-90.0, 90.0])  # gimbal lock
        markers[i] = Marker(i, rng.uniform(-3, 3, 3), R_xyz_deg(*angles),
                            float(rng.uniform(0.01, 0.2)))
    m = MarkerMap(markers, dictionary="DICT_4X4_50", default_length=0.05, origin_id=0,
                  x_id=1, y_id=2, reference_length=None,
                  name='quote " back\\slash tab\t newline\n é ∑ \x7f')
    p = tmp_path / "r.toml"
    save_map_toml(m, p)
    back = load_map(p)
    assert_same_map(m, back)
    assert back.reference_length is None
    assert back.ref_length() == pytest.approx(m.ref_length())


def test_toml_map_with_defaults(tmp_path: Path) -> None:
    p = tmp_path / "small.toml"
    p.write_text("""
dictionary = "DICT_4X4_50"
default_length = 0.1

[[markers]]
id = 13
x = 0
y = 0
z = 0

[[markers]]
id = 16
x = 1.5
y = 0.0
z = 0.0
rz_deg = 90
length = 0.2

[[markers]]
id = 4
x = 0.0
y = 1.0
z = 0.0
""")
    m = load_map(p)
    assert m.ids == [4, 13, 16] and m.name == "small"
    assert m[13].length == 0.1 and m[16].length == 0.2
    assert np.allclose(m[16].rotation, R_xyz_deg(0, 0, 90), atol=1e-15)
    assert (m.origin_id, m.x_id, m.y_id) == (13, 16, 4)
    assert m.reference_length is None
    assert m.ref_length() == pytest.approx(math.hypot(1.5, 1.0))


# ---------------------------------------------------------------------- CSV

def test_csv_with_only_the_required_columns(tmp_path: Path) -> None:
    p = tmp_path / "plain.csv"
    p.write_text("id,x,y,z\n13,0,0,0\n\n16,0.5,0,0\n4,0,0.25,0\n")
    m = load_map(p, dictionary="DICT_6X6_250", default_length=0.08)
    assert m.ids == [4, 13, 16]
    assert m.dictionary == "DICT_6X6_250" and m.default_length == 0.08
    assert all(m[i].length == 0.08 for i in m.ids)
    assert all(np.array_equal(m[i].rotation, np.eye(3)) for i in m.ids)
    assert m[16].position.tolist() == [0.5, 0, 0]
    assert m.name == "plain" and m.ref_length() == pytest.approx(math.hypot(0.5, 0.25))


def test_csv_with_the_optional_columns_in_any_order(tmp_path: Path) -> None:
    p = tmp_path / "full.csv"
    # A BOM, spaces, reordered columns and empty optional cells (= defaults).
    p.write_text("\ufeffx, id ,y,z,length,rz_deg,ry_deg,rx_deg\n"
                 "0.1,1,0.2,0.3,0.05,30,0,90\n"
                 "0.4,2,0.5,0.6,,,,\n", encoding="utf-8")
    m = load_map(p, default_length=0.07)
    assert np.allclose(m[1].rotation, R_xyz_deg(90, 0, 30), atol=1e-15)
    assert m[1].length == 0.05 and m[1].position.tolist() == [0.1, 0.2, 0.3]
    assert np.array_equal(m[2].rotation, np.eye(3)) and m[2].length == 0.07


def test_shared_wall_table_loads_as_csv(shared_dir: Path) -> None:
    m = load_map(shared_dir / "raf4" / "wall_markers.csv", dictionary="DICT_5X5_100",
                 default_length=0.04)
    assert len(m) == 16
    assert np.allclose(m[54].rotation, default_map()[54].rotation, atol=0)
    # The anchors are on the floor table, so check_map says LMEA cannot run on this map.
    assert any("origin_id 13 is not in the map" in w for w in check_map(m))


# ---------------------------------------------------------------- bad files

BAD_CSV = [
    ("id,x,y,z,colour\n1,0,0,0,red\n", "line 1: unknown column(s) ['colour']"),
    ("id,x,y\n1,0,0\n", "line 1: missing column 'z'"),
    ("id,x,y,z,x\n1,0,0,0,0\n", "line 1: duplicate column(s) ['x']"),
    ("id,x,y,z\n1,0,0,0\n2,1,0,0\n1,2,0,0\n", "line 4: duplicate marker id 1"),
    ("id,x,y,z\n1,0,0,0\n2,abc,0,0\n", "line 3: x: expected a number, got 'abc'"),
    ("id,x,y,z\n1,0,nan,0\n", "line 2: y: value must be finite, got 'nan'"),
    ("id,x,y,z\n1,0,0,inf\n", "line 2: z: value must be finite, got 'inf'"),
    ("id,x,y,z,length\n1,0,0,0,0\n", "line 2: length: 0 m is outside [0.0001, 10] m"),
    ("id,x,y,z,length\n1,0,0,0,-0.1\n", "line 2: length: -0.1 m is outside [0.0001, 10] m"),
    ("id,x,y,z\n1.5,0,0,0\n", "line 2: id: expected a non-negative integer id, got '1.5'"),
    ("id,x,y,z\n-1,0,0,0\n", "line 2: id: expected a non-negative integer id, got '-1'"),
    ("id,x,y,z\n1,0,0,0,9\n", "line 2: more values than columns"),
    ("id,x,y,z\n1,0,0\n", "line 2: z: missing value"),
    ("id,x,y,z\n", "no markers"),
    # Physical bounds (issue 30: each was accepted and warned on every frame, or never
    # estimated): positions within 10 km, one turn of angle, ids a dictionary can have.
    ("id,x,y,z\n1,1e308,0,0\n", "line 2: x: 1e+308 m is outside [-10000, 10000] m "
                                 "(positions are metres from the venue's origin)"),
    ("id,x,y,z\n1,0,0.355e200,0\n", "line 2: y: 3.55e+199 m is outside [-10000, 10000] m "
                                     "(positions are metres from the venue's origin)"),
    ("id,x,y,z,rx_deg\n1,0,0,0,1e300\n",
     "line 2: rx_deg: 1e+300 degrees is outside [-360, 360] degrees (one turn either way)"),
    ("id,x,y,z\n100000000000000000000,0,0,0\n",
     "line 2: id: 1e+20 is beyond 4095, more markers than any ArUco dictionary has"),
    ("id,x,y,z\n1e20,0,0,0\n",
     "line 2: id: 1e+20 is beyond 4095, more markers than any ArUco dictionary has"),
    ("id,x,y,z,length\n1,0,0,0,1e300\n", "line 2: length: 1e+300 m is outside [0.0001, 10] m"),
    ("id,x,y,z,length\n1,0,0,0,1e-300\n",
     "line 2: length: 1e-300 m is outside [0.0001, 10] m"),
    ("", "line 1: missing column 'id'"),
]


def _assert_one_line_error(path: Path, text: str, message: str) -> None:
    path.write_text(text)
    with pytest.raises(MapError) as ei:
        load_map(path)
    msg = str(ei.value)
    assert msg == f"{path}: {message}"
    assert "\n" not in msg


@pytest.mark.parametrize(("text", "message"), BAD_CSV)
def test_bad_csv_gives_one_line_naming_file_and_line(tmp_path: Path, text: str,
                                                     message: str) -> None:
    _assert_one_line_error(tmp_path / "bad.csv", text, message)


HEAD = "[[markers]]\nid = 1\nx = 0\ny = 0\nz = 0\n"
BAD_TOML = [
    ("colour = 1\n" + HEAD, "unknown key(s) ['colour']"),
    (HEAD + "rz = 5\n", "markers[0] (line 1): unknown key(s) ['rz']"),
    (HEAD + "\n" + HEAD, "markers[1] (line 7): duplicate marker id 1"),
    ("[[markers]]\nid = 1\nx = 0\ny = 0\n", "markers[0] (line 1): missing key 'z'"),
    (HEAD.replace("x = 0", 'x = "0.5"'), "markers[0] (line 1): x: expected a number, got the "
                                         "string '0.5' (a number is written without quotes)"),
    (HEAD.replace("x = 0", "x = true"), "markers[0] (line 1): x: expected a number, got True"),
    (HEAD.replace("x = 0", "x = nan"), "markers[0] (line 1): x: value must be finite, got nan"),
    (HEAD.replace("x = 0", "x = -inf"),
     "markers[0] (line 1): x: value must be finite, got -inf"),
    (HEAD.replace("id = 1", "id = 1.0"),
     "markers[0] (line 1): id: expected an integer id, got 1.0"),
    (HEAD + "length = 0\n", "markers[0] (line 1): length: 0 m is outside [0.0001, 10] m"),
    ("default_length = 0\n" + HEAD, "default_length: 0 m is outside [0.0001, 10] m"),
    ('dictionary = "DICT_5X5_51"\n' + HEAD,
     "dictionary: unknown ArUco dictionary 'DICT_5X5_51' (e.g. DICT_5X5_50, DICT_5X5_100, "
     "DICT_4X4_50; or a .yml/.json dictionary file)"),
    ("origin_id = 7\n" + HEAD, "origin_id: marker 7 is not in the map"),
    ("reference_length = -2\n" + HEAD, "reference_length: -2 m is outside [0.0001, 34641] m"),
    ("name = 3\n" + HEAD, "name must be a string, got 3"),
    ("markers = []\n", "markers: expected a non-empty array of tables [[markers]]"),
    ("x = = 1\n", "invalid TOML: Invalid value (at line 1, column 5)"),
    (HEAD.replace("z = 0", "z = -2e4"), "markers[0] (line 1): z: -20000 m is outside "
     "[-10000, 10000] m (positions are metres from the venue's origin)"),
    (HEAD + "rz_deg = -400.0\n", "markers[0] (line 1): rz_deg: -400 degrees is outside "
     "[-360, 360] degrees (one turn either way)"),
    (HEAD.replace("id = 1", "id = 4096"), "markers[0] (line 1): id: 4096 is beyond 4095, "
     "more markers than any ArUco dictionary has"),
    # An integer of 400 digits once overflowed float() into a traceback.
    (HEAD.replace("id = 1", "id = 1" + "0" * 400),
     "markers[0] (line 1): id: value too large, got <huge int>"),
    (HEAD.replace("x = 0", "x = 1" + "0" * 400),
     "markers[0] (line 1): x: value too large, got <huge int>"),
    ("reference_length = 1e300\n" + HEAD,
     "reference_length: 1e+300 m is outside [0.0001, 34641] m"),
]


@pytest.mark.parametrize(("text", "message"), BAD_TOML)
def test_bad_toml_gives_one_line_naming_file_and_key(tmp_path: Path, text: str,
                                                     message: str) -> None:
    _assert_one_line_error(tmp_path / "bad.toml", text, message)


def test_unreadable_and_unknown_files(tmp_path: Path) -> None:
    with pytest.raises(MapError, match=r"missing\.toml: cannot read: No such file"):
        load_map(tmp_path / "missing.toml")
    (tmp_path / "m.json").write_text("{}")
    with pytest.raises(MapError, match=r"m\.json: unknown map format '\.json'"):
        load_map(tmp_path / "m.json")
    (tmp_path / "bin.csv").write_bytes(b"id,x,y,z\n\xff\xfe\x00\n")
    with pytest.raises(MapError, match=r"bin\.csv: not a UTF-8 text file"):
        load_map(tmp_path / "bin.csv")
    (tmp_path / "ok.csv").write_text("id,x,y,z\n1,0,0,0\n")
    with pytest.raises(MapError, match=r"ok\.csv: dictionary: unknown ArUco dictionary"):
        load_map(tmp_path / "ok.csv", dictionary="DICT_NOPE")


def test_marker_validation() -> None:
    with pytest.raises(MapError, match="marker 3: rotation must be a proper"):
        Marker(3, np.zeros(3), np.diag([1.0, 1.0, -1.0]), 0.06)
    with pytest.raises(MapError, match="marker 3: position must be 3 finite"):
        Marker(3, [0.0, np.nan, 0.0], np.eye(3), 0.06)
    with pytest.raises(MapError, match=r"marker 3: length must be 0\.0001-10 m"):
        Marker(3, [0.0, 0.0, 0.0], np.eye(3), 0.0)
    # The model holds the bounds too: maps from recordings and the survey pass no file.
    with pytest.raises(MapError, match=r"marker 3: position \[0.0, 1e\+200, 0.0\] m is beyond"):
        Marker(3, [0.0, 1e200, 0.0], np.eye(3), 0.06)
    with pytest.raises(MapError, match="marker id must be an integer 0-4095, got 4096"):
        Marker(4096, [0.0, 0.0, 0.0], np.eye(3), 0.06)
    mk = Marker(3, [0, 0, 1], np.eye(3).tolist(), 0.06)
    assert mk.position.dtype == float and mk.position.tolist() == [0, 0, 1]
    with pytest.raises(ValueError, match="read-only"):
        mk.position[0] = 5.0  # a surveyed pose is never edited in place


def test_check_map_warnings() -> None:
    markers = {i: Marker(i, [0.1 * i, 0.0, 0.0], np.eye(3), 0.06) for i in (13, 16, 60)}
    markers[61] = Marker(61, [3.0 + 0.01, 0.0, 0.0], np.eye(3), 0.06)
    markers[62] = Marker(62, [3.0, 0.0, 0.0], np.eye(3), 0.06)
    # 63 sits 1 cm from 62 but faces the other way (back to back): no overlap.
    markers[63] = Marker(63, [3.0, 0.01, 0.0], np.diag([1.0, -1.0, -1.0]), 0.06)
    w = check_map(MarkerMap(markers, dictionary="DICT_5X5_50"))
    assert w == ["y_id 4 is not in the map (LMEA cannot run)",
                 "DICT_5X5_50 has ids 0-49; ids [60, 61, 62, 63] can never be detected",
                 "markers 61 and 62 overlap (centres 0.0100 m apart)"]


def test_dumps_starts_with_the_units_comment() -> None:
    text = dumps_map_toml(default_map())
    assert text.startswith("# KMEA marker map: metres; rotations in degrees")


# ---------------------------------------------------------------------- CLI

def test_map_cli_show_check_convert(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    assert kmea_main(["map"]) == 0
    out = capsys.readouterr().out
    assert "RobotAtFactory 4.0" in out and "anchors    origin 13, +X 16, +Y 4" in out
    assert "  50  -0.6950   0.5650   0.1000    90.00     0.00     0.00  0.040" in out

    src = tmp_path / "floor.csv"
    src.write_text("id,x,y,z\n13,0,0,0\n16,0.7,0,0\n4,0,0.35,0\n")
    assert kmea_main(["map", "check", str(src)]) == 0
    # The same dictionary as `map show`, `print` and kmead (kmea.maps.model.DEFAULT_DICTIONARY).
    assert "OK, 3 markers, DICT_5X5_100" in capsys.readouterr().out

    out_toml = tmp_path / "floor.toml"
    assert kmea_main(["map", "convert", str(src), "--dictionary", "DICT_4X4_50",
                      "--length", "0.05", "--reference-length", "2.0"]) == 0
    assert f"wrote {out_toml}: 3 markers" in capsys.readouterr().out
    back = load_map(out_toml)
    assert back.dictionary == "DICT_4X4_50" and back.reference_length == 2.0
    assert back[16].length == 0.05 and back[16].position.tolist() == [0.7, 0, 0]
    # No silent overwrite.
    assert kmea_main(["map", "convert", str(src)]) == 1
    assert "exists (use --force" in capsys.readouterr().err

    bad = tmp_path / "bad.csv"
    bad.write_text("id,x,y,z\n1,0,0,zero\n")
    assert kmea_main(["map", "check", str(bad)]) == 1
    assert capsys.readouterr().err.strip() == \
        f"kmea map: {bad}: line 2: z: expected a number, got 'zero'"


def test_map_accepts_every_dictionary_the_config_accepts(tmp_path: Path) -> None:
    """One dictionary table: a predefined name in any spelling the detector takes, or a
    custom dictionary file next to the map (what ``detector.dictionary`` accepts)."""
    import cv2

    from kmea.vision.dictionary import get_dictionary

    custom = cv2.aruco.extendDictionary(12, 5, cv2.aruco.getPredefinedDictionary(
        cv2.aruco.DICT_5X5_50), 3)
    fs = cv2.FileStorage(str(tmp_path / "floor_dict.yml"), cv2.FILE_STORAGE_WRITE)
    custom.writeDictionary(fs)
    fs.release()
    body = "\n[[markers]]\nid = 1\nx = 0\ny = 0\nz = 0\n"
    (tmp_path / "custom.toml").write_text('dictionary = "floor_dict.yml"\n' + body)
    m = load_map(tmp_path / "custom.toml")
    assert Path(m.dictionary) == tmp_path / "floor_dict.yml"
    assert np.array_equal(get_dictionary(m.dictionary).bytesList, custom.bytesList)
    assert check_map(m) == ["origin_id 13 is not in the map (LMEA cannot run)",
                            "x_id 16 is not in the map (LMEA cannot run)",
                            "y_id 4 is not in the map (LMEA cannot run)"]
    (tmp_path / "lower.toml").write_text('dictionary = "5x5_100"\n' + body)
    assert load_map(tmp_path / "lower.toml").dictionary == "DICT_5X5_100"
    # A saved map writes the canonical name and loads back the same.
    save_map_toml(load_map(tmp_path / "lower.toml"), tmp_path / "again.toml")
    assert 'dictionary = "DICT_5X5_100"' in (tmp_path / "again.toml").read_text()


def _raf_rows() -> list[str]:
    from importlib import resources

    text = resources.files("kmea").joinpath("data/raf4_floor_markers.csv").read_text()
    return text.strip().splitlines()


def test_a_map_in_millimetres_is_named_at_check(tmp_path: Path, capsys) -> None:
    rows = _raf_rows()
    head = rows[0].split(",")
    mm = [rows[0]]
    for r in rows[1:]:
        v = dict(zip(head, r.split(","), strict=True))
        for k in ("x", "y", "z"):
            v[k] = str(float(v[k]) * 1000)
        mm.append(",".join(v[k] for k in head))
    p = tmp_path / "mm.csv"
    p.write_text("\n".join(mm) + "\n")
    assert kmea_main(["map", "check", str(p)]) == 0
    out = capsys.readouterr().out
    assert "are these millimetres?" in out and "metres" in out
    # The same map in metres says nothing of the kind.
    q = tmp_path / "m.csv"
    q.write_text("\n".join(rows) + "\n")
    assert kmea_main(["map", "check", str(q)]) == 0
    assert "are these millimetres" not in capsys.readouterr().out


def test_a_line_far_from_all_others_is_named_by_its_line(tmp_path: Path, capsys) -> None:
    rows = _raf_rows()
    head = rows[0].split(",")
    slip = dict.fromkeys(head, "0")
    slip.update(id="45", x="227", y="150")
    rows.append(",".join(slip[k] for k in head))
    p = tmp_path / "slip.csv"
    p.write_text("\n".join(rows) + "\n")
    assert kmea_main(["map", "check", str(p)]) == 0
    out = capsys.readouterr().out
    assert f"line {len(rows)}: marker 45 at (227, 150, 0) m" in out
    assert "are these millimetres" not in out  # the rest of the map is in metres


def test_markers_all_at_one_point_are_refused(tmp_path: Path, capsys) -> None:
    p = tmp_path / "zero.csv"
    p.write_text("id,x,y,z\n" + "".join(f"{i},0,0,0\n" for i in range(20)))
    assert kmea_main(["map", "check", str(p)]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "span 0 m" in err and str(p) in err
