"""The headless daemon talks: a one-line status every few seconds on stderr, a clear final
line, and the same line as the systemd ``STATUS=``.

Lines carry a timestamp unless stderr is the systemd journal (which stamps them itself):
systemd sets ``$JOURNAL_STREAM`` to ``DEVICE:INODE`` of the stream it connected, so we
compare it with stderr's.
"""

from __future__ import annotations

import os
import sys
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any, TextIO


def stderr_is_journal(env: Mapping[str, str] | None = None, fd: int | None = None) -> bool:
    """True when ``fd`` (default stderr) is the journal stream named by ``$JOURNAL_STREAM``."""
    env = os.environ if env is None else env
    value = env.get("JOURNAL_STREAM", "")
    dev, _, ino = value.partition(":")
    if not (dev.isdigit() and ino.isdigit()):
        return False
    try:
        st = os.fstat(sys.stderr.fileno() if fd is None else fd)
    except (OSError, ValueError, AttributeError):
        return False
    return st.st_dev == int(dev) and st.st_ino == int(ino)


def format_status(p: Mapping[str, Any]) -> str:
    """One line from a progress snapshot (see ``Daemon.progress``).

    Keys: frames, fps, robots_tracked, robots, loo_mean_m (None when not computed),
    dropped, bad_frames.
    """
    loo = p.get("loo_mean_m")
    loo_text = f"LOO {loo * 1e3:.2f} mm" if isinstance(loo, (int, float)) else "LOO -"
    return (f"frames {p.get('frames', 0)}, {p.get('fps', 0.0):.1f} frames/s, robots "
            f"{p.get('robots_tracked', 0)}/{p.get('robots', 0)} tracked, {loo_text}, "
            f"dropped {p.get('dropped', 0)}, bad {p.get('bad_frames', 0)}")


class StatusReporter:
    """Every ``period_s``: ``snapshot()`` -> one line on ``stream`` (when given) and to
    ``on_line`` (the systemd status). ``timestamps``: prefix the local time."""

    def __init__(self, snapshot: Callable[[], Mapping[str, Any]], period_s: float = 5.0,
                 stream: TextIO | None = None, timestamps: bool = True,
                 on_line: Callable[[str], Any] | None = None) -> None:
        self.snapshot = snapshot
        self.period_s = period_s
        self.stream = stream
        self.timestamps = timestamps
        self.on_line = on_line
        self.lines = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def stamp(self, text: str) -> str:
        if not self.timestamps:
            return f"kmead: {text}"
        return f"{time.strftime('%Y-%m-%d %H:%M:%S')} kmead: {text}"

    def emit(self) -> str:
        line = format_status(self.snapshot())
        if self.stream is not None:
            print(self.stamp(line), file=self.stream, flush=True)
        if self.on_line is not None:
            self.on_line(line)
        self.lines += 1
        return line

    def start(self) -> None:
        def loop() -> None:
            while not self._stop.wait(self.period_s):
                try:
                    self.emit()
                except Exception as e:  # a status line must never stop the daemon
                    if self.stream is not None:
                        print(self.stamp(f"status line failed: {e}"), file=self.stream)

        self._thread = threading.Thread(target=loop, name="kmead-status", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
