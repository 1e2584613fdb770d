"""The camera thumbnail renderer: scaling to the pane, outlines, labels, hostile bodies."""

from __future__ import annotations

import base64

import pytest
from rich.console import Console

from kmea_tui.widgets.camera_view import (
    HALF_BLOCK,
    CameraFrame,
    FrameError,
    camera_caption,
    display_size,
    layout,
    render_camera,
)


def _body(w=64, h=48, fw=640, fh=480, pixels=None, markers=(), focus=50.0) -> dict:
    if pixels is None:
        # Left half dark (40), right half bright (220).
        pixels = bytes(40 if x < w // 2 else 220 for _ in range(h) for x in range(w))
    return {"width": w, "height": h, "full_width": fw, "full_height": fh,
            "encoding": "gray8", "data": base64.b64encode(pixels).decode(),
            "markers": list(markers), "focus": focus, "frame": 7}


def _square(mid, x, y, s, kind="detected"):
    return {"id": mid, "corners": [[x, y], [x + s, y], [x + s, y + s], [x, y + s]], "kind": kind}


@pytest.mark.parametrize(("cols", "rows"), [(78, 17), (118, 33), (40, 10), (5, 3)])
@pytest.mark.parametrize("braille", [False, True])
def test_every_line_fills_the_pane_exactly(cols, rows, braille):
    f = CameraFrame.from_body(_body(markers=[_square(3, 100, 100, 80)]))
    lines = render_camera(f, cols, rows, braille)
    assert len(lines) == rows
    assert all(t.cell_len == cols for t in lines)


def test_aspect_is_kept_and_image_centred():
    lay = layout(640, 480, 80, 20, braille=False)
    # 20 rows = 40 half-block pixels high; 4:3 gives 53 wide, centred in 80.
    assert (lay.dw, lay.dh) == (53, 40)
    assert lay.ox == (80 - 53) // 2
    assert display_size(640, 480, 80, 20) == (53, 40)
    assert display_size(640, 480, 80, 20, braille=True) == (107, 80)


def test_half_blocks_carry_the_grey_levels():
    f = CameraFrame.from_body(_body())
    lines = render_camera(f, 40, 10)
    lay = layout(640, 480, 40, 10, braille=False)
    row = lines[5]
    spans = [(row.plain[i], row.get_style_at_offset(Console(), i)) for i in range(row.cell_len)]
    left = spans[lay.ox + 1]
    right = spans[lay.ox + lay.dw - 2]
    assert left[0] == right[0] == HALF_BLOCK
    lt = left[1].color.get_truecolor()
    rt = right[1].color.get_truecolor()
    assert lt.red < 60 and rt.red > 200
    assert spans[0][0] == " "  # outside the image: blank


def test_outlines_labels_and_kinds():
    markers = [_square(3, 80, 80, 120), _square(7, 400, 80, 120, "suspect"),
               _square(12, 80, 300, 120, "expected"), _square(9, 400, 300, 120, "rejected")]
    f = CameraFrame.from_body(_body(markers=markers))
    text = "\n".join(t.plain for t in render_camera(f, 80, 24))
    assert "3" in text and "7?" in text and "(12)" in text and "9" in text
    lines = render_camera(f, 80, 24)
    # The suspect marker's outline is yellow somewhere on its row span.
    colours = {str(s.style).split(" on ")[0] for t in lines for s in t.spans}
    assert any("bright_yellow" in c for c in colours)
    assert any("bright_cyan" in c for c in colours)
    assert any("bright_green" in c for c in colours)


def test_dim_draws_no_colour():
    f = CameraFrame.from_body(_body(markers=[_square(3, 80, 80, 120)]))
    lines = render_camera(f, 60, 16, dim=True)
    styles = [s.style for t in lines for s in t.spans]
    assert styles
    assert not any("green" in str(s) for s in styles)
    for s in styles:
        if hasattr(s, "color") and s.color is not None and s.color.triplet is not None:
            assert s.color.triplet.red <= 80  # greys divided by three


def test_braille_sets_dots_where_bright():
    f = CameraFrame.from_body(_body())
    lines = render_camera(f, 40, 10, braille=True)
    lay = layout(640, 480, 40, 10, braille=True)
    row = lines[4].plain
    c_left = lay.ox // 2 + 1
    c_right = (lay.ox + lay.dw) // 2 - 2
    dots = lambda ch: bin(ord(ch) - 0x2800).count("1") if ch != " " else 0  # noqa: E731
    assert dots(row[c_right]) > dots(row[c_left])


def test_caption_counts_and_focus():
    markers = [_square(3, 80, 80, 120), _square(7, 400, 80, 120, "suspect"),
               _square(12, 80, 300, 120, "expected")]
    f = CameraFrame.from_body(_body(markers=markers, focus=123.4))
    cap = camera_caption(f, best_focus=150)
    assert cap.startswith("2 seen")
    assert "1 suspect" in cap and "1 expected unseen (12)" in cap
    assert "focus 123 (best 150)" in cap and "( )" not in cap
    assert camera_caption(None) == "no camera image yet"


@pytest.mark.parametrize(("patch", "field"), [
    ({"width": 0}, "width"),
    ({"width": "64"}, "width"),
    ({"encoding": "jpeg"}, "encoding"),
    ({"data": "!!!"}, "data"),
    ({"data": base64.b64encode(b"x" * 10).decode()}, "data"),
    ({"width": 4096, "height": 4096}, "larger"),
    ({"markers": [{"id": 1, "corners": [[0, 0]]}]}, "markers[0]"),
    ({"markers": [{"id": 1, "corners": [[0, 0]] * 4, "kind": "bogus"}]}, "markers[0]"),
    ({"markers": [{"id": 1, "corners": [[float("nan"), 0]] * 4}]}, "markers[0]"),
])
def test_hostile_bodies_are_refused_with_the_field_named(patch, field):
    body = _body()
    body.update(patch)
    with pytest.raises(FrameError, match=field.replace("[", r"\[").replace("]", r"\]")):
        CameraFrame.from_body(body)
