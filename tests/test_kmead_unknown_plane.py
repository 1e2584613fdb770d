"""The daemon publishes where ``estimator.unknown_plane`` put each marker of unknown plane:
CSV rows of kind ``plane`` (real simulated frames, real detection)."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest

from kmead import cli
from kmead.outputs.csvlog import HEADER

NET = ["--set", 'network.telemetry=""', "--set", 'network.control=""']
FAST = ["--set", "source.width=820", "--set", "source.height=616", "--set", "source.fps=0"]


def _rows(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        assert f.readline().rstrip("\n") == HEADER
        f.seek(0)
        return list(csv.DictReader(f))


@pytest.mark.parametrize(("mode", "want"), [("auto", "free"), ("floor", "floor"),
                                             ("free", "free")])
def test_unconfigured_robot_markers_get_a_plane_row(tmp_path: Path, mode: str, want: str,
                                                    capsys) -> None:
    # No robot configured: the robots' 20 cm high markers 40-42 have no known plane.
    out = tmp_path / "out.csv"
    code = cli.main(["--source", "sim", "--headless", "--frames", "3", "--log", str(out),
                     "--set", "robots=[]", "--set", f'estimator.unknown_plane="{mode}"',
                     *FAST, *NET])
    assert code == 0, capsys.readouterr().err
    rows = _rows(out)
    planes = [r for r in rows if r["kind"] == "plane"]
    assert {int(r["id"]) for r in planes} == {40, 41, 42}
    for r in planes:
        if want == "free":
            assert r["x"] == r["y"] == r["z"] == r["error"] == ""
        else:  # the floor: normal +z, offset 0
            assert (float(r["x"]), float(r["y"]), float(r["z"])) == (0.0, 0.0, 1.0)
            assert float(r["error"]) == pytest.approx(0.0, abs=1e-9)
    markers = {int(r["id"]): r for r in rows if r["kind"] == "marker"}
    z = float(markers[40]["z"])
    assert (abs(z) < 1e-9) if want == "floor" else (abs(z - 0.20) < 0.02)


def test_telemetry_markers_carry_the_plane_choice() -> None:
    import threading

    import zmq

    from kmea.wire import protocol as P
    from kmead.config.layers import load_config
    from kmead.run.daemon import Daemon

    cfg = load_config(None, ["source.width=820", "source.height=616", "source.fps=10",
                             'network.telemetry="tcp://127.0.0.1:*"', 'network.control=""',
                             "robots=[]", 'estimator.unknown_plane="floor"'])
    daemon = Daemon(cfg, max_frames=100000)
    runner = threading.Thread(target=daemon.run)
    ctx = zmq.Context()
    sub = ctx.socket(zmq.SUB)
    sub.setsockopt(zmq.SUBSCRIBE, b"markers")
    sub.connect(daemon.telemetry.bound)
    try:
        runner.start()
        body = None
        for _ in range(200):
            if sub.poll(100):
                topic, body = P.decode(sub.recv_multipart())
                if topic == "markers" and any(m["id"] == 40 and m["detected"]
                                              for m in body["markers"]):
                    break
        assert body is not None
        by_id = {m["id"]: m for m in body["markers"]}
        assert by_id[40]["plane"] == "floor" and by_id[40]["plane_stat"] is None
        assert by_id[13]["plane"] is None  # a map marker's plane is known
    finally:
        daemon.stop()
        runner.join(30)
        daemon.close()
        sub.close(0)
        ctx.term()
