"""Marker detection: dictionaries, detector configuration, real and rendered frames."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from kmea.vision.detection import DEFAULT_PARAMETERS, DetectorConfig, MarkerDetector, as_gray
from kmea.vision.dictionary import DictionaryError, get_dictionary

# OpenCV's own test (test_arucodetection.cpp, tutorial board) expects these for marker 0.
MARKER0 = np.array([(252, 74), (286, 81), (274, 102), (238, 95)], dtype=float)


# ---------------------------------------------------------------- the real tutorial photo

@pytest.mark.parametrize("refinement", ["subpix", "none", "contour"])
def test_gridboard_photo_all_35_markers(shared_dir, refinement: str) -> None:
    d = shared_dir / "opencv-gridboard"
    det = MarkerDetector(DetectorConfig(str(d / "tutorial_dict.yml"), refinement))
    frame = cv2.imread(str(d / "gboriginal.png"))
    assert frame is not None and frame.ndim == 3  # a colour frame: converted inside
    found = det.detect(frame)
    assert sorted(found.ids.tolist()) == list(range(35))
    assert found.corners.shape == (35, 4, 2) and found.corners.dtype == np.float64
    c0 = found.corners[found.ids.tolist().index(0)]
    assert np.abs(c0 - MARKER0).max() < 1.0, c0
    # Grey input gives the same answer as colour.
    again = det.detect(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY))
    np.testing.assert_array_equal(again.ids, found.ids)
    np.testing.assert_allclose(again.corners, found.corners)


def test_gridboard_photo_needs_its_own_dictionary(shared_dir) -> None:
    """A predefined dictionary of the same bit size decodes none of the tutorial's codes."""
    d = shared_dir / "opencv-gridboard"
    other = MarkerDetector(DetectorConfig("DICT_6X6_250")).detect(
        cv2.imread(str(d / "gboriginal.png"), cv2.IMREAD_GRAYSCALE))
    assert len(other) == 0 and other.rejected >= 35


# ---------------------------------------------------------------- dictionaries

def test_predefined_names() -> None:
    a = get_dictionary("DICT_5X5_100")
    b = get_dictionary("5x5_100")
    assert a.markerSize == 5 and a.bytesList.shape[0] == 100
    np.testing.assert_array_equal(a.bytesList, b.bytesList)
    assert get_dictionary("DICT_APRILTAG_36h11").markerSize == 6


@pytest.mark.parametrize("suffix,name", [(".yml", ""), (".json", ""), (".xml", ""),
                                         (".yml", "mydict")])
def test_custom_dictionary_files_round_trip(tmp_path, suffix: str, name: str) -> None:
    src = cv2.aruco.extendDictionary(20, 5, cv2.aruco.getPredefinedDictionary(
        cv2.aruco.DICT_5X5_50), 3)
    path = tmp_path / f"d{suffix}"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    src.writeDictionary(fs, name) if name else src.writeDictionary(fs)
    fs.release()
    got = get_dictionary(path)
    assert got.markerSize == 5 and got.maxCorrectionBits == src.maxCorrectionBits
    np.testing.assert_array_equal(got.bytesList, src.bytesList)
    assert get_dictionary(str(path)).bytesList.shape == src.bytesList.shape


def test_tutorial_dictionary_file(shared_dir) -> None:
    d = get_dictionary(shared_dir / "opencv-gridboard" / "tutorial_dict.yml")
    assert d.markerSize == 6 and d.bytesList.shape[0] == 35


def test_bad_dictionaries_name_the_problem(tmp_path, shared_dir) -> None:
    with pytest.raises(DictionaryError, match="'DICT_5X5_77': not a predefined"):
        get_dictionary("DICT_5X5_77")
    with pytest.raises(DictionaryError, match="expected a name"):
        get_dictionary("")
    missing = tmp_path / "nope.yml"
    with pytest.raises(DictionaryError, match=f"{missing}: no such file"):
        get_dictionary(missing)
    cam = shared_dir / "opencv-gridboard" / "tutorial_camera_params.yml"
    with pytest.raises(DictionaryError, match=f"{cam}: missing key 'nmarkers'"):
        get_dictionary(cam)
    png = shared_dir / "opencv-gridboard" / "gboriginal.png"
    with pytest.raises(DictionaryError, match="not an OpenCV FileStorage file"):
        get_dictionary(png)
    bad_bits = tmp_path / "bits.yml"
    bad_bits.write_text('%YAML:1.0\nnmarkers: 2\nmarkersize: 2\nmarker_0: "0110"\n'
                        'marker_1: "01a0"\n')
    with pytest.raises(DictionaryError, match="key 'marker_1' must be a string of 4"):
        get_dictionary(bad_bits)
    short = tmp_path / "short.json"
    short.write_text('{"nmarkers": 3, "markersize": 2, "marker_0": "0110"}')
    with pytest.raises(DictionaryError, match="key 'marker_1'"):
        get_dictionary(short)


# ---------------------------------------------------------------- configuration and frames

def test_parameter_overrides_are_validated() -> None:
    p = DetectorConfig(parameters={"adaptiveThreshConstant": 9, "detectInvertedMarker": True,
                                   "minDistanceToBorder": 2}).detector_parameters()
    assert p.adaptiveThreshConstant == 9.0 and p.detectInvertedMarker and p.minDistanceToBorder == 2
    assert p.cornerRefinementMethod == cv2.aruco.CORNER_REFINE_SUBPIX
    # Our defaults are applied where not overridden.
    assert p.minMarkerPerimeterRate == DEFAULT_PARAMETERS["minMarkerPerimeterRate"]
    assert p.cornerRefinementWinSize == DEFAULT_PARAMETERS["cornerRefinementWinSize"]
    assert DetectorConfig(corner_refinement="none").detector_parameters() \
        .cornerRefinementMethod == cv2.aruco.CORNER_REFINE_NONE
    bad = [
        ({"adaptiveThreshConstnt": 7},
         "unknown detector parameter 'adaptiveThreshConstnt'; did you mean"),
        ({"minDistanceToBorder": 1.5}, "minDistanceToBorder: expected an integer"),
        ({"detectInvertedMarker": 1}, "detectInvertedMarker: expected true or false"),
        ({"errorCorrectionRate": "high"}, "errorCorrectionRate: expected a number"),
        ({"errorCorrectionRate": math.inf}, "errorCorrectionRate: expected a finite number"),
        ({"cornerRefinementMethod": 1}, "through corner_refinement"),
        ({"adaptiveThreshWinSizeMax": 2}, r"WinSizeMax: must be an integer in \[3, 255\]"),
        ({"adaptiveThreshWinSizeMin": 30, "adaptiveThreshWinSizeMax": 10}, "is below"),
        # A rule the daemon's configuration always had, now the library's own.
        ({"adaptiveThreshWinSizeMax": 255, "adaptiveThreshWinSizeStep": 1},
         "253 thresholding passes"),
    ]
    for params, message in bad:
        with pytest.raises(ValueError, match=message):
            DetectorConfig(parameters=params).detector_parameters()
    with pytest.raises(ValueError, match="corner_refinement: 'subpixel' is not one of"):
        MarkerDetector(DetectorConfig(corner_refinement="subpixel"))
    with pytest.raises(DictionaryError):
        MarkerDetector(DetectorConfig(dictionary="DICT_9X9_5"))


def test_bad_frames_give_clear_errors() -> None:
    det = MarkerDetector()
    cases = [
        ([[0, 1], [2, 3]], "expected a numpy array, got list"),
        (np.zeros((0, 640), np.uint8), "empty image"),
        (np.zeros((48, 64), np.float32), "expected dtype uint8, got float32"),
        (np.zeros((48, 64, 2), np.uint8), r"expected shape .*got \(48, 64, 2\)"),
        (np.zeros((2, 48, 64, 3), np.uint8), r"expected shape .*got \(2, 48, 64, 3\)"),
        (np.zeros((4, 4), np.uint8), r"image too small \(4x4\)"),
    ]
    for frame, message in cases:
        with pytest.raises(ValueError, match="frame: " + message):
            det.detect(frame)  # type: ignore[arg-type]
    assert as_gray(np.zeros((48, 64, 4), np.uint8)).shape == (48, 64)
    assert as_gray(np.zeros((48, 64, 1), np.uint8)).shape == (48, 64)
    empty = det.detect(np.full((48, 64), 255, np.uint8))
    assert len(empty) == 0 and empty.ids.shape == (0,) and empty.corners.shape == (0, 4, 2)


# ---------------------------------------------------------------- rendered frames

def render_markers(dictionary: cv2.aruco.Dictionary, quads: dict[int, np.ndarray],
                   size: tuple[int, int], rng: np.random.Generator, ss: int = 4,
                   blur: float = 0.7) -> np.ndarray:
    """Markers (with a white quiet zone one module wide) warped onto a grey floor at exact
    sub-pixel corners: drawn ``ss`` times larger, box-filtered down (ideal pixels), blurred
    by ``blur`` px (lens) and given 2 grey levels of noise."""
    w, h = size
    canvas = np.full((h * ss, w * ss), 120, np.uint8)
    module = 20
    side = (dictionary.markerSize + 2) * module
    img = None
    for mid, quad in quads.items():
        img = cv2.aruco.generateImageMarker(dictionary, mid, side)
        img = cv2.copyMakeBorder(img, module, module, module, module, cv2.BORDER_CONSTANT,
                                 value=255)
        # Pixel-edge corners of the black square in the marker image (pixel centres at
        # integers), mapped to the supersampled canvas's own pixel convention.
        src = np.array([(0, 0), (side, 0), (side, side), (0, side)], np.float32) + module - 0.5
        dst = ((quad + 0.5) * ss - 0.5).astype(np.float32)
        H = cv2.getPerspectiveTransform(src, dst)
        warped = cv2.warpPerspective(img, H, (w * ss, h * ss), flags=cv2.INTER_LINEAR)
        mask = cv2.warpPerspective(np.full_like(img, 255), H, (w * ss, h * ss),
                                   flags=cv2.INTER_NEAREST)
        canvas[mask > 0] = warped[mask > 0]
    small = cv2.resize(canvas, (w, h), interpolation=cv2.INTER_AREA).astype(float)
    if blur > 0:
        small = cv2.GaussianBlur(small, (0, 0), blur)
    return np.clip(small + rng.normal(0, 2.0, small.shape), 0, 255).astype(np.uint8)


def random_quads(rng: np.random.Generator, n: int, size: tuple[int, int], lo: float = 25,
                 hi: float = 60) -> dict[int, np.ndarray]:
    """n markers lo-hi px wide, rotated and mildly foreshortened, one per grid cell."""
    w, h = size
    cols, rows = 4, math.ceil(n / 4)
    quads = {}
    for k in range(n):
        cx = (k % cols + 0.5) * w / cols + rng.uniform(-10, 10)
        cy = (k // cols + 0.5) * h / rows + rng.uniform(-10, 10)
        s = rng.uniform(lo, hi) / 2
        a = rng.uniform(-math.pi, math.pi)
        sq = np.array([(-s, -s), (s, -s), (s, s), (-s, s)])
        sq[:, 0] *= rng.uniform(0.8, 1.0)  # foreshortening
        rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
        quads[3 * k + 1] = sq @ rot.T + (cx, cy)
    return quads


def test_rendered_markers_found_with_subpixel_corners() -> None:
    """Markers 40-70 px wide (60 mm from 1.2-1.5 m at 1640x1232 is 55-70 px): all found with
    the right ids; sub-pixel refinement beats the raw contour corners, which sit about half
    a pixel inside the true square."""
    rng = np.random.default_rng(5)
    size = (800, 600)
    d = get_dictionary("DICT_5X5_100")
    err: dict[str, list[np.ndarray]] = {"subpix": [], "none": []}
    radial: dict[str, list[np.ndarray]] = {"subpix": [], "none": []}
    for _ in range(3):
        quads = random_quads(rng, 12, size, 40, 70)
        frame = render_markers(d, quads, size, rng)
        for method in err:
            found = MarkerDetector(DetectorConfig("DICT_5X5_100", method)).detect(frame)
            assert sorted(found.ids.tolist()) == sorted(quads), method
            for mid, c in zip(found.ids.tolist(), found.corners, strict=True):
                q = quads[mid]
                out = (q - q.mean(axis=0)) / np.linalg.norm(q - q.mean(axis=0), axis=1)[:, None]
                err[method].append(np.linalg.norm(c - q, axis=1))
                radial[method].append(((c - q) * out).sum(axis=1))
    sub, raw = np.concatenate(err["subpix"]), np.concatenate(err["none"])
    assert np.median(sub) < 0.3 and sub.max() < 0.6, (np.median(sub), sub.max())
    assert np.median(sub) < 0.6 * np.median(raw)
    bias_sub, bias_raw = np.mean(radial["subpix"]), np.mean(radial["none"])
    assert -0.35 < bias_sub < 0.1 and bias_raw < -0.35, (bias_sub, bias_raw)
