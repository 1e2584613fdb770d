"""kmead's command-line shell: its stderr log."""

from __future__ import annotations

import io
import logging
import sys

from kmead.cli import _setup_logging


def test_the_log_goes_to_the_current_stderr_not_a_closed_one(monkeypatch) -> None:
    # main() may run more than once in a process (tests, the UI's embedded daemon): a
    # record written after the stderr of an earlier call was closed must reach today's.
    first = io.StringIO()
    monkeypatch.setattr(sys, "stderr", first)
    _setup_logging("info", timestamps=False)
    log = logging.getLogger("kmead")
    log.info("before")
    first.close()
    second = io.StringIO()
    monkeypatch.setattr(sys, "stderr", second)
    log.info("after")
    assert second.getvalue() == "kmead: INFO: after\n"
