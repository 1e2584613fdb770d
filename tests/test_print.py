"""Printable markers, floor and ChArUco boards: pixel sizes for the DPI, PNG/PDF files that
state their size, and markers that OpenCV decodes where the map says they are."""

from __future__ import annotations

import re
import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from kmea.cli import main
from kmea.geometry import rot_z
from kmea.maps.files import Marker, MarkerMap, default_map
from kmea.vision.printing import (
    charuco_page,
    floor_page,
    label_box,
    marker_page,
    px,
    save_printable,
)


def _detect(img: np.ndarray, dict_name: str) -> dict[int, np.ndarray]:
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dict_name))
    corners, ids, _ = cv2.aruco.ArucoDetector(d, cv2.aruco.DetectorParameters()).detectMarkers(img)
    return {} if ids is None else {int(i): c.reshape(4, 2) for i, c in zip(ids.ravel(), corners,
                                                                           strict=True)}


def _png_ppm(data: bytes) -> tuple[int, int, int]:
    pos = 8
    while pos < len(data):
        (n,) = struct.unpack(">I", data[pos:pos + 4])
        kind = data[pos + 4:pos + 8]
        body = data[pos + 8:pos + 8 + n]
        (crc,) = struct.unpack(">I", data[pos + 8 + n:pos + 12 + n])
        assert crc == zlib.crc32(kind + body) & 0xFFFFFFFF, kind
        if kind == b"pHYs":
            return struct.unpack(">IIB", body)
        assert kind != b"IDAT", "pHYs must come before the image data"
        pos += 12 + n
    raise AssertionError("no pHYs chunk")


def _pdf_page(data: bytes) -> tuple[tuple[float, float], np.ndarray]:
    """Check the xref offsets and return (MediaBox size in points, the decoded image)."""
    assert data.startswith(b"%PDF-1.") and data.rstrip().endswith(b"%%EOF")
    start = int(re.search(rb"startxref\s+(\d+)", data).group(1))
    assert data[start:start + 4] == b"xref"
    count = int(re.match(rb"xref\s+0 (\d+)", data[start:]).group(1))
    entries = re.findall(rb"(\d{10}) 00000 n ", data[start:])
    assert len(entries) == count - 1
    for i, off in enumerate(entries, 1):
        assert data[int(off):].startswith(f"{i} 0 obj".encode()), i
    box = re.search(rb"/MediaBox \[0 0 ([\d.]+) ([\d.]+)\]", data)
    w = int(re.search(rb"/Width (\d+)", data).group(1))
    h = int(re.search(rb"/Height (\d+)", data).group(1))
    n = int(re.search(rb"/Subtype /Image .*?/Length (\d+)", data, re.S).group(1))
    s = data.index(b"stream\n", data.index(b"/Subtype /Image")) + 7
    img = np.frombuffer(zlib.decompress(data[s:s + n]), np.uint8).reshape(h, w)
    return (float(box.group(1)), float(box.group(2))), img


def test_marker_png_size_dpi_and_decoding(tmp_path: Path) -> None:
    page = marker_page(13, "DICT_5X5_100", size_mm=60, dpi=200, margin_mm=12)
    side, margin = px(60, 200), px(12, 200)
    assert side == 472 and page.image.shape == (side + 2 * margin, side + 2 * margin)
    path = save_printable(page, tmp_path / "m.png")
    data = path.read_bytes()
    assert _png_ppm(data) == (7874, 7874, 1)  # 200 dpi in pixels per metre
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    np.testing.assert_array_equal(img, page.image)
    found = _detect(img, "DICT_5X5_100")
    assert list(found) == [13]
    c = found[13]
    assert np.linalg.norm(c[1] - c[0]) == pytest.approx(side, abs=2)
    assert c[0] == pytest.approx([margin - 0.5, margin - 0.5], abs=1.5)  # upright: TL first


def test_marker_pdf_prints_at_size(tmp_path: Path) -> None:
    page = marker_page(7, "DICT_4X4_50", size_mm=50, dpi=150, margin_mm=10)
    path = save_printable(page, tmp_path / "m.pdf")
    (wpt, hpt), img = _pdf_page(path.read_bytes())
    side_mm = (px(50, 150) + 2 * px(10, 150)) / 150 * 25.4
    assert wpt == pytest.approx(side_mm / 25.4 * 72, abs=0.01) == hpt
    assert wpt == pytest.approx(70 / 25.4 * 72, abs=0.5)  # 50 + 2 x 10 mm
    np.testing.assert_array_equal(img, page.image)
    assert list(_detect(img, "DICT_4X4_50")) == [7]


def _world_of(pxy: np.ndarray, page_w: int, page_h: int, dpi: float) -> np.ndarray:
    """Page pixel (centre convention) -> world metres for a canvas centred on the origin."""
    pitch = 0.0254 / dpi
    return np.stack([(pxy[:, 0] + 0.5) * pitch - page_w * pitch / 2,
                     page_h * pitch / 2 - (pxy[:, 1] + 0.5) * pitch], axis=1)


def test_floor_is_one_to_one_with_markers_at_map_positions() -> None:
    dpi = 40.0
    mp = default_map()
    page = floor_page(mp, dpi=dpi)
    assert page.image.shape == (px(1200, dpi), px(1700, dpi))
    found = _detect(page.image, "DICT_5X5_100")
    floor = {m.id for m in mp.markers.values() if m.on_floor}
    assert set(found) == floor and len(floor) == 33  # floor markers only, all decoded
    h, w = page.image.shape
    for mid, c in found.items():
        # The floor markers' extent is symmetric about marker 13, so the canvas is centred on it.
        world = _world_of(c, w, h, dpi)
        expect = mp[mid].corners_world()[:, :2]
        assert np.abs(world - expect).max() < 1.5 * 0.0254 / dpi, mid  # corners, in order


def test_floor_prints_each_markers_id_under_it() -> None:
    dpi = 60.0
    mp = default_map()
    page = floor_page(mp, dpi=dpi)
    found = _detect(page.image, "DICT_5X5_100")
    side = 0.06 / (0.0254 / dpi)
    for mid, c in found.items():
        x0, y0, x1, y1 = label_box(c, side)
        ink = page.image[y0:y1 + 1, x0:x1 + 1] < 128
        assert ink.sum() > 5, mid  # the id's strokes
        # Wider ids print wider: two-digit labels reach further from the centre.
        cols = np.nonzero(ink.any(axis=0))[0]
        assert (cols.max() - cols.min() > 0.8 * (y1 - y0)) == (mid >= 10), mid


def test_floor_draws_yawed_markers_turned(tmp_path: Path) -> None:
    markers = {}
    for i, (x, y, yaw) in enumerate([(-0.3, 0.1, 0.0), (0.0, -0.1, np.pi / 6),
                                     (0.3, 0.1, np.pi / 2), (0.15, 0.2, -2.5)]):
        markers[i] = Marker(i, np.array([x, y, 0.0]), rot_z(yaw), 0.08)
    mp = MarkerMap(markers, dictionary="DICT_4X4_50", name="yawed")
    page = floor_page(mp, dpi=60, canvas_m=(0.8, 0.6))
    found = _detect(page.image, "DICT_4X4_50")
    assert set(found) == set(markers)
    h, w = page.image.shape
    # centre of this canvas: the middle of the markers' corner extent
    allc = np.vstack([m.corners_world() for m in markers.values()])
    centre = (allc[:, :2].min(axis=0) + allc[:, :2].max(axis=0)) / 2
    for mid, c in found.items():
        world = _world_of(c, w, h, 60) + centre
        assert np.abs(world - markers[mid].corners_world()[:, :2]).max() < 0.0015, mid


def test_charuco_board_detected_fully(tmp_path: Path) -> None:
    page = charuco_page(5, 4, square_mm=30, marker_mm=22, dict_name="DICT_5X5_100", dpi=150)
    margin = px(15, 150)
    assert page.image.shape == (px(120, 150) + 2 * margin, px(150, 150) + 2 * margin)
    board = cv2.aruco.CharucoBoard((5, 4), 0.03, 0.022,
                                   cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_5X5_100))
    ch_corners, ch_ids, _, _ = cv2.aruco.CharucoDetector(board).detectBoard(page.image)
    assert ch_ids is not None and sorted(ch_ids.ravel().tolist()) == list(range(12))
    # corner 0 is one square in from the board's top-left corner
    i0 = int(np.where(ch_ids.ravel() == 0)[0][0])
    q = px(30, 150)
    assert ch_corners[i0].ravel() == pytest.approx([margin + q - 0.5, margin + q - 0.5], abs=1.0)


def test_print_cli(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "m.png"
    assert main(["print", "marker", "21", "--dict", "DICT_5X5_50", "--dpi", "100",
                 "--out", str(out)]) == 0
    assert "print at 100 %" in capsys.readouterr().out
    assert list(_detect(cv2.imread(str(out), cv2.IMREAD_GRAYSCALE), "DICT_5X5_50")) == [21]
    assert main(["print", "charuco", "4x3", "--dpi", "100", "--out",
                 str(tmp_path / "c.pdf")]) == 0
    (wpt, _), _img = _pdf_page((tmp_path / "c.pdf").read_bytes())
    assert wpt == pytest.approx((px(120, 100) + 2 * px(15, 100)) / 100 * 72, abs=0.01)
    capsys.readouterr()
    assert main(["print", "marker", "60", "--dict", "DICT_5X5_50", "--out",
                 str(tmp_path / "x.png")]) == 2
    assert "not in DICT_5X5_50" in capsys.readouterr().err
    assert main(["print", "charuco", "7by5", "--out", str(tmp_path / "x.png")]) == 2
    assert main(["print", "marker", "1", "--out", str(tmp_path / "x.jpg")]) == 2
    assert "use .png or .pdf" in capsys.readouterr().err


def test_print_marker_at_its_map_size(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """A wall marker of the built-in map is 40 mm, a floor marker 60 mm; --size-mm wins."""
    for mid, side in ((60, 40.0), (13, 60.0), (99, 60.0)):
        out = tmp_path / f"m{mid}.pdf"
        assert main(["print", "marker", str(mid), "--dpi", "100", "--out", str(out)]) == 0
        text = capsys.readouterr().out
        assert f"id {mid}, {side:g} mm" in text
        assert ("not in the map" in text) == (mid == 99)
    assert main(["print", "marker", "60", "--size-mm", "50", "--dpi", "100", "--out",
                 str(tmp_path / "x.pdf")]) == 0
    assert "id 60, 50 mm" in capsys.readouterr().out
