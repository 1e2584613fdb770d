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
import threading
from pathlib import Path

import zmq
import zmq.auth
from zmq.auth.thread import ThreadAuthenticator

from kmea.wire.curve_client import (
    DEFAULT_CLIENT,
    CurveKeyError,
    apply_client_keys,
    read_certificate,
    read_client_keys,
)

__all__ = ["OPERATOR", "VIEWER", "CurveServer", "KeyRing", "KeysError", "add_client",
           "connect_client", "init_keys", "keyed_context", "read_client_keys"]

log = logging.getLogger("kmead.keys")

OPERATOR, VIEWER = "operator", "viewer"
_FOLDERS = {OPERATOR: "operators", VIEWER: "viewers"}


class KeysError(CurveKeyError):
    """A key directory that cannot be used or made; one line naming the file."""


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


class KeyRing:
    """The allowed client keys of a key directory, re-read when its folders change.

    Thread-safe: the ZAP thread calls :meth:`callback`, the control thread :meth:`role`.
    """

    def __init__(self, keys_dir: str | Path) -> None:
        self.dir = Path(keys_dir).expanduser()
        try:
            self.server_public, self.server_secret = read_certificate(
                self.dir / "server.key_secret")
        except CurveKeyError as e:
            raise KeysError(f"network.keys: {e} (make keys with `kmea keys init "
                            f"{self.dir}`)") from None
        if self.server_secret is None:
            raise KeysError(f"network.keys: {self.dir / 'server.key_secret'}: no secret key")
        self._lock = threading.Lock()
        self._signature: tuple = ()
        self._roles: dict[bytes, tuple[str, str]] = {}
        self.reloads = 0
        self.refresh(force=True)

    def _current_signature(self) -> tuple:
        sig = []
        for role, folder in _FOLDERS.items():
            p = self.dir / folder
            try:
                entries = sorted((e.name, e.stat().st_mtime_ns, e.stat().st_size)
                                 for e in os.scandir(p) if e.name.endswith(".key"))
            except OSError:
                entries = []
            sig.append((role, tuple(entries)))
        return tuple(sig)

    def refresh(self, force: bool = False) -> bool:
        """Re-read the folders if they changed (or ``force``); True when re-read."""
        sig = self._current_signature()
        with self._lock:
            if sig == self._signature and not force:
                return False
        roles: dict[bytes, tuple[str, str]] = {}
        for role, folder in _FOLDERS.items():  # operators first: a key also in viewers/ is
            for f in sorted((self.dir / folder).glob("*.key")):  # a viewer (less rights win)
                try:
                    public, _ = read_certificate(f)
                except CurveKeyError as e:
                    log.warning("key ignored: %s", e)
                    continue
                roles[public] = (role, f.stem)
        with self._lock:
            self._roles, self._signature = roles, sig
            self.reloads += 1
        log.info("client keys loaded from %s: %d operator(s), %d viewer(s)", self.dir,
                 sum(r == OPERATOR for r, _ in roles.values()),
                 sum(r == VIEWER for r, _ in roles.values()))
        return True

    def role(self, public_z85: bytes | str | None) -> tuple[str, str] | None:
        """(role, client name) of a Z85 public key, or None if not allowed now."""
        if public_z85 is None:
            return None
        k = public_z85.encode("ascii", "replace") if isinstance(public_z85, str) else public_z85
        with self._lock:
            return self._roles.get(k)

    # zmq.auth credentials provider
    def callback(self, domain: str, key: bytes) -> bool:
        try:
            self.refresh()
        except Exception:  # the ZAP thread must answer whatever happens
            log.exception("reading client keys")
        ok = self.role(key) is not None
        if not ok:
            log.info("connection refused: unknown CURVE key %s on %s", key[:8].decode(
                "ascii", "replace") + "...", domain or "*")
        return ok


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


def is_local_endpoint(endpoint: str) -> bool:
    """True for endpoints only this machine can reach: ``ipc://``, ``inproc://`` and TCP on
    a loopback address (127.0.0.0/8, ``localhost``, ``[::1]``)."""
    if not endpoint or endpoint.startswith(("ipc://", "inproc://")):
        return True
    if not endpoint.startswith("tcp://"):
        return False
    host = endpoint[len("tcp://"):].rpartition(":")[0]
    if host in ("localhost", "[::1]", "::1"):
        return True
    parts = host.split(".")
    return (len(parts) == 4 and parts[0] == "127"
            and all(p.isdigit() and 0 <= int(p) <= 255 for p in parts))


def exposure(endpoints: dict[str, str], keys: str, insecure: bool) -> tuple[str | None,
                                                                              str | None]:
    """(error, warning) for the network settings: binding beyond loopback needs keys.

    endpoints: config key -> endpoint, e.g. {"network.control": "tcp://0.0.0.0:5556"}.
    """
    open_ = [f"{k} = {v}" for k, v in endpoints.items() if not is_local_endpoint(v)]
    if not open_ or keys:
        return None, None
    if insecure:
        return None, (f"network.insecure = true: {', '.join(open_)} open to the network "
                      "WITHOUT authentication; anyone who reaches it can control the robots "
                      "(make keys: kmea keys init DIR, then network.keys = \"DIR\")")
    return (f"{open_[0]}: refusing to bind beyond loopback without keys; make them with "
            "`kmea keys init DIR` and set network.keys = \"DIR\" (docs/security.md), or set "
            "network.insecure = true"), None


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
