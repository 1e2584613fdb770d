"""Frame sources: image folders (with a corrupt file), video files, cameras (picamera: see
test_picamera_source.py)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from kmea.sources.base import Frame, FrameSource, SourceError
from kmea.sources.registry import open_source, parse_source_spec, register_source, source_prefixes


def _numbered(i: int, w: int = 160, h: int = 120) -> np.ndarray:
    """A BGR image whose bright block sits in column ``i``: the frame's number is readable."""
    img = np.full((h, w, 3), 40, np.uint8)
    img[40:80, 10 * i:10 * i + 10] = 230
    return img


def _block_column(img: np.ndarray) -> int:
    g = img if img.ndim == 2 else img.mean(axis=2)
    return int(np.argmax(g[40:80].mean(axis=0).reshape(-1, 10).mean(axis=1)))


def test_image_folder_natural_order_and_corrupt_file(tmp_path: Path) -> None:
    for i in (1, 2, 10):
        cv2.imwrite(str(tmp_path / f"img{i}.png"), _numbered(i))
    (tmp_path / "img3.jpg").write_bytes(b"\xff\xd8 this is not a jpeg")
    (tmp_path / "notes.txt").write_text("not an image: skipped, not an error")
    with open_source(f"images:{tmp_path}") as src:
        assert not src.live and len(src) == 4  # type: ignore[arg-type]
        frames = list(src)
        assert src.read() is None  # stays at the end
    assert [Path(f.meta["path"]).name for f in frames] == ["img1.png", "img2.png", "img3.jpg",
                                                           "img10.png"]
    assert [f.index for f in frames] == [0, 1, 2, 3]
    bad = frames[2]
    assert bad.image is None and not bad.ok and bad.error == "img3.jpg: cannot decode"
    assert [_block_column(f.image) for f in frames if f.ok] == [1, 2, 10]
    assert frames[3].image.shape == (120, 160, 3)
    assert src.size == (160, 120)
    assert frames[1].timestamp == pytest.approx(1 / 30)


def test_image_folder_gray_option_in_spec(tmp_path: Path) -> None:
    cv2.imwrite(str(tmp_path / "a.png"), _numbered(4))
    with open_source(f"images:{tmp_path}?gray=true&fps=10") as src:
        f = src.read()
        assert f is not None and f.image.ndim == 2 and _block_column(f.image) == 4
        assert src.read() is None


def test_image_folder_errors(tmp_path: Path) -> None:
    with pytest.raises(SourceError, match="not a folder"):
        open_source(f"images:{tmp_path / 'missing'}")
    (tmp_path / "readme.md").write_text("x")
    with pytest.raises(SourceError, match="no image files"):
        open_source(f"images:{tmp_path}")


def test_video_file_ends_cleanly(tmp_path: Path) -> None:
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (160, 120))
    assert writer.isOpened()
    for i in range(12):
        writer.write(_numbered(i))
    writer.release()
    src = open_source(f"video:{path}")
    assert not src.live and src.size == (160, 120)
    frames = list(src)
    assert src.read() is None and src.read() is None
    src.close()
    assert src.read() is None
    assert len(frames) == 12
    assert [_block_column(f.image) for f in frames] == list(range(12))
    np.testing.assert_allclose([f.timestamp for f in frames], np.arange(12) / 25.0)


def test_video_errors(tmp_path: Path) -> None:
    with pytest.raises(SourceError, match="no such file"):
        open_source(f"video:{tmp_path / 'none.avi'}")
    junk = tmp_path / "junk.avi"
    junk.write_bytes(b"\x00" * 100)
    with pytest.raises(SourceError, match="cannot open as a video"):
        open_source(f"video:{junk}")


def test_missing_camera_index_is_a_clear_error() -> None:
    with pytest.raises(SourceError, match=r"camera:63: cannot open camera 63"):
        open_source("camera:63")
    with pytest.raises(SourceError, match="INDEX must be an integer"):
        open_source("camera:front")


def test_unknown_spec_and_bad_options(tmp_path: Path) -> None:
    with pytest.raises(SourceError, match=r"unknown source 'rtsp'.*images:.*video:"):
        open_source("rtsp://host/stream")
    cv2.imwrite(str(tmp_path / "a.png"), _numbered(0))
    with pytest.raises(SourceError, match="option 'width' is not supported"):
        open_source(f"images:{tmp_path}", width=640)
    with pytest.raises(TypeError):  # callers that retry without size options catch TypeError
        open_source(f"video:{tmp_path / 'a.png'}", fps=5)
    with pytest.raises(SourceError, match="not key=value"):
        open_source(f"images:{tmp_path}?gray")


class _Counter(FrameSource):
    live = True

    def __init__(self, rest: str, n: int = 2) -> None:
        super().__init__()
        self.rest, self.n, self.i = rest, n, 0
        self.size = (4, 3)

    def read(self) -> Frame | None:
        if self.i >= self.n:
            return None
        self.i += 1
        return Frame(self.i - 1, float(self.i), np.zeros((3, 4), np.uint8), {"rest": self.rest})


def test_register_source_plugs_in_a_prefix() -> None:
    register_source("testcount", lambda rest, **o: _Counter(rest, **o))
    with open_source("testcount:abc?n=3") as src:
        frames = list(src)
    assert src.closed
    assert [f.meta["rest"] for f in frames] == ["abc"] * 3
    with pytest.raises(ValueError, match="prefix"):
        register_source("Bad Prefix", _Counter)


def test_sim_spec_reaches_the_simulator() -> None:
    """``sim`` opens kmea.sim's SimSource with the spec's options."""
    with open_source("sim?width=320&height=240&frames=2") as src:
        frames = list(src)
    assert len(frames) == 2 and src.size == (320, 240)
    assert frames[0].image.shape == (240, 320) and frames[1].index == 1


def test_parse_source_spec_is_the_one_grammar() -> None:
    p = parse_source_spec("camera:0?width=1280&height=960&fps=30&gray=off")
    assert (p.prefix, p.rest) == ("camera", "0")
    assert p.options == {"width": 1280, "height": 960, "fps": 30, "gray": False}
    assert parse_source_spec("sim").prefix == "sim" and parse_source_spec("sim").rest == ""
    assert parse_source_spec("images:/a:b/c").rest == "/a:b/c"  # only the first ':' splits
    assert {"images", "video", "camera", "picamera", "sim", "replay"} <= set(source_prefixes())
    for bad, msg in (("camera:front", "camera:INDEX"), ("images:", "images:DIR"),
                     ("picamera:x", "picamera"), ("rtsp://h/s", "unknown source 'rtsp'")):
        parse_source_spec(bad)  # the grammar alone accepts it
        with pytest.raises(SourceError, match=msg):
            parse_source_spec(bad, check=True)


def test_bad_scene_and_missing_recording_are_source_errors(tmp_path: Path) -> None:
    with pytest.raises(SourceError, match="sim:nowhere"):
        open_source("sim:nowhere")
    with pytest.raises(SourceError, match="no such file"):
        open_source(f"replay:{tmp_path / 'none.jsonl'}")
