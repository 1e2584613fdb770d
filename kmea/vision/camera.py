"""Camera models: pinhole intrinsics with OpenCV distortion coefficients.

Pixel convention is OpenCV's: the centre of the top-left pixel is (0, 0).
File reading and writing (OpenCV FileStorage YAML/XML/JSON and TOML) live here too; the
formats are described in ``docs/camera.md``.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from kmea.geometry.camera import (
    DISTORTION_COUNTS,
    CameraIntrinsics,
    check_camera,
    check_camera_matrix,
    check_distortion,
    check_focal,
    distortion_problem,
)
from kmea.wire import tomlvalue as toml

__all__ = ["CameraError", "CameraModel", "load_camera", "model_for_frame", "pi_camera_v2",
           "save_camera"]

FILESTORAGE_SUFFIXES = (".yml", ".yaml", ".xml", ".json")

# Distortion coefficients, in magnitude. Calibrations of wide lenses with the rational
# model reach hundreds to a few thousands, numerator and denominator nearly cancelling
# (k1 ~ k4); 1e4 leaves that room, and anything beyond moves image points by more than any
# lens (1e300 overflows and no pose is ever estimated).
MAX_DISTORTION = 1e4
# OpenCV's FileStorage parsers recurse per nesting level and overflow the stack (a
# segmentation fault, no message) at some 50,000 levels; a camera file nests 2. The size
# bound also bounds YAML's indentation nesting (a file of N levels is N^2 / 2 bytes).
MAX_FILESTORAGE_NESTING = 32
MAX_FILESTORAGE_BYTES = 1 << 20  # kmea calibrate writes under 2 KB
# Skew is ignored by cv2.projectPoints and solvePnP, so a camera matrix whose skew would
# move the image's edge by more than this many pixels describes another camera.
MAX_IGNORED_SKEW_PX = 1.0


class CameraError(ValueError):
    """A camera file or model is invalid; the message names the file and key."""


@dataclass(frozen=True)
class CameraModel:
    """Pinhole camera with OpenCV distortion.

    camera_matrix: (3, 3) K, pixels. dist_coeffs: (n,) with n in {4, 5, 8, 12, 14}, OpenCV
    order (k1, k2, p1, p2[, k3[, k4, k5, k6[, s1..s4[, tx, ty]]]]). width, height: pixels.
    size_known: False when the file gave no image size (OpenCV's tutorial files often
    don't); width/height are then a guess from the principal point and the first
    ``scaled_to`` adopts the frame size as it is instead of scaling.
    """

    camera_matrix: np.ndarray
    dist_coeffs: np.ndarray
    width: int
    height: int
    size_known: bool = True

    def __post_init__(self) -> None:
        try:
            K, d = check_camera(self.camera_matrix, self.dist_coeffs, self.width, self.height)
        except ValueError as e:
            raise CameraError(str(e)) from None
        object.__setattr__(self, "camera_matrix", K)
        object.__setattr__(self, "dist_coeffs", d if d.size else np.zeros(5))
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    @property
    def fx(self) -> float:
        return float(self.camera_matrix[0, 0])

    @property
    def fy(self) -> float:
        return float(self.camera_matrix[1, 1])

    @property
    def cx(self) -> float:
        return float(self.camera_matrix[0, 2])

    @property
    def cy(self) -> float:
        return float(self.camera_matrix[1, 2])

    @property
    def intrinsics(self) -> CameraIntrinsics:
        """The numpy-only view the estimators take."""
        return CameraIntrinsics(self.camera_matrix, self.dist_coeffs, self.width, self.height)

    def scaled_to(self, width: int, height: int) -> CameraModel:
        """The same camera at another resolution with the same aspect ratio.

        Sensor modes that bin or scale keep the field of view, so K scales with the image
        (pixel centres: x' + 0.5 = s (x + 0.5)). Distortion is in normalized coordinates and
        does not change. Another aspect ratio is a crop we cannot know: ``CameraError``.
        """
        if (width, height) == (self.width, self.height):
            return self if self.size_known else replace(self, size_known=True)
        if not self.size_known:
            return replace(self, width=int(width), height=int(height), size_known=True)
        sx, sy = width / self.width, height / self.height
        if not math.isclose(sx, sy, rel_tol=2e-3):
            raise CameraError(
                f"frame size {width}x{height} has another aspect ratio than the calibration "
                f"{self.width}x{self.height}; recalibrate at this resolution")
        K = self.camera_matrix.copy()
        K[0, 0] *= sx
        K[1, 1] *= sy
        K[0, 1] *= sx
        K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
        K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
        return CameraModel(K, self.dist_coeffs.copy(), width, height)


def pi_camera_v2(width: int = 1640, height: int = 1232) -> CameraModel:
    """A nominal Raspberry Pi Camera Module v2 (Sony IMX219) in its binned 1640x1232 mode.

    3.04 mm lens, 1.12 um pixels binned 2x2 -> f = 3.04 / 0.00224 = 1357 px; mild barrel
    distortion typical of the module. Scaled to (width, height) if they differ (4:3 only).
    """
    K = np.array([[1357.0, 0.0, 819.5], [0.0, 1357.0, 615.5], [0.0, 0.0, 1.0]])
    dist = np.array([0.12, -0.25, 0.0, 0.0, 0.10])
    return CameraModel(K, dist, 1640, 1232).scaled_to(width, height)


def model_for_frame(model: CameraModel, width: int, height: int) -> CameraModel:
    """``model`` for frames of ``width`` x ``height`` pixels (see ``CameraModel.scaled_to``).

    Raises ``CameraError`` for another aspect ratio than the calibration's.
    """
    return model.scaled_to(int(width), int(height))


# ---------------------------------------------------------------------------- files

# Accepted spellings, first one written. The second ones are from OpenCV's older
# calibration sample (out_camera_data.xml).
# The last ones are the TOML names, which a hand-written JSON or YAML file may well use: a
# size key ignored would have the size guessed and the intrinsics never scaled.
_K_KEYS = ("camera_matrix", "Camera_Matrix")
_D_KEYS = ("distortion_coefficients", "Distortion_Coefficients", "dist_coeffs")
_W_KEYS = ("image_width", "image_Width", "width")
_H_KEYS = ("image_height", "image_Height", "height")

_TOML_KEYS = {"camera_matrix", "dist_coeffs", "width", "height", "fx", "fy", "cx", "cy",
              "skew", "meta"}


def _finite_array(value: object, where: str) -> np.ndarray:
    try:
        a = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise CameraError(f"{where}: expected numbers, got {value!r}") from None
    if not np.all(np.isfinite(a)):
        raise CameraError(f"{where}: non-finite value in {a.reshape(-1).tolist()}")
    return a


def _check_K(K: np.ndarray, where: str) -> np.ndarray:
    try:
        return check_camera_matrix(K)
    except ValueError as e:
        raise CameraError(f"{where}: {e}") from None


_DIST_NAMES = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4",
               "tx", "ty")


def _check_dist(d: np.ndarray, where: str) -> np.ndarray:
    d = d.reshape(-1)
    if d.size not in DISTORTION_COUNTS[1:]:
        raise CameraError(f"{where}: expected 4, 5, 8, 12 or 14 coefficients, got {d.size}")
    big = np.nonzero(np.abs(d) > MAX_DISTORTION)[0]
    if big.size:
        i = int(big[0])
        raise CameraError(f"{where}: {_DIST_NAMES[i]} = {d[i]:g} is beyond +-{MAX_DISTORTION:g}: "
                          "no lens distorts that much")
    return d


def _check_focal(K: np.ndarray, width: int, height: int, where: str) -> None:
    try:
        check_focal(float(K[0, 0]), float(K[1, 1]), width, height)
    except ValueError as e:
        raise CameraError(f"{where}: {e}") from None


def _size(value: object, where: str) -> int:
    if isinstance(value, bool) or value is None:
        raise CameraError(f"{where}: expected a positive integer, got {value!r}")
    try:
        v = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise CameraError(f"{where}: expected a positive integer, got {value!r}") from None
    if not math.isfinite(v) or v != int(v) or v <= 0:
        raise CameraError(f"{where}: expected a positive integer, got {value!r}")
    return int(v)


def _build(K: np.ndarray, d: np.ndarray, w: int | None, h: int | None, source: str,
           image_size: tuple[int, int] | None, k_where: str, d_where: str) -> CameraModel:
    """The model; ``k_where`` names the camera matrix's key for a focal length that cannot
    belong to the image (the file's size, the caller's, else the guessed one), ``d_where``
    the distortion's for a distortion no lens has on it."""
    known = w is not None and h is not None
    if not known:
        if image_size is not None:
            w, h = int(image_size[0]), int(image_size[1])
            known = True
        else:
            # A guess only: the principal point is near the centre. size_known=False makes
            # the first scaled_to() adopt the real frame size instead of scaling.
            w = max(1, round(2.0 * (K[0, 2] + 0.5)))
            h = max(1, round(2.0 * (K[1, 2] + 0.5)))
    try:
        model = CameraModel(K, d, int(w), int(h), size_known=known)  # type: ignore[arg-type]
    except CameraError as e:
        raise CameraError(f"{source}: {e}") from None
    _check_focal(model.camera_matrix, model.width, model.height, k_where)
    shift = abs(model.camera_matrix[0, 1]) * model.height / (2.0 * model.fy)
    if shift > MAX_IGNORED_SKEW_PX:
        raise CameraError(f"{k_where}: skew {model.camera_matrix[0, 1]:g} px would move the "
                          f"image's edge by {shift:.3g} px, and OpenCV ignores skew: "
                          "calibrate without it (0)")
    try:
        problem = distortion_problem(model.camera_matrix, check_distortion(model.dist_coeffs),
                                     model.width, model.height)
    except ValueError as e:  # a tilted sensor (tauX, tauY), which no stage models
        problem = str(e)
    if problem:
        raise CameraError(f"{d_where}: {problem}")
    return model


def _fs_error(exc: BaseException) -> str:
    """The useful line of a cv2.error (the python binding wraps it in a SystemError)."""
    err = exc.__cause__ or exc
    text = str(err).strip()
    m = re.search(r"in function '(.*)'", text, re.S)
    if m:
        return m.group(1).strip()
    return text.splitlines()[-1] if text else type(exc).__name__


def _fs_number(node: object, where: str) -> float:
    # real() of a string or a map is DBL_MAX or 0, not an error: ask what the node is first.
    if not (node.isReal() or node.isInt()):  # type: ignore[attr-defined]
        raise CameraError(f"{where}: expected numbers")
    return float(node.real())  # type: ignore[attr-defined]


def _fs_node_array(node: object, where: str) -> np.ndarray:
    """An ``!!opencv-matrix``, a plain list of numbers or a list of rows of numbers."""
    if node.isMap():  # type: ignore[attr-defined]
        try:
            mat = node.mat()  # type: ignore[attr-defined]
        except Exception:  # cv2.error: a map that is no !!opencv-matrix
            mat = None
        if mat is None:
            raise CameraError(f"{where}: expected a matrix (!!opencv-matrix) or a list of "
                              "numbers")
        return _finite_array(mat, where)
    if node.isSeq():  # type: ignore[attr-defined]
        vals: list = []
        for i in range(node.size()):  # type: ignore[attr-defined]
            item = node.at(i)  # type: ignore[attr-defined]
            if item.isSeq():
                vals.append([_fs_number(item.at(j), where) for j in range(item.size())])
            else:
                vals.append(_fs_number(item, where))
        if any(isinstance(v, list) for v in vals) and not all(isinstance(v, list) and
                                                              len(v) == len(vals[0])
                                                              for v in vals):
            raise CameraError(f"{where}: expected a list of numbers or of rows of equal length")
        return _finite_array(vals, where)
    return _finite_array([_fs_number(node, where)], where)


_OPEN_CLOSE = re.compile(r'"(?:[^"\\]|\\.)*"|[\[{]|[\]}]|<[A-Za-z_][^>]*?/>|<[A-Za-z_]|</')


def _nesting(text: str) -> int:
    """The deepest nesting of [ ], { } and XML elements outside JSON/YAML strings."""
    depth = deepest = 0
    for m in _OPEN_CLOSE.finditer(text):
        tok = m.group()
        if tok[0] in "[{" or (tok[0] == "<" and tok[1] != "/" and not tok.endswith("/>")):
            depth += 1
            deepest = max(deepest, depth)
        elif tok[0] in "]}" or tok == "</":
            depth -= 1
    return deepest


def _load_filestorage(path: Path, image_size: tuple[int, int] | None) -> CameraModel:
    import cv2

    try:
        with open(path, "rb") as f:
            data = f.read(MAX_FILESTORAGE_BYTES + 1)
    except OSError as e:
        raise CameraError(f"{path}: cannot read: {e.strerror or e}") from None
    if len(data) > MAX_FILESTORAGE_BYTES:
        raise CameraError(f"{path}: larger than {MAX_FILESTORAGE_BYTES >> 20} MB: not a camera "
                          "file")
    if _nesting(data.decode("utf-8", "replace")) > MAX_FILESTORAGE_NESTING:
        raise CameraError(f"{path}: nested more than {MAX_FILESTORAGE_NESTING} levels deep: not "
                          "a camera file")
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except Exception as e:  # cv2.error, surfacing as SystemError from the constructor
        raise CameraError(f"{path}: not a valid OpenCV FileStorage file: {_fs_error(e)}") from None
    try:
        return _read_filestorage(fs, path, image_size)
    except cv2.error as e:  # a node of an unexpected kind: still one line naming the file
        raise CameraError(f"{path}: cannot read: {_fs_error(e)}") from None
    finally:
        fs.release()


def _read_filestorage(fs: object, path: Path, image_size: tuple[int, int] | None
                      ) -> CameraModel:
    if not fs.isOpened():  # type: ignore[attr-defined]
        raise CameraError(f"{path}: cannot open as an OpenCV FileStorage file")
    if not fs.root().isMap():  # type: ignore[attr-defined]
        raise CameraError(f"{path}: expected keys (camera_matrix, distortion_coefficients), "
                          "got a top-level list or value")

    def node(keys: tuple[str, ...]) -> tuple[str, object | None]:
        found = [(k, n) for k in keys
                 for n in [fs.getNode(k)]  # type: ignore[attr-defined]
                 if not n.empty() and not n.isNone()]
        if len(found) > 1:
            raise CameraError(f"{path}: {found[0][0]!r} and {found[1][0]!r} are the same key: "
                              "give one")
        return found[0] if found else (keys[0], None)

    kk, kn = node(_K_KEYS)
    if kn is None:
        raise CameraError(f"{path}: missing key {kk!r} (or {_K_KEYS[1]!r})")
    K = _check_K(_fs_node_array(kn, f"{path}: {kk}"), f"{path}: {kk}")
    dk, dn = node(_D_KEYS)
    if dn is None:
        raise CameraError(f"{path}: missing key {dk!r} (or {_D_KEYS[1]!r})")
    d = _check_dist(_fs_node_array(dn, f"{path}: {dk}"), f"{path}: {dk}")
    wk, wn = node(_W_KEYS)
    hk, hn = node(_H_KEYS)
    if (wn is None) != (hn is None):
        missing = wk if wn is None else hk
        raise CameraError(f"{path}: missing key {missing!r} (give both image size keys or "
                          f"neither)")
    w = h = None
    if wn is not None and hn is not None:
        if not ((wn.isInt() or wn.isReal()) and (hn.isInt() or hn.isReal())):  # type: ignore[attr-defined]
            raise CameraError(f"{path}: {wk}/{hk}: expected positive integers")
        w = _size(wn.real(), f"{path}: {wk}")  # type: ignore[attr-defined]
        h = _size(hn.real(), f"{path}: {hk}")  # type: ignore[attr-defined]
    return _build(K, d, w, h, str(path), image_size, f"{path}: {kk}", f"{path}: {dk}")


def _load_toml(path: Path, image_size: tuple[int, int] | None) -> CameraModel:
    try:
        data = toml.loads(path.read_text())
    except UnicodeDecodeError:
        raise CameraError(f"{path}: not a text file") from None
    except (toml.TOMLDecodeError, toml.TooDeep) as e:
        raise CameraError(f"{path}: invalid TOML: {e}") from None
    unknown = set(data) - _TOML_KEYS
    if unknown:
        raise CameraError(f"{path}: unknown key(s) {sorted(unknown)}")
    if "camera_matrix" in data:
        extra = {"fx", "fy", "cx", "cy", "skew"} & set(data)
        if extra:
            raise CameraError(f"{path}: give either camera_matrix or fx/fy/cx/cy, not both "
                              f"(found {sorted(extra)})")
        K = _check_K(_finite_array(data["camera_matrix"], f"{path}: camera_matrix"),
                     f"{path}: camera_matrix")
    else:
        vals = {}
        for k in ("fx", "fy", "cx", "cy"):
            if k not in data:
                raise CameraError(f"{path}: missing key 'camera_matrix' (or {k!r})")
            a = _finite_array(data[k], f"{path}: {k}")
            if a.ndim != 0:
                raise CameraError(f"{path}: {k}: expected a number, got {data[k]!r}")
            vals[k] = float(a)
        skew = _finite_array(data.get("skew", 0.0), f"{path}: skew")
        if skew.ndim != 0:
            raise CameraError(f"{path}: skew: expected a number, got {data['skew']!r}")
        K = _check_K(np.array([[vals["fx"], float(skew), vals["cx"]], [0.0, vals["fy"], vals["cy"]],
                               [0.0, 0.0, 1.0]]), f"{path}: fx/fy/cx/cy")
    if "dist_coeffs" not in data:
        raise CameraError(f"{path}: missing key 'dist_coeffs' (use [0, 0, 0, 0, 0] for none)")
    d = _check_dist(_finite_array(data["dist_coeffs"], f"{path}: dist_coeffs"),
                    f"{path}: dist_coeffs")
    if ("width" in data) != ("height" in data):
        raise CameraError(f"{path}: missing key {'height' if 'width' in data else 'width'!r}")
    w = h = None
    if "width" in data:
        w = _size(data["width"], f"{path}: width")
        h = _size(data["height"], f"{path}: height")
    if "meta" in data and not isinstance(data["meta"], dict):
        raise CameraError(f"{path}: meta: expected a table")
    k_where = f"{path}: camera_matrix" if "camera_matrix" in data else str(path)
    return _build(K, d, w, h, str(path), image_size, k_where, f"{path}: dist_coeffs")


def load_camera(path: str | Path, image_size: tuple[int, int] | None = None) -> CameraModel:
    """Read a camera file: OpenCV FileStorage (.yml/.yaml/.xml/.json) or TOML (.toml).

    FileStorage keys: ``camera_matrix`` (3x3) and ``distortion_coefficients`` (4, 5, 8, 12 or
    14), also spelled ``Camera_Matrix`` / ``Distortion_Coefficients``; optional
    ``image_width`` / ``image_height`` (also ``image_Width`` / ``image_Height``). TOML keys:
    see ``docs/camera.md``. ``image_size`` (width, height) is used when the file gives none;
    without either the model's ``size_known`` is False. Raises ``CameraError`` naming the
    file and the key.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (*FILESTORAGE_SUFFIXES, ".toml"):
        raise CameraError(f"{path}: unknown camera file format {path.suffix!r} "
                          f"(use .yml, .yaml, .xml, .json or .toml)")
    try:
        with open(path, "rb") as f:
            head = f.read(1)
    except OSError as e:
        raise CameraError(f"{path}: cannot read: {e.strerror or e}") from None
    if not head:
        raise CameraError(f"{path}: empty file")
    if suffix == ".toml":
        return _load_toml(path, image_size)
    return _load_filestorage(path, image_size)


def save_camera(model: CameraModel, path: str | Path, meta: dict | None = None) -> None:
    """Write ``model`` to ``path``; the format follows the suffix (as in :func:`load_camera`).

    ``meta``: extra scalars (str, int, float, bool) stored beside the model, e.g. the RMS
    reprojection error (``avg_reprojection_error`` in FileStorage files as OpenCV's sample
    writes it). The image size is written only when known.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    meta = dict(meta or {})
    for k, v in meta.items():
        if not isinstance(v, (str, int, float, bool)):
            raise CameraError(f"{path}: meta {k!r}: only str/int/float/bool values can be saved")
    if suffix == ".toml":
        import tomli_w

        # Written by hand: one matrix row per line reads better than tomli_w's layout.
        lines = ["# Camera model: pixels; dist_coeffs in OpenCV order (k1, k2, p1, p2, k3, ...)"]
        if model.size_known:
            lines += [f"width = {model.width}", f"height = {model.height}"]
        lines.append("camera_matrix = [")
        lines += ["    [" + ", ".join(repr(float(v)) for v in row) + "],"
                  for row in model.camera_matrix]
        lines.append("]")
        lines.append("dist_coeffs = [" + ", ".join(repr(float(v)) for v in model.dist_coeffs)
                     + "]")
        text = "\n".join(lines) + "\n"
        if meta:
            text += "\n" + tomli_w.dumps({"meta": meta})
        try:
            path.write_text(text)
        except OSError as e:
            raise CameraError(f"{path}: cannot write: {e.strerror or e}") from None
        return
    if suffix not in FILESTORAGE_SUFFIXES:
        raise CameraError(f"{path}: unknown camera file format {path.suffix!r} "
                          f"(use .yml, .yaml, .xml, .json or .toml)")
    import cv2

    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    except Exception as e:
        raise CameraError(f"{path}: cannot write: {_fs_error(e)}") from None
    if not fs.isOpened():
        raise CameraError(f"{path}: cannot open for writing")
    try:
        if model.size_known:
            fs.write("image_width", int(model.width))
            fs.write("image_height", int(model.height))
        fs.write("camera_matrix", np.ascontiguousarray(model.camera_matrix, dtype=np.float64))
        fs.write("distortion_coefficients",
                 np.ascontiguousarray(model.dist_coeffs.reshape(-1, 1), dtype=np.float64))
        for k, v in meta.items():
            key = "avg_reprojection_error" if k == "rms" else k
            if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", key):
                raise CameraError(f"{path}: meta key {k!r} is not a valid FileStorage name")
            fs.write(key, int(v) if isinstance(v, bool) else v)
    finally:
        fs.release()
