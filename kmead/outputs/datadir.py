"""The data directory: the only place a control request can make the daemon write.

A name that arrives over the network (``log_start``, ``record_start``) must be a plain file
name: letters, digits, ``.``, ``_`` and ``-``, not starting with a dot, with the suffix of
its kind (``.csv`` for the CSV log; ``.jsonl.zst``, compressed, or ``.jsonl`` for a
recording). It names a new file directly
inside the data directory: never an absolute path, ``..``, a sub-directory, an existing file
or a symlink (dangling or not), and never the file the other output is writing. The file is
created with ``O_CREAT | O_EXCL | O_NOFOLLOW``, so the check and the creation are one step.

Paths from the command line and the configuration file are the operator's own and are not
confined (they are checked for log = record only); see docs/security.md.
"""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from kmead.config.checks import same_file

__all__ = ["SUFFIXES", "DataDir", "FileRefused", "free_bytes", "low_space", "next_part",
           "same_file", "split_suffix"]


class FileRefused(ValueError):
    """A file name a control request may not use; the message says why, in one line."""


# kind -> the suffixes a name may end with (the first is the one kmead's own names use)
SUFFIXES = {"log": (".csv",), "record": (".jsonl.zst", ".jsonl")}
_NAME_RE = re.compile(r"^[A-Za-z0-9_-][A-Za-z0-9._-]{0,127}$")


def split_suffix(path: str | Path) -> tuple[str, str]:
    """(the path without its suffix, the suffix), a compound one kept whole:
    ``run.jsonl.zst`` -> (``run``, ``.jsonl.zst``), so a new name goes before it."""
    p = str(path)
    for suffix in (*SUFFIXES["record"], *SUFFIXES["log"]):
        if p.endswith(suffix) and len(p) > len(suffix):
            return p[:-len(suffix)], suffix
    stem, dot, ext = p.rpartition(".")
    return (stem, dot + ext) if dot and "/" not in ext and stem else (p, "")


def next_part(path: str | Path, part: int) -> tuple[Path, int]:
    """A new, empty file for part ``part`` (or the first free later one) of the recording
    ``path``, created exclusively (nothing is ever written over): ``run.jsonl.zst`` ->
    ``run-part2.jsonl.zst``. (its path, its part number); OSError when it cannot be made."""
    base, suffix = split_suffix(path)
    base = re.sub(r"-part\d+$", "", base)
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0)
    for k in range(part, part + 10000):
        p = Path(f"{base}-part{k}{suffix}")
        try:
            os.close(os.open(p, flags, 0o644))
        except FileExistsError:
            continue
        return p, k
    raise OSError(f"{base}-part{part}{suffix} to -part{part + 9999}: all exist")


def free_bytes(path: str | Path) -> int | None:
    """Bytes an unprivileged process may still write on the filesystem of ``path`` (its
    nearest existing ancestor), or None where that cannot be known (no statvfs)."""
    p = Path(path).absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    try:
        st = os.statvfs(p)
    except (OSError, AttributeError):
        return None
    if st.f_blocks == 0:  # /proc, /sys: no blocks to run out of (a write fails on its own)
        return None
    return st.f_bavail * st.f_frsize


def low_space(path: str | Path, floor_mb: float) -> str | None:
    """Why an output in ``path`` (a file or its directory) must not run: one line when the
    free space there is below ``floor_mb`` MB (10^6 bytes; 0 = no floor), else None."""
    if floor_mb <= 0:
        return None
    free = free_bytes(path)
    if free is None or free >= floor_mb * 1e6:
        return None
    where = Path(path).absolute()
    return (f"{free / 1e6:.1f} MB free on the disk of {where}, below log.min_free_mb = "
            f"{floor_mb:g} MB")


class DataDir:
    """The confined directory ``root`` (created if missing; "" = the working directory)."""

    def __init__(self, root: str | Path = "") -> None:
        p = Path(root or ".").expanduser()
        try:
            p.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise FileRefused(f"data directory {p}: cannot create it: {e.strerror or e}") from None
        if not p.is_dir():
            raise FileRefused(f"data directory {p}: not a directory")
        self.root = p.resolve()

    def check_name(self, name: Any, kind: str) -> Path:
        """The path of a new file ``name`` of ``kind`` ("log" or "record") in the directory;
        :class:`FileRefused` naming the rule it breaks."""
        suffixes = SUFFIXES[kind]
        if not isinstance(name, str) or not name:
            raise FileRefused(f"{kind} file: expected a file name, got {type(name).__name__}")
        shown = name if len(name) <= 60 else name[:57] + "..."
        if "/" in name or "\\" in name or "\x00" in name:
            raise FileRefused(f"{kind} file {shown!r}: a plain file name only (no directories); "
                              f"files go to the data directory {self.root}")
        if name in (".", "..") or ".." in name:
            raise FileRefused(f"{kind} file {shown!r}: '..' is not allowed")
        if not _NAME_RE.match(name):
            raise FileRefused(f"{kind} file {shown!r}: use letters, digits, '.', '_' and '-' "
                              "(not starting with '.'), at most 128 characters")
        if not any(name.endswith(x) and name != x for x in suffixes):
            raise FileRefused(f"{kind} file {shown!r}: the name must end with "
                              f"{' or '.join(suffixes)}")
        path = self.root / name
        if os.path.lexists(path):
            raise FileRefused(f"{kind} file {shown!r}: already exists in {self.root}; "
                              "choose a new name (existing files are never overwritten)")
        return path

    def create(self, name: Any, kind: str, busy: Sequence[str | Path] = ()) -> Path:
        """Check ``name`` and create the empty file atomically; ``busy``: paths of files the
        daemon is writing (the other output), which ``name`` must not be."""
        path = self.check_name(name, kind)
        for other in busy:
            if other and same_file(path, other):
                raise FileRefused(f"{kind} file {name!r}: already in use by the other output")
        flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0)
        try:
            fd = os.open(path, flags, 0o644)
        except FileExistsError:
            raise FileRefused(f"{kind} file {name!r}: already exists in {self.root}") from None
        except OSError as e:
            raise FileRefused(f"{kind} file {name!r}: cannot create it in {self.root}: "
                              f"{e.strerror or e}") from None
        os.close(fd)
        return path
