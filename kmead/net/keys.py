"""CURVE authentication and encryption for the daemon's two sockets (pyzmq's ``zmq.auth``).

The key directory contract (``kmea keys init DIR``, ``kmea keys add DIR NAME [--viewer]``)
is described in :mod:`kmea.wire.curve_client`. With ``[network] keys = "DIR"`` the daemon:

- makes both sockets CURVE servers with ``DIR/server.key_secret``;
- runs a ZAP handler (:class:`zmq.auth.thread.ThreadAuthenticator`) that accepts a client
  only if its public key is in ``DIR/operators/`` or ``DIR/viewers/``; the folders are
  re-read when they change (checked at every new connection) and on an operator's control
  request;
- serves a control request only if the key that sent it (the ``User-Id`` ZeroMQ attaches to
  every message once ZAP accepted the peer) is an operator's *now*; a viewer's requests get
  an error reply.

A client connects with :func:`connect_client` (or :func:`kmea.wire.curve_client.apply_client_keys`
on a socket it made).
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
from pathlib import Path

import zmq
import zmq.auth
from zmq.auth.thread import ThreadAuthenticator

from kmea.wire.curve_client import (
    DEFAULT_CLIENT,
    apply_client_keys,
    read_client_keys,
)
from kmead.config.keyring import (
    _FOLDERS,
    OPERATOR,
    VIEWER,
    KeyRing,
    KeysError,
    exposure,
    is_local_endpoint,
)

__all__ = ["OPERATOR", "VIEWER", "CurveServer", "KeyRing", "KeysError", "add_client",
           "connect_client", "exposure", "init_keys", "is_local_endpoint", "keyed_context",
           "read_client_keys"]

log = logging.getLogger("kmead.keys")



def _check_name(name: str) -> str:
    import re

    if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z0-9_-]{1,32}", name):
        raise KeysError(f"client name {name!r}: use 1-32 letters, digits, '_' or '-'")
    return name


def _private_dir(p: Path) -> None:
    p.mkdir(parents=True, exist_ok=True)
    os.chmod(p, 0o700)


def _new_pair(keys_dir: Path, name: str, public_to: Path, secret_to: Path) -> None:
    """Make a key pair; public certificate to ``public_to``, secret one to ``secret_to``."""
    for p in (public_to, secret_to):
        if os.path.lexists(p):
            raise KeysError(f"{p}: already exists (remove it first to replace the key)")
    with tempfile.TemporaryDirectory(dir=keys_dir) as tmp:
        os.chmod(tmp, 0o700)
        pub, sec = zmq.auth.create_certificates(tmp, name)
        os.chmod(sec, 0o600)
        os.chmod(pub, 0o644)
        shutil.move(pub, public_to)
        shutil.move(sec, secret_to)


def init_keys(keys_dir: str | Path) -> list[Path]:
    """Make a key directory: the daemon's pair and a first operator ``operator``.

    Returns the files written. Refuses a directory that already holds a server key.
    """
    d = Path(keys_dir).expanduser()
    if (d / "server.key_secret").exists() or (d / "server.key").exists():
        raise KeysError(f"{d}: already holds server.key; add clients with "
                        f"`kmea keys add {d} NAME`")
    _private_dir(d)
    for sub in ("operators", "viewers"):
        (d / sub).mkdir(exist_ok=True)
    _private_dir(d / "clients")
    _new_pair(d, "server", d / "server.key", d / "server.key_secret")
    return [d / "server.key", d / "server.key_secret",
            *add_client(d, DEFAULT_CLIENT)]


def add_client(keys_dir: str | Path, name: str, viewer: bool = False) -> list[Path]:
    """Add client ``name``: public key to ``operators/`` (or ``viewers/``), secret key to
    ``clients/NAME.key_secret``. Returns the files written."""
    d = Path(keys_dir).expanduser()
    _check_name(name)
    if not (d / "server.key").is_file():
        raise KeysError(f"{d}: no server.key; make the directory with `kmea keys init {d}`")
    for folder in _FOLDERS.values():
        if (d / folder / f"{name}.key").exists():
            raise KeysError(f"{d / folder / (name + '.key')}: client {name!r} exists already")
    folder = d / _FOLDERS[VIEWER if viewer else OPERATOR]
    folder.mkdir(exist_ok=True)
    _private_dir(d / "clients")
    public, secret = folder / f"{name}.key", d / "clients" / f"{name}.key_secret"
    _new_pair(d, name, public, secret)
    return [public, secret]


class CurveServer:
    """The ZAP handler of one ZeroMQ context plus the daemon's key pair.

    ``context`` should be the daemon's own (a context has one ZAP handler).
    """

    def __init__(self, context: zmq.Context, keys_dir: str | Path) -> None:
        self.ring = KeyRing(keys_dir)
        self.auth = ThreadAuthenticator(context, log=logging.getLogger("kmead.zap"))
        self.auth.start()
        # zmq.auth looks the provider up by the socket's exact ZAP domain ("*" only matches
        # sockets without one), so each domain is registered in secure().
        self.auth.configure_curve_callback("*", credentials_provider=self.ring)

    def secure(self, sock: zmq.Socket, domain: str) -> None:
        """Make ``sock`` a CURVE server (call before ``bind``)."""
        sock.curve_secretkey = self.ring.server_secret
        sock.curve_publickey = self.ring.server_public
        sock.curve_server = True
        sock.zap_domain = domain.encode("ascii")
        self.auth.configure_curve_callback(domain, credentials_provider=self.ring)

    def peer(self, frame: zmq.Frame) -> tuple[str, str] | None:
        """(role, name) of the client that sent ``frame`` (received with ``copy=False``),
        from the key folders as they are now (a revoked key stops at its next request)."""
        try:
            user = frame.get("User-Id")
        except (zmq.ZMQError, AttributeError, UnicodeDecodeError):
            return None
        try:
            self.ring.refresh()
        except Exception:
            log.exception("reading client keys")
        return self.ring.role(user if isinstance(user, str) else None)

    def stop(self) -> None:
        self.auth.stop()


def connect_client(ctx: zmq.Context, endpoint: str, keys_dir: str | Path,
                   client_name: str = DEFAULT_CLIENT, socket_type: int = zmq.REQ
                   ) -> zmq.Socket:
    """A socket of ``socket_type`` connected to a keyed kmead at ``endpoint``.

    Example (control)::

        ctx = zmq.Context()
        req = connect_client(ctx, "tcp://pi.local:5556", "~/kmea-keys", "laptop")
        req.send_json({"v": 2, "cmd": "ping"}); print(req.recv_json())

    For telemetry pass ``socket_type=zmq.SUB`` and subscribe. A key the daemon does not
    know gets no connection at all (the socket stays silent; use a receive timeout).
    """
    sock = ctx.socket(socket_type)
    sock.setsockopt(zmq.LINGER, 0)
    try:
        apply_client_keys(sock, keys_dir, client_name)
        sock.connect(endpoint)
    except BaseException:
        sock.close(linger=0)
        raise
    return sock


def keyed_context(keys_dir: str | Path) -> tuple[zmq.Context, CurveServer]:
    """A ZeroMQ context of its own and the CURVE server of ``keys_dir`` on it: the one
    set-up of the daemon and the fusion node (a context has one ZAP handler, so a keyed
    process never shares ``zmq.Context.instance()``). :class:`KeysError` when the keys
    cannot be used (the context is terminated then)."""
    ctx = zmq.Context()
    try:
        return ctx, CurveServer(ctx, keys_dir)
    except BaseException:
        ctx.term()
        raise
