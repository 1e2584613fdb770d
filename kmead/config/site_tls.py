"""A site's mutual TLS and Zenoh access control: ``kmea keys site`` (docs/security.md).

One directory per site holds its certificate authority (``ca.pem``, ``ca.key``), one
certificate and key per peer (``<name>.pem``, ``<name>.key``: cameras, fusion nodes and
robots, the certificate's common name being the peer's name) and ``acl.json5``, Zenoh's
``access_control`` for the site. Every kmead and fusion node loads it (``zenoh.acl``) and
applies it to what its peers send (Zenoh's ACL, keyed by the certificate's common name):

- a camera ``<id>`` may publish only under ``<site>/cam/<id>/``, hold only its own token
  ``<site>/cam/<id>``, answer only its own ``meta``, and speak the robots' outputs (the
  binary pose and the ROS 2 topics) for as long as no fusion node does;
- a fusion node ``<id>`` may hold tokens and publish only under ``<site>/fusion/<id>/`` and
  the robots' outputs;
- a robot may only subscribe and query (and hold its own ROS 2 graph tokens);
- everyone may subscribe to and query everything on the site; anything else is denied.

A camera's id is its certificate's common name (:func:`certificate_name`), so two cameras
cannot share an id by accident, and a camera's certificate cannot speak for another.
``cryptography`` (the zenoh extra) makes the keys: elliptic-curve P-256, SHA-256.
"""

from __future__ import annotations

import datetime
import ipaddress
import json
import os
import re
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

CA_NAME = "ca"
ACL_FILE = "acl.json5"
DAYS = 3650  # certificates for a site's equipment: renewed with the equipment, not yearly
NAME_RE = re.compile(r"^[A-Za-z0-9_-]{1,32}$")
ROLES = ("camera", "node", "robot")

# What a peer may send, by Zenoh's ACL message names (ingress: from that peer).
_READ = ["declare_subscriber", "declare_liveliness_subscriber", "query", "liveliness_query"]
_SPEAK = ["put", "delete", "liveliness_token", "declare_queryable", "reply"]
_ALL = sorted({*_READ, *_SPEAK})


class SiteTlsError(Exception):
    """A site directory that cannot be made or read: one line naming the file."""


def _crypto() -> Any:
    try:
        import cryptography  # noqa: F401
    except ImportError:
        raise SiteTlsError("the zenoh extra is not installed (pip install 'kmea[zenoh]'): "
                           "it brings cryptography, which makes the site's certificates") from None
    from cryptography import x509
    return x509


def certificate_name(path: str | Path) -> str:
    """The common name of the PEM certificate at ``path``: a peer's name on its site."""
    x509 = _crypto()
    from cryptography.x509.oid import NameOID
    p = Path(path).expanduser()
    try:
        cert = x509.load_pem_x509_certificate(p.read_bytes())
    except OSError as e:
        raise SiteTlsError(f"{p}: cannot read it ({e.strerror})") from None
    except ValueError as e:
        raise SiteTlsError(f"{p}: not a PEM certificate ({e})") from None
    names = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    if not names:
        raise SiteTlsError(f"{p}: the certificate has no common name (CN)")
    return str(names[0].value)


def check_name(name: str) -> str:
    if not NAME_RE.match(name):
        raise SiteTlsError(f"name {name!r}: 1-32 letters, digits, '_' or '-' (it is the "
                           "certificate's common name and the peer's part of its keys)")
    if name == CA_NAME:
        raise SiteTlsError(f"name {name!r} is the certificate authority's file name")
    return name


def acl(site: str, peers: dict[str, str], ros_domain: int = 0,
        ros_namespace: str = "/kmea") -> dict:
    """Zenoh's ``access_control`` for a site whose peers are ``{name: role}`` (module
    docstring). Robots' outputs: ``<site>/robots/*/pose``, the ROS 2 topics of
    ``ros_namespace`` and ``/tf`` in ``ros_domain`` (rmw_zenoh's keys and the DDS bridge's)
    and the ROS 2 graph's tokens."""
    ns = ros_namespace.strip("/")
    outputs = [f"{site}/robots/*/pose", f"{ros_domain}/tf/**"]
    if ns:
        outputs += [f"{ros_domain}/{ns}/**", f"{ns}/*/pose", "tf"]
    rules: list[dict] = [
        {"id": "read", "permission": "allow", "flows": ["ingress"], "messages": _READ,
         "key_exprs": ["**"]},
        {"id": "hear", "permission": "allow", "flows": ["egress"], "messages": _ALL,
         "key_exprs": ["**"]},
        {"id": "ros-graph", "permission": "allow", "flows": ["ingress"],
         "messages": ["liveliness_token"], "key_exprs": [f"@ros2_lv/{ros_domain}/**"]},
    ]
    subjects, policies = [], []
    for name, role in sorted(peers.items()):
        if role not in ROLES:
            raise SiteTlsError(f"peer {name}: role {role!r}, expected one of {ROLES}")
        subjects.append({"id": name, "cert_common_names": [name]})
        own = {"camera": [f"{site}/cam/{name}", f"{site}/cam/{name}/**"],
               "node": [f"{site}/fusion/{name}", f"{site}/fusion/{name}/**"],
               "robot": []}[role]
        names = ["read", "hear", "ros-graph"]
        if own:
            rules.append({"id": f"{role}-{name}", "permission": "allow", "flows": ["ingress"],
                          "messages": _SPEAK, "key_exprs": own + outputs})
            names.append(f"{role}-{name}")
        policies.append({"rules": names, "subjects": [name]})
    return {"enabled": True, "default_permission": "deny", "rules": rules,
            "subjects": subjects, "policies": policies}


def load_acl(path: str | Path) -> dict:
    """The ``access_control`` table of an ACL file (JSON, as :func:`make_site` writes it)."""
    p = Path(path).expanduser()
    try:
        data = json.loads(p.read_text())
    except OSError as e:
        raise SiteTlsError(f"{p}: cannot read it ({e.strerror})") from None
    except (ValueError, UnicodeDecodeError) as e:
        raise SiteTlsError(f"{p}: not JSON ({e})") from None
    table = data.get("access_control") if isinstance(data, dict) else None
    if not isinstance(table, dict) or not isinstance(table.get("rules"), list):
        raise SiteTlsError(f"{p}: no 'access_control' table with 'rules' (make it with "
                           "kmea keys site)")
    return table


def _write_private(path: Path, data: bytes) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(data)


def _names(values: Iterable[str]) -> list[Any]:
    x509 = _crypto()
    out: list[Any] = []
    for v in values:
        try:
            out.append(x509.IPAddress(ipaddress.ip_address(v)))
        except ValueError:
            out.append(x509.DNSName(v))
    return out


def make_site(directory: str | Path, site: str, cameras: Sequence[str] = (),
              nodes: Sequence[str] = (), robots: Sequence[str] = (),
              hosts: Sequence[str] = (), ros_domain: int = 0,
              ros_namespace: str = "/kmea") -> list[Path]:
    """Write a new site directory (module docstring); the files written. ``hosts``: the
    host names and addresses peers connect to (every certificate carries them and
    ``localhost``, ``127.0.0.1``), since a connecting peer checks the listener's name."""
    x509 = _crypto()
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    d = Path(directory).expanduser()
    peers: dict[str, str] = {}
    for role, names in (("camera", cameras), ("node", nodes), ("robot", robots)):
        for n in names:
            check_name(n)
            if n in peers:
                raise SiteTlsError(f"name {n!r} given twice: one certificate per peer")
            peers[n] = role
    if not peers:
        raise SiteTlsError("no peers: give --cameras, --nodes or --robots")
    if (d / f"{CA_NAME}.key").exists():
        raise SiteTlsError(f"{d / (CA_NAME + '.key')} exists: a site has one CA (a new "
                           "directory for a new site)")
    d.mkdir(parents=True, exist_ok=True)
    now = datetime.datetime.now(datetime.timezone.utc)
    start, end = now - datetime.timedelta(hours=1), now + datetime.timedelta(days=DAYS)

    def subject(cn: str) -> Any:
        return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, cn)])

    def pem_key(k: Any) -> bytes:
        return k.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                               serialization.NoEncryption())

    written: list[Path] = []
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_subject = subject(f"{site} site CA")
    ca = (x509.CertificateBuilder().subject_name(ca_subject).issuer_name(ca_subject)
          .public_key(ca_key.public_key()).serial_number(x509.random_serial_number())
          .not_valid_before(start).not_valid_after(end)
          .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
          .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True,
                                       crl_sign=True, content_commitment=False,
                                       key_encipherment=False, data_encipherment=False,
                                       key_agreement=False, encipher_only=False,
                                       decipher_only=False), critical=True)
          .sign(ca_key, hashes.SHA256()))
    _write_private(d / f"{CA_NAME}.key", pem_key(ca_key))
    (d / f"{CA_NAME}.pem").write_bytes(ca.public_bytes(serialization.Encoding.PEM))
    written += [d / f"{CA_NAME}.pem", d / f"{CA_NAME}.key"]
    alt = x509.SubjectAlternativeName(_names(["localhost", "127.0.0.1", *hosts]))
    usage = x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH,
                                   ExtendedKeyUsageOID.CLIENT_AUTH])
    for name in peers:
        k = ec.generate_private_key(ec.SECP256R1())
        cert = (x509.CertificateBuilder().subject_name(subject(name)).issuer_name(ca_subject)
                .public_key(k.public_key()).serial_number(x509.random_serial_number())
                .not_valid_before(start).not_valid_after(end)
                .add_extension(alt, critical=False).add_extension(usage, critical=False)
                .add_extension(x509.BasicConstraints(ca=False, path_length=None),
                               critical=True)
                .sign(ca_key, hashes.SHA256()))
        _write_private(d / f"{name}.key", pem_key(k))
        (d / f"{name}.pem").write_bytes(cert.public_bytes(serialization.Encoding.PEM))
        written += [d / f"{name}.pem", d / f"{name}.key"]
    table = acl(site, peers, ros_domain, ros_namespace)
    (d / ACL_FILE).write_text(json.dumps({"access_control": table}, indent=1) + "\n")
    written.append(d / ACL_FILE)
    return written
