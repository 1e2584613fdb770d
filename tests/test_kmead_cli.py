"""kmead's command-line shell: its stderr log, and nothing of it left behind in-process."""

from __future__ import annotations

import io
import logging
import sys
import threading

import pytest
from deadlines import JOIN

from kmead import cli
from kmead.tools.kmea_cli import main as kmea_main

NET = ["--set", 'network.telemetry="tcp://127.0.0.1:*"', "--set", 'network.control=""']


def test_the_log_goes_to_the_current_stderr_not_a_closed_one(monkeypatch) -> None:
    # main() may run more than once in a process (tests, the UI's embedded daemon): a
    # record written after the stderr of an earlier call was closed must reach today's.
    first = io.StringIO()
    monkeypatch.setattr(sys, "stderr", first)
    with cli.stderr_logging("info", timestamps=False):
        log = logging.getLogger("kmead")
        log.info("before")
        first.close()
        second = io.StringIO()
        monkeypatch.setattr(sys, "stderr", second)
        log.info("after")
    assert second.getvalue() == "kmead: INFO: after\n"


def _state() -> tuple:
    log = logging.getLogger("kmead")
    return list(log.handlers), log.level, log.propagate


def _later_daemon_logs(capsys) -> str:
    """What a daemon started later in this process would print on stderr at INFO."""
    capsys.readouterr()
    logging.getLogger("kmead.daemon").info("a later in-process daemon")
    return capsys.readouterr().err


def test_in_process_kmead_leaves_no_log_handler_behind(capsys) -> None:
    before = _state()
    assert cli.main(["--headless", "--frames", "1", "--status-every", "0",
                     "--set", "source.width=320", "--set", "source.height=240", *NET]) == 0
    assert "kmead: stopped" in capsys.readouterr().err  # it did run, with its stderr log
    assert _state() == before
    assert _later_daemon_logs(capsys) == ""


def test_in_process_fusion_node_leaves_no_log_handler_behind(capsys) -> None:
    pytest.importorskip("zenoh", reason="the zenoh extra is not installed")
    from zenoh_helpers import FakeCamera, free_port, meta

    port = free_port()
    done = threading.Event()

    def camera() -> None:  # a camera's measurements until the node has its one
        cam = FakeCamera(port, "cam0", meta("cam0", "d" * 16))
        k = 0
        try:
            while not done.wait(0.05):
                cam.measurement("amr1", 100.0 + 0.1 * k, 0.5, 0.3)
                cam.put("frame", {"t": 100.0 + 0.1 * k, "frames": k})
                k += 1
        finally:
            cam.close()

    before = _state()
    t = threading.Thread(target=camera, daemon=True)
    t.start()
    try:
        assert kmea_main(["fuse", "--headless", "--frames", "1", *NET, "--set",
                          "zenoh.lease_s=0.5", "--set",
                          f'zenoh.listen=["tcp/127.0.0.1:{port}"]']) == 0
    finally:
        done.set()
        t.join(timeout=JOIN)
    assert "kmea fuse: 1 fused outputs" in capsys.readouterr().out
    assert _state() == before
    assert _later_daemon_logs(capsys) == ""
