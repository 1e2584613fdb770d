"""kmead end to end on the simulated floor: real rendering and detection, real sockets.

Frames are 640x480 (``--set source.width/height``) and the simulator unpaced
(``source.fps = 0``: every rendered frame processed in order) to keep the file fast.
"""

from __future__ import annotations

import csv
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import fakepi
import numpy as np
import pytest
import zmq
from deadlines import DEADLINE, JOIN

from kmea.maps.files import default_map
from kmea.sim.renderer import Renderer
from kmea.sim.scenes import scene_from_spec
from kmea.vision.camera import save_camera
from kmea.wire import protocol as P
from kmead import cli
from kmead.config.layers import load_config
from kmead.outputs.csvlog import HEADER
from kmead.outputs.relay import parse_datagram
from kmead.run.daemon import Daemon

ROOT = Path(__file__).resolve().parent.parent
NET = ["--set", 'network.telemetry="tcp://127.0.0.1:*"',
       "--set", 'network.control="tcp://127.0.0.1:*"']
SMALL = ["--set", "source.width=640", "--set", "source.height=480"]
FAST = [*SMALL, "--set", "source.fps=0"]


def read_csv(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        assert f.readline().rstrip("\n") == HEADER
        f.seek(0)
        return list(csv.DictReader(f))


def test_sim_run_logs_csv_close_to_truth_and_replays_exactly(tmp_path: Path,
                                                              capsys: pytest.CaptureFixture
                                                              ) -> None:
    out, rec = tmp_path / "out.csv", tmp_path / "rec.jsonl"
    code = cli.main(["--source", "sim", "--headless", "--frames", "100", "--log", str(out),
                     "--record", str(rec), *FAST, *NET])
    assert code == 0
    summary = capsys.readouterr().out
    assert "100 frames" in summary and "robots tracked: 2 of 2" in summary

    rows = read_csv(out)
    assert {r["frame"] for r in rows} == {str(i) for i in range(100)}
    assert {r["algorithm"] for r in rows} == {"corner-pnp"}
    assert {r["kind"] for r in rows} <= {"marker", "robot"}
    world_map = default_map()
    for r in rows:
        assert int(r["refs"]) >= 3
        if r["kind"] == "marker" and int(r["id"]) not in world_map:
            assert r["error"] == ""  # LOO errors exist for map markers only
    map_errors = [float(r["error"]) for r in rows if r["kind"] == "marker" and r["error"]]
    assert len(map_errors) > 100 * 20

    # Robots against the simulator's truth at the same frame times.
    scene = scene_from_spec("sim", width=640, height=480)
    dist: dict[str, list[float]] = {"amr1": [], "amr2": []}
    for r in rows:
        if r["kind"] == "robot":
            x, y, _ = scene.robot_poses(int(r["frame"]) / scene.fps)[r["id"]]
            dist[r["id"]].append(float(np.hypot(float(r["x"]) - x, float(r["y"]) - y)))
    for name, d in dist.items():
        assert len(d) >= 90, name
        assert np.median(d) < 0.005, (name, np.median(d))

    # The recording replays to the very same rows; another algorithm runs on the same data.
    again = tmp_path / "again.csv"
    assert cli.main(["--source", f"replay:{rec}", "--headless", "--log", str(again), *NET]) == 0
    assert again.read_text() == out.read_text()
    other = tmp_path / "umeyama.csv"
    assert cli.main(["--source", f"replay:{rec}", "--headless", "--log", str(other),
                     "--algorithm", "umeyama", "--set", "filter.alpha=0.5", *NET]) == 0
    rows_u = read_csv(other)
    assert {r["algorithm"] for r in rows_u} == {"umeyama"}
    assert len(rows_u) == len(rows)
    head = json.loads(rec.read_text().splitlines()[0])
    assert head["format"] == "kmead-recording" and head["camera"]["width"] == 640
    frame0 = json.loads(rec.read_text().splitlines()[1])
    assert {"frame", "t", "ids", "corners", "markers", "truth"} <= set(frame0)
    # Format version 2: what a replay reads (no repeated corners, no second IPPE pose).
    assert {"id", "R", "t", "length", "reproj", "alt_reproj"} == set(frame0["markers"][0])


class _Sub:
    def __init__(self, endpoint: str, topics: tuple[str, ...] = ("",)) -> None:
        self.ctx = zmq.Context()
        self.sock = self.ctx.socket(zmq.SUB)
        for t in topics:
            self.sock.setsockopt(zmq.SUBSCRIBE, t.encode())
        self.sock.connect(endpoint)

    def collect(self, until, timeout: float = 60.0) -> dict[str, list[dict]]:
        """Messages by topic until ``until(got)`` holds (or ``timeout`` s passed)."""
        got: dict[str, list[dict]] = {}
        end = time.monotonic() + timeout
        while time.monotonic() < end and not until(got):
            if self.sock.poll(50):
                topic, body = P.decode(self.sock.recv_multipart())
                got.setdefault(topic, []).append(body)
        return got

    def close(self) -> None:
        self.sock.close(0)
        self.ctx.term()


def _request(ctx: zmq.Context, endpoint: str, payload: bytes | list[bytes],
             timeout: float = 5.0) -> dict:
    req = ctx.socket(zmq.REQ)
    req.setsockopt(zmq.LINGER, 0)
    req.connect(endpoint)
    try:
        if isinstance(payload, list):
            req.send_multipart(payload)
        else:
            req.send(payload)
        assert req.poll(timeout * 1000), "no reply from the daemon"
        return P.decode_body(req.recv())
    finally:
        req.close(0)


def _cmd(ctx: zmq.Context, endpoint: str, cmd: str, **args: object) -> dict:
    return _request(ctx, endpoint, P.encode_body({"cmd": cmd, **args}))


@pytest.fixture
def udp() -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.settimeout(30.0)
    yield s
    s.close()


def _frames_after(daemon: Daemon, n: int, timeout: float = 60.0) -> bool:
    """Waits until the daemon has processed ``n`` frames in all."""
    end = time.monotonic() + timeout
    while daemon.totals.frames < n and time.monotonic() < end:
        time.sleep(0.05)
    return daemon.totals.frames >= n


def test_live_daemon_telemetry_udp_and_control(tmp_path: Path, udp: socket.socket) -> None:
    port = udp.getsockname()[1]
    out = tmp_path / "live.csv"
    site = tmp_path / "site.toml"
    site.write_text("# site configuration, comments must survive\n[filter]\nalpha = 1.0\n")
    robots = ('robots=[{name="amr1", markers=[40, 41], height=0.2, '
              f'destinations=["udp:127.0.0.1:{port}"]}}, '
              '{name="amr2", markers=[42], height=0.2}]')
    cfg = load_config(str(site), [*(a for a in FAST[1::2]), *(a for a in NET[1::2]),
                                  robots, f'log.csv="{out}"', f'log.dir="{tmp_path}"'])
    daemon = Daemon(cfg, max_frames=100000)
    runner = threading.Thread(target=daemon.run)
    sub = _Sub(daemon.telemetry.bound)
    ctx = zmq.Context()
    ctrl = daemon.control.bound
    try:
        runner.start()
        topics = ("frame", "markers", "robots", "stats", "status", "robot.amr1")
        got = sub.collect(lambda g: all(t in g for t in topics))
        # ---- telemetry: every topic of docs/protocol.md with its fields
        for topic in topics:
            assert got.get(topic), f"no {topic!r} message"
        fr = got["frame"][-1]
        assert {"t", "frame", "source", "algorithm", "ok", "reason", "n_detected", "n_refs",
                "fps", "dropped", "timings_ms", "flips", "ambiguous"} <= set(fr)
        assert set(fr["timings_ms"]) == {"capture", "detect", "pose", "estimate", "loo",
                                         "filter", "robots", "output", "total"}
        assert fr["ok"] and fr["n_detected"] > 20
        mk = got["markers"][-1]["markers"]
        assert {m["id"] for m in mk} >= set(default_map().ids)
        m13 = next(m for m in mk if m["id"] == 13)
        assert m13["in_map"] and m13["detected"] and m13["error"] is not None
        assert abs(m13["x"] - m13["map_x"]) < 0.02
        wall = [m for m in mk if m["in_map"] and not m["detected"]]
        assert wall and all(m["x"] is None for m in wall)
        rb = {r["name"]: r for r in got["robots"][-1]["robots"]}
        assert rb["amr1"]["valid"] and rb["amr1"]["sent"] > 0
        assert rb["amr1"]["destinations"] == [f"udp:127.0.0.1:{port}"]
        st = got["status"][-1]
        assert st["logging"]["active"] and st["logging"]["path"] == str(out)
        assert st["camera"]["width"] == 640 and st["map"]["n"] == len(default_map())
        assert got["stats"][-1]["markers"] and got["stats"][-1]["mean_error"] > 0

        # ---- UDP datagrams, well-formed, increasing sequence
        msgs = [parse_datagram(udp.recv(1024)) for _ in range(5)]
        assert all(m["name"] == "amr1" and m["valid"] for m in msgs)
        assert [m["seq"] for m in msgs] == sorted(m["seq"] for m in msgs)
        assert all(-0.9 < m["x"] < 0.9 and -0.65 < m["y"] < 0.65 for m in msgs)

        # ---- garbage on the control socket: error replies, the daemon keeps going
        for bad in (b"not json", b"[1, 2]", b'{"v": 2}', b'{"v": 99, "cmd": "ping"}',
                    b'{"v": 2, "cmd": 42}', b'{"v": 2, "cmd": "format_disk"}',
                    b"\xff\xfe", b'{"v": 2, "cmd": "set", "key": "filter.alpha", "value": 7}',
                    b'{"v": 2, "cmd": "set", "key": "source.spec", "value": "sim"}',
                    b'{"v": 2, "cmd": "log_start", "path": 5}',
                    b"x" * (P.MAX_MESSAGE_BYTES + 10)):
            reply = _request(ctx, ctrl, bad)
            assert reply["ok"] is False and reply["error"], bad[:40]
        assert _request(ctx, ctrl, [b'{"v":2,"cmd":"ping"}', b"extra"])["ok"] is False
        assert _cmd(ctx, ctrl, "ping")["ok"]
        def refused(g):
            return any("control request refused" in e["text"] for e in g.get("event", []))
        assert refused(sub.collect(refused))

        # ---- control: state, config, live algorithm switch visible in the CSV
        state = _cmd(ctx, ctrl, "get_state")
        assert state["ok"] and state["status"]["algorithm"] == "corner-pnp"
        conf = _cmd(ctx, ctrl, "get_config")
        assert conf["config"]["filter"]["alpha"] == 1.0
        assert conf["overlay_file"] == str(tmp_path / "site.local.toml")
        r = _cmd(ctx, ctrl, "set", key="estimator.algorithm", value="umeyama")
        assert r["ok"] and r["value"] == "umeyama"
        n_before = daemon.totals.frames
        assert _frames_after(daemon, n_before + 3)
        assert _cmd(ctx, ctrl, "set", key="filter.alpha", value=0.5)["ok"]

        def logged(g):  # the daemon's own log lines
            return any(m["text"] == "set filter.alpha = 0.5" and m["level"] == "info"
                       and m["logger"] == "kmead" for m in g.get("log", []))
        got = sub.collect(logged)
        assert logged(got), got.get("log")
        saved = _cmd(ctx, ctrl, "save_config")
        assert saved["ok"] and saved["path"] == str(tmp_path / "site.local.toml")
        assert _cmd(ctx, ctrl, "reset_stats")["ok"]
        assert _cmd(ctx, ctrl, "reload_map")["map"]["n"] == len(default_map())
        stopped = _cmd(ctx, ctrl, "log_stop")
        assert stopped["ok"] and stopped["path"] == str(out)
        assert _cmd(ctx, ctrl, "log_stop")["ok"] is False  # not logging any more
        second = tmp_path / "second.csv"
        n_before = daemon.totals.frames
        assert _cmd(ctx, ctrl, "log_start", path="second.csv")["path"] == str(second)
        assert _frames_after(daemon, n_before + 2)  # rows for second.csv
    finally:
        daemon.stop()
        runner.join(timeout=JOIN)
        daemon.close()
        sub.close()
        ctx.term()
    assert not runner.is_alive()
    rows = read_csv(out)
    algos = [r["algorithm"] for r in rows]
    first_u = algos.index("umeyama")
    assert set(algos[:first_u]) == {"corner-pnp"} and set(algos[first_u:]) == {"umeyama"}
    # whole frames only: each frame's rows carry one algorithm
    per_frame: dict[str, set[str]] = {}
    for r in rows:
        per_frame.setdefault(r["frame"], set()).add(r["algorithm"])
    assert all(len(v) == 1 for v in per_frame.values())
    assert read_csv(second)  # started live, rows written, closed on exit
    assert site.read_text().startswith("# site configuration, comments must survive")
    overlay = (tmp_path / "site.local.toml").read_text()
    assert 'algorithm = "umeyama"' in overlay and "alpha = 0.5" in overlay


def _render(n: int, size: tuple[int, int] = (640, 480)) -> tuple[list[np.ndarray], object]:
    scene = scene_from_spec("sim", width=size[0], height=size[1])
    r = Renderer(scene)
    return [r.render(i).image for i in range(n)], scene


def test_images_folder_with_camera_and_csv_map(tmp_path: Path,
                                               capsys: pytest.CaptureFixture) -> None:
    frames, scene = _render(3)
    d = tmp_path / "frames"
    d.mkdir()
    for i, img in enumerate(frames):
        cv2.imwrite(str(d / f"frame{i:02d}.png"), img)
    (d / "frame01b.png").write_bytes(b"\x89PNG\r\n\x1a\n this is not an image")
    cam = tmp_path / "camera.yml"
    save_camera(scene.camera, cam)
    floor = tmp_path / "floor.csv"
    m = default_map()
    floor.write_text("id,x,y,z\n" + "".join(
        f"{mid},{float(mk.position[0])!r},{float(mk.position[1])!r},{float(mk.position[2])!r}\n"
        for mid, mk in m.markers.items() if mk.on_floor))
    out = tmp_path / "images.csv"
    code = cli.main(["--source", f"images:{d}", "--camera", str(cam), "--map", str(floor),
                     "--headless", "--log", str(out), *NET])
    cap = capsys.readouterr()
    assert code == 0, cap.err
    assert "frame01b.png: cannot decode" in cap.err  # reported, and the run went on
    assert "3 frames" in cap.out and "bad frames: 1" in cap.out
    rows = read_csv(out)
    assert sorted({int(r["frame"]) for r in rows}) == [0, 1, 3]  # index 2 was the bad file
    robots = [r for r in rows if r["kind"] == "robot"]
    assert len(robots) == 6


def test_video_that_ends(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    frames, _ = _render(4)
    path = tmp_path / "clip.avi"
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (640, 480), False)
    assert w.isOpened()
    for f in frames:
        w.write(f)
    w.release()
    out = tmp_path / "video.csv"
    assert cli.main(["--source", f"video:{path}", "--headless", "--log", str(out), *NET]) == 0
    assert "4 frames" in capsys.readouterr().out
    assert {r["frame"] for r in read_csv(out)} == {"0", "1", "2", "3"}


def _spawn(tmp_path: Path, out: Path) -> subprocess.Popen:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return subprocess.Popen(
        [sys.executable, "-m", "kmead.cli", "--headless", "--log", str(out), *SMALL,
         "--set", "source.fps=15", *NET], cwd=tmp_path, env=env, stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True)


def _wait_rows(out: Path, proc: subprocess.Popen, n: int = 150,
               timeout: float = DEADLINE) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if out.exists() and out.read_text().count("\n") > n:
            return
        assert proc.poll() is None, proc.communicate()
        time.sleep(0.1)
    raise AssertionError("no CSV rows in time")


def test_sigterm_flushes_and_summarises_sigkill_leaves_whole_rows(tmp_path: Path) -> None:
    out_term, out_kill = tmp_path / "term.csv", tmp_path / "kill.csv"
    p1, p2 = _spawn(tmp_path, out_term), _spawn(tmp_path, out_kill)
    try:
        _wait_rows(out_term, p1)
        p1.send_signal(signal.SIGTERM)
        stdout, stderr = p1.communicate(timeout=DEADLINE)
        assert p1.returncode == 0, stderr
        assert "kmead summary" in stdout and "robots tracked" in stdout
        _wait_rows(out_kill, p2)
        p2.send_signal(signal.SIGKILL)
        p2.communicate(timeout=DEADLINE)
    finally:
        for p in (p1, p2):
            if p.poll() is None:
                p.kill()
                p.communicate()
    for out in (out_term, out_kill):
        text = out.read_text()
        assert text.endswith("\n")
        lines = text.splitlines()
        assert lines[0] == HEADER
        assert all(len(line.split(",")) == 11 for line in lines)
        frames = [int(line.split(",")[0]) for line in lines[1:]]
        assert frames == sorted(frames)


def test_picamera_source_through_the_daemon(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                            capsys: pytest.CaptureFixture) -> None:
    """The daemon on the fake picamera2 (tests/fake_picamera2): rows for every frame, times
    from the sensor timestamps (unix time of the start of readout)."""
    frames, scene = _render(2)
    rig = fakepi.install(monkeypatch).rig
    try:
        rig.scene = lambda n, w, h: frames[n % 2]
        rig.readout_s = 5.0  # far larger than the real ~20 ms: the row times must show it
        cam = tmp_path / "pi.yml"
        save_camera(scene.camera, cam)
        out = tmp_path / "pi.csv"
        t0 = time.time()
        code = cli.main(["--source", "picamera", "--camera", str(cam), *SMALL, "--frames", "6",
                         "--headless", "--log", str(out), *NET])
        t1 = time.time()
        assert code == 0, capsys.readouterr().err
        rows = read_csv(out)
        assert len({r["frame"] for r in rows}) == 6
        assert {r["id"] for r in rows if r["kind"] == "robot"} == {"amr1", "amr2"}
        stamps = sorted({float(r["timestamp"]) for r in rows})
        # each frame's time is the start of its readout, 5 s before it reached the daemon
        assert t0 - 5.5 < stamps[0] and stamps[-1] < t1 - 4.5
        # a robot's row is at its markers' mid-exposure: its rows' readout (18.9 us a sensor
        # row, 2 a row at 640x480... of the 1640x1232 mode: 48.5 us) less half the 2 ms
        # exposure (camera.max_exposure_ms) after the frame's time (its markers' rows)
        frame_t = {r["frame"]: float(r["timestamp"]) for r in rows if r["kind"] == "marker"}
        for r in rows:
            if r["kind"] == "robot":
                dt = float(r["timestamp"]) - frame_t[r["frame"]]
                assert -0.001 < dt < 480 * 48.5e-6 - 0.001, r
                assert dt != 0.0
    finally:
        fakepi.forget()


def test_long_exposure_warns_once_with_the_figure(tmp_path: Path,
                                                  monkeypatch: pytest.MonkeyPatch,
                                                  capsys: pytest.CaptureFixture) -> None:
    """camera.max_exposure_ms = 0: the camera's auto exposure (8 ms on the fake rig) smears a
    robot at filter.max_speed (1.5 m/s) by 12 mm: one warning saying so and what to set."""
    frames, scene = _render(1)
    rig = fakepi.install(monkeypatch).rig
    try:
        rig.scene = lambda n, w, h: frames[0]
        cam = tmp_path / "pi.yml"
        save_camera(scene.camera, cam)
        code = cli.main(["--source", "picamera", "--camera", str(cam), *SMALL, "--frames", "4",
                         "--headless", "--set", "camera.max_exposure_ms=0", *NET])
        err = capsys.readouterr().err
        assert code == 0, err
        warn = ("camera exposure 8.0 ms: a robot at 1.5 m/s (filter.max_speed) smears by "
                "12.0 mm, more than 4.5 mm: moving robots' markers blur and may be lost; set "
                "camera.max_exposure_ms to at most 3.0 (docs/motion.md)")
        assert err.count(warn) == 1, err
    finally:
        fakepi.forget()


def test_stalled_picamera_ends_the_daemon_non_zero(tmp_path: Path,
                                                   monkeypatch: pytest.MonkeyPatch,
                                                   capsys: pytest.CaptureFixture) -> None:
    """A camera that stops delivering: reopened, then the daemon exits 1 (systemd restarts it
    with Restart=on-failure) instead of hanging."""
    frames, _ = _render(1)
    rig = fakepi.install(monkeypatch).rig
    try:
        rig.scene = lambda n, w, h: frames[0]
        rig.stall_after = [2, 0, 0, 0]
        # default timeout: 10 frame periods (0.1 s at 100 fps) when that is above the floor
        monkeypatch.setattr("kmea.sources.picamera.MIN_STALL_TIMEOUT_S", 0.0)
        code = cli.main(["--source", "picamera", *SMALL, "--set", "source.fps=100",
                         "--headless", *NET])
        err = capsys.readouterr().err
        assert code == 1, err
        assert "4 times in a row (camera reopened 3 times)" in err
    finally:
        fakepi.forget()


def test_picamera2_missing_is_a_clear_error(monkeypatch: pytest.MonkeyPatch,
                                            capsys: pytest.CaptureFixture) -> None:
    monkeypatch.setitem(sys.modules, "picamera2", None)
    assert cli.main(["--source", "picamera", "--headless", "--frames", "1", *NET]) == 1
    assert "apt install python3-picamera2" in capsys.readouterr().err


def test_detection_worker_pool_gives_the_same_rows(tmp_path: Path) -> None:
    outs = []
    for workers in (0, 2):
        out = tmp_path / f"w{workers}.csv"
        assert cli.main(["--source", "sim", "--headless", "--frames", "12", "--log", str(out),
                         "--set", f"detector.workers={workers}", *FAST, *NET]) == 0
        outs.append(out.read_text())
    assert outs[0] == outs[1]
    assert len({line.split(",")[0] for line in outs[0].splitlines()[1:]}) == 12


def test_robust_estimator_rejected_reference_in_csv_and_events(
        tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    # The map says marker 16 is 5 cm further right than it is on the floor.
    m = default_map()
    moved = tmp_path / "moved.csv"
    moved.write_text("id,x,y,z\n" + "".join(
        f"{mid},{float(mk.position[0]) + (0.05 if mid == 16 else 0.0)!r},"
        f"{float(mk.position[1])!r},0\n" for mid, mk in m.markers.items() if mk.on_floor))
    out = tmp_path / "robust.csv"
    assert cli.main(["--source", "sim", "--map", str(moved), "--algorithm", "kmea-robust",
                     "--frames", "3", "--headless", "--log", str(out), *FAST, *NET]) == 0
    assert "marker 16 looks displaced by" in capsys.readouterr().err
    rows = read_csv(out)
    rejected = [r for r in rows if r["kind"] == "rejected"]
    assert {r["id"] for r in rejected} == {"16"}
    assert {r["frame"] for r in rejected} == {"0", "1", "2"}
    assert all(0.03 < float(r["error"]) < 0.07 for r in rejected)
    # its estimate is still logged as a marker row, near where it really is
    m16 = [r for r in rows if r["kind"] == "marker" and r["id"] == "16"]
    assert len(m16) == 3 and all(abs(float(r["x"]) - m[16].position[0]) < 0.02 for r in m16)


def test_a_fast_path_recording_says_its_replay_differs(tmp_path: Path,
                                                      capsys: pytest.CaptureFixture) -> None:
    """A paced (live) simulator run uses the fixed-camera fast path: the recording's header
    says so and its replay warns that rows will differ; an unpaced run's header does not."""
    rec = tmp_path / "live.jsonl"
    assert cli.main(["--source", "sim", "--headless", "--frames", "5", "--record", str(rec),
                     "--set", "source.width=640", "--set", "source.height=480",
                     "--set", "source.fps=30", *NET]) == 0
    assert json.loads(rec.read_text().splitlines()[0])["fast_path"] is True
    capsys.readouterr()
    assert cli.main(["--source", f"replay:{rec}", "--headless", *NET]) == 0
    assert "recorded with the fixed-camera fast path" in capsys.readouterr().err
    flat = tmp_path / "flat.jsonl"
    assert cli.main(["--source", "sim", "--headless", "--frames", "2", "--record", str(flat),
                     *FAST, *NET]) == 0
    assert json.loads(flat.read_text().splitlines()[0])["fast_path"] is False
    capsys.readouterr()
    assert cli.main(["--source", f"replay:{flat}", "--headless", *NET]) == 0
    assert "fast path" not in capsys.readouterr().err
