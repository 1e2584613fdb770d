"""Zenoh's mutual TLS on loopback, with certificates this test makes (openssl), through
the session configuration kmead builds (kmead.outputs.zenoh_session): a peer with a certificate
from the site's CA gets through; one with a certificate from another CA does not."""

from __future__ import annotations

import shutil
import socket
import subprocess
import threading
import time
from pathlib import Path

import pytest
from deadlines import DEADLINE, JOIN

zenoh = pytest.importorskip("zenoh", reason="the zenoh extra is not installed "
                                            "(pip install 'kmea[zenoh]')")
if shutil.which("openssl") is None:
    pytest.skip("no openssl command to make the test's certificates", allow_module_level=True)

from kmead.config.layers import load_config  # noqa: E402
from kmead.outputs.zenoh_session import open_session  # noqa: E402


def _openssl(*args: str, cwd: Path) -> None:
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True, timeout=JOIN)


def make_ca_and_cert(d: Path, name: str) -> tuple[Path, Path, Path]:
    """A CA and a certificate it signs for localhost / 127.0.0.1 (the commands of
    docs/ros2.md, Security)."""
    d.mkdir(parents=True, exist_ok=True)
    _openssl("req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1",
             "-nodes", "-keyout", "ca.key", "-out", "ca.pem", "-days", "2",
             "-subj", f"/CN={name} test CA", cwd=d)
    _openssl("req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
             "-keyout", "key.pem", "-out", "node.csr", "-subj", "/CN=localhost", cwd=d)
    (d / "san.ext").write_text("subjectAltName=DNS:localhost,IP:127.0.0.1\n"
                               "extendedKeyUsage=serverAuth,clientAuth\n")
    _openssl("x509", "-req", "-in", "node.csr", "-CA", "ca.pem", "-CAkey", "ca.key",
             "-CAcreateserial", "-out", "cert.pem", "-days", "2", "-extfile", "san.ext", cwd=d)
    return d / "ca.pem", d / "cert.pem", d / "key.pem"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _zenoh_table(ca: Path, cert: Path, key: Path, *sets: str) -> dict:
    return load_config(None, ["zenoh.enabled=true", f'zenoh.tls_ca="{ca}"',
                              f'zenoh.tls_cert="{cert}"', f'zenoh.tls_key="{key}"', *sets],
                       use_local=False)["zenoh"]


def test_mutual_tls_admits_the_sites_certificates_only(tmp_path) -> None:
    site = make_ca_and_cert(tmp_path / "site", "site")
    other = make_ca_and_cert(tmp_path / "other", "other")
    port = _free_port()
    listener = open_session(_zenoh_table(*site, f'zenoh.listen=["tls/localhost:{port}"]'))
    got: list[bytes] = []
    arrived = threading.Event()

    def on_sample(s) -> None:
        got.append(s.payload.to_bytes())
        arrived.set()

    sub = listener.declare_subscriber("kmea/tls/**", on_sample)
    good = open_session(_zenoh_table(*site, f'zenoh.connect=["tls/localhost:{port}"]'))
    intruder = None
    try:
        deadline = time.monotonic() + DEADLINE
        while not arrived.is_set() and time.monotonic() < deadline:
            good.put("kmea/tls/good", b"from the site")
            arrived.wait(0.2)
        assert got and got[0] == b"from the site"
        assert good.info.zid() in list(listener.info.peers_zid())
        # A peer that trusts the site's CA but whose own certificate another CA signed: the
        # listener's check of client certificates (mutual TLS) refuses it; whatever it puts
        # never arrives. (Waiting can only miss a wrongly admitted peer, never fail a
        # correct one.)
        intruder = open_session(_zenoh_table(site[0], other[1], other[2],
                                             f'zenoh.connect=["tls/localhost:{port}"]'))
        for _ in range(10):
            intruder.put("kmea/tls/intruder", b"from elsewhere")
            time.sleep(0.2)
        assert b"from elsewhere" not in got
        assert intruder.info.zid() not in list(listener.info.peers_zid())
    finally:
        sub.undeclare()
        for s in (good, intruder, listener):
            if s is not None:
                s.close()
