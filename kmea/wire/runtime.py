"""Where the running daemons of this machine listen: one small file per process.

A ``kmead`` or ``kmea fuse`` that has bound its sockets writes ``<pid>.json`` (its kind,
telemetry and control endpoints as a client on this machine reaches them, its key
directory, its start time) into :func:`runtime_dir`, and removes it when it stops. So
``kmea-tui`` without endpoints finds the daemon that ``make run`` started on free ports. A
file whose process is gone (killed) is ignored and removed by the next reader. Stdlib only:
the UI imports it.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
import time
from pathlib import Path

__all__ = ["announce", "live_daemons", "runtime_dir", "withdraw"]


def runtime_dir() -> Path:
    """``$XDG_RUNTIME_DIR/kmea`` (systemd's per-user runtime directory), else
    ``<tmp>/kmea-<uid>``: private to the user (mode 0700)."""
    base = os.environ.get("XDG_RUNTIME_DIR")
    if base and Path(base).is_dir():
        return Path(base) / "kmea"
    return Path(tempfile.gettempdir()) / f"kmea-{os.getuid()}"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process: alive, not ours to judge
        return True
    return True


def announce(kind: str, telemetry: str, control: str, keys: str = "",
             directory: Path | None = None) -> Path | None:
    """Write this process's endpoints; the file, or None when it cannot be written (a
    read-only or foreign directory: the UI then needs its endpoints typed, nothing else
    changes)."""
    d = directory or runtime_dir()
    body = {"kind": kind, "pid": os.getpid(), "telemetry": telemetry, "control": control,
            "keys": keys, "started": time.time()}
    try:
        d.mkdir(mode=0o700, parents=True, exist_ok=True)
        if d.stat().st_uid != os.getuid():
            return None
        path = d / f"{os.getpid()}.json"
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps(body))
        tmp.replace(path)
        return path
    except OSError:
        return None


def withdraw(path: Path | None) -> None:
    if path is not None:
        with contextlib.suppress(OSError):
            path.unlink()


def live_daemons(directory: Path | None = None) -> list[dict]:
    """The announced daemons whose process is alive, newest first; stale files removed."""
    d = directory or runtime_dir()
    out = []
    try:
        files = list(d.glob("*.json"))
    except OSError:
        return []
    for f in files:
        try:
            body = json.loads(f.read_text())
            pid = int(body["pid"])
            ok = (isinstance(body.get("telemetry"), str) and isinstance(body.get("control"), str)
                  and isinstance(body.get("started"), (int, float)))
        except (OSError, ValueError, KeyError, TypeError):
            continue
        if not _alive(pid):
            with contextlib.suppress(OSError):
                f.unlink()
            continue
        if ok:
            out.append(body)
    return sorted(out, key=lambda b: -b["started"])
