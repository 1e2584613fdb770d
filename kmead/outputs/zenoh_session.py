"""The Zenoh session from the ``[zenoh]`` section (the optional extra ``kmea[zenoh]``).

Every setting is explicit, none left to Zenoh's defaults where they would expose more than
configured: a peer listens only on ``listen`` (Zenoh's own default is every interface, a
random port), multicast scouting is off unless asked, and TLS endpoints use mutual TLS with
the configured CA (a peer without a certificate signed by it is refused).
"""

from __future__ import annotations

import json

from kmead.run.startup import EXIT_RUNTIME, StartupError

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
    put("connect/endpoints", list(z["connect"]))
    if z["mode"] == "peer":
        put("listen/endpoints", list(z["listen"]))
    put("scouting/multicast/enabled", bool(z["multicast"]))
    put("transport/link/tx/lease", max(1, round(z["lease_s"] * 1000)))  # ms
    if z["tls_ca"]:
        put("transport/link/tls/root_ca_certificate", z["tls_ca"])
    if z["tls_cert"] and z["tls_key"]:
        # The same certificate proves this kmead both as a listener and when it connects.
        for side in ("listen", "connect"):
            put(f"transport/link/tls/{side}_certificate", z["tls_cert"])
            put(f"transport/link/tls/{side}_private_key", z["tls_key"])
        put("transport/link/tls/enable_mtls", True)
    return conf


def open_session(z: dict):
    """The open session; StartupError (exit 1) when Zenoh cannot open it (a port in use, a
    certificate it cannot load)."""
    zenoh = import_zenoh()
    try:
        return zenoh.open(session_config(z))
    except zenoh.ZError as e:
        raise StartupError(f"zenoh: cannot open the session: {str(e).splitlines()[0]}",
                           EXIT_RUNTIME) from None
