"""Issue 12: every reproduction of the hostile-client review, each as its own test, plus CURVE,
file confinement, rollback and robots told at shutdown, all against a real daemon on loopback
(real ZeroMQ sockets, real UDP listeners, the simulated floor through real detection).
"""

from __future__ import annotations

import contextlib
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
from deadlines import DEADLINE, JOIN
from security_helpers import LiveDaemon, robots_toml, udp_listener

from kmea.sim.renderer import Renderer
from kmea.sim.scenes import scene_from_spec
from kmea.vision.camera import pi_camera_v2, save_camera
from kmea.wire import protocol as P
from kmead import cli
from kmead.net.keys import connect_client
from kmead.outputs.relay import parse_datagram
from kmead.tools import kmea_cli

NET = ["--set", 'network.telemetry="tcp://127.0.0.1:*"',
       "--set", 'network.control="tcp://127.0.0.1:*"']
SMALL = ["--set", "source.width=640", "--set", "source.height=480"]


@pytest.fixture(scope="module")
def shared(tmp_path_factory: pytest.TempPathFactory) -> LiveDaemon:
    """One daemon for the reproductions that leave its state as it was."""
    d = LiveDaemon(tmp_path_factory.mktemp("shared"))
    yield d
    d.close()


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file() or p.is_symlink()}


def _refused(d: LiveDaemon, cmd: str, match: str, **args: object) -> str:
    reply = d.cmd(cmd, **args)
    assert reply["ok"] is False and match in reply["error"], reply
    assert d.cmd("ping")["ok"]
    return reply["error"]


def _datagrams(s: socket.socket, seconds: float) -> list[dict]:
    out, end = [], time.monotonic() + seconds
    s.settimeout(0.1)
    while time.monotonic() < end:
        with contextlib.suppress(TimeoutError):
            out.append(parse_datagram(s.recv(1024)))
    return out


# ----------------------------------------------------------------------------- writing anywhere

def test_log_start_cannot_truncate_a_file_outside(shared: LiveDaemon, tmp_path: Path) -> None:
    bashrc = tmp_path / ".bashrc"
    bashrc.write_text("alias ll='ls -l'\n")
    _refused(shared, "log_start", "plain file name", path=str(bashrc))
    _refused(shared, "record_start", "plain file name", path=str(bashrc))
    assert bashrc.read_text() == "alias ll='ls -l'\n"


def test_dotdot_cannot_create_directories_outside(shared: LiveDaemon) -> None:
    before = _files(shared.root)
    _refused(shared, "record_start", "plain file name", path="../made/by/remote/x.csv")
    _refused(shared, "log_start", "plain file name", path="../made/by/remote/x.csv")
    assert not (shared.root / "made").exists() and _files(shared.root) == before


def test_robot_destination_with_shell_text_is_refused(shared: LiveDaemon) -> None:
    robots = [{"name": "amr1", "markers": [40, 41],
               "destinations": [f"udp:$(touch {shared.root}/PWNED):9"]}]
    _refused(shared, "set", "destination must be", key="robots", value=robots)
    assert shared.cmd("get_config")["config"]["robots"] == shared.cfg["robots"]
    assert not (shared.root / "PWNED").exists()


def test_save_config_writes_only_the_overlay(shared: LiveDaemon, tmp_path: Path) -> None:
    profile = tmp_path / ".profile"
    profile.write_text("# mine\n")
    for path in (str(profile), "../.profile", str(shared.site)):
        _refused(shared, "save_config", "writes only the daemon's overlay", path=path)
    assert profile.read_text() == "# mine\n"
    assert shared.site.read_text().startswith("# the operator's own file")
    saved = shared.cmd("save_config", path=str(shared.cfg.overlay_path))
    assert saved["ok"] and saved["path"] == str(shared.root / "site.local.toml")


def test_log_start_onto_the_config_file_is_refused_and_the_next_start_works(
        shared: LiveDaemon) -> None:
    for name in (str(shared.site), "../site.toml"):
        _refused(shared, "log_start", "plain file name", path=name)
    (shared.data / "site.toml").write_text("[filter]\n")  # a config file inside the directory
    _refused(shared, "log_start", "must end with .csv", path="site.toml")
    _refused(shared, "record_start", "must end with .jsonl", path="site.toml")
    assert shared.site.read_text().startswith("# the operator's own file")
    assert cli.main(["--config", str(shared.site), "--headless", "--frames", "1", *SMALL,
                     *NET, "--set", "source.fps=0"]) == 0


def test_log_and_recording_can_never_share_a_file(shared: LiveDaemon, tmp_path: Path,
                                                  capsys: pytest.CaptureFixture) -> None:
    same = tmp_path / "both.csv"
    assert cli.main(["--headless", "--frames", "1", "--log", str(same), "--record", str(same),
                     *SMALL, *NET]) == 2
    err = [x for x in capsys.readouterr().err.splitlines() if "log.record" in x]
    assert len(err) == 1 and "log.csv and log.record" in err[0]
    assert not same.exists()
    # Over control the kinds have different suffixes, and a path is never a name.
    assert shared.cmd("log_start", path="run7.csv")["ok"]
    _refused(shared, "record_start", "must end with .jsonl", path="run7.csv")
    assert shared.cmd("log_stop")["ok"]


# ----------------------------------------------------------------------------- file confinement

def test_confinement_absolute_dotdot_symlink_existing_config_all_refused(
        shared: LiveDaemon, tmp_path: Path) -> None:
    outside = tmp_path / "victim.csv"
    outside.write_text("keep\n")
    for suffix in (".csv", ".jsonl"):
        (shared.data / f"out{suffix}").symlink_to(outside)
        (shared.data / f"old{suffix}").write_text("old\n")
    before, before_out = _files(shared.data), outside.read_text()
    cases = [(str(tmp_path / "abs.csv"), "plain file name"), ("../x.csv", "plain file name"),
             ("out.csv", "already exists"), ("old.csv", "already exists"),
             (str(shared.site), "plain file name"), ("sub/x.csv", "plain file name")]
    for kind in ("log_start", "record_start"):
        for name, why in cases:
            name = name.replace(".csv", ".jsonl") if kind == "record_start" else name
            _refused(shared, kind, why, path=name)
    assert _files(shared.data) == before and outside.read_text() == before_out
    assert not (tmp_path / "abs.csv").exists()


# ----------------------------------------------------------------------------- control never dies

def test_nested_json_gets_an_error_reply_and_the_socket_lives(shared: LiveDaemon) -> None:
    for depth in (990, 995, 1000, 100000):
        reply = shared.request(b"[" * depth + b"]" * depth)
        assert reply is not None and reply["ok"] is False
        assert "nested" in reply["error"] or "too large" in reply["error"]
        assert shared.cmd("ping")["ok"]


@pytest.mark.parametrize("key", ["detector.foo", "detector", "detector.", "detector.a.b",
                                 "detector.parameters.minDistanceToBorder"])
def test_set_of_an_unknown_detector_key_is_an_error_reply(shared: LiveDaemon, key: str) -> None:
    _refused(shared, "set", "detector", key=key, value=1)


@pytest.mark.parametrize("name", ["adaptiveThreshWinSizeMax", "minMarkerPerimeterRate"])
def test_overflowing_detector_parameter_is_an_error_reply(shared: LiveDaemon, name: str) -> None:
    _refused(shared, "set", name, key="detector.parameters",
             value={name: 100000000000000000000})


def test_version_must_be_exactly_the_integer_one(shared: LiveDaemon) -> None:
    for v in (b"true", b"2.0", b'"2"', b"null", b"1"):
        reply = shared.request(b'{"v": ' + v + b', "cmd": "ping"}')
        assert reply is not None and reply["ok"] is False and "protocol version" in reply["error"]
    assert shared.request(P.encode_body({"cmd": "ping"}))["ok"]


# ----------------------------------------------------------------------------- absurd values

@pytest.mark.parametrize("key", ["stats.window", "stats.displaced_frames"])
def test_huge_stats_values_are_refused_and_the_daemon_runs_on(shared: LiveDaemon,
                                                               key: str) -> None:
    _refused(shared, "set", "must be an integer in", key=key, value=10**30)
    assert shared.frames_flow() and shared.alive()


@pytest.mark.parametrize("sets", [["stats.window=1000000000000000000000000000000"],
                                  ["stats.displaced_frames=1000000000000000000000000000000"],
                                  ["detector.fixed_full_every=1000000000000000000000000000000"]])
def test_huge_values_from_set_refuse_to_start(sets: list[str],
                                              capsys: pytest.CaptureFixture) -> None:
    args = [a for s in sets for a in ("--set", s)]
    assert cli.main(["--headless", "--frames", "1", *args, *SMALL, *NET]) == 2
    err = [x for x in capsys.readouterr().err.splitlines() if "--set" in x]
    assert len(err) == 1 and "--set: key" in err[0] and "integer in" in err[0]


def test_stopping_localisation_values_are_refused(shared: LiveDaemon) -> None:
    _refused(shared, "set", "markerBorderBits", key="detector.parameters",
             value={"markerBorderBits": 0})
    _refused(shared, "set", "perspectiveRemovePixelPerCell", key="detector.parameters",
             value={"perspectiveRemovePixelPerCell": 2000})
    assert shared.cmd("get_config")["config"]["detector"]["parameters"] == {}


def test_dictionary_path_tells_nothing_about_files(shared: LiveDaemon, tmp_path: Path) -> None:
    real = tmp_path / "dict.yml"
    real.write_text("%YAML:1.0\n")
    e1 = _refused(shared, "set", "predefined name", key="detector.dictionary", value=str(real))
    e2 = _refused(shared, "set", "predefined name", key="detector.dictionary",
                  value=str(tmp_path / "missing.yml"))
    assert e1.replace(str(real), "P") == e2.replace(str(tmp_path / "missing.yml"), "P")


def test_camera_file_with_principal_point_outside_the_image_refuses_to_start(
        tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    cam = pi_camera_v2()
    K = cam.camera_matrix.copy()
    K[0, 2] = 1e9
    bad = tmp_path / "cam.yml"
    save_camera(type(cam)(K, cam.dist_coeffs, cam.width, cam.height), bad)
    assert cli.main(["--headless", "--frames", "1", "--camera", str(bad), *SMALL, *NET]) == 2
    line = [x for x in capsys.readouterr().err.splitlines() if "principal point" in x]
    assert len(line) == 1 and str(bad) in line[0] and line[0].startswith("kmead: camera:")


def test_map_id_outside_the_dictionary_is_named_in_a_warning(tmp_path: Path,
                                                             capsys: pytest.CaptureFixture
                                                             ) -> None:
    from kmea.maps.files import default_map, map_to_dict

    doc = map_to_dict(default_map())
    rows = doc["markers"]
    rows.append({**rows[-1], "id": 2000, "x": 0.5, "y": 0.5})  # DICT_5X5_100: ids 0-99
    import tomli_w

    m = tmp_path / "floor.toml"
    m.write_text(tomli_w.dumps(doc))
    assert cli.main(["--headless", "--frames", "2", "--map", str(m), *SMALL, *NET,
                     "--set", "source.fps=0"]) == 0
    err = capsys.readouterr().err
    assert "2000" in err and "can never be detected" in err
    # An id beyond every dictionary is a slip, not a marker: refused, not warned (issue 30).
    rows[-1]["id"] = 99999999999999
    m.write_text(tomli_w.dumps(doc))
    assert cli.main(["--headless", "--frames", "2", "--map", str(m), *SMALL, *NET,
                     "--set", "source.fps=0"]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert str(m) in line and "id: 99999999999999 is beyond 4095" in line, line


# ----------------------------------------------------------------------------- robots are told

def test_live_removal_sends_valid0_then_nothing(tmp_path: Path) -> None:
    a, b = udp_listener(), udp_listener()
    d = LiveDaemon(tmp_path, site=robots_toml({"amr1": a.getsockname()[1],
                                                "amr2": b.getsockname()[1]}))
    try:
        assert d.wait(lambda: any(m["valid"] for m in _datagrams(b, 0.2)), 20)
        keep = [r for r in d.cmd("get_config")["config"]["robots"] if r["name"] == "amr1"]
        assert d.cmd("set", key="robots", value=keep)["ok"]
        after = _datagrams(b, 1.0)  # (a valid=1 sent before the change may still arrive)
        assert [m["valid"] for m in after if m["name"] == "amr2"][-1:] == [False]
        assert sum(not m["valid"] for m in after) == 1
        assert any(m["valid"] for m in _datagrams(a, 0.5))  # the robot that stays goes on
    finally:
        d.close()
        a.close()
        b.close()


def _spawn(tmp_path: Path, port: int, *extra: str) -> subprocess.Popen:
    site = tmp_path / "site.toml"
    site.write_text(robots_toml({"amr1": port}))
    return subprocess.Popen(
        [sys.executable, "-m", "kmead.cli", "--headless", "--config", str(site), *SMALL,
         *NET, *extra], cwd=tmp_path, env={**os.environ, "PYTHONUNBUFFERED": "1"},
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


@pytest.mark.parametrize("how", ["SIGTERM", "SIGINT", "end of frames"])
def test_every_robot_gets_valid0_at_shutdown(tmp_path: Path, how: str) -> None:
    u = udp_listener()
    port = u.getsockname()[1]
    extra = ["--frames", "30", "--set", "source.fps=0"] if how == "end of frames" else \
        ["--set", "source.fps=15"]
    p = _spawn(tmp_path, port, *extra)
    try:
        got: list[dict] = []
        end = time.monotonic() + DEADLINE
        while time.monotonic() < end and not any(m["valid"] for m in got):
            got += _datagrams(u, 0.2)
        assert any(m["valid"] for m in got), p.stderr.read() if p.poll() is not None else ""
        if how != "end of frames":
            p.send_signal(getattr(signal, how))
        _, err = p.communicate(timeout=DEADLINE)
        assert p.returncode == 0, err
        assert "Traceback" not in err
        got += _datagrams(u, 0.5)
    finally:
        if p.poll() is None:
            p.kill()
            p.communicate()
        u.close()
    assert got[-1]["valid"] is False and got[-1]["name"] == "amr1"
    assert [m["seq"] for m in got] == sorted(m["seq"] for m in got)


def test_watchdog_tick_racing_shutdown_does_not_raise(tmp_path: Path) -> None:
    # SIGTERM while no frame came for relay.stale_after_s: the service thread's watchdog
    # passed its check, then close() closed the relay under the lock it waits for.
    d = LiveDaemon(tmp_path, sets=["relay.stale_after_s=0.01"])
    d.daemon.stop()
    d.thread.join(10)
    daemon = d.daemon
    daemon.live, daemon._last_frame_wall = True, 0.0
    errors: list[BaseException] = []

    def tick() -> None:
        try:
            daemon.tick()
        except BaseException as e:
            errors.append(e)

    with daemon.lock:  # tick() waits here, after its checks, as in the race
        t = threading.Thread(target=tick)
        t.start()
        time.sleep(0.1)
        daemon.close()  # what SIGTERM's shutdown does, under the lock
    t.join(5)
    d.close()
    assert errors == []


def test_refused_udp_sends_are_counted_as_errors(tmp_path: Path) -> None:
    closed = udp_listener()
    port = closed.getsockname()[1]
    closed.close()
    d = LiveDaemon(tmp_path, site=robots_toml({"amr1": port}))
    try:
        assert d.wait(lambda: d.daemon.relay.channels["amr1"].errors >= 5)
        tr = d.daemon.relay.channels["amr1"]
        assert tr.errors >= tr.sent - 1
    finally:
        d.close()


def test_video_that_ends_early_is_an_error(tmp_path: Path, capsys: pytest.CaptureFixture
                                           ) -> None:
    scene = scene_from_spec("sim", width=640, height=480)
    r = Renderer(scene)
    path = tmp_path / "clip.avi"
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (640, 480), False)
    for i in range(10):
        w.write(np.ascontiguousarray(r.render(i).image))
    w.release()
    data = path.read_bytes()
    cut = tmp_path / "cut.avi"
    cut.write_bytes(data[: int(len(data) * 0.55)])
    assert cli.main(["--source", f"video:{path}", "--headless", *NET]) == 0
    capsys.readouterr()
    assert cli.main(["--source", f"video:{cut}", "--headless", *NET]) == 1
    err = capsys.readouterr().err
    assert "of the 10 frames" in err and "truncated" in err


# ----------------------------------------------------------------------------- rollback

def test_a_live_change_that_breaks_the_pipeline_is_rolled_back_and_never_saved(
        tmp_path: Path) -> None:
    d = LiveDaemon(tmp_path)
    sub = d.ctx.socket(zmq.SUB)
    sub.setsockopt(zmq.SUBSCRIBE, b"event")
    sub.connect(d.telemetry)
    try:
        assert d.frames_flow() and d.wait(lambda: d.daemon.guard.healthy_before())
        # A valid dictionary, but not the floor's: no marker is found, nothing is estimated.
        assert d.cmd("set", key="detector.dictionary", value="DICT_4X4_50")["ok"]
        saved = d.cmd("save_config")  # waits for the trial: never the broken value
        assert saved["ok"]
        assert "DICT_4X4_50" not in (tmp_path / "site.local.toml").read_text()
        assert d.wait(lambda: d.daemon.cfg["detector"]["dictionary"] == "")
        assert d.cmd("get_config")["config"]["detector"]["dictionary"] == ""
        texts = []
        end = time.monotonic() + DEADLINE
        while time.monotonic() < end and not any("rolled back" in t for t in texts):
            if sub.poll(100):
                texts.append(P.decode(sub.recv_multipart())[1]["text"])
        assert any("set detector.dictionary rolled back" in t for t in texts), texts
        assert d.wait(lambda: d.daemon.last_result is not None
                      and d.daemon.last_result.estimate.ok)
        # A harmless change is kept and saved.
        # A harmless change saved during its trial reaches the file once the trial passes.
        assert d.cmd("set", key="detector.corner_refinement", value="contour")["ok"]
        saved = d.cmd("save_config")
        assert saved["ok"] and saved["held"] == ["detector.corner_refinement"]
        overlay = tmp_path / "site.local.toml"
        assert d.wait(lambda: 'corner_refinement = "contour"' in overlay.read_text(), 60)
        assert d.daemon.cfg["detector"]["corner_refinement"] == "contour"
    finally:
        sub.close(0)
        d.close()


def test_save_config_leaves_no_temporary_file_when_the_rename_fails(shared: LiveDaemon
                                                                    ) -> None:
    overlay = shared.cfg.overlay_path
    if overlay.exists():
        overlay.unlink()
    overlay.mkdir()  # a directory where the file should go: the rename fails
    try:
        reply = shared.cmd("save_config")
        assert reply["ok"] is False
        assert not overlay.with_name(overlay.name + ".tmp").exists()
    finally:
        overlay.rmdir()


# ----------------------------------------------------------------------------- CURVE

@pytest.fixture(scope="module")
def keys(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("keys") / "keys"
    assert kmea_cli.main(["keys", "init", str(d)]) == 0
    assert kmea_cli.main(["keys", "add", str(d), "screen", "--viewer"]) == 0
    return d


def test_curve_operator_viewer_stranger_and_plain_client(tmp_path: Path, keys: Path) -> None:
    d = LiveDaemon(tmp_path, sets=[f'network.keys="{keys}"'], keys=keys, client="operator")
    ctx = zmq.Context()
    try:
        assert d.cmd("ping")["ok"]  # an operator: replies
        assert d.cmd("set", key="filter.alpha", value=0.9)["ok"]
        # A viewer: telemetry, but control refused.
        sub = connect_client(ctx, d.telemetry, keys, "screen", zmq.SUB)
        sub.setsockopt(zmq.SUBSCRIBE, b"frame")
        assert sub.poll(3000) and sub.recv_multipart()[0] == b"frame"
        sub.close(0)
        req = connect_client(ctx, d.control, keys, "screen")

        def ask(body: dict) -> dict:
            req.send(P.encode_body(body))
            assert req.poll(10000)
            return P.decode_body(req.recv())

        reply = ask({"cmd": "set", "key": "filter.alpha", "value": 0.5})
        assert reply["ok"] is False and "viewer 'screen'" in reply["error"]
        assert "needs an operator key" in reply["error"]
        # It sees everything the operator sees, read-only, and is told its role.
        assert ask({"cmd": "ping"})["role"] == "viewer"
        assert ask({"cmd": "get_config"})["config"]["filter"]["alpha"] == 0.9
        assert ask({"cmd": "get_state"})["ok"] is True
        assert ask({"cmd": "get_log", "limit": 5})["ok"] is True
        assert ask({"cmd": "log_start"})["ok"] is False
        req.close(0)
        assert d.cmd("ping")["role"] == "operator"
        assert d.daemon.cfg["filter"]["alpha"] == 0.9
        # An unknown key and a plain client: nothing within 1 s, on either socket.
        pub, sec = zmq.curve_keypair()
        server = (keys / "server.key").read_text().split('public-key = "')[1][:40].encode()
        for make in ("stranger", "plain"):
            r = ctx.socket(zmq.REQ)
            s = ctx.socket(zmq.SUB)
            for sock in (r, s):
                sock.setsockopt(zmq.LINGER, 0)
                if make == "stranger":
                    sock.curve_publickey, sock.curve_secretkey = pub, sec
                    sock.curve_serverkey = server
            s.setsockopt(zmq.SUBSCRIBE, b"")
            r.connect(d.control)
            s.connect(d.telemetry)
            # Not blocking: once the server has refused the handshake the REQ socket
            # has no peer and a blocking send would wait forever (nothing sent is the
            # outcome this checks too).
            with contextlib.suppress(zmq.Again):
                r.send(P.encode_body({"cmd": "ping"}), zmq.NOBLOCK)
            assert not r.poll(1000), make
            assert not s.poll(100), make
            r.close(0)
            s.close(0)
        assert d.frames_flow()
    finally:
        ctx.term()
        d.close()


def test_non_loopback_bind_without_keys_exits_2_with_one_line(
        capsys: pytest.CaptureFixture, keys: Path) -> None:
    for ep in ('network.control="tcp://0.0.0.0:*"', 'network.telemetry="tcp://*:*"'):
        assert cli.main(["--headless", "--frames", "1", *SMALL, *NET, "--set", ep]) == 2
        err = [x for x in capsys.readouterr().err.splitlines() if "network." in x]
        assert len(err) == 1 and "kmea keys init DIR" in err[0] and "refusing" in err[0]
    # Explicitly insecure: allowed, with a warning; with keys: allowed, no warning.
    open_ = ["--set", 'network.control="tcp://0.0.0.0:*"', "--set", "source.fps=0"]
    assert cli.main(["--headless", "--frames", "1", *SMALL, *NET, *open_,
                     "--set", "network.insecure=true"]) == 0
    assert "WITHOUT authentication" in capsys.readouterr().err
    assert cli.main(["--headless", "--frames", "1", *SMALL, *NET, *open_,
                     "--set", f'network.keys="{keys}"']) == 0
    assert "WITHOUT authentication" not in capsys.readouterr().err


def test_missing_keys_directory_is_a_one_line_error(tmp_path: Path,
                                                    capsys: pytest.CaptureFixture) -> None:
    assert cli.main(["--headless", "--frames", "1", *SMALL, *NET,
                     "--set", f'network.keys="{tmp_path / "nokeys"}"']) == 2
    err = [x for x in capsys.readouterr().err.splitlines() if "network.keys" in x]
    assert len(err) == 1 and "kmea keys init" in err[0] and "nokeys" in err[0]



# ----------------------------------------------------------------------------- fusion node

def test_fusion_node_has_the_same_rules(tmp_path: Path) -> None:
    pytest.importorskip("zenoh", reason="the zenoh extra is not installed")
    from zenoh_helpers import free_port, zenoh_sets

    from kmead.config.layers import ConfigError, load_config
    from kmead.fusion.node import FusionNode

    z = zenoh_sets(listen=free_port())
    open_ = load_config(None, ['network.control="tcp://0.0.0.0:*"',
                               'network.telemetry="tcp://127.0.0.1:*"', *z])
    with pytest.raises(ConfigError, match="kmea keys init DIR"):
        FusionNode(open_)
    # Zenoh beyond loopback: the same rule (mutual TLS, or zenoh.insecure).
    exposed = load_config(None, ['network.control=""', 'network.telemetry=""',
                                 *zenoh_sets(), 'zenoh.listen=["tcp/0.0.0.0:7447"]'])
    with pytest.raises(ConfigError, match=r"zenoh\.listen"):
        FusionNode(exposed)
    cfg = load_config(None, ['network.control="tcp://127.0.0.1:*"',
                             'network.telemetry="tcp://127.0.0.1:*"',
                             f'log.dir="{tmp_path / "data"}"', *z])
    node = FusionNode(cfg)
    assert node.control is not None
    ctx = zmq.Context()
    try:
        node.control.start()
        req = ctx.socket(zmq.REQ)
        req.setsockopt(zmq.LINGER, 0)
        req.connect(node.control.bound)
        for path, why in ((str(tmp_path / "x.csv"), "plain file name"),
                          ("../x.csv", "plain file name"), ("ok.csv", None)):
            req.send(P.encode_body({"cmd": "log_start", "path": path}))
            assert req.poll(5000)
            reply = P.decode_body(req.recv())
            assert reply["ok"] is (why is None) and (why is None or why in reply["error"])
        assert (tmp_path / "data" / "ok.csv").exists() and not (tmp_path / "x.csv").exists()
        req.close(0)
    finally:
        ctx.term()
        node.close()


def test_robots_gone_stale_because_the_frames_stopped_say_so(tmp_path: Path) -> None:
    """A live daemon whose frames stop (a stalled camera, a loaded machine): its robots go
    stale on the wall clock, and the line says the frames stopped, not the robots."""
    d = LiveDaemon(tmp_path, sets=["relay.stale_after_s=0.5"])
    daemon = d.daemon
    deadline = time.monotonic() + DEADLINE
    while "amr1" not in daemon.totals.robots_seen and time.monotonic() < deadline:
        time.sleep(0.05)
    assert "amr1" in daemon.totals.robots_seen
    daemon.stop()  # the frames stop; the service thread's watchdog goes on
    d.thread.join(JOIN)
    events: list[str] = []
    daemon.event = lambda level, text: events.append(text)  # type: ignore[method-assign]
    daemon.live = True
    while not events and time.monotonic() < deadline + DEADLINE:
        daemon._last_frame_wall = time.time() - 3.0
        daemon.tick()  # robots go stale relay.stale_after_s after their last fix
        time.sleep(0.05)
    d.close()
    stale = [e for e in events if "amr1" in e]
    # 3.0 s and the time until the tick read the clock (a loaded machine: 3.1 s and more).
    assert stale and re.match(r"no frame for 3\.\d s \(the camera or this machine "
                              r"stalled\): robot amr1 stale \(valid=0 sent\)", stale[0]), events
