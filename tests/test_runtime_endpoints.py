"""kmea-tui without endpoints finds the kmead that ``make run`` started on free ports: the
daemon announces its endpoints in a runtime file (kmea.wire.runtime) while it runs."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import zmq
from deadlines import DEADLINE, JOIN

from kmea.wire import protocol
from kmea.wire.runtime import announce, live_daemons, withdraw
from kmea_tui.cli import _endpoints, build_parser

ROOT = Path(__file__).resolve().parent.parent


def test_a_dead_processs_file_is_ignored_and_removed(tmp_path) -> None:
    own = announce("kmead", "tcp://127.0.0.1:1", "tcp://127.0.0.1:2", directory=tmp_path)
    assert own is not None
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True, timeout=JOIN)
    stale = tmp_path / f"{dead.stdout.strip()}.json"
    stale.write_text(json.dumps({"kind": "kmead", "pid": int(dead.stdout), "started": 1e12,
                                 "telemetry": "tcp://127.0.0.1:3", "control": "x"}))
    (tmp_path / "garbage.json").write_text("{")
    found = live_daemons(tmp_path)
    assert [d["pid"] for d in found] == [os.getpid()]
    assert not stale.exists()
    withdraw(own)
    assert live_daemons(tmp_path) == []


def test_given_endpoints_win_and_none_anywhere_gives_the_defaults(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    args = build_parser().parse_args([])
    _endpoints(args)
    assert (args.telemetry, args.control) == (protocol.DEFAULT_TELEMETRY,
                                              protocol.DEFAULT_CONTROL)
    announce("kmead", "tcp://127.0.0.1:7001", "tcp://127.0.0.1:7002")
    args = build_parser().parse_args(["--telemetry", "tcp://127.0.0.1:6001", "--control",
                                      "tcp://127.0.0.1:6002"])
    _endpoints(args)
    assert args.telemetry == "tcp://127.0.0.1:6001"


def test_the_ui_finds_a_free_ports_kmead_and_forgets_it_when_it_stops(tmp_path,
                                                                      monkeypatch) -> None:
    env = dict(os.environ, XDG_RUNTIME_DIR=str(tmp_path),
               PYTHONPATH=f"{ROOT}{os.pathsep}" + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.Popen(
        [sys.executable, "-m", "kmead.cli", "--headless", "--free-ports", "--status-every", "0",
         "--set", "source.width=320", "--set", "source.height=240"],
        cwd=tmp_path, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + DEADLINE
        found: list[dict] = []
        while not found and time.monotonic() < deadline and proc.poll() is None:
            found = live_daemons(tmp_path / "kmea")
            time.sleep(0.1)
        assert found, "kmead announced no endpoints"
        assert found[0]["pid"] == proc.pid and found[0]["kind"] == "kmead"
        monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
        args = argparse.Namespace(telemetry=None, control=None, keys=None)
        _endpoints(args)
        assert args.telemetry == found[0]["telemetry"] != protocol.DEFAULT_TELEMETRY
        ctx = zmq.Context.instance()
        req = ctx.socket(zmq.REQ)
        req.setsockopt(zmq.LINGER, 0)
        req.connect(args.control)
        req.send_json({"v": protocol.PROTOCOL_VERSION, "cmd": "ping"})
        assert req.poll(int(DEADLINE * 1000)), "the announced control socket did not answer"
        assert req.recv_json()["ok"] is True
        req.close()
    finally:
        proc.terminate()
        proc.wait(JOIN)
    assert live_daemons(tmp_path / "kmea") == []
    assert not list((tmp_path / "kmea").glob("*.json"))
