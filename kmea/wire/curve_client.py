"""The client half of kmead's CURVE key contract (standard library only).

A key directory made by ``kmea keys init DIR`` / ``kmea keys add DIR NAME``::

    DIR/server.key              the daemon's public key (give it to every client)
    DIR/server.key_secret       the daemon's secret key (stays on the Pi)
    DIR/operators/NAME.key      public keys allowed to control and watch
    DIR/viewers/NAME.key        public keys allowed to watch only
    DIR/clients/NAME.key_secret a client's key pair (copy it to that client only)

Files are ZeroMQ certificates (the ZPL text that pyzmq's ``zmq.auth`` and czmq write). A
client needs ``server.key`` and its own ``clients/NAME.key_secret``; :func:`apply_client_keys`
sets them on a pyzmq socket before ``connect`` (pyzmq sockets take options as attributes, so
this module needs no import of zmq and the terminal UI can use it). ``kmead.net.keys`` has the
daemon's half and ``connect_client``.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any, NamedTuple

__all__ = ["DEFAULT_CLIENT", "ClientKeys", "CurveKeyError", "apply_client_keys",
           "read_certificate", "read_client_keys"]

DEFAULT_CLIENT = "operator"
_Z85 = r"[0-9A-Za-z.\-:+=^!/*?&<>()\[\]{}@%$#]{40}"
_KEY_RE = re.compile(rf'^\s*(public|secret)-key\s*=\s*"?({_Z85})"?\s*$')


class CurveKeyError(ValueError):
    """A missing or malformed key file; the message names the file, in one line."""


class ClientKeys(NamedTuple):
    """Z85-encoded keys (40 ASCII bytes each)."""

    public: bytes
    secret: bytes
    server: bytes


def read_certificate(path: str | Path) -> tuple[bytes, bytes | None]:
    """(public, secret or None) of a ZeroMQ certificate file, Z85 bytes."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise CurveKeyError(f"{p}: no such key file") from None
    except (OSError, UnicodeDecodeError) as e:
        raise CurveKeyError(f"{p}: cannot read key file: {e}") from None
    keys: dict[str, bytes] = {}
    for line in text.splitlines():
        if line.lstrip().startswith("#"):
            continue
        m = _KEY_RE.match(line)
        if m:
            keys.setdefault(m.group(1), m.group(2).encode("ascii"))
    if "public" not in keys:
        raise CurveKeyError(f"{p}: not a ZeroMQ certificate (no public-key line)")
    return keys["public"], keys.get("secret")


def read_client_keys(keys_dir: str | Path, client: str = DEFAULT_CLIENT) -> ClientKeys:
    """The key pair of ``client`` and the daemon's public key from ``keys_dir``."""
    d = Path(keys_dir).expanduser()
    if not re.fullmatch(r"[A-Za-z0-9_-]{1,32}", client or ""):
        raise CurveKeyError(f"client name {client!r}: 1-32 letters, digits, '_' or '-'")
    server, _ = read_certificate(d / "server.key")
    public, secret = read_certificate(d / "clients" / f"{client}.key_secret")
    if secret is None:
        raise CurveKeyError(f"{d / 'clients' / (client + '.key_secret')}: no secret-key line")
    return ClientKeys(public, secret, server)


def apply_client_keys(sock: Any, keys_dir: str | Path, client: str = DEFAULT_CLIENT) -> None:
    """Make pyzmq socket ``sock`` a CURVE client of the daemon (call before ``connect``)."""
    k = read_client_keys(keys_dir, client)
    sock.curve_secretkey = k.secret
    sock.curve_publickey = k.public
    sock.curve_serverkey = k.server
