"""Whole records on disk: the CSV log and the recording write each frame in one call, and a
write that fails part-way (a full disk: ``ENOSPC``) is cut back to the last whole record, so
a reader never meets a cut row.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

__all__ = ["open_output", "write_whole"]


def open_output(path: Path, append: bool = False) -> Any:
    """The unbuffered binary file an output writes (the one place outputs open files, so a
    test can put a full disk here)."""
    return open(path, "ab" if append else "wb", buffering=0)


def write_whole(f: Any, data: bytes, end: int) -> None:
    """Write all of ``data`` to the unbuffered file ``f`` whose last whole record ends at byte
    ``end``. On an OSError (ENOSPC, EIO) part of ``data`` may be on disk: the file is cut
    back to ``end`` (truncating needs no free space) and the error raised again, with
    ``cut_back`` set to whether the cut worked."""
    view = memoryview(data)
    try:
        while view:
            n = f.write(view)
            view = view[n or 0:]
    except OSError as e:
        try:
            f.truncate(end)
            e.cut_back = True  # type: ignore[attr-defined]
        except (OSError, ValueError):
            e.cut_back = False  # type: ignore[attr-defined]
        raise
