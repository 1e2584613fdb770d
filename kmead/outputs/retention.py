"""How long kmead's own files are kept: one rule for CSV logs, recordings and snapshots.

A service that logs every frame writes about 3.4 KB a frame (370 MB an hour at 30
frames/s): a week of practice days fills an SD card. So every output is cut into parts
(``log.part_mb`` / ``log.part_min``, :mod:`kmead.outputs.files`) and the directories kmead
writes to keep at most ``log.keep_days`` days and ``log.keep_mb`` MB of kmead's files: the
oldest go first, never a file being written.

Only files kmead made are ever counted or removed, recognised by their content, not their
name: a CSV whose first line is the log's header, a recording whose first line is a
recording header, a ``snapshot-*.png``. A user's other files in the same directory are never
touched.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from kmea.recordings.format import RecordingError, read_header
from kmead.outputs.csvlog import has_header

__all__ = ["KmeaFile", "Usage", "kmea_files", "prune", "usage"]

DAY_S = 86400.0


@dataclass(frozen=True)
class KmeaFile:
    path: Path
    kind: str  # "log", "record", "snapshot"
    bytes: int
    mtime: float  # s since the epoch


@dataclass(frozen=True)
class Usage:
    """What kmead's files in some directories take (``kmea doctor``)."""

    files: int
    bytes: int
    oldest_days: float | None


def _kind(p: Path) -> str | None:
    name = p.name
    try:
        if name.endswith(".csv"):
            return "log" if has_header(p) else None
        if name.endswith((".jsonl", ".jsonl.zst")):
            read_header(p)
            return "record"
    except (OSError, RecordingError, ValueError):
        return None
    if name.startswith("snapshot-") and name.endswith(".png"):
        return "snapshot"
    return None


def kmea_files(directories: Iterable[Path]) -> list[KmeaFile]:
    """kmead's files directly in ``directories`` (module docstring), oldest first."""
    out: dict[Path, KmeaFile] = {}
    for d in directories:
        try:
            entries = list(Path(d).iterdir())
        except OSError:
            continue
        for p in entries:
            try:
                st = p.lstat()
            except OSError:
                continue
            if not p.is_file() or p.is_symlink():
                continue
            kind = _kind(p)
            if kind is not None:
                rp = p.resolve()
                out[rp] = KmeaFile(rp, kind, st.st_size, st.st_mtime)
    return sorted(out.values(), key=lambda f: f.mtime)


def usage(directories: Iterable[Path], now: float | None = None) -> Usage:
    files = kmea_files(directories)
    now = time.time() if now is None else now
    return Usage(len(files), sum(f.bytes for f in files),
                 (now - files[0].mtime) / DAY_S if files else None)


def prune(directories: Iterable[Path], keep_days: float, keep_mb: float,
          active: Iterable[Path] = (), now: float | None = None) -> list[KmeaFile]:
    """Remove kmead's files older than ``keep_days`` days, then the oldest until they take at
    most ``keep_mb`` MB (10^6 bytes; 0 = no limit of that kind); never one of ``active``.
    The files removed (a file that cannot be removed is left and not listed)."""
    now = time.time() if now is None else now
    keep = {Path(a).resolve() for a in active}
    files = [f for f in kmea_files(directories) if f.path not in keep]
    total = sum(f.bytes for f in files) + sum(
        f.bytes for f in kmea_files(directories) if f.path in keep)
    removed: list[KmeaFile] = []
    for f in files:  # oldest first
        too_old = keep_days > 0 and now - f.mtime > keep_days * DAY_S
        too_much = keep_mb > 0 and total > keep_mb * 1e6
        if not (too_old or too_much):
            continue
        with contextlib.suppress(OSError):
            f.path.unlink()
            removed.append(f)
            total -= f.bytes
    return removed
