"""Camera files: FileStorage (YAML/XML/JSON) and TOML, bad files, scaling to other sizes."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from kmea.vision.camera import (
    CameraError,
    CameraModel,
    load_camera,
    model_for_frame,
    pi_camera_v2,
    save_camera,
)

K = np.array([[612.5, 0.0, 318.25], [0.0, 611.75, 241.5], [0.0, 0.0, 1.0]])
DIST = np.array([0.11, -0.23, 0.0012, -0.0007, 0.09])


def _model() -> CameraModel:
    return CameraModel(K, DIST, 640, 480)


def test_tutorial_camera_params_has_no_image_size(shared_dir: Path) -> None:
    path = shared_dir / "opencv-gridboard" / "tutorial_camera_params.yml"
    m = load_camera(path)
    np.testing.assert_allclose(m.camera_matrix, [[628.158, 0, 324.099], [0, 628.156, 260.908],
                                                 [0, 0, 1]])
    np.testing.assert_allclose(m.dist_coeffs, [0.0995485, -0.206384, 0.00754589, 0.00336531, 0])
    assert not m.size_known
    # The first frame size is adopted, not scaled: the file has no size to scale from.
    at = model_for_frame(m, 640, 480)
    assert (at.width, at.height, at.size_known) == (640, 480, True)
    np.testing.assert_allclose(at.camera_matrix, m.camera_matrix)
    # ... and an explicit size is used as the calibration size.
    m2 = load_camera(path, image_size=(640, 480))
    assert m2.size_known and (m2.width, m2.height) == (640, 480)


@pytest.mark.parametrize("suffix", [".yml", ".yaml", ".xml", ".json", ".toml"])
def test_round_trip(tmp_path: Path, suffix: str) -> None:
    path = tmp_path / f"cam{suffix}"
    save_camera(_model(), path, meta={"rms": 0.21, "board": "chessboard:9x7:0.025"})
    m = load_camera(path)
    np.testing.assert_allclose(m.camera_matrix, K, rtol=0, atol=1e-12)
    np.testing.assert_allclose(m.dist_coeffs, DIST, rtol=0, atol=1e-12)
    assert (m.width, m.height, m.size_known) == (640, 480, True)


@pytest.mark.parametrize("suffix", [".yml", ".xml", ".json"])
def test_filestorage_is_readable_by_opencv(tmp_path: Path, suffix: str) -> None:
    path = tmp_path / f"cam{suffix}"
    save_camera(_model(), path, meta={"rms": 0.21})
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    np.testing.assert_allclose(fs.getNode("camera_matrix").mat(), K)
    np.testing.assert_allclose(fs.getNode("distortion_coefficients").mat().ravel(), DIST)
    assert int(fs.getNode("image_width").real()) == 640
    assert fs.getNode("avg_reprojection_error").real() == pytest.approx(0.21)
    fs.release()


def test_old_sample_spelling(tmp_path: Path) -> None:
    """OpenCV's older calibration sample writes Camera_Matrix, image_Width, ..."""
    path = tmp_path / "out_camera_data.yml"
    path.write_text(
        "%YAML:1.0\n---\n"
        'calibration_Time: "08/19/11 20:44:38"\n'
        "nrOfFrames: 8\nimage_Width: 384\nimage_Height: 288\n"
        "Camera_Matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
        "   data: [ 305.2, 0., 197.4, 0., 304.9, 149.3, 0., 0., 1. ]\n"
        "Distortion_Coefficients: !!opencv-matrix\n   rows: 5\n   cols: 1\n   dt: d\n"
        "   data: [ 0.198, -0.445, 0.0022, 0.0033, 0.287 ]\n"
        "Avg_Reprojection_Error: 1.68e-01\n")
    m = load_camera(path)
    assert (m.fx, m.fy, m.cx, m.cy) == (305.2, 304.9, 197.4, 149.3)
    assert m.dist_coeffs[4] == pytest.approx(0.287)
    assert (m.width, m.height) == (384, 288)


def test_toml_convenience_keys(tmp_path: Path) -> None:
    path = tmp_path / "cam.toml"
    path.write_text("width = 1640\nheight = 1232\nfx = 1357.0\nfy = 1356.0\ncx = 819.5\n"
                    "cy = 615.5\ndist_coeffs = [0.1, -0.2, 0.0, 0.0]\n")
    m = load_camera(path)
    np.testing.assert_allclose(m.camera_matrix, [[1357, 0, 819.5], [0, 1356, 615.5], [0, 0, 1]])
    assert m.dist_coeffs.tolist() == [0.1, -0.2, 0.0, 0.0]


def test_scaling_keeps_the_rays() -> None:
    """A binned mode sees the same ray at the scaled pixel: x' + 0.5 = s (x + 0.5)."""
    full = pi_camera_v2(1640, 1232)
    half = model_for_frame(full, 820, 616)
    assert half.fx == pytest.approx(full.fx / 2)
    p = np.array([[0.31, -0.12, 1.4]])
    a, _ = cv2.projectPoints(p, np.zeros(3), np.zeros(3), full.camera_matrix, full.dist_coeffs)
    b, _ = cv2.projectPoints(p, np.zeros(3), np.zeros(3), half.camera_matrix, half.dist_coeffs)
    np.testing.assert_allclose(b.ravel() + 0.5, (a.ravel() + 0.5) / 2, atol=1e-9)
    back = half.scaled_to(1640, 1232)
    np.testing.assert_allclose(back.camera_matrix, full.camera_matrix, atol=1e-9)


def test_other_aspect_ratio_is_an_error() -> None:
    with pytest.raises(CameraError, match=r"1280x720 has another aspect ratio .* 1640x1232"):
        model_for_frame(pi_camera_v2(), 1280, 720)


def _fs_file(path: Path, **nodes: object) -> Path:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for k, v in nodes.items():
        fs.write(k, v)
    fs.release()
    return path


BAD_FS = {
    "no_matrix": ({"distortion_coefficients": DIST.reshape(-1, 1)}, "camera_matrix"),
    "no_dist": ({"camera_matrix": K}, "distortion_coefficients"),
    "matrix_2x3": ({"camera_matrix": K[:2], "distortion_coefficients": DIST.reshape(-1, 1)},
                   "camera_matrix"),
    "dist_6": ({"camera_matrix": K, "distortion_coefficients": np.zeros((6, 1))},
               "distortion_coefficients"),
    "nan": ({"camera_matrix": np.where(np.eye(3) > 0, np.nan, K),
             "distortion_coefficients": DIST.reshape(-1, 1)}, "camera_matrix"),
    "inf_dist": ({"camera_matrix": K,
                  "distortion_coefficients": np.array([[0.1], [np.inf], [0], [0], [0]])},
                 "distortion_coefficients"),
    "width_only": ({"camera_matrix": K, "distortion_coefficients": DIST.reshape(-1, 1),
                    "image_width": 640}, "image_height"),
    "zero_height": ({"camera_matrix": K, "distortion_coefficients": DIST.reshape(-1, 1),
                     "image_width": 640, "image_height": 0}, "image_height"),
    "negative_f": ({"camera_matrix": K * [[-1], [1], [1]],
                    "distortion_coefficients": DIST.reshape(-1, 1)}, "camera_matrix"),
}


@pytest.mark.parametrize("suffix", [".yml", ".json"])
@pytest.mark.parametrize("case", sorted(BAD_FS))
def test_bad_filestorage_names_file_and_key(tmp_path: Path, case: str, suffix: str) -> None:
    nodes, key = BAD_FS[case]
    path = _fs_file(tmp_path / f"{case}{suffix}", **nodes)
    with pytest.raises(CameraError) as e:
        load_camera(path)
    msg = str(e.value)
    assert str(path) in msg and key in msg, msg
    assert "\n" not in msg


BAD_TOML = {
    "missing_matrix": ("dist_coeffs = [0, 0, 0, 0, 0]\n", "camera_matrix"),
    "missing_dist": ("camera_matrix = [[600, 0, 320], [0, 600, 240], [0, 0, 1]]\n",
                     "dist_coeffs"),
    "ragged": ("camera_matrix = [[600, 0, 320], [0, 600], [0, 0, 1]]\n"
               "dist_coeffs = [0, 0, 0, 0, 0]\n", "camera_matrix"),
    "shape": ("camera_matrix = [[600, 0, 320], [0, 600, 240]]\n"
              "dist_coeffs = [0, 0, 0, 0, 0]\n", "camera_matrix"),
    "nan": ("camera_matrix = [[nan, 0, 320], [0, 600, 240], [0, 0, 1]]\n"
            "dist_coeffs = [0, 0, 0, 0, 0]\n", "camera_matrix"),
    "text": ("camera_matrix = [[600, 0, 320], [0, 600, 240], [0, 0, 1]]\n"
             "dist_coeffs = [0, 'a', 0, 0, 0]\n", "dist_coeffs"),
    "unknown": ("camera_matrix = [[600, 0, 320], [0, 600, 240], [0, 0, 1]]\n"
                "dist_coeffs = [0, 0, 0, 0, 0]\nfocal = 3\n", "focal"),
    "fx_missing_cy": ("fx = 600\nfy = 600\ncx = 320\ndist_coeffs = [0, 0, 0, 0]\n", "cy"),
    "float_width": ("camera_matrix = [[600, 0, 320], [0, 600, 240], [0, 0, 1]]\n"
                    "dist_coeffs = [0, 0, 0, 0, 0]\nwidth = 640.5\nheight = 480\n", "width"),
    "syntax": ("camera_matrix = [[600, 0, 320]\n", "invalid TOML"),
}


@pytest.mark.parametrize("case", sorted(BAD_TOML))
def test_bad_toml_names_file_and_key(tmp_path: Path, case: str) -> None:
    text, key = BAD_TOML[case]
    path = tmp_path / f"{case}.toml"
    path.write_text(text)
    with pytest.raises(CameraError) as e:
        load_camera(path)
    msg = str(e.value)
    assert str(path) in msg and key in msg, msg


@pytest.mark.parametrize("name,text,expect", [
    ("broken.yml", "%YAML:1.0\ncamera_matrix: [1, 2\n  foo: :\n", "not a valid OpenCV FileStorage"),
    ("broken.xml", '<?xml version="1.0"?><opencv_storage><camera_matrix>', "not a valid"),
    ("broken.json", '{"camera_matrix": ', "not a valid"),
    ("empty.yml", "", "empty file"),
    ("cam.ini", "fx = 1\n", "unknown camera file format"),
])
def test_unreadable_files(tmp_path: Path, name: str, text: str, expect: str) -> None:
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(CameraError, match=expect) as e:
        load_camera(path)
    assert str(path) in str(e.value)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(CameraError, match=r"nope\.yml: cannot read"):
        load_camera(tmp_path / "nope.yml")


def test_unknown_size_not_written(tmp_path: Path) -> None:
    m = CameraModel(K, DIST, 640, 480, size_known=False)
    for suffix in (".yml", ".toml"):
        save_camera(m, tmp_path / f"c{suffix}")
        assert not load_camera(tmp_path / f"c{suffix}").size_known
        assert "width" not in (tmp_path / f"c{suffix}").read_text()


def test_model_validation_message() -> None:
    with pytest.raises(CameraError, match="distortion_coefficients"):
        CameraModel(K, np.zeros(3), 640, 480)
    assert math.isclose(_model().intrinsics.camera_matrix[0, 0], 612.5)


# ---------------------------------------------------------------- plain lists (issue 30)

PLAIN_K = "[1357.0, 0, 819.5, 0, 1357.0, 615.5, 0, 0, 1]"
NESTED_K = "[[1357.0, 0, 819.5], [0, 1357.0, 615.5], [0, 0, 1]]"
PLAIN_D = "[0.12, -0.25, 0, 0, 0.1]"
PLAIN_FILES = {
    "flat.json": f'{{"camera_matrix": {PLAIN_K}, "distortion_coefficients": {PLAIN_D}, '
                 '"image_width": 1640, "image_height": 1232}',
    # The TOML names, as someone writing JSON by analogy would: a size key ignored would
    # leave the size guessed and the intrinsics unscaled.
    "nested.json": f'{{"camera_matrix": {NESTED_K}, "dist_coeffs": {PLAIN_D}, '
                   '"width": 1640, "height": 1232}',
    "flat.yml": f"%YAML:1.0\n---\ncamera_matrix: {PLAIN_K}\n"
                f"distortion_coefficients: {PLAIN_D}\nimage_width: 1640\nimage_height: 1232\n",
    "nested.yaml": f"%YAML:1.0\n---\nimage_width: 1640\nimage_height: 1232\n"
                   f"camera_matrix: {NESTED_K}\ndist_coeffs: {PLAIN_D}\n",
    "plain.xml": '<?xml version="1.0"?>\n<opencv_storage>\n<image_width>1640</image_width>\n'
                 "<image_height>1232</image_height>\n"
                 "<camera_matrix>1357.0 0 819.5 0 1357.0 615.5 0 0 1</camera_matrix>\n"
                 "<distortion_coefficients>0.12 -0.25 0 0 0.1</distortion_coefficients>\n"
                 "</opencv_storage>\n",
    "flat.toml": f"width = 1640\nheight = 1232\ncamera_matrix = {PLAIN_K}\n"
                 f"dist_coeffs = {PLAIN_D}\n",
}


@pytest.mark.parametrize("name", sorted(PLAIN_FILES))
def test_plain_lists_load_as_the_matrix_form(tmp_path: Path, name: str) -> None:
    """docs/camera.md accepts a plain list instead of an !!opencv-matrix; OpenCV 5's
    FileNode.mat() asserts isMap() on a list, which was a cv2.error traceback."""
    reference = tmp_path / "reference.yml"
    save_camera(pi_camera_v2(), reference)  # the !!opencv-matrix form
    assert "!!opencv-matrix" in reference.read_text()
    toml = tmp_path / "reference.toml"
    save_camera(pi_camera_v2(), toml)
    path = tmp_path / name
    path.write_text(PLAIN_FILES[name])
    m = load_camera(path)
    for ref in (load_camera(reference), load_camera(toml)):
        np.testing.assert_array_equal(m.camera_matrix, ref.camera_matrix)
        np.testing.assert_array_equal(m.dist_coeffs, ref.dist_coeffs)
        assert (m.width, m.height, m.size_known) == (ref.width, ref.height, True)


BAD_PLAIN = {
    # FileNode.real() of a string is DBL_MAX, not an error: once read as 1.8e308.
    "string.json": ('{"camera_matrix": [1357, 0, 819.5, 0, 1357, 615.5, 0, 0, "one"], '
                    f'"dist_coeffs": {PLAIN_D}}}', "camera_matrix: expected numbers"),
    "string_row.json": ('{"camera_matrix": [[1357, 0, 819.5], [0, 1357, "615"], [0, 0, 1]], '
                        f'"dist_coeffs": {PLAIN_D}}}', "camera_matrix: expected numbers"),
    "ragged.yml": (f"%YAML:1.0\n---\ncamera_matrix: [[1357, 0, 819.5], [0, 1357], [0, 0, 1]]\n"
                   f"dist_coeffs: {PLAIN_D}\n", "camera_matrix: expected a list of numbers or "
                                                "of rows"),
    "map.json": (f'{{"camera_matrix": {{"fx": 1357}}, "dist_coeffs": {PLAIN_D}}}',
                 "camera_matrix: expected a matrix"),
    "eight.json": (f'{{"camera_matrix": [1357, 0, 819.5, 0, 1357, 615.5, 0, 0], '
                   f'"dist_coeffs": {PLAIN_D}}}', "camera_matrix: expected a 3x3 matrix"),
    "top_list.yml": ("%YAML:1.0\n---\n- 1\n- 2\n", "expected keys (camera_matrix"),
    "both.json": (f'{{"camera_matrix": {PLAIN_K}, "dist_coeffs": {PLAIN_D}, '
                  f'"distortion_coefficients": {PLAIN_D}}}',
                  "'distortion_coefficients' and 'dist_coeffs' are the same key"),
}


@pytest.mark.parametrize("name", sorted(BAD_PLAIN))
def test_bad_plain_lists_name_file_and_key(tmp_path: Path, name: str) -> None:
    text, expect = BAD_PLAIN[name]
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(CameraError) as e:
        load_camera(path)
    msg = str(e.value)
    assert msg.startswith(f"{path}: ") and expect in msg and "\n" not in msg, msg


# ---------------------------------------------------------------- physical bounds (issue 30)

def _toml_camera(K: list, dist: list, size: tuple[int, int] | None = (1640, 1232)) -> str:
    head = f"width = {size[0]}\nheight = {size[1]}\n" if size else ""
    return head + f"camera_matrix = {K}\ndist_coeffs = {dist}\n"


GOOD_K = [[1357.0, 0.0, 819.5], [0.0, 1357.0, 615.5], [0.0, 0.0, 1.0]]
BAD_BOUNDS = {
    # Each loaded and then left every frame "not estimated" with exit 0.
    "k1_huge": (_toml_camera(GOOD_K, [1e300, -0.25, 0, 0, 0.1]),
                "dist_coeffs: k1 = 1e+300 is beyond +-10000: no lens distorts that much"),
    "k6_large": (_toml_camera(GOOD_K, [0.1, 0, 0, 0, 0, 0, 0, -2e4]),
                 "dist_coeffs: k6 = -20000 is beyond +-10000"),
    # Within +-1e4 but no lens: every frame failed in OpenCV's SQPnP (the whole image
    # undistorts to 4.6 degrees, every marker to a point).
    "k1_9000": (_toml_camera(GOOD_K, [9000, 0, 0, 0, 0]),
                "dist_coeffs: the distortion pushes the image's border 15 times out from "
                "where the pinhole puts it (at most 3)"),
    # Barrel that turns back before the image's edge: its corners have no direction.
    "k1_folds": (_toml_camera(GOOD_K, [-5, 0, 0, 0, 0]),
                 "dist_coeffs: the distortion folds over inside the image"),
    "fy_tiny": (_toml_camera([[1357.0, 0, 819.5], [0, 0.001, 615.5], [0, 0, 1]], [0, 0, 0, 0]),
                "camera_matrix: fy = 0.001 px is outside [164, 164000] px, 0.1 to 100 times "
                "the 1640x1232 image's larger side"),
    "fx_huge": (_toml_camera([[1e7, 0, 819.5], [0, 1357.0, 615.5], [0, 0, 1]], [0, 0, 0, 0]),
                "camera_matrix: fx = 1e+07 px is outside [164, 164000] px"),
    # Without a size, against the one guessed from the principal point (1640x1232).
    "fx_tiny_no_size": (_toml_camera([[100.0, 0, 819.5], [0, 100.0, 615.5], [0, 0, 1]],
                                     [0, 0, 0, 0], None),
                        "camera_matrix: fx = 100 px is outside [164, 164000] px"),
    "fy_convenience": ("fx = 1357.0\nfy = 1.0\ncx = 819.5\ncy = 615.5\ndist_coeffs = [0, 0, 0, 0]\n"
                       "width = 1640\nheight = 1232\n", "fy = 1 px is outside [164, 164000] px"),
}


@pytest.mark.parametrize("case", sorted(BAD_BOUNDS))
def test_physically_impossible_cameras_are_refused(tmp_path: Path, case: str) -> None:
    text, expect = BAD_BOUNDS[case]
    path = tmp_path / f"{case}.toml"
    path.write_text(text)
    with pytest.raises(CameraError) as e:
        load_camera(path)
    msg = str(e.value)
    assert msg.startswith(f"{path}: ") and expect in msg and "\n" not in msg, msg


def test_bounds_hold_for_filestorage_files_too(tmp_path: Path) -> None:
    path = _fs_file(tmp_path / "cam.json", camera_matrix=K,
                    distortion_coefficients=np.array([[0.1], [1e300], [0], [0], [0]]))
    with pytest.raises(CameraError, match=r"cam\.json: distortion_coefficients: k2 = 1e\+300"):
        load_camera(path)


def test_the_bounds_leave_real_cameras_alone(tmp_path: Path) -> None:
    """A wide lens (fx a quarter of the width: 127 degrees across) with a rational model whose
    numerator and denominator nearly cancel, as such calibrations come out."""
    path = tmp_path / "wide.toml"
    path.write_text(_toml_camera([[410.0, 0, 819.5], [0, 410.0, 615.5], [0, 0, 1]],
                                 [850.0, -120.0, 0.001, -0.002, 40.0, 851.0, -95.0, 60.0]))
    m = load_camera(path)
    assert m.fx == 410.0 and m.dist_coeffs[0] == 850.0


def test_skew_that_opencv_would_ignore_is_refused(tmp_path: Path) -> None:
    """cv2.projectPoints and solvePnP ignore K[0, 1]: a skew that moves the image's edge by
    more than a pixel describes another camera than the one estimated with."""
    path = tmp_path / "skew.toml"
    path.write_text("width = 1640\nheight = 1232\nfx = 1357.0\nfy = 1357.0\ncx = 819.5\n"
                    "cy = 615.5\nskew = 5.0\ndist_coeffs = [0, 0, 0, 0]\n")
    with pytest.raises(CameraError, match=r"skew\.toml: skew 5 px would move the image's "
                                          r"edge by 2\.27 px, and OpenCV ignores skew"):
        load_camera(path)
    path.write_text(path.read_text().replace("skew = 5.0", "skew = 0.5"))
    assert load_camera(path).camera_matrix[0, 1] == 0.5  # 0.23 px: kept, as calibrated


@pytest.mark.parametrize("suffix", [".yml", ".json", ".xml"])
def test_deep_nesting_is_one_line_not_a_crash(tmp_path: Path, suffix: str) -> None:
    """OpenCV's parsers recurse per level: 60,000 levels (a 120-420 KB file) was a
    segmentation fault, so the load runs in a child process."""
    import subprocess
    import sys

    d = 60_000
    path = tmp_path / f"deep{suffix}"
    path.write_text({
        ".yml": "%YAML:1.0\n---\ncamera_matrix: " + "[" * d + "]" * d + "\n",
        ".json": '{"camera_matrix": ' + "[" * d + "]" * d + "}",
        ".xml": '<?xml version="1.0"?>\n<opencv_storage><camera_matrix>' + "<_>" * d
                + "</_>" * d + "</camera_matrix></opencv_storage>\n",
    }[suffix])
    code = ("import sys\nfrom kmea.vision.camera import CameraError, load_camera\n"
            "try:\n    load_camera(sys.argv[1])\nexcept CameraError as e:\n    print(e)\n")
    run = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True,
                         text=True, timeout=120)
    assert run.returncode == 0, run.stderr[-300:]
    assert run.stdout.strip() == f"{path}: nested more than 32 levels deep: not a camera file"


def test_a_camera_file_of_megabytes_is_refused(tmp_path: Path) -> None:
    path = _fs_file(tmp_path / "big.yml", camera_matrix=K,
                    distortion_coefficients=DIST.reshape(-1, 1))
    path.write_text(path.read_text() + "padding: \"" + "x" * (1 << 20) + "\"\n")
    with pytest.raises(CameraError, match=r"big\.yml: larger than 1 MB: not a camera file"):
        load_camera(path)
