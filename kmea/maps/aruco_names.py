"""The one table of ArUco dictionary names (standard library only).

A dictionary is named either by one of OpenCV's predefined dictionaries (case-insensitive,
the ``DICT_`` prefix optional: ``"5x5_100"`` is ``DICT_5X5_100``) or by a custom dictionary
file (a path, or any name ending in .yml/.yaml/.xml/.json/.gz, as ``writeDictionary``
writes). The configuration (``detector.dictionary``), map files and the detector
(:mod:`kmea.vision.dictionary`) all accept exactly this.
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["FILE_SUFFIXES", "MAX_MARKER_ID", "PREDEFINED", "canonical_name",
           "check_dictionary_name", "is_dictionary_file"]


def _sizes() -> dict[str, int]:
    sizes = {f"DICT_{b}X{b}_{n}": n for b in (4, 5, 6, 7) for n in (50, 100, 250, 1000)}
    sizes.update({"DICT_ARUCO_ORIGINAL": 1024, "DICT_APRILTAG_16h5": 30,
                  "DICT_APRILTAG_25h9": 35, "DICT_APRILTAG_36h10": 2320,
                  "DICT_APRILTAG_36h11": 587, "DICT_ARUCO_MIP_36h12": 250})
    return sizes


# OpenCV's predefined ArUco dictionaries and their number of markers (valid ids 0..n-1).
PREDEFINED: dict[str, int] = _sizes()
_BY_KEY = {n.upper(): n for n in PREDEFINED}
# The largest id a map or a robot may name: above every predefined dictionary (the
# largest, DICT_APRILTAG_36h10, has 2320 markers), so an id beyond is a slip (1e20), not a
# marker; the dictionary in use is checked against its own size where it is known.
MAX_MARKER_ID = 4095

FILE_SUFFIXES = (".yml", ".yaml", ".xml", ".json", ".gz")


def is_dictionary_file(text: str) -> bool:
    """The name denotes a custom dictionary file (by suffix, a path separator, or an
    existing file) rather than a predefined name."""
    return (text.lower().endswith(FILE_SUFFIXES) or "/" in text or "\\" in text
            or Path(text).is_file())


def canonical_name(name: str) -> str | None:
    """OpenCV's spelling of a predefined dictionary (``"5x5_100"`` -> ``"DICT_5X5_100"``),
    or None when ``name`` is not one."""
    key = name.strip().upper()
    if not key.startswith("DICT_"):
        key = "DICT_" + key
    return _BY_KEY.get(key)


def check_dictionary_name(value: object, where: str) -> str:
    """A predefined name (returned in OpenCV's spelling) or a custom dictionary file name
    (returned as given; the detector reads and checks the file). ``ValueError`` naming
    ``where`` otherwise."""
    if not isinstance(value, str) or not value.strip():
        raise ValueError(f"{where}: expected a dictionary name or file, got {value!r}")
    text = value.strip()
    if is_dictionary_file(text):
        return text
    name = canonical_name(text)
    if name is None:
        raise ValueError(f"{where}: unknown ArUco dictionary {value!r} (e.g. DICT_5X5_50, "
                         f"DICT_5X5_100, DICT_4X4_50; or a .yml/.json dictionary file)")
    return name
