"""The CURVE key contract with real ZeroMQ sockets on loopback (kmead.net.keys, kmea keys)."""

from __future__ import annotations

import contextlib
import os
import time
from pathlib import Path

import pytest
import zmq
import zmq.auth

from kmea.wire.curve_client import CurveKeyError, read_certificate, read_client_keys
from kmead.net.keys import OPERATOR, VIEWER, CurveServer, KeysError, add_client, connect_client
from kmead.tools import kmea_cli


@pytest.fixture
def keys(tmp_path: Path) -> Path:
    d = tmp_path / "keys"
    assert kmea_cli.main(["keys", "init", str(d)]) == 0
    assert kmea_cli.main(["keys", "add", str(d), "laptop"]) == 0
    assert kmea_cli.main(["keys", "add", str(d), "screen", "--viewer"]) == 0
    return d


def test_keys_init_and_add_write_the_contract_files(keys: Path) -> None:
    names = {str(p.relative_to(keys)) for p in keys.rglob("*") if p.is_file()}
    assert names == {"server.key", "server.key_secret", "operators/operator.key",
                     "clients/operator.key_secret", "operators/laptop.key",
                     "clients/laptop.key_secret", "viewers/screen.key",
                     "clients/screen.key_secret"}
    for secret in [keys / "server.key_secret", *(keys / "clients").iterdir()]:
        assert os.stat(secret).st_mode & 0o077 == 0, f"{secret} readable by others"
    # Public files hold no secret; secret files are valid ZeroMQ certificates.
    for public in [keys / "server.key", *(keys / "operators").iterdir(),
                   *(keys / "viewers").iterdir()]:
        assert zmq.auth.load_certificate(public)[1] is None
    for name in ("operator", "laptop", "screen"):
        mine = read_client_keys(keys, name)
        assert (mine.public, mine.secret) == zmq.auth.load_certificate(
            keys / "clients" / f"{name}.key_secret")
        assert mine.server == zmq.auth.load_certificate(keys / "server.key")[0]


def test_keys_refuse_overwrite_bad_names_and_missing_dir(keys: Path, tmp_path: Path,
                                                        capsys: pytest.CaptureFixture) -> None:
    before = (keys / "server.key_secret").read_bytes()
    assert kmea_cli.main(["keys", "init", str(keys)]) == 2
    assert (keys / "server.key_secret").read_bytes() == before
    assert "already holds server.key" in capsys.readouterr().err
    with pytest.raises(KeysError, match="exists already"):
        add_client(keys, "laptop", viewer=True)
    for bad in ("../x", "a b", "", "x" * 40, ".hidden"):
        with pytest.raises(KeysError, match="client name"):
            add_client(keys, bad)
    with pytest.raises(KeysError, match="kmea keys init"):
        add_client(tmp_path / "nowhere", "x")
    with pytest.raises(CurveKeyError, match="no such key file"):
        read_client_keys(keys, "nobody")
    (tmp_path / "junk.key").write_text("hello\n")
    with pytest.raises(CurveKeyError, match="not a ZeroMQ certificate"):
        read_certificate(tmp_path / "junk.key")


class _Server:
    """A CURVE REP + PUB pair guarded by CurveServer, as the daemon sets them up."""

    def __init__(self, keys: Path) -> None:
        self.ctx = zmq.Context()
        self.curve = CurveServer(self.ctx, keys)
        self.rep = self.ctx.socket(zmq.REP)
        self.pub = self.ctx.socket(zmq.PUB)
        for sock, domain in ((self.rep, "control"), (self.pub, "telemetry")):
            sock.setsockopt(zmq.LINGER, 0)
            self.curve.secure(sock, domain)
        self.control = f"tcp://127.0.0.1:{self.rep.bind_to_random_port('tcp://127.0.0.1')}"
        self.telemetry = f"tcp://127.0.0.1:{self.pub.bind_to_random_port('tcp://127.0.0.1')}"

    def serve_one(self, timeout_ms: int = 1000) -> tuple[str, str] | bool | None:
        """Answer one request with the sender's role; False if none arrived."""
        if not self.rep.poll(timeout_ms):
            return False
        frames = self.rep.recv_multipart(copy=False)
        who = self.curve.peer(frames[0])
        self.rep.send_json({"role": who[0] if who else None})
        return who

    def close(self) -> None:
        self.curve.stop()
        self.rep.close(0)
        self.pub.close(0)
        self.ctx.term()


def _subscriber_gets(server: _Server, sub: zmq.Socket, seconds: float = 1.0) -> bool:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        server.pub.send_multipart([b"frame", b'{"v":1}'])
        if sub.poll(50):
            return sub.recv_multipart()[0] == b"frame"
    return False


def test_operator_viewer_unknown_and_plain_clients(keys: Path) -> None:
    server = _Server(keys)
    ctx = zmq.Context()
    try:
        for name, role in (("operator", OPERATOR), ("laptop", OPERATOR), ("screen", VIEWER)):
            req = connect_client(ctx, server.control, keys, name)
            req.send(b"{}")
            assert server.serve_one() == (role, name)
            assert req.poll(1000) and req.recv_json() == {"role": role}
            req.close(0)
            sub = connect_client(ctx, server.telemetry, keys, name, zmq.SUB)
            sub.setsockopt(zmq.SUBSCRIBE, b"")
            assert _subscriber_gets(server, sub), f"{name} got no telemetry"
            sub.close(0)

        # An unknown key and a plain (NULL) client: no request arrives, no telemetry.
        pub, sec = zmq.curve_keypair()
        stranger = ctx.socket(zmq.REQ)
        stranger.curve_publickey, stranger.curve_secretkey = pub, sec
        stranger.curve_serverkey = server.curve.ring.server_public
        plain = ctx.socket(zmq.REQ)
        for s in (stranger, plain):
            s.setsockopt(zmq.LINGER, 0)
            s.connect(server.control)
            # Not blocking: a REQ socket whose handshake was refused has no peer and a
            # blocking send would wait forever.
            with contextlib.suppress(zmq.Again):
                s.send(b"{}", zmq.NOBLOCK)
        assert server.serve_one(1000) is False
        for s in (stranger, plain):
            assert not s.poll(100)
            s.close(0)
        plain_sub = ctx.socket(zmq.SUB)
        plain_sub.setsockopt(zmq.SUBSCRIBE, b"")
        plain_sub.connect(server.telemetry)
        assert not _subscriber_gets(server, plain_sub, 1.0)
        plain_sub.close(0)
    finally:
        ctx.term()
        server.close()


def test_key_folders_are_reread_when_they_change(keys: Path) -> None:
    server = _Server(keys)
    ctx = zmq.Context()
    try:
        add_client(keys, "late")  # added while the server runs: accepted at once
        req = connect_client(ctx, server.control, keys, "late")
        req.send(b"{}")
        assert server.serve_one() == (OPERATOR, "late")
        req.recv()
        # Revoked: the connected peer's next request is no longer an operator's ...
        (keys / "operators" / "late.key").unlink()
        req.send(b"{}")
        assert server.serve_one() is None
        assert req.recv_json() == {"role": None}
        req.close(0)
        # ... and a new connection with that key is refused by ZAP.
        again = connect_client(ctx, server.control, keys, "late")
        # Not blocking: once ZAP refused the handshake the socket has no peer, and a
        # blocking send would wait forever (whether the refusal comes first is a race).
        with contextlib.suppress(zmq.Again):
            again.send(b"{}", zmq.NOBLOCK)
        assert server.serve_one(1000) is False
        again.close(0)
        # Moving a key from operators/ to viewers/ demotes it.
        os.replace(keys / "operators" / "laptop.key", keys / "viewers" / "laptop.key")
        req = connect_client(ctx, server.control, keys, "laptop")
        req.send(b"{}")
        assert server.serve_one() == (VIEWER, "laptop")
        req.recv()
        req.close(0)
    finally:
        ctx.term()
        server.close()
