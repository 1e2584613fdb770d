"""Issue 30: nothing lost when the world misbehaves. A real daemon (the paced simulated floor
through real detection, real ZeroMQ sockets on loopback, real UDP listeners for the robots)
meets a full disk, a disk below the free-space floor, control requests that would wipe a log,
settings that break every frame, and a save after --free-ports.

A full disk cannot be made here without root (no mount): the files' disk is a fake that takes
a budget of bytes, writes part of the write that crosses it and then raises ENOSPC, as a full
filesystem does; the free-space floor reads a monkeypatched ``os.statvfs``.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import socket
import time
from pathlib import Path

import pytest
import zmq
from deadlines import DEADLINE
from security_helpers import LiveDaemon, robots_toml, udp_listener

from kmea.recordings import wholewrite
from kmea.wire import protocol as P
from kmead.outputs.csvlog import COLUMNS, HEADER
from kmead.outputs.relay import parse_datagram


class Disk:
    """A filesystem with ``free`` bytes left, shared by every file opened on it."""

    def __init__(self, free: int) -> None:
        self.free = free
        self.partial_writes = 0  # writes cut short by the full disk
        self.refused = 0  # writes that raised ENOSPC


class FullingFile:
    """An unbuffered file on ``disk``: a write beyond its free space writes what fits and
    returns the short count; the next one raises ENOSPC (what write(2) does)."""

    def __init__(self, real, disk: Disk) -> None:
        self.real, self.disk = real, disk

    def write(self, data) -> int:
        if self.disk.free <= 0:
            self.disk.refused += 1
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        n = min(len(data), self.disk.free)
        if n < len(data):
            self.disk.partial_writes += 1
        written = self.real.write(bytes(data[:n]))
        self.disk.free -= written
        return written

    def __getattr__(self, name: str):  # truncate, seek, fileno, close, closed
        return getattr(self.real, name)


@pytest.fixture
def full_disk(monkeypatch: pytest.MonkeyPatch):
    """Files opened by the outputs go to a Disk; the test sets how much it holds."""
    disk = Disk(0)
    real_open = wholewrite.open_output
    monkeypatch.setattr(wholewrite, "open_output",
                        lambda path, append=False: FullingFile(real_open(path, append), disk))
    return disk


def _watch(d: LiveDaemon, topics: tuple[str, ...]) -> zmq.Socket:
    sub = d.ctx.socket(zmq.SUB)
    for t in topics:
        sub.setsockopt(zmq.SUBSCRIBE, t.encode())
    sub.connect(d.telemetry)
    return sub


def _until(sub: zmq.Socket, pred, timeout: float = DEADLINE) -> list[tuple[str, dict]]:
    """Telemetry messages until one satisfies ``pred(topic, body)`` (all of them, in order)."""
    seen: list[tuple[str, dict]] = []
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if sub.poll(100):
            topic, body = P.decode(sub.recv_multipart())
            seen.append((topic, body))
            if pred(topic, body):
                return seen
    raise AssertionError(f"not seen within {timeout} s; last: {seen[-3:]}")


def _valid_datagrams(s: socket.socket, n: int, timeout: float = DEADLINE) -> list[dict]:
    """``n`` datagrams with valid=1 received from now on (a robot still being localised)."""
    got: list[dict] = []
    end = time.monotonic() + timeout
    s.settimeout(0.2)
    while time.monotonic() < end and len(got) < n:
        with contextlib.suppress(TimeoutError):
            m = parse_datagram(s.recv(1024))
            if m["valid"]:
                got.append(m)
    assert len(got) >= n, f"robots got {len(got)} valid poses in {timeout} s, expected {n}"
    return got


def assert_whole_csv(path: Path) -> int:
    """Header, then rows of 11 fields each ending with a newline; returns the row count."""
    data = path.read_bytes()
    assert data.endswith(b"\n"), f"{path}: last row cut: {data[-60:]!r}"
    lines = data.decode().splitlines()
    assert lines[0] == HEADER
    for i, line in enumerate(lines[1:], 2):
        fields = line.split(",")
        assert len(fields) == len(COLUMNS), f"{path}: line {i} cut: {line!r}"
        int(fields[0]), float(fields[1])  # frame, timestamp
    return len(lines) - 1


def assert_whole_jsonl(path: Path) -> int:
    """Every line a whole JSON object (header first); returns the frame lines."""
    data = path.read_bytes()
    assert data.endswith(b"\n"), f"{path}: last line cut: {data[-60:]!r}"
    lines = data.decode().splitlines()
    assert json.loads(lines[0])["format"] == "kmead-recording"
    for line in lines[1:]:
        assert "frame" in json.loads(line)
    return len(lines) - 1


# ----------------------------------------------------------------------------- a full disk

def test_a_full_disk_stops_the_files_and_the_robots_keep_their_poses(
        tmp_path: Path, full_disk: Disk) -> None:
    s1 = udp_listener()
    data = tmp_path / "data"
    csv_path, rec_path = data / "run.csv", data / "run.jsonl"
    # Room for the recording's header and a few frames of both files, then the disk is full.
    full_disk.free = 150_000
    d = LiveDaemon(tmp_path, site=robots_toml({"amr1": s1.getsockname()[1]}),
                   sets=[f'log.csv="{csv_path}"', f'log.record="{rec_path}"',
                         "log.min_free_mb=0"])
    sub = _watch(d, ("status", "event"))
    try:
        seen = _until(sub, lambda t, b: t == "status" and b["logging"]["error"]
                      and b["recording"]["error"])
        st = seen[-1][1]
        assert not st["logging"]["active"] and not st["recording"]["active"]
        assert "No space left on device" in st["logging"]["error"]
        assert "No space left on device" in st["recording"]["error"]
        events = [b["text"] for t, b in seen if t == "event" and b["level"] == "error"]
        assert any("CSV log" in e and "write failed" in e for e in events), events
        assert any("recording" in e and "write failed" in e for e in events), events
        assert all("\n" not in e for e in events)
        assert full_disk.partial_writes >= 1  # a write was cut by the disk: the cut-back ran
        # The robots go on being localised and told, telemetry goes on.
        _valid_datagrams(s1, 10)
        frame = d.daemon.totals.frames
        _until(sub, lambda t, b: t == "status" and b["frames"] > frame + 5)
        assert d.alive(), d.error
        # What was written before the disk filled is whole.
        assert assert_whole_csv(csv_path) > 0
        assert assert_whole_jsonl(rec_path) > 0
    finally:
        sub.close(0)
        d.close()
        s1.close()
    assert d.error is None


def test_record_start_and_log_start_on_a_full_data_directory_are_refused(
        tmp_path: Path, full_disk: Disk) -> None:
    s1 = udp_listener()
    d = LiveDaemon(tmp_path, site=robots_toml({"amr1": s1.getsockname()[1]}),
                   sets=["log.min_free_mb=0"])
    try:
        assert d.frames_flow()
        for cmd, name in (("record_start", "full.jsonl"), ("log_start", "full.csv")):
            reply = d.cmd(cmd, path=name)
            assert reply["ok"] is False and "No space left on device" in reply["error"], reply
            # The refused request leaves nothing behind: the name can be tried again.
            assert not (d.data / name).exists()
        assert full_disk.refused >= 2
        _valid_datagrams(s1, 10)
        full_disk.free = 10**9  # room again: the same request works
        assert d.cmd("record_start", path="full.jsonl")["ok"]
        assert d.cmd("record_stop")["ok"]
        assert assert_whole_jsonl(d.data / "full.jsonl") >= 0
        assert d.alive(), d.error
    finally:
        d.close()
        s1.close()


# ----------------------------------------------------------------------------- the floor

class FakeSpace:
    """``os.statvfs`` reporting ``free`` bytes available under ``root``, the truth elsewhere."""

    def __init__(self, root: Path, free: int) -> None:
        self.root, self.free, self.real = str(root.resolve()), free, os.statvfs

    def __call__(self, path):
        p = os.path.realpath(os.fspath(path))
        if not (p + "/").startswith(self.root + "/"):
            return self.real(path)
        blocks = 10**7
        return os.statvfs_result((4096, 4096, blocks, self.free // 4096, self.free // 4096,
                                  10**6, 10**6, 10**6, 0, 255))


def test_the_free_space_floor_stops_a_running_log_cleanly_and_refuses_new_ones(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    space = FakeSpace(tmp_path, 10**10)
    monkeypatch.setattr(os, "statvfs", space)
    s1 = udp_listener()
    data = tmp_path / "data"
    d = LiveDaemon(tmp_path, site=robots_toml({"amr1": s1.getsockname()[1]}),
                   sets=[f'log.csv="{data / "run.csv"}"', f'log.record="{data / "run.jsonl"}"',
                         "log.min_free_mb=50"])
    sub = _watch(d, ("status", "event"))
    try:
        assert d.wait(lambda: d.daemon.csv is not None and d.daemon.csv.rows > 50, DEADLINE)
        space.free = 20 * 10**6  # 20 MB: below the floor of 50
        seen = _until(sub, lambda t, b: t == "status" and b["logging"]["error"]
                      and b["recording"]["error"])
        st = seen[-1][1]
        assert not st["logging"]["active"] and not st["recording"]["active"]
        for what in ("logging", "recording"):
            assert "20.0 MB free" in st[what]["error"]
            assert "log.min_free_mb = 50 MB" in st[what]["error"]
        events = [b["text"] for t, b in seen if t == "event" and b["level"] == "error"]
        assert any("CSV log" in e and "min_free_mb" in e for e in events), events
        assert assert_whole_csv(data / "run.csv") > 50
        assert_whole_jsonl(data / "run.jsonl")
        for cmd, name in (("log_start", "next.csv"), ("record_start", "next.jsonl")):
            reply = d.cmd(cmd, path=name)
            assert reply["ok"] is False, reply
            assert "not started" in reply["error"] and "min_free_mb" in reply["error"]
            assert "\n" not in reply["error"] and not (data / name).exists()
        _valid_datagrams(s1, 10)
        space.free = 10**10
        assert d.cmd("log_start", path="next.csv")["ok"]
        assert d.wait(lambda: d.daemon.status()["logging"]["error"] is None)
        assert d.alive(), d.error
    finally:
        sub.close(0)
        d.close()
        s1.close()


def test_a_start_below_the_floor_runs_without_the_log(tmp_path: Path,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(os, "statvfs", FakeSpace(tmp_path, 10**6))
    s1 = udp_listener()
    csv_path = tmp_path / "data" / "run.csv"
    d = LiveDaemon(tmp_path, site=robots_toml({"amr1": s1.getsockname()[1]}),
                   sets=[f'log.csv="{csv_path}"'])
    try:
        st = d.daemon.status()
        assert not st["logging"]["active"] and "below log.min_free_mb" in st["logging"]["error"]
        assert not csv_path.exists()
        _valid_datagrams(s1, 10)
        assert d.alive(), d.error
    finally:
        d.close()
        s1.close()


# ----------------------------------------------------------------------------- restarts

def _frames_in_csv(path: Path) -> list[int]:
    return [int(line.split(",", 1)[0]) for line in path.read_text().splitlines()[1:]]


def test_restarting_the_log_and_the_recording_over_control_never_wipes_them(
        tmp_path: Path) -> None:
    data = tmp_path / "data"
    csv_path, rec_path = data / "run.csv", data / "run.jsonl"
    d = LiveDaemon(tmp_path, sets=[f'log.csv="{csv_path}"', f'log.record="{rec_path}"'])
    try:
        assert d.wait(lambda: d.daemon.csv.rows > 100 and d.daemon.recorder.frames > 5,
                      DEADLINE)
        assert d.cmd("log_stop")["ok"] and d.cmd("record_stop")["ok"]
        first_csv, first_rec = csv_path.read_bytes(), rec_path.read_bytes()
        first_frames = _frames_in_csv(csv_path)

        log = d.cmd("log_start")
        assert log["ok"] and log["path"] == str(csv_path) and log["mode"] == "append", log
        rec = d.cmd("record_start")
        assert rec["ok"] and rec["mode"] == "new name", rec
        assert rec["path"] == str(data / "run-2.jsonl")
        assert d.wait(lambda: d.daemon.csv.rows > 100 and d.daemon.recorder.frames > 5,
                      DEADLINE)
        assert d.cmd("log_stop")["ok"] and d.cmd("record_stop")["ok"]

        # The first run's rows are all still there, then the second's: one header.
        assert csv_path.read_bytes().startswith(first_csv)
        assert csv_path.read_text().count(HEADER) == 1
        frames = _frames_in_csv(csv_path)
        assert len(frames) > len(first_frames) + 100
        assert frames == sorted(frames) and frames[-1] > first_frames[-1]
        assert_whole_csv(csv_path)
        assert rec_path.read_bytes() == first_rec
        assert assert_whole_jsonl(data / "run-2.jsonl") > 5

        # A file at the log's path that is not a whole log of this format is kept as it is.
        csv_path.write_text("my notes, not a kmead log\n")
        log = d.cmd("log_start")
        assert log["ok"] and log["mode"] == "new name" and log["path"] == str(data / "run-2.csv")
        rec = d.cmd("record_start")
        assert rec["ok"] and rec["path"] == str(data / "run-3.jsonl")
        assert d.cmd("log_stop")["ok"] and d.cmd("record_stop")["ok"]
        assert csv_path.read_text() == "my notes, not a kmead log\n"
        assert rec_path.read_bytes() == first_rec
        assert d.alive(), d.error
    finally:
        d.close()


# ----------------------------------------------------------------------------- settings

def test_every_filter_value_the_schema_accepts_runs_the_tracker() -> None:
    """Each numeric [filter] key at both ends of its range, with both motion models, through
    a drive with outliers and a 3 s gap: no exception, finite poses (a radius of 1e-300 m was
    once accepted and divided by zero in every frame)."""
    import math
    import random

    from kmea.pipeline import tracker_config
    from kmea.robots.tracking import Tracker
    from kmead.config.layers import load_config
    from kmead.config.schema import SCHEMA

    base = load_config(None, [], use_local=False)["filter"]
    checked = 0
    for key, check in SCHEMA["filter"].items():
        if not hasattr(check, "lo"):
            continue  # choices, booleans, integers
        for value in (check.lo, check.hi):
            for model in ("ctrv", "cv"):
                tr = Tracker(tracker_config({**base, key: value, "model": model}))
                rng = random.Random(1)
                t = 0.0
                for i in range(200):
                    t += 3.0 if i == 100 else 1 / 30
                    x, y = 0.5 * math.cos(t / 2), 0.4 * math.sin(t / 2)
                    x += 0.3 if i % 17 == 5 else 0.0  # an outlier now and then
                    tr.update("r", t, x + rng.gauss(0, 0.003), y + rng.gauss(0, 0.003),
                              t / 2, 0.003)
                    st = tr.predict("r", t + 0.05)
                    assert st is not None and all(
                        math.isfinite(v) for v in (st.x, st.y, st.theta, st.sigma)), (
                        key, value, model, st)
                checked += 1
    numeric = sum(hasattr(c, "lo") for c in SCHEMA["filter"].values())
    assert numeric >= 8 and checked == 4 * numeric  # every numeric filter key was driven


def test_a_live_setting_that_breaks_every_frame_is_rolled_back_whatever_its_key(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from kmea.robots import tracking

    # Stand-in for a value inside its range that the filter still cannot digest (the
    # ranges now refuse the 1e-300 that did this): every new track raises.
    real_init = tracking.Track.__init__

    def init(self, name="", config=None):
        if config is not None and config.step_k == 0.5:
            raise ZeroDivisionError("float division by zero")
        real_init(self, name, config)

    monkeypatch.setattr(tracking.Track, "__init__", init)
    s1 = udp_listener()
    d = LiveDaemon(tmp_path, site=robots_toml({"amr1": s1.getsockname()[1]}))
    sub = _watch(d, ("event",))
    try:
        assert d.wait(lambda: d.daemon.guard.healthy_before(), DEADLINE)
        refused = d.cmd("set", key="filter.step_k", value=1e-300)
        assert refused["ok"] is False
        assert "filter.step_k" in refused["error"]
        assert "must be in [0.01, 1e+09]" in refused["error"]

        assert d.cmd("set", key="filter.step_k", value=0.5)["ok"]
        saved = d.cmd("save_config")  # during the trial: the previous value
        assert saved["ok"] and saved["held"] == ["filter.step_k"]
        seen = _until(sub, lambda t, b: "rolled back" in b["text"])
        assert seen[-1][1]["level"] == "error"
        assert "set filter.step_k rolled back" in seen[-1][1]["text"]
        assert d.daemon.cfg["filter"]["step_k"] == 1.2
        assert d.cmd("get_config")["config"]["filter"]["step_k"] == 1.2
        assert "step_k" not in d.cfg.overlay_path.read_text()
        _valid_datagrams(s1, 10)  # the robots are localised again
        assert d.alive(), d.error
    finally:
        sub.close(0)
        d.close()
        s1.close()


# ----------------------------------------------------------------------------- start-up

NET = ["--set", 'network.telemetry="tcp://127.0.0.1:*"',
       "--set", 'network.control="tcp://127.0.0.1:*"']
FAST = ["--set", "source.width=640", "--set", "source.height=480", "--set", "source.fps=0"]


def _failing_pipeline(monkeypatch: pytest.MonkeyPatch, first_ok: int | None = None) -> dict:
    """Pipeline.process raises ZeroDivisionError (what a radius of 1e-300 m once did) for every
    frame, or for the frames before ``first_ok`` calls."""
    from kmea.pipeline import Pipeline

    real = Pipeline.process
    calls = {"n": 0}

    def process(self, inp, **kw):
        calls["n"] += 1
        if first_ok is None or calls["n"] <= first_ok:
            raise ZeroDivisionError("float division by zero")
        return real(self, inp, **kw)

    monkeypatch.setattr(Pipeline, "process", process)
    return calls


@contextlib.contextmanager
def _sigterm_after(seconds: float):
    """A run that would never end (the defect) is stopped by SIGTERM (kmead's handler) after
    ``seconds``, so the test fails instead of hanging."""
    import signal
    import threading

    timer = threading.Timer(seconds, lambda: os.kill(os.getpid(), signal.SIGTERM))
    timer.start()
    try:
        yield
    finally:
        timer.cancel()


def _error_lines(err: str) -> list[str]:
    return [x for x in err.splitlines() if "no frame succeeded" in x]


def test_a_start_where_every_frame_fails_exits_1_naming_the_first_error(
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture) -> None:
    from kmead import cli

    calls = _failing_pipeline(monkeypatch)
    # No --frames: the unpaced simulator never ends; the failures end the run.
    with _sigterm_after(120):
        assert cli.main(["--headless", "--status-every", "0", *FAST, *NET]) == 1
    lines = _error_lines(capsys.readouterr().err)
    assert len(lines) == 1, lines
    assert "30 failed in a row" in lines[0]
    assert "The first: frame 0: ZeroDivisionError: float division by zero" in lines[0]
    assert calls["n"] >= 30

    # --frames counts the frames read: 20 failed frames end a --frames 20 run, exit 1.
    calls["n"] = 0
    with _sigterm_after(120):
        assert cli.main(["--headless", "--frames", "20", "--status-every", "0", *FAST,
                         *NET]) == 1
    lines = _error_lines(capsys.readouterr().err)
    assert len(lines) == 1 and "20 failed in a row" in lines[0], lines
    assert calls["n"] == 20


def test_failed_frames_at_start_followed_by_good_ones_are_not_a_broken_start(
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture) -> None:
    from kmead import cli

    _failing_pipeline(monkeypatch, first_ok=5)
    with _sigterm_after(120):
        assert cli.main(["--headless", "--frames", "40", "--status-every", "0", *FAST,
                         *NET]) == 0
    out = capsys.readouterr()
    assert not _error_lines(out.err)
    assert "35 frames" in out.out  # the summary counts the frames that succeeded


# ----------------------------------------------------------------------------- --free-ports

def test_a_save_after_a_free_ports_run_keeps_the_configured_endpoints(tmp_path: Path) -> None:
    import re
    import signal
    import subprocess
    import sys
    import threading

    site = tmp_path / "site.toml"
    site.write_text('[network]\ntelemetry = "tcp://127.0.0.1:5755"\n'
                    'control = "tcp://127.0.0.1:5756"\n')
    env = {**os.environ, "XDG_CONFIG_HOME": str(tmp_path / "home")}
    proc = subprocess.Popen(
        [sys.executable, "-m", "kmead.cli", "--config", str(site), "--headless", "--free-ports",
         "--status-every", "0", "--set", "source.width=640", "--set", "source.height=480",
         "--set", "source.fps=10", "--set", "detector.workers=0"],
        cwd=tmp_path, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stderr), daemon=True)
    reader.start()
    ctx = zmq.Context()
    overlay = tmp_path / "site.local.toml"
    try:
        end = time.monotonic() + DEADLINE
        found = None
        while found is None and time.monotonic() < end and proc.poll() is None:
            found = next((m for x in list(lines) if (m := re.search(
                r"control (tcp://127\.0\.0\.1:\d+)", x))), None)
            time.sleep(0.05)
        assert found, lines
        control = found.group(1)
        assert control != "tcp://127.0.0.1:5756"  # --free-ports bound another port

        def cmd(name: str, **args: object) -> dict:
            req = ctx.socket(zmq.REQ)
            req.setsockopt(zmq.LINGER, 0)
            req.connect(control)
            try:
                req.send(P.encode_body({"cmd": name, **args}))
                assert req.poll(15000), f"no reply to {name}"
                return P.decode_body(req.recv())
            finally:
                req.close(0)

        assert cmd("set", key="filter.alpha", value=0.5)["ok"]
        assert cmd("save_config")["ok"]
        end = time.monotonic() + DEADLINE  # saved again once the change's trial passed
        while time.monotonic() < end and not (overlay.exists()
                                              and "alpha = 0.5" in overlay.read_text()):
            time.sleep(0.05)
        saved = overlay.read_text()
        assert "alpha = 0.5" in saved
        assert "network" not in saved and "*" not in saved and control not in saved, saved
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=DEADLINE)
        reader.join(timeout=DEADLINE)
        proc.stderr.close()
        ctx.term()
    # The next start without --free-ports binds the configured endpoints.
    check = subprocess.run([sys.executable, "-m", "kmead.cli", "--config", str(site), "--check"],
                           cwd=tmp_path, env=env, capture_output=True, text=True, timeout=60)
    assert check.returncode == 0, check.stderr
    assert 'telemetry = "tcp://127.0.0.1:5755"' in check.stdout
    assert 'control = "tcp://127.0.0.1:5756"' in check.stdout


# ----------------------------------------------------------------------------- bad files

@pytest.mark.parametrize("depth", [600, 3000])
def test_toml_nested_too_deeply_is_one_line_naming_the_file(
        tmp_path: Path, capsys: pytest.CaptureFixture, depth: int) -> None:
    from kmead import cli

    deep = "x = " + "[" * depth + "]" * depth + "\n"
    cases = {"config": ["--config", str(tmp_path / "c.toml")],
             "map": ["--map", str(tmp_path / "m.toml")],
             "camera": ["--camera", str(tmp_path / "k.toml")],
             "--set": ["--set", "filter.alpha=" + "[" * depth + "]" * depth]}
    for name in ("c", "m", "k"):
        (tmp_path / f"{name}.toml").write_text(deep)
    for what, args in cases.items():
        code = cli.main(["--headless", "--frames", "1", *args, *NET])
        err = capsys.readouterr().err.strip()
        assert code == 2, (what, err[-300:])
        assert err.count("\n") == 0 and "Traceback" not in err, (what, err[:300])
        if what == "--set":
            assert "filter.alpha" in err
        else:
            assert args[1] in err and "nested too deeply" in err, (what, err)
