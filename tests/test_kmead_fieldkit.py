"""The technician's field kit, daemon side, with real sockets and processes: --version,
--check, the headless status line, systemd notify, the shutdown announcement, thumbnails
on request, snapshots, the log ring, port-in-use advice, start-up warnings."""

from __future__ import annotations

import base64
import json
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import zmq
from deadlines import DEADLINE

from kmea.wire import protocol as P
from kmea_tui import cli as tui_cli
from kmea_tui.widgets.camera_view import CameraFrame
from kmead import cli
from kmead.config.layers import load_config
from kmead.run.daemon import Daemon
from kmead.tools import kmea_cli

NET = ["--set", 'network.telemetry="tcp://127.0.0.1:*"',
       "--set", 'network.control="tcp://127.0.0.1:*"']
SMALL = ["--set", "source.width=640", "--set", "source.height=480"]
STAMP = r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d kmead: "


@pytest.mark.parametrize(("main", "name"), [(cli.main, "kmead"), (kmea_cli.main, "kmea"),
                                            (tui_cli.main, "kmea-tui")])
def test_version_on_every_command(main, name, capsys):
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0
    assert re.fullmatch(rf"{name} \d+\.\d+\.\d+\S*\n", capsys.readouterr().out)


@pytest.mark.parametrize("argv", [["--help"], ["map", "--help"], ["export", "mcap", "--help"],
                                  ["snapshot", "--help"], ["bench", "--help"]])
def test_help_is_plain_text(argv, capsys):
    with pytest.raises(SystemExit):
        kmea_cli.main(argv)
    text = capsys.readouterr().out
    assert "usage: kmea" in text
    assert "``" not in text and ":func:" not in text and ":class:" not in text


def test_check_prints_the_effective_configuration_and_binds_nothing(tmp_path, capsys):
    # A port held by someone else: --check must not try to bind it.
    ctx = zmq.Context.instance()
    held = ctx.socket(zmq.PUB)
    port = held.bind_to_random_port("tcp://127.0.0.1")
    try:
        code = cli.main(["--check", "--source", "camera:7", "--set",
                         f'network.telemetry="tcp://127.0.0.1:{port}"',
                         "--set", "stats.window=77"])
    finally:
        held.close(linger=0)
    out, err = capsys.readouterr()
    assert code == 0
    assert "window = 77" in out and f'telemetry = "tcp://127.0.0.1:{port}"' in out
    assert "the Configuration tab's Save writes:" in out
    assert "camera:7 is a live camera: not opened" in err
    assert err.strip().splitlines()[-1].startswith("kmead: configuration OK")


@pytest.mark.parametrize(("setup", "expect"), [
    (lambda d: ["--map", str(_write(d / "bad.toml", "[[markers]]\nid = 1\n"))], "bad.toml"),
    (lambda d: ["--camera", str(_write(d / "cam.yml", "%YAML:1.0\nfoo: 1\n"))], "cam.yml"),
    (lambda d: ["--config", str(_write(d / "k.toml", "[stats]\nwindow = -3\n"))], "window"),
    (lambda d: ["--source", f"replay:{_write(d / 'r.jsonl', 'not json')}"], "r.jsonl"),
    (lambda d: ["--log", "/proc/no/such/dir/x.csv"], "log.csv"),
    (lambda d: ["--record", str(_write(d / "f.txt", "") / "r.jsonl")], "log.record"),
])
def test_check_bad_file_exit_2_one_line(tmp_path, capsys, setup, expect):
    code = cli.main(["--check", *setup(tmp_path)])
    out, err = capsys.readouterr()
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and expect in lines[0], err
    assert out == ""


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def test_check_warns_like_kmea_map_check(tmp_path, capsys):
    m = _write(tmp_path / "m.csv", "id,x,y,z,rx_deg,ry_deg,rz_deg\n13,0,0,0,0,0,0\n"
               "16,1,0,0,0,0,0\n4,0,1,0,0,0,0\n77,1,1,0,0,0,0\n")
    assert cli.main(["--check", "--map", str(m), "--set",
                     'detector.dictionary="DICT_5X5_50"']) == 0
    err = capsys.readouterr().err
    assert "ids [77] can never be detected" in err


def _run(args: list[str], cwd: Path, env: dict | None = None, timeout: float = 120,
         stderr_file: Path | None = None) -> subprocess.CompletedProcess:
    e = {**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})}
    if stderr_file is None:
        return subprocess.run([sys.executable, "-m", "kmead.cli", *args], cwd=cwd, env=e,
                              capture_output=True, text=True, timeout=timeout)
    with open(stderr_file, "w") as f:
        r = subprocess.run([sys.executable, "-m", "kmead.cli", *args], cwd=cwd, env=e,
                           stdout=subprocess.PIPE, stderr=f, text=True, timeout=timeout)
    r.stderr = stderr_file.read_text()
    return r


def test_headless_status_lines_notify_datagrams_and_final_line(tmp_path):
    sock_path = str(tmp_path / "notify.sock")
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    listener.bind(sock_path)
    listener.settimeout(0.2)
    grams: list[str] = []
    done = threading.Event()

    def read() -> None:  # like systemd: read as they come (the queue holds only a few)
        while not done.is_set():
            try:
                grams.append(listener.recv(4096).decode())
            except TimeoutError:
                continue

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        r = _run(["--headless", "--frames", "25", "--status-every", "0.3", *SMALL,
                  "--set", "source.fps=10", *NET], tmp_path,
                 env={"NOTIFY_SOCKET": sock_path, "WATCHDOG_USEC": "400000"})
        end = time.monotonic() + DEADLINE  # the reader may still be behind: STOPPING is the last
        while time.monotonic() < end and not any(g.startswith("STOPPING=1") for g in grams):
            time.sleep(0.05)
    finally:
        done.set()
        reader.join(2)
        listener.close()
    assert r.returncode == 0, r.stderr
    status = [line for line in r.stderr.splitlines() if " frames/s, robots " in line]
    assert len(status) >= 3
    assert all(re.match(STAMP + r"frames \d+, [\d.]+ frames/s, robots \d/2 tracked, "
                        r"LOO (-|[\d.]+ mm), dropped \d+, bad \d+$", s) for s in status), status
    last = r.stderr.strip().splitlines()[-1]
    assert re.match(STAMP + r"stopped \(--frames 25 reached\): 25 frames, exit code 0$", last)
    # systemd: READY first, watchdog pings, the status line as STATUS=, STOPPING last.
    assert grams[0].startswith("READY=1")
    assert "WATCHDOG=1" in grams
    assert any(g.startswith("STATUS=frames ") for g in grams)
    assert grams[-1].startswith("STOPPING=1"), grams


def test_no_timestamps_when_stderr_is_the_journal(tmp_path):
    err = tmp_path / "stderr.txt"
    err.write_text("")
    st = os.stat(err)
    r = _run(["--headless", "--frames", "3", *SMALL, "--set", "source.fps=0", *NET], tmp_path,
             env={"JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino}"}, stderr_file=err)
    assert r.returncode == 0
    lines = r.stderr.strip().splitlines()
    assert lines[-1].startswith("kmead: stopped (--frames 3 reached)")
    assert not any(re.match(r"^\d{4}-", line) for line in lines)


def test_sigterm_announces_stopped_on_telemetry(tmp_path):
    err = tmp_path / "err.txt"
    with open(err, "w") as f:
        proc = subprocess.Popen([sys.executable, "-m", "kmead.cli", "--headless", *SMALL,
                                 "--set", "source.fps=5", *NET], cwd=tmp_path, stderr=f,
                                stdout=subprocess.DEVNULL,
                                env={**os.environ, "PYTHONUNBUFFERED": "1"})
    ctx = zmq.Context.instance()
    sub = ctx.socket(zmq.SUB)
    sub.setsockopt(zmq.LINGER, 0)
    try:
        end = time.monotonic() + DEADLINE
        while not (m := re.search(r"telemetry (tcp://\S+),", err.read_text())):
            assert time.monotonic() < end and proc.poll() is None, err.read_text()
            time.sleep(0.05)
        sub.connect(m.group(1))
        sub.setsockopt(zmq.SUBSCRIBE, b"status")
        sub.setsockopt(zmq.SUBSCRIBE, b"frame")
        states = []
        while not states or states[-1] != "running":  # connected and receiving
            assert sub.poll(30000), "no telemetry"
            topic, body = P.decode(sub.recv_multipart())
            if topic == "frame":
                states.append("running")
        proc.send_signal(signal.SIGTERM)
        while True:
            assert sub.poll(20000), f"no 'stopped' status; got {states}"
            topic, body = P.decode(sub.recv_multipart())
            if topic == "status":  # "state" is only in the last one
                states.append(body.get("state", "running"))
                if body.get("state") == "stopped":
                    P.check_body(topic, body, exact=True)
                    break
        assert proc.wait(20) == 0
    finally:
        sub.close(linger=0)
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_port_in_use_names_the_likely_cause_and_the_way_out(tmp_path):
    ctx = zmq.Context.instance()
    held = ctx.socket(zmq.PUB)
    port = held.bind_to_random_port("tcp://127.0.0.1")
    try:
        r = _run(["--headless", "--frames", "1", *SMALL, "--set",
                  f'network.telemetry="tcp://127.0.0.1:{port}"'], tmp_path)
    finally:
        held.close(linger=0)
    assert r.returncode == 1
    line = r.stderr.strip().splitlines()[-1]
    assert "another kmead is probably running" in line and "--free-ports" in line
    # And the way out works.
    r = _run(["--headless", "--frames", "1", "--free-ports", *SMALL, "--set",
              "source.fps=0"], tmp_path)
    assert r.returncode == 0, r.stderr


# ---------------------------------------------------------------- in-process, real sockets
@pytest.fixture
def running(tmp_path, monkeypatch):
    """A daemon on the simulator (one covered map marker) in a thread, with a REQ and a SUB."""
    yield from _running(tmp_path, monkeypatch)


def _running(tmp_path, monkeypatch, *extra: str):
    monkeypatch.chdir(tmp_path)  # the data directory: snapshots land here
    cfg = load_config(None, ['source.spec="sim:default?covered=4"', "source.width=640",
                             "source.height=480", "source.fps=8",
                             'network.telemetry="tcp://127.0.0.1:*"',
                             'network.control="tcp://127.0.0.1:*"', *extra])
    d = Daemon(cfg)
    t = threading.Thread(target=d.run, daemon=True)
    t.start()
    ctx = zmq.Context.instance()
    req = ctx.socket(zmq.REQ)
    req.setsockopt(zmq.LINGER, 0)
    req.connect(d.control.bound)
    sub = ctx.socket(zmq.SUB)
    sub.setsockopt(zmq.LINGER, 0)
    sub.connect(d.telemetry.bound)

    def ask(**body) -> dict:
        req.send(P.encode_body(body))
        assert req.poll(30000), f"no reply to {body}"
        return P.decode_body(req.recv())

    try:
        yield d, ask, sub
    finally:
        d.stop()
        t.join(10)
        d.close()
        req.close(linger=0)
        sub.close(linger=0)


def _collect(sub, topic: str, seconds: float, until=None) -> list[dict]:
    """``topic``'s messages for ``seconds`` s, or until one arrives or ``until()`` holds."""
    out = []
    end = time.monotonic() + seconds
    while (left := end - time.monotonic()) > 0:
        if until is not None and until():
            break
        if sub.poll(max(1, min(100, int(left * 1000)))):
            t, body = P.decode(sub.recv_multipart())
            if t == topic:
                out.append(body)
                if until is None:
                    break
    return out


def _frames_after(d, n: int):
    """``until`` for :func:`_collect`: the daemon has processed ``n`` more frames."""
    target = d.totals.frames + n
    return lambda: d.totals.frames >= target


def test_thumbnails_only_while_watched_rate_limited(running):
    d, ask, sub = running
    sub.setsockopt(zmq.SUBSCRIBE, b"camera")
    sub.setsockopt(zmq.SUBSCRIBE, b"frame")
    assert _collect(sub, "frame", 60.0), "the daemon is not running"
    # Nobody watches: nothing sent, however many frames go by.
    assert _collect(sub, "camera", 60.0, until=_frames_after(d, 4)) == []
    reply = ask(cmd="camera_watch", width=120, height=90, lease_s=2.0)
    assert reply["ok"] and reply["images"] and (reply["width"], reply["height"]) == (120, 90)
    # The lease's thumbnails: until it has ended on the daemon's clock and the frame that
    # was being processed then is out (a loaded machine sends fewer, never more).
    bodies = _collect(sub, "camera", 60.0, until=lambda: not d.camera_feed.watched)
    bodies += _collect(sub, "camera", 60.0, until=_frames_after(d, 2))
    bodies += _collect(sub, "camera", 0.5, until=lambda: False)
    assert 1 <= len(bodies) <= 5  # at most 2 a second during the 2 s lease
    for b in bodies:
        P.check_body("camera", b, exact=True)
    f = CameraFrame.from_body(bodies[-1])
    assert (f.width, f.height) == (120, 90) and (f.full_width, f.full_height) == (640, 480)
    kinds = {m.kind for m in f.markers}
    assert "detected" in kinds
    expected = {m.id for m in f.markers if m.kind == "expected"}
    assert 4 in expected  # the covered marker is in view but not seen
    assert f.focus is not None and f.focus > 0
    assert _collect(sub, "camera", 60.0, until=_frames_after(d, 4)) == []  # the lease ended
    # Hostile or hurried requests.
    assert not ask(cmd="camera_watch", width="big")["ok"]
    assert ask(cmd="camera_watch", width=10**6, height=10**6, lease_s=999)["width"] == 320
    bad = ask(cmd="camera_watch")
    assert not bad["ok"] and "at most one request" in bad["error"]


def test_snapshot_full_resolution_png_with_and_without_overlay(running, tmp_path):
    _d, ask, sub = running
    sub.setsockopt(zmq.SUBSCRIBE, b"frame")
    assert _collect(sub, "frame", 60.0)
    plain = ask(cmd="snapshot")
    assert plain["ok"], plain
    over = ask(cmd="snapshot", overlay=True)
    assert over["ok"] and over["path"].endswith("-overlay.png")
    a = cv2.imread(plain["path"], cv2.IMREAD_UNCHANGED)
    b = cv2.imread(over["path"], cv2.IMREAD_UNCHANGED)
    assert a.shape == (480, 640) and b.shape == (480, 640, 3)
    assert Path(plain["path"]).parent == tmp_path
    green = (b[:, :, 1] > 150) & (b[:, :, 0] < 80) & (b[:, :, 2] < 80)
    assert green.sum() > 100  # outlines drawn
    assert not ask(cmd="snapshot", overlay="yes")["ok"]


@pytest.fixture
def limited(tmp_path, monkeypatch):
    """The same daemon with room for two snapshots or 1 MB of them."""
    yield from _running(tmp_path, monkeypatch, "log.snapshots_max=2", "log.snapshots_max_mb=1")


def test_snapshots_pile_up_to_their_limits_then_a_request_is_refused(limited, tmp_path):
    # Any client, a viewer too, may take snapshots: 36 of 1-2.7 MB were once all accepted.
    _d, ask, sub = limited
    sub.setsockopt(zmq.SUBSCRIBE, b"frame")
    assert _collect(sub, "frame", 60.0)
    assert ask(cmd="snapshot")["ok"] and ask(cmd="snapshot")["ok"]
    third = ask(cmd="snapshot")
    assert not third["ok"] and "log.snapshots_max = 2" in third["error"], third
    assert len(list(tmp_path.glob("snapshot-*.png"))) == 2
    # The bytes: one snapshot file of 1 MB (someone else's, or an old big one) fills it.
    for p in tmp_path.glob("snapshot-*.png"):
        p.unlink()
    (tmp_path / "snapshot-old.png").write_bytes(b"\0" * 1_000_000)
    full = ask(cmd="snapshot")
    assert not full["ok"] and "log.snapshots_max_mb = 1 MB" in full["error"], full
    assert "\n" not in full["error"]


def test_log_ring_sent_on_request(running):
    _d, ask, sub = running
    sub.setsockopt(zmq.SUBSCRIBE, b"frame")
    assert _collect(sub, "frame", 60.0)  # running (and so it has logged that it is)
    reply = ask(cmd="get_log")
    assert reply["ok"]
    texts = [line["text"] for line in reply["lines"]]
    assert any(t.startswith("running: source sim") for t in texts)
    assert all({"t", "level", "text"} <= set(line) for line in reply["lines"])
    assert len(ask(cmd="get_log", limit=1)["lines"]) == 1
    assert not ask(cmd="get_log", limit=0)["ok"]


def test_kmea_snapshot_command(running, capsys):
    d, _ask, sub = running
    sub.setsockopt(zmq.SUBSCRIBE, b"frame")
    assert _collect(sub, "frame", 60.0)
    assert kmea_cli.main(["snapshot", "--control", d.control.bound]) == 0
    out = capsys.readouterr().out
    path = re.match(r"saved (\S+\.png) \(frame \d+\)", out).group(1)
    assert cv2.imread(path).shape[:2] == (480, 640)


def test_startup_warnings_for_map_ids_and_rescaled_camera(tmp_path, capsys):
    from kmea.vision.camera import pi_camera_v2, save_camera

    cam = tmp_path / "cam.toml"
    save_camera(pi_camera_v2(1640, 1232), cam)
    m = _write(tmp_path / "m.csv", "id,x,y,z,rx_deg,ry_deg,rz_deg\n13,0,0,0,0,0,0\n"
               "16,1,0,0,0,0,0\n4,0,1,0,0,0,0\n77,1,1,0,0,0,0\n")
    code = cli.main(["--headless", "--frames", "1", "--map", str(m), "--camera", str(cam),
                     "--set", 'detector.dictionary="DICT_5X5_50"', *SMALL,
                     "--set", "source.fps=0", *NET])
    err = capsys.readouterr().err
    assert code == 0
    assert "ids [77] can never be detected" in err
    assert "is for 1640x1232; rescaled to the frame size 640x480" in err


def test_unwritable_record_names_the_record_key(tmp_path, capsys):
    assert cli.main(["--headless", "--frames", "1", "--record", "/proc/none/r.jsonl",
                     *SMALL, *NET]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "log.record" in err[0] and "log.csv" not in err[0]


def test_bogus_source_names_the_source_option(capsys):
    assert cli.main(["--headless", "--source", "bogus:1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("kmead: configuration error: --source:") and "--spec" not in err


def test_summary_says_why_robots_are_not_tracked(tmp_path, capsys):
    cfg = _write(tmp_path / "k.toml", '[[robots]]\nname = "ghost"\nmarkers = [48, 49]\n')
    assert cli.main(["--headless", "--frames", "3", "--config", str(cfg), *SMALL,
                     "--set", "source.fps=0", *NET]) == 0
    out = capsys.readouterr().out
    assert "robots tracked: 0 of 1" in out
    assert "ghost not tracked: marker 48, 49 never detected" in out


def test_camera_body_is_json_and_small():
    from kmea.vision.overlay import OverlayMarker
    from kmead.net.camera_feed import camera_body

    img = (np.arange(480 * 640) % 251).astype(np.uint8).reshape(480, 640)
    q = np.array([[100, 100], [200, 100], [200, 200], [100, 200]], float)
    body = camera_body(img, [OverlayMarker(3, q)], 160, 120, 5, 1.5)
    data = P.encode_body(body)
    assert len(data) < 40_000
    back = json.loads(data)
    P.check_body("camera", back, exact=True)  # the declared type, exactly
    assert len(base64.b64decode(back["data"])) == 160 * 120
    assert back["markers"][0]["corners"][2] == [200.0, 200.0]


def test_truncated_replay_ends_with_a_warning(tmp_path, capsys):
    rec = tmp_path / "r.jsonl"
    assert cli.main(["--headless", "--frames", "4", "--record", str(rec), *SMALL,
                     "--set", "source.fps=0", *NET]) == 0
    text = rec.read_text()
    rec.write_text(text[:-50])  # a kill in the middle of the last line
    capsys.readouterr()
    assert cli.main(["--headless", "--source", f"replay:{rec}", *NET]) == 0
    cap = capsys.readouterr()
    assert "3 frames" in cap.out
    assert "line 5 is partial (a recording cut short?); replay ends at frame 3" in cap.err


def test_a_snapshot_is_refused_below_the_data_directorys_free_space_floor(tmp_path):
    from kmead.outputs.datadir import free_bytes
    from kmead.outputs.snapshot import Limits, SnapshotError, check_room

    free = free_bytes(tmp_path)
    if free is None:
        pytest.skip("no statvfs here")
    check_room(tmp_path, Limits(min_free_mb=1.0), 1000)  # plenty of room
    floor = (free + 10**9) / 1e6  # a floor above what this disk has free
    with pytest.raises(SnapshotError) as e:
        check_room(tmp_path, Limits(min_free_mb=floor), 1000)
    assert f"below log.min_free_mb = {floor:g} MB" in str(e.value)
    with pytest.raises(SnapshotError, match=r"snapshots are off \(log.snapshots_max = 0\)"):
        check_room(tmp_path, Limits(max_count=0), 0)
