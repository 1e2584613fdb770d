"""The ``[zenoh]`` section's values and the rule on what a Zenoh session may expose.

No Zenoh import (the extra is optional and ``kmead --check`` must judge a configuration
without it). The values' types and ranges are in :mod:`kmead.config.checks` with every
other key's; here: :func:`zenoh_exposure`, the same rule as the ZeroMQ sockets' (listening
beyond loopback needs mutual TLS, with certificate files, or an explicit ``insecure =
true``; docs/ros2.md, "Security"), and whether a robot name can be a ROS 2 topic token.
"""

from __future__ import annotations

import re

from kmead.config.checks import ROS_TOKEN_RE

LOOPBACK_HOSTS = ("localhost", "[::1]")


def ros_token_problem(name: str) -> str | None:
    """Why robot ``name`` cannot be a ROS 2 topic token (``/kmea/<robot>/pose``), or None."""
    if ROS_TOKEN_RE.match(name):
        return None
    return (f"robot name {name!r} cannot be part of a ROS 2 topic name (letters, digits, '_', "
            "not starting with a digit); rename it or set zenoh.ros2 = false")


def endpoint_host(endpoint: str) -> str:
    return endpoint.split("/", 1)[1].rsplit(":", 1)[0]


def is_loopback_host(host: str) -> bool:
    return host in LOOPBACK_HOSTS or bool(re.match(r"^127\.\d{1,3}\.\d{1,3}\.\d{1,3}$", host))


def tls_files(z: dict) -> tuple[str, str, str]:
    return z["tls_ca"], z["tls_cert"], z["tls_key"]


def zenoh_exposure(z: dict) -> tuple[str | None, str | None]:
    """(error, warning) for the ``[zenoh]`` table ``z``: the ZeroMQ sockets' rule.

    - client mode listens nowhere (``listen`` must be empty) and needs somewhere to connect;
    - a ``tls/`` endpoint (listen or connect) needs the three certificate files;
    - listening beyond loopback: only ``tls/`` endpoints (mutual TLS: a peer without a
      certificate from the CA is refused), unless ``insecure = true`` (then a warning).
    Only checked when the section is enabled.
    """
    if not z.get("enabled"):
        return None, None
    listen, connect = z["listen"], z["connect"]
    if z["mode"] == "client" and listen:
        return ("key 'zenoh.listen': a client listens nowhere (it connects to a router or "
                "peer); empty the list or set zenoh.mode = \"peer\""), None
    if z["mode"] == "client" and not connect and not z["multicast"]:
        return ("key 'zenoh.connect': a client needs an endpoint to connect to (a router or "
                "peer, e.g. [\"tcp/127.0.0.1:7447\"]) or zenoh.multicast = true"), None
    files = tls_files(z)
    if any(e.startswith("tls/") for e in (*listen, *connect)) and not all(files):
        return ("key 'zenoh.tls_ca': a tls/ endpoint needs zenoh.tls_ca, zenoh.tls_cert and "
                "zenoh.tls_key (certificate files: docs/ros2.md, Security)"), None
    exposed = [e for e in listen if not is_loopback_host(endpoint_host(e))]
    plain = [e for e in exposed if not e.startswith("tls/")]
    if plain and not z["insecure"]:
        return (f"key 'zenoh.listen': {plain[0]} listens beyond loopback without TLS; use a "
                "tls/ endpoint with zenoh.tls_ca/tls_cert/tls_key (mutual TLS, docs/ros2.md) "
                "or set zenoh.insecure = true"), None
    if plain:
        return None, (f"zenoh.insecure = true: {', '.join(plain)} accepts any peer on the "
                      "network, unauthenticated and unencrypted (it can read and publish "
                      "robot poses)")
    return None, None
