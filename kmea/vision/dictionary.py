"""ArUco dictionaries: OpenCV's predefined ones by name, or custom ones from a file.

Names follow the one table of :mod:`kmea.maps.aruco_names` (shared with map files).

A custom dictionary file is what ``cv2.aruco.Dictionary.writeDictionary`` writes (OpenCV
FileStorage, YAML / XML / JSON): ``nmarkers``, ``markersize``, optional
``maxCorrectionBits`` and ``marker_0 .. marker_{n-1}`` bit strings, at the root or under
one named node.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np

from kmea.maps.aruco_names import PREDEFINED, canonical_name, is_dictionary_file

__all__ = ["DictionaryError", "get_dictionary", "predefined_names"]


class DictionaryError(ValueError):
    """Unknown dictionary name or unreadable dictionary file (the message names which)."""


def predefined_names() -> list[str]:
    """Names of OpenCV's predefined dictionaries (``DICT_4X4_50`` ... ``DICT_ARUCO_MIP_36h12``)."""
    return sorted(PREDEFINED)


def get_dictionary(name_or_path: str | Path) -> cv2.aruco.Dictionary:
    """A predefined dictionary by name (``"DICT_5X5_100"``, case-insensitive, ``DICT_`` optional)
    or a custom dictionary file (a path, or any name ending in .yml/.yaml/.xml/.json).

    Raises ``DictionaryError`` naming the unknown name or the bad file.
    """
    if isinstance(name_or_path, Path):
        return _read_file(str(name_or_path))
    if not isinstance(name_or_path, str) or not name_or_path.strip():
        raise DictionaryError(f"dictionary: expected a name or a file path, got {name_or_path!r}")
    text = name_or_path.strip()
    if is_dictionary_file(text):
        return _read_file(text)
    return _predefined(text)


def _predefined(name: str) -> cv2.aruco.Dictionary:
    key = name.upper() if name.upper().startswith("DICT_") else "DICT_" + name.upper()
    key = canonical_name(name) or key
    code = getattr(cv2.aruco, key, None)
    if not isinstance(code, int):
        close = [n for n in predefined_names() if key[5:8] in n][:6] or predefined_names()[:6]
        raise DictionaryError(
            f"dictionary {name!r}: not a predefined OpenCV dictionary nor an existing file "
            f"(e.g. {', '.join(close)}; or a .yml/.json file written by writeDictionary)")
    return cv2.aruco.getPredefinedDictionary(code)


@lru_cache(maxsize=16)
def _read_file_cached(path: str, mtime_ns: int) -> tuple[np.ndarray, int, int]:
    p = Path(path)
    try:
        fs = cv2.FileStorage(path, cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError):
        # OpenCV raises (sometimes wrapped in SystemError) on a file it cannot parse.
        raise DictionaryError(f"dictionary file {p}: not an OpenCV FileStorage file "
                              "(YAML, XML or JSON as written by writeDictionary)") from None
    try:
        if not fs.isOpened():
            raise DictionaryError(f"dictionary file {p}: OpenCV cannot parse it")
        node = fs.root()
        if node.getNode("nmarkers").empty():
            # writeDictionary(fs, name) nests the dictionary under one named node.
            children = [node.getNode(k) for k in node.keys()]  # noqa: SIM118 (FileNode is not iterable)
            nested = [c for c in children if c.isMap() and not c.getNode("nmarkers").empty()]
            if len(nested) != 1:
                raise DictionaryError(f"dictionary file {p}: missing key 'nmarkers'")
            node = nested[0]
        for key in ("nmarkers", "markersize"):
            n = node.getNode(key)
            if n.empty() or not n.isInt() or int(n.real()) <= 0:
                raise DictionaryError(
                    f"dictionary file {p}: key {key!r} must be a positive integer")
        nmarkers = int(node.getNode("nmarkers").real())
        size = int(node.getNode("markersize").real())
        for i in range(nmarkers):
            bits = node.getNode(f"marker_{i}")
            s = bits.string() if bits.isString() else ""
            if len(s) != size * size or set(s) - {"0", "1"}:
                raise DictionaryError(
                    f"dictionary file {p}: key 'marker_{i}' must be a string of "
                    f"{size * size} '0'/'1' characters")
        d = cv2.aruco.Dictionary()
        if not d.readDictionary(node):
            raise DictionaryError(f"dictionary file {p}: OpenCV's readDictionary rejected it")
        return d.bytesList.copy(), int(d.markerSize), int(d.maxCorrectionBits)
    finally:
        fs.release()


def _read_file(path: str) -> cv2.aruco.Dictionary:
    p = Path(path).expanduser()
    if not p.is_file():
        raise DictionaryError(f"dictionary file {p}: no such file")
    bytes_list, size, max_corr = _read_file_cached(str(p), p.stat().st_mtime_ns)
    return cv2.aruco.Dictionary(bytes_list.copy(), size, max_corr)
