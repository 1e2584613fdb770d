"""The CURVE key directory as configuration reads it: its allowed client keys
(:class:`KeyRing`, re-read when its folders change) and the rule for the sockets' exposure
(:func:`exposure`: beyond loopback only with keys). The sockets' side (the ZAP handler,
making keys, connecting) is :mod:`kmead.net.keys`; start-up judges the keys with this
module (kmead.config.plan) before any socket opens."""

from __future__ import annotations

import logging
import os
import threading
from pathlib import Path

from kmea.wire.curve_client import CurveKeyError, read_certificate

__all__ = ["OPERATOR", "VIEWER", "KeyRing", "KeysError", "exposure", "is_local_endpoint"]

log = logging.getLogger("kmead.keys")

OPERATOR, VIEWER = "operator", "viewer"
_FOLDERS = {OPERATOR: "operators", VIEWER: "viewers"}


class KeysError(CurveKeyError):
    """A key directory that cannot be used or made; one line naming the file."""


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
