"""A site's peers only where they belong: ``kmea keys site`` makes the CA, a certificate per
peer and Zenoh's access control; real Zenoh sessions on loopback, configured the way kmead
and the fusion node configure theirs (kmead.outputs.zenoh_session), show that a camera's
certificate cannot publish another camera's measurements, hold another camera's or a fusion
node's token, and that a robot's can only listen.

Denials are shown without sleeping: a peer sends the denied messages first and an allowed
one last on the same link (Zenoh's reliable channel keeps a link's order), so once the
allowed one has arrived, the denied ones would have arrived before it."""

from __future__ import annotations

import socket
import threading
from pathlib import Path

import pytest
from deadlines import DEADLINE

zenoh = pytest.importorskip("zenoh", reason="the zenoh extra is not installed "
                                            "(pip install 'kmea[zenoh]')")
pytest.importorskip("cryptography", reason="the zenoh extra is not installed")

from kmead.config.layers import load_config  # noqa: E402
from kmead.config.plan import zenoh_plan  # noqa: E402
from kmead.config.site_tls import certificate_name  # noqa: E402
from kmead.config.startup import StartupError  # noqa: E402
from kmead.outputs.zenoh_camera import camera_id  # noqa: E402
from kmead.outputs.zenoh_session import open_session  # noqa: E402
from kmead.tools.kmea_cli import main as kmea_main  # noqa: E402


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("site") / "kmea-site"
    assert kmea_main(["keys", "site", str(d), "--cameras", "cam0", "cam1", "--nodes",
                      "fuse0", "fuse1", "--robots", "amr1"]) == 0
    return d


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _cfg(site: Path, name: str, *sets: str):
    return load_config(None, ["zenoh.enabled=true", f'zenoh.tls_ca="{site / "ca.pem"}"',
                              f'zenoh.tls_cert="{site / (name + ".pem")}"',
                              f'zenoh.tls_key="{site / (name + ".key")}"',
                              f'zenoh.acl="{site / "acl.json5"}"', *sets], use_local=False)


class Listener:
    """The fusion node's side: every sample and token it is let to see."""

    def __init__(self, session) -> None:
        self.lock = threading.Lock()
        self.keys: list[str] = []
        self.tokens: list[str] = []
        self.event = threading.Event()
        self.subs = [session.declare_subscriber("**", self._sample),
                     session.liveliness().declare_subscriber("**", self._token, history=True)]

    def _sample(self, s) -> None:
        with self.lock:
            self.keys.append(str(s.key_expr))
        self.event.set()

    def _token(self, s) -> None:
        with self.lock:
            if str(s.kind).endswith("PUT"):
                self.tokens.append(str(s.key_expr))
        self.event.set()

    def wait_for(self, what: str, kind: str) -> list[str]:
        """Everything of ``kind`` seen once ``what`` arrived (fails after the deadline)."""
        deadline = threading.Event()
        timer = threading.Timer(DEADLINE, deadline.set)
        timer.start()
        try:
            while not deadline.is_set():
                with self.lock:
                    seen = list(self.keys if kind == "put" else self.tokens)
                if what in seen:
                    return seen
                self.event.wait(0.2)
                self.event.clear()
        finally:
            timer.cancel()
        raise AssertionError(f"{what} never arrived; saw {seen}")


@pytest.fixture
def node(site):
    port = _free_port()
    z = _cfg(site, "fuse0", f'zenoh.listen=["tls/localhost:{port}"]')["zenoh"]
    session = open_session(z)
    listener = Listener(session)
    yield port, listener
    for s in listener.subs:
        s.undeclare()
    session.close()


def _peer(site: Path, name: str, port: int):
    return open_session(_cfg(site, name, f'zenoh.connect=["tls/localhost:{port}"]')["zenoh"])


def test_a_camera_publishes_its_own_measurements_and_the_robots_poses_only(site, node) -> None:
    port, listener = node
    cam = _peer(site, "cam0", port)
    try:
        # Until the node's subscription has reached the camera, puts go nowhere: repeat the
        # whole sequence until the allowed last one arrives.
        done = threading.Event()

        def send() -> None:
            while not done.is_set():
                cam.put("kmea/cam/cam1/robots/amr1", b'{"x": 9}')  # another camera's
                cam.put("kmea/fusion/fuse0/active", b"x")  # a node's key
                cam.put("kmea/robots/amr1/pose", b"pose")  # the robots' output: allowed
                cam.put("kmea/cam/cam0/robots/amr1", b'{"x": 1}')  # its own: allowed
                done.wait(0.2)

        t = threading.Thread(target=send, daemon=True)
        t.start()
        seen = listener.wait_for("kmea/cam/cam0/robots/amr1", "put")
        done.set()
        t.join(DEADLINE)
        assert "kmea/robots/amr1/pose" in seen
        assert "kmea/cam/cam1/robots/amr1" not in seen
        assert "kmea/fusion/fuse0/active" not in seen
    finally:
        cam.close()


def test_a_camera_holds_its_own_token_only(site, node) -> None:
    port, listener = node
    cam = _peer(site, "cam0", port)
    try:
        foreign = [cam.liveliness().declare_token(k) for k in
                   ("kmea/cam/cam1", "kmea/fusion/fuse0/active", "kmea/fusion/x/whatever")]
        own = cam.liveliness().declare_token("kmea/cam/cam0")
        seen = listener.wait_for("kmea/cam/cam0", "token")
        assert not {"kmea/cam/cam1", "kmea/fusion/fuse0/active",
                    "kmea/fusion/x/whatever"} & set(seen)
        for tok in (*foreign, own):
            tok.undeclare()
    finally:
        cam.close()


def test_a_node_holds_its_own_fusion_tokens_and_a_robot_only_listens(site, node) -> None:
    port, listener = node
    other = _peer(site, "fuse1", port)
    robot = _peer(site, "amr1", port)
    try:
        bad = [other.liveliness().declare_token("kmea/fusion/fuse0/active"),
               other.liveliness().declare_token("kmea/cam/cam0"),
               robot.liveliness().declare_token("kmea/fusion/amr1/active")]
        good = other.liveliness().declare_token("kmea/fusion/fuse1/standby")
        seen = listener.wait_for("kmea/fusion/fuse1/standby", "token")
        assert not {"kmea/fusion/fuse0/active", "kmea/cam/cam0",
                    "kmea/fusion/amr1/active"} & set(seen)
        done = threading.Event()

        def send() -> None:
            while not done.is_set():
                robot.put("kmea/robots/amr1/pose", b"robot")
                robot.put("kmea/cam/cam0/robots/amr1", b"robot")
                other.put("kmea/robots/amr2/pose", b"node")
                done.wait(0.2)

        t = threading.Thread(target=send, daemon=True)
        t.start()
        keys = listener.wait_for("kmea/robots/amr2/pose", "put")
        done.set()
        t.join(DEADLINE)
        assert "kmea/robots/amr1/pose" not in keys and "kmea/cam/cam0/robots/amr1" not in keys
        for tok in (*bad, good):
            tok.undeclare()
    finally:
        other.close()
        robot.close()


def test_a_cameras_id_is_its_certificates_name(site) -> None:
    assert certificate_name(site / "cam1.pem") == "cam1"
    cfg = _cfg(site, "cam1")
    assert camera_id(cfg["zenoh"], "sim:wide?camera=0") == "cam1"
    assert zenoh_plan(cfg) == []
    with pytest.raises(StartupError, match=r"zenoh\.camera.*'cam0'.*'cam1'"):
        zenoh_plan(_cfg(site, "cam1", 'zenoh.camera="cam0"'))


def test_an_acl_without_certificates_or_unreadable_is_one_line(site, tmp_path) -> None:
    cfg = load_config(None, ["zenoh.enabled=true", f'zenoh.acl="{site / "acl.json5"}"'],
                      use_local=False)
    with pytest.raises(StartupError, match=r"zenoh\.acl.*certificates"):
        zenoh_plan(cfg)
    bad = tmp_path / "acl.json5"
    bad.write_text("{not json")
    with pytest.raises(StartupError, match=r"zenoh\.acl.*acl\.json5: not JSON"):
        zenoh_plan(_cfg(site, "cam0", f'zenoh.acl="{bad}"'))
    assert kmea_main(["keys", "site", str(site), "--cameras", "cam9"]) == 2  # one CA a site
