"""The focus a calibration was made at: the lens position stored beside the camera model.

An autofocus camera (Camera Module 3, the IMX708) moves its lens to focus. Focus changes
the focal length a little and the distortion with it, so a calibration, and the map
measured through it, hold at one lens position only. ``kmea calibrate`` stores the lens
position the camera reported while it saw the board (``lens_position``, dioptres: 1 /
the focus distance in metres, 0 = infinity, libcamera's ``LensPosition``) in the camera
file: a top-level key of a FileStorage file (.yml, .yaml, .xml, .json), ``[meta]
lens_position`` of a TOML one. kmead locks the lens there (``AfMode`` manual,
``LensPosition``) and warns when the lens reports another position.
"""

from __future__ import annotations

import math
from pathlib import Path

from kmea.vision.camera import FILESTORAGE_SUFFIXES, CameraError
from kmea.wire import tomlvalue as toml

__all__ = ["LENS_KEY", "LENS_MAX_DIOPTRE", "LENS_TOL_DIOPTRE", "lens_differs",
           "load_lens_position"]

LENS_KEY = "lens_position"
#: libcamera's LensPosition range on the Raspberry Pi (ipa_base.cpp defaultAfControls:
#: 0-32 dioptres, default 1).
LENS_MAX_DIOPTRE = 32.0
#: A reported lens position this far (dioptres) from the calibration's counts as another
#: focus: 0.05 dioptre moves the focus of a camera 2 m above the floor (0.5 dioptre) by
#: about 0.2 m.
LENS_TOL_DIOPTRE = 0.05


def _check(value: object, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise CameraError(f"{where}: expected a number of dioptres, got {value!r}")
    v = float(value)
    if not (math.isfinite(v) and 0.0 <= v <= LENS_MAX_DIOPTRE):
        raise CameraError(f"{where}: {v!r} dioptres is outside 0..{LENS_MAX_DIOPTRE:g} "
                          f"(libcamera's LensPosition)")
    return v


def load_lens_position(path: str | Path) -> float | None:
    """The lens position (dioptres) stored in the camera file ``path``, or None when it
    stores none (a fixed-focus camera, or a calibration from before). Raises
    :class:`CameraError` naming the file and the key for a bad value or an unreadable file.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    where = f"{path}: {LENS_KEY}"
    if suffix == ".toml":
        try:
            data = toml.loads(path.read_text())
        except (OSError, UnicodeDecodeError, toml.TOMLDecodeError, toml.TooDeep) as e:
            raise CameraError(f"{path}: cannot read: {e}") from None
        meta = data.get("meta", {})
        if not isinstance(meta, dict) or LENS_KEY not in meta:
            return None
        return _check(meta[LENS_KEY], f"{path}: meta.{LENS_KEY}")
    if suffix not in FILESTORAGE_SUFFIXES:
        raise CameraError(f"{path}: unknown camera file format {path.suffix!r}")
    import cv2

    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except Exception as e:  # cv2.error from the constructor
        raise CameraError(f"{path}: cannot read: {e}") from None
    try:
        if not fs.isOpened():
            raise CameraError(f"{path}: cannot open as an OpenCV FileStorage file")
        node = fs.getNode(LENS_KEY)
        if node.empty() or node.isNone():
            return None
        if not (node.isInt() or node.isReal()):
            raise CameraError(f"{where}: expected a number of dioptres")
        return _check(node.real(), where)
    finally:
        fs.release()


def lens_differs(stored: float | None, reported: float | None) -> bool:
    """The lens reports a position other than the calibration's (both known)."""
    return (stored is not None and reported is not None
            and abs(float(reported) - float(stored)) > LENS_TOL_DIOPTRE)
