"""The Zenoh session from the ``[zenoh]`` section (the optional extra ``kmea[zenoh]``).

Every setting is explicit, none left to Zenoh's defaults where they would expose more than
configured: a peer listens only on ``listen`` (Zenoh's own default is every interface, a
random port), multicast scouting is off unless asked, and TLS endpoints use mutual TLS with
the configured CA (a peer without a certificate signed by it is refused).

**This machine** (peer mode, no ``connect``, no ``listen``, no multicast): the processes of
one machine find each other on loopback without an endpoint typed. Each listens on a free
loopback port and on the shared rendezvous port :data:`RENDEZVOUS` (only the first one
started gets it; once its holder is gone, the next process that starts takes it) and
connects to it; Zenoh's gossip then tells every peer the others' ports and the peers form a
full mesh, which the death of the rendezvous holder does not break.
"""

from __future__ import annotations

import json

from kmead.config.site_tls import load_acl
from kmead.config.startup import EXIT_RUNTIME, StartupError

#: The loopback rendezvous of the processes of one machine (Zenoh's own default port).
RENDEZVOUS = "tcp/127.0.0.1:7447"

INSTALL_HINT = "the zenoh extra is not installed (pip install 'kmea[zenoh]')"


def import_zenoh():
    try:
        import zenoh
    except ImportError:
        raise StartupError(f"key 'zenoh.enabled': {INSTALL_HINT}") from None
    return zenoh


def session_config(z: dict):
    """A ``zenoh.Config`` for the ``[zenoh]`` table ``z`` (already validated)."""
    zenoh = import_zenoh()
    conf = zenoh.Config()

    def put(key: str, value) -> None:
        conf.insert_json5(key, json.dumps(value))

    put("mode", z["mode"])
    if this_machine(z):
        put("connect/endpoints", [RENDEZVOUS])
        put("listen/endpoints", [RENDEZVOUS, "tcp/127.0.0.1:0"])
        put("listen/exit_on_failure", False)  # the rendezvous port is taken: go on
        # No retry in the background (a session retrying its listener cannot close): when
        # the holder goes, the next process that starts takes the port, and the others'
        # connections, retried every half lease, reach it.
        put("listen/timeout_ms", 0)
    else:
        put("connect/endpoints", list(z["connect"]))
        if z["mode"] == "peer":
            put("listen/endpoints", list(z["listen"]))
    put("scouting/multicast/enabled", bool(z["multicast"]))
    lease_ms = max(1, round(z["lease_s"] * 1000))
    # Zenoh declares a link dead when nothing came for its lease, and looks every quarter
    # of it: three quarters of lease_s find a silent peer gone within lease_s (a frozen
    # fusion node's standby takes over, a frozen camera is dropped, within the lease).
    put("transport/link/tx/lease", max(1, lease_ms * 3 // 4))
    # A lost connection is retried every half lease at most (Zenoh's default backs off to
    # 4 s): a fusion node that restarts on the port the others connect to is found within
    # its first two leases, before it may claim the robots (kmead.fusion.Election).
    retry_ms = max(100, lease_ms // 2)
    put("connect/retry", {"period_init_ms": min(1000, retry_ms), "period_max_ms": retry_ms,
                          "period_increase_factor": 2})
    if z["tls_ca"]:
        put("transport/link/tls/root_ca_certificate", z["tls_ca"])
    if z["tls_cert"] and z["tls_key"]:
        # The same certificate proves this kmead both as a listener and when it connects.
        for side in ("listen", "connect"):
            put(f"transport/link/tls/{side}_certificate", z["tls_cert"])
            put(f"transport/link/tls/{side}_private_key", z["tls_key"])
        put("transport/link/tls/enable_mtls", True)
    if z.get("acl"):
        put("access_control", load_acl(z["acl"]))
    return conf


def this_machine(z: dict) -> bool:
    """True when ``z`` gives no way to meet another peer: the loopback rendezvous is used."""
    return (z["mode"] == "peer" and not z["connect"] and not z["listen"]
            and not z["multicast"])


def open_session(z: dict):
    """The open session; StartupError (exit 1) when Zenoh cannot open it (a port in use, a
    certificate it cannot load)."""
    zenoh = import_zenoh()
    try:
        return zenoh.open(session_config(z))
    except zenoh.ZError as e:
        raise StartupError(f"zenoh: cannot open the session: {str(e).splitlines()[0]}",
                           EXIT_RUNTIME) from None
