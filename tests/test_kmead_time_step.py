"""A source whose time steps back, or jumps forward by more than relay.max_time_step_s: the
robots get valid=0 at once (before any pose of the new time), the filters restart, an event
says so, and the robots get valid poses again at the new time. A recording edited to step
back 10 s and then forward 1 h, replayed by the real command line, a real UDP listener."""

from __future__ import annotations

import json
import socket
from pathlib import Path

import pytest

from kmead import cli
from kmead.outputs.relay import parse_datagram

SMALL = ["--set", "source.width=640", "--set", "source.height=480", "--set", "source.fps=0",
         "--set", 'network.telemetry="tcp://127.0.0.1:*"', "--set", 'network.control=""',
         "--headless"]


def test_a_source_time_step_sends_valid_0_at_once_and_restarts(
        tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    rec = tmp_path / "run.jsonl"
    assert cli.main(["--source", "sim:default", "--frames", "30", "--record", str(rec),
                     *SMALL]) == 0
    lines = rec.read_text().splitlines()
    frames = [json.loads(x) for x in lines[1:]]
    for f in frames:
        if 10 <= f["frame"] < 20:
            f["t"] -= 10.0
        elif f["frame"] >= 20:
            f["t"] += 3600.0
    edited = tmp_path / "stepped.jsonl"
    edited.write_text("\n".join([lines[0], *(json.dumps(f) for f in frames)]) + "\n")
    t10, t20 = frames[10]["t"], frames[20]["t"]
    udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    udp.bind(("127.0.0.1", 0))
    udp.settimeout(0.5)
    port = udp.getsockname()[1]
    robots = (f'robots=[{{name="amr1", markers=[40, 41], height=0.2, '
              f'destinations=["udp:127.0.0.1:{port}"]}}]')
    capsys.readouterr()
    try:
        assert cli.main(["--source", f"replay:{edited}", *SMALL, "--set", robots]) == 0
        got = []
        while True:
            try:
                got.append(parse_datagram(udp.recv(2048)))
            except TimeoutError:
                break
    finally:
        udp.close()
    err = capsys.readouterr().err
    assert "source time steps back 9.967 s" in err
    assert "source time steps forward 3610.033 s" in err
    seq = [(m["t"], m["valid"]) for m in got]
    for t_new in (t10, t20):
        first = next(i for i, (t, _) in enumerate(seq) if abs(t - t_new) < 1e-5)
        # The first message of the new time is valid=0 (the robot withdrawn), before any
        # valid pose of that time; valid poses follow.
        assert seq[first][1] is False, seq
        assert any(v for t, v in seq[first + 1:first + 12]), seq
    # Every valid pose after a step is of the new time, never of the old one.
    i10 = next(i for i, (t, _) in enumerate(seq) if abs(t - t10) < 1e-5)
    assert all(t < t10 + 1.0 for t, v in seq[i10:] if v and t < t20 - 1.0)
