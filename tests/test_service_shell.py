"""The service shell (kmead.net.service) and the control protocol's two parts
(kmead.net.control): real sockets on loopback, real files.

- A service without the camera part answers what every service answers and refuses each
  of a camera's commands with one line; a fusion node is such a service.
- Teardown is the reverse of opening, whatever opened: after a full start, after a start
  that failed half way (a control port taken), and past a close that raises.
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path
from typing import Any

import pytest
import zmq
from deadlines import DEADLINE, JOIN, wait_until

from kmea.wire import protocol as P
from kmead.config.layers import load_config
from kmead.net.control import CAMERA_COMMANDS, COMMANDS, NO_CAMERA, SERVICE_COMMANDS
from kmead.net.service import Service

NET = ['network.telemetry="tcp://127.0.0.1:*"', 'network.control="tcp://127.0.0.1:*"',
       'log.level="warning"']


class Shell(Service):
    """The smallest service: the shell and what every service answers, no camera part;
    ``order`` records what closed, in order."""

    def __init__(self, cfg: Any, camera: bool = False) -> None:
        super().__init__(cfg)
        self.order: list[str] = []
        try:
            self.open_telemetry()
            self.closing.callback(self.order.append, "telemetry")  # runs just before it
            self.open_files()
            self.closing.callback(self.order.append, "files")
            self.open_relay()
            self.closing.callback(self.order.append, "relay")
            self.open_control(self)
            self.closing.callback(self.order.append, "control")
        except BaseException:
            self.close()
            raise

    def farewell(self) -> None:
        # The control server stopped and the CSV log closed before the last telemetry.
        self.order.append("farewell")
        files = getattr(self, "files", None)
        self.at_farewell = (self.control is None, files is None or files.csv is None)

    def status(self) -> P.StatusBody:
        return {"t": 0.0}  # type: ignore[typeddict-item]

    def state(self) -> dict[str, Any]:
        return {"status": self.status(), "frame": {}, "stats": {}}

    def tick(self) -> None:
        pass

    def apply_setting(self, key: str, value: Any, remote: bool = False) -> Any:
        return self.cfg.set(key, value, remote=remote)

    def start_csv(self, path: str, remote: bool = False, keep: bool = False) -> Any:
        return self.files.start_csv(path, remote, keep)

    def stop_csv(self) -> dict:
        return self.files.stop_csv()


def _request(endpoint: str, cmd: str, **fields: Any) -> dict:
    ctx = zmq.Context.instance()
    sock = ctx.socket(zmq.REQ)
    sock.setsockopt(zmq.LINGER, 0)
    sock.setsockopt(zmq.RCVTIMEO, int(DEADLINE * 1000))
    try:
        sock.connect(endpoint)
        sock.send(P.encode_body({"cmd": cmd, **fields}))
        return P.decode_body(sock.recv())
    finally:
        sock.close()


def _binds(endpoint: str) -> bool:
    sock = zmq.Context.instance().socket(zmq.PUB)
    try:
        sock.bind(endpoint)
        return True
    except zmq.ZMQError:
        return False
    finally:
        sock.close(linger=0)


def _handlers() -> list:
    return list(logging.getLogger("kmead").handlers)


def test_the_commands_are_the_two_parts() -> None:
    assert set(SERVICE_COMMANDS) | set(CAMERA_COMMANDS) == set(COMMANDS)
    assert not set(SERVICE_COMMANDS) & set(CAMERA_COMMANDS)


def test_a_service_without_a_camera_refuses_its_commands_in_one_line(tmp_path: Path) -> None:
    shell = Shell(load_config(None, [*NET, f'log.dir="{tmp_path}"']))
    try:
        assert shell.control is not None
        shell.control.start()
        endpoint = shell.control.bound
        assert set(shell.control.handlers) == set(SERVICE_COMMANDS)
        for cmd in CAMERA_COMMANDS:
            reply = _request(endpoint, cmd)
            assert reply == {"v": P.PROTOCOL_VERSION, "ok": False, "error": f"{cmd}: {NO_CAMERA}"}
            assert "\n" not in reply["error"]
        assert _request(endpoint, "ping")["ok"] is True
        state = _request(endpoint, "get_state")
        assert state["ok"] is True and state["frame"] == {}
        started = _request(endpoint, "log_start", path="x.csv")
        assert started["ok"] is True and Path(started["path"]).parent == tmp_path
        assert _request(endpoint, "log_stop")["ok"] is True
        assert _request(endpoint, "get_log", limit=5)["ok"] is True
    finally:
        shell.close()


def test_teardown_is_the_reverse_of_opening(tmp_path: Path) -> None:
    before = _handlers()
    shell = Shell(load_config(None, [*NET, f'log.dir="{tmp_path}"']))
    assert shell.control is not None and shell.telemetry is not None
    telemetry = shell.telemetry.bound
    csv = shell.start_csv(str(tmp_path / "run.csv"))
    assert len(_handlers()) == len(before) + 2  # the log ring and the telemetry's
    shell.close()
    assert shell.order == ["control", "relay", "files", "telemetry", "farewell"]
    assert shell.at_farewell == (True, True)
    assert shell.control is None and shell.telemetry is None and shell.files.csv is None
    assert csv.path.read_text().startswith("frame")  # flushed and closed: its header
    assert _handlers() == before
    shell.close()  # idempotent
    assert shell.order == ["control", "relay", "files", "telemetry", "farewell"]
    # The sockets are gone: their ports bind again (once ZeroMQ's I/O thread let go).
    wait_until(lambda: _binds(telemetry), "the telemetry port free again")


def test_a_start_that_fails_half_way_closes_what_opened(tmp_path: Path) -> None:
    before = _handlers()
    taken = zmq.Context.instance().socket(zmq.REP)
    taken.bind("tcp://127.0.0.1:*")
    endpoint = taken.getsockopt_string(zmq.LAST_ENDPOINT)
    opened: list[Shell] = []

    class Failing(Shell):
        def open_control(self, *args: Any, **kw: Any) -> Any:
            opened.append(self)
            return super().open_control(*args, **kw)

    try:
        cfg = load_config(None, ['network.telemetry="tcp://127.0.0.1:*"',
                                 f'network.control="{endpoint}"', f'log.dir="{tmp_path}"'])
        with pytest.raises(OSError, match="cannot bind"):
            Failing(cfg)
    finally:
        taken.close(linger=0)
    shell = opened[0]
    # What opened before the control server closed, in reverse; nothing else ran.
    assert shell.order == ["relay", "files", "telemetry", "farewell"]
    assert shell.closed and shell.telemetry is None and shell.control is None
    assert _handlers() == before


def test_a_close_that_raises_does_not_keep_the_others_open(tmp_path: Path) -> None:
    before = _handlers()
    shell = Shell(load_config(None, [*NET, f'log.dir="{tmp_path}"']))

    def broken() -> None:
        raise RuntimeError("a part that fails to close")

    shell.closing.callback(broken)  # the last opened: the first to close
    with pytest.raises(RuntimeError, match="fails to close"):
        shell.close()
    assert shell.order == ["control", "relay", "files", "telemetry", "farewell"]
    assert _handlers() == before


def test_a_fusion_node_refuses_a_cameras_commands(tmp_path: Path) -> None:
    pytest.importorskip("zenoh", reason="the zenoh extra is not installed")
    from zenoh_helpers import free_port, zenoh_sets

    from kmead.fusion.node import FusionNode

    node = FusionNode(load_config(None, [*NET, f'log.dir="{tmp_path}"',
                                         *zenoh_sets(listen=free_port())]))
    run = threading.Thread(target=node.run, daemon=True)
    run.start()
    try:
        assert node.control is not None
        endpoint = node.control.bound
        for cmd in CAMERA_COMMANDS:
            assert _request(endpoint, cmd)["error"] == f"{cmd}: {NO_CAMERA}"
        state = _request(endpoint, "get_state")
        assert state["ok"] is True and state["frame"] == {}
        assert state["stats"]["algorithm"] == "fusion" and state["stats"]["markers"] == []
        assert "fusion" in state["status"]
    finally:
        node.stop()
        run.join(JOIN)
        node.close()
    assert node.closed and node.control is None and node.telemetry is None
