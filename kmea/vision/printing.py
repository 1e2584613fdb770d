"""Printable images: single ArUco markers, the whole floor of a map at 1:1, ChArUco boards.

Every image is greyscale uint8 at a given DPI, with its physical size written in the margin.
:func:`save_printable` writes PNG (DPI stored in the ``pHYs`` chunk) or a one-page PDF whose
page size in points makes it print 1:1 (both written here with zlib; no extra dependency).
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from kmea.maps.files import MarkerMap

__all__ = ["Printable", "charuco_page", "floor_page", "marker_page", "px", "save_printable"]

MM_PER_INCH = 25.4


def px(mm: float, dpi: float) -> int:
    """Millimetres to whole pixels at ``dpi``."""
    return round(mm / MM_PER_INCH * dpi)


@dataclass
class Printable:
    """image: (H, W) uint8, white paper = 255. dpi: pixels per inch. title: one line."""

    image: np.ndarray
    dpi: float
    title: str

    @property
    def size_mm(self) -> tuple[float, float]:
        h, w = self.image.shape[:2]
        return w / self.dpi * MM_PER_INCH, h / self.dpi * MM_PER_INCH


def dictionary(name: str) -> cv2.aruco.Dictionary:
    """A predefined dictionary by name, or a custom dictionary file (via kmea.vision.dictionary
    when present)."""
    try:
        from kmea.vision.dictionary import get_dictionary
    except ImportError:  # pragma: no cover - the detection module is part of the package
        from kmea.vision.calibration import aruco_dictionary as get_dictionary
    return get_dictionary(name)


def _text_lines(img: np.ndarray, lines: list[str], x0: int, y0: int, width: int,
                height_px: int) -> None:
    """Black text lines from (x0, y0) (top-left), shrunk to fit ``width`` pixels."""
    font = cv2.FONT_HERSHEY_SIMPLEX
    (_, h1), _ = cv2.getTextSize("Hg", font, 1.0, 1)
    y = y0
    for line in lines:
        scale = height_px / h1
        (tw, _), _ = cv2.getTextSize(line, font, scale, 1)
        if tw > width > 0:
            scale *= width / tw
        thick = max(1, round(scale * 1.6))
        (tw, th), base = cv2.getTextSize(line, font, scale, thick)
        y += th
        cv2.putText(img, line, (x0, y), font, scale, 0, thick, cv2.LINE_AA)
        y += base + max(2, th // 3)


def label_box(corners_px: np.ndarray, side_px: float) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1) pixels of a marker's id label: centred under the marker (page
    down), a quarter of its side high, a fifth of its side below (clear of the quiet
    zone the detector needs)."""
    cx = float(corners_px[:, 0].mean())
    y_top = float(corners_px[:, 1].max()) + 0.2 * side_px
    h = max(6.0, 0.25 * side_px)
    return round(cx - 1.5 * h), round(y_top), round(cx + 1.5 * h), round(y_top + h)


def _id_label(img: np.ndarray, marker_id: int, corners_px: np.ndarray, side_px: float) -> None:
    """The marker id in black under the marker (the printed floor names its markers)."""
    font = cv2.FONT_HERSHEY_SIMPLEX
    x0, y0, x1, y1 = label_box(corners_px, side_px)
    text = str(marker_id)
    (_, h1), _ = cv2.getTextSize("0", font, 1.0, 1)
    scale = (y1 - y0) / h1
    thick = max(1, round(scale * 1.6))
    (tw, _), _ = cv2.getTextSize(text, font, scale, thick)
    org = (round((x0 + x1) / 2 - tw / 2), y1)
    cv2.putText(img, text, org, font, scale, 0, thick, cv2.LINE_AA)


def _check_dpi(dpi: float) -> float:
    if not (dpi >= 30 and dpi <= 2400):
        raise ValueError(f"dpi must be between 30 and 2400, got {dpi}")
    return float(dpi)


def marker_page(marker_id: int, dict_name: str = "DICT_5X5_100", size_mm: float = 60.0,
                dpi: float = 300.0, margin_mm: float = 12.0) -> Printable:
    """One marker, black square ``size_mm`` wide, in a white margin with its id, dictionary
    and size written below it."""
    dpi = _check_dpi(dpi)
    if size_mm <= 0 or margin_mm < 5:
        raise ValueError("size_mm must be > 0 and margin_mm >= 5")
    d = dictionary(dict_name)
    n = d.bytesList.shape[0]
    if not 0 <= marker_id < n:
        raise ValueError(f"marker id {marker_id} is not in {dict_name} (ids 0-{n - 1})")
    side = px(size_mm, dpi)
    if side < d.markerSize + 2:
        raise ValueError(f"{size_mm} mm at {dpi:g} dpi is {side} px, too small for a "
                         f"{d.markerSize}x{d.markerSize} marker")
    margin = px(margin_mm, dpi)
    marker = cv2.aruco.generateImageMarker(d, int(marker_id), side, borderBits=1)
    img = np.full((side + 2 * margin, side + 2 * margin), 255, np.uint8)
    img[margin:margin + side, margin:margin + side] = marker
    title = f"ArUco {dict_name} id {marker_id}"
    _text_lines(img, [title, f"black square {size_mm:g} mm, {dpi:g} dpi: print at 100 %"],
                margin // 2, margin + side + margin // 6, img.shape[1] - margin,
                px(min(3.0, margin_mm / 4.5), dpi))
    return Printable(img, dpi, f"{title}, {size_mm:g} mm")


def _paste_warped(canvas: np.ndarray, src: np.ndarray, dst_corners: np.ndarray) -> None:
    """Draw ``src`` (S, S) so its outer corners TL, TR, BR, BL land on ``dst_corners`` (4, 2)
    (pixel-centre coordinates of the corner *edges*)."""
    s = src.shape[0]
    src_c = np.array([[-0.5, -0.5], [s - 0.5, -0.5], [s - 0.5, s - 0.5], [-0.5, s - 0.5]],
                     np.float32)
    x0 = int(np.floor(dst_corners[:, 0].min())) - 1
    y0 = int(np.floor(dst_corners[:, 1].min())) - 1
    x1 = int(np.ceil(dst_corners[:, 0].max())) + 2
    y1 = int(np.ceil(dst_corners[:, 1].max())) + 2
    H, W = canvas.shape
    if x0 < 0 or y0 < 0 or x1 > W or y1 > H:
        raise ValueError("marker outside the canvas")
    H_ = cv2.getPerspectiveTransform(src_c, (dst_corners - [x0, y0]).astype(np.float32))
    roi = (x1 - x0, y1 - y0)
    warped = cv2.warpPerspective(src, H_, roi, flags=cv2.INTER_NEAREST, borderValue=255)
    mask = cv2.warpPerspective(np.full_like(src, 255), H_, roi, flags=cv2.INTER_NEAREST,
                               borderValue=0)
    region = canvas[y0:y1, x0:x1]
    region[mask > 0] = warped[mask > 0]


def floor_page(marker_map: MarkerMap, dpi: float = 150.0,
               canvas_m: tuple[float, float] = (1.7, 1.2)) -> Printable:
    """The map's floor markers at 1:1 on a ``canvas_m`` (width, height) metre canvas, seen from
    above (page right = world +x, page up = world +y), centred on the floor markers' extent.

    Each marker is drawn at its map position, side and yaw, from the dictionary of the map,
    with its id printed under it. The margin text gives the canvas size and where the world
    origin lies.
    """
    dpi = _check_dpi(dpi)
    floor = [m for m in marker_map.markers.values() if m.on_floor]
    if not floor:
        raise ValueError(f"{marker_map.source}: no floor markers (z = 0, facing up)")
    cw, ch = canvas_m
    W, H = px(cw * 1000, dpi), px(ch * 1000, dpi)
    if W * H > 400e6:
        raise ValueError(f"{cw} x {ch} m at {dpi:g} dpi is {W}x{H} px: lower --dpi")
    pitch = MM_PER_INCH / 1000.0 / dpi  # metres per pixel
    corners = np.vstack([m.corners_world() for m in floor])
    cx = 0.5 * (corners[:, 0].min() + corners[:, 0].max())
    cy = 0.5 * (corners[:, 1].min() + corners[:, 1].max())
    left, top = cx - W * pitch / 2, cy + H * pitch / 2
    if (corners[:, 0].max() - corners[:, 0].min() > cw
            or corners[:, 1].max() - corners[:, 1].min() > ch):
        raise ValueError(f"the floor markers do not fit on a {cw} x {ch} m canvas")
    d = dictionary(marker_map.dictionary)
    canvas = np.full((H, W), 255, np.uint8)
    for m in sorted(floor, key=lambda m: m.id):
        side = max(px(m.length * 1000, dpi), d.markerSize + 2)
        img = cv2.aruco.generateImageMarker(d, m.id, side, borderBits=1)
        wc = m.corners_world()
        # Pixel edges: world x = left is the left edge of pixel 0, i.e. x_px = -0.5.
        dst = np.stack([(wc[:, 0] - left) / pitch - 0.5, (top - wc[:, 1]) / pitch - 0.5], 1)
        _paste_warped(canvas, img, dst)
        _id_label(canvas, m.id, dst, m.length / pitch)
    ox_mm = (0.0 - left) * 1000
    oy_mm = (0.0 - (top - H * pitch)) * 1000
    lines = [f"{marker_map.name}: {len(floor)} floor markers ({marker_map.dictionary}), "
             f"canvas {cw * 1000:.0f} x {ch * 1000:.0f} mm at {dpi:g} dpi: print at 100 %",
             f"world origin (marker {marker_map.origin_id} centre) {ox_mm:.1f} mm from the left "
             f"edge, {oy_mm:.1f} mm from the bottom edge; +x right, +y up"]
    margin = px(8, dpi)
    _text_lines(canvas, lines, margin, H - px(22, dpi), W - 2 * margin, px(6, dpi))
    return Printable(canvas, dpi, f"{marker_map.name} floor {cw:g} x {ch:g} m")


def charuco_page(cols: int, rows: int, square_mm: float = 30.0, marker_mm: float = 22.0,
                 dict_name: str = "DICT_5X5_100", dpi: float = 300.0,
                 margin_mm: float = 15.0) -> Printable:
    """A ChArUco board of ``cols`` x ``rows`` squares (OpenCV layout) with its
    ``kmea calibrate`` board spec written in the margin."""
    dpi = _check_dpi(dpi)
    if cols < 3 or rows < 3:
        raise ValueError("a ChArUco board needs at least 3x3 squares")
    if not 0 < marker_mm < square_mm:
        raise ValueError(f"marker {marker_mm} mm must be smaller than the square {square_mm} mm")
    d = dictionary(dict_name)
    need = (cols * rows) // 2
    if d.bytesList.shape[0] < need:
        raise ValueError(f"{dict_name} has {d.bytesList.shape[0]} markers; a {cols}x{rows} "
                         f"board needs {need}")
    board = cv2.aruco.CharucoBoard((cols, rows), square_mm / 1000, marker_mm / 1000, d)
    bw, bh = px(cols * square_mm, dpi), px(rows * square_mm, dpi)
    img_b = board.generateImage((bw, bh), marginSize=0, borderBits=1)
    margin = px(margin_mm, dpi)
    img = np.full((bh + 2 * margin, bw + 2 * margin), 255, np.uint8)
    img[margin:margin + bh, margin:margin + bw] = img_b
    spec = f"charuco:{cols}x{rows}:{square_mm / 1000:g}:{marker_mm / 1000:g}:{dict_name}"
    _text_lines(img, [f"ChArUco {cols}x{rows} squares of {square_mm:g} mm, markers "
                      f"{marker_mm:g} mm, {dict_name}; {dpi:g} dpi: print at 100 %",
                      f"kmea calibrate --board {spec}  (measure a square; fix the spec if "
                      f"the printer scaled it)"],
                margin // 2, margin + bh + margin // 6, img.shape[1] - margin,
                px(min(3.5, margin_mm / 5), dpi))
    return Printable(img, dpi, f"ChArUco {cols}x{rows} {square_mm:g}/{marker_mm:g} mm")


# ---------------------------------------------------------------------------- files

def _png_bytes(img: np.ndarray, dpi: float) -> bytes:
    ok, buf = cv2.imencode(".png", img)
    if not ok:  # pragma: no cover
        raise ValueError("PNG encoding failed")
    data = buf.tobytes()
    ppm = round(dpi / 0.0254)
    body = struct.pack(">IIB", ppm, ppm, 1)  # unit 1: metre
    chunk = struct.pack(">I", len(body)) + b"pHYs" + body + \
        struct.pack(">I", zlib.crc32(b"pHYs" + body) & 0xFFFFFFFF)
    # The signature (8 bytes) and IHDR (4 + 4 + 13 + 4) come first; pHYs must precede IDAT.
    return data[:33] + chunk + data[33:]


def _pdf_bytes(img: np.ndarray, dpi: float, title: str) -> bytes:
    h, w = img.shape
    wpt, hpt = w / dpi * 72.0, h / dpi * 72.0
    stream = zlib.compress(np.ascontiguousarray(img, np.uint8).tobytes(), 6)
    content = f"q {wpt:.4f} 0 0 {hpt:.4f} 0 0 cm /Im0 Do Q".encode()
    safe = title.replace("\\", "\\\\").replace("(", "\\(").replace(")", "\\)")
    objs = [
        b"<< /Type /Catalog /Pages 2 0 R >>",
        b"<< /Type /Pages /Kids [3 0 R] /Count 1 >>",
        (f"<< /Type /Page /Parent 2 0 R /MediaBox [0 0 {wpt:.4f} {hpt:.4f}] "
         f"/Resources << /XObject << /Im0 4 0 R >> >> /Contents 5 0 R >>").encode(),
        (f"<< /Type /XObject /Subtype /Image /Width {w} /Height {h} /ColorSpace /DeviceGray "
         f"/BitsPerComponent 8 /Filter /FlateDecode /Length {len(stream)} >>\nstream\n"
         ).encode() + stream + b"\nendstream",
        f"<< /Length {len(content)} >>\nstream\n".encode() + content + b"\nendstream",
        f"<< /Title ({safe}) /Producer (kmea print) >>".encode(),
    ]
    out = bytearray(b"%PDF-1.4\n%\xe2\xe3\xcf\xd3\n")
    offsets = []
    for i, body in enumerate(objs, 1):
        offsets.append(len(out))
        out += f"{i} 0 obj\n".encode() + body + b"\nendobj\n"
    xref = len(out)
    out += f"xref\n0 {len(objs) + 1}\n0000000000 65535 f \n".encode()
    for off in offsets:
        out += f"{off:010d} 00000 n \n".encode()
    out += (f"trailer\n<< /Size {len(objs) + 1} /Root 1 0 R /Info {len(objs)} 0 R >>\n"
            f"startxref\n{xref}\n%%EOF\n").encode()
    return bytes(out)


def save_printable(p: Printable, path: str | Path) -> Path:
    """Write ``p`` as .png (with its DPI) or .pdf (page = image size, prints 1:1)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".png":
        data = _png_bytes(p.image, p.dpi)
    elif suffix == ".pdf":
        data = _pdf_bytes(p.image, p.dpi, p.title)
    else:
        raise ValueError(f"{path}: use .png or .pdf")
    try:
        path.write_bytes(data)
    except OSError as e:
        raise ValueError(f"{path}: cannot write: {e.strerror or e}") from None
    return path
