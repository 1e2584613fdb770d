"""Zenoh on loopback for the fusion tests: explicit endpoints, no scouting (never the
machine's rendezvous port, which another process may hold), and a camera played by the test
(a liveliness token, a metadata queryable, measurements it sends when told)."""

from __future__ import annotations

import json
import socket
from typing import Any

SITE = "kmea"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def zenoh_sets(listen: int | None = None, connect: int | None = None,
               lease_s: float = 2.0) -> list[str]:
    """``--set`` items: Zenoh on, peer mode, listening on and/or connecting to loopback
    ports, no ROS 2 output (the ROS tests cover it)."""
    out = ["zenoh.enabled=true", f"zenoh.lease_s={lease_s}", "zenoh.ros2=false"]
    if listen is not None:
        out.append(f'zenoh.listen=["tcp/127.0.0.1:{listen}"]')
    if connect is not None:
        out.append(f'zenoh.connect=["tcp/127.0.0.1:{connect}"]')
    return out


def open_peer(connect: int | None = None, listen: int | None = None) -> Any:
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("listen/endpoints",
                      json.dumps([f"tcp/127.0.0.1:{listen}"] if listen else []))
    conf.insert_json5("connect/endpoints",
                      json.dumps([f"tcp/127.0.0.1:{connect}"] if connect else []))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(conf)


class FakeCamera:
    """A camera of the site played by the test: ``meta`` is what its queryable answers
    (bytes as they are, a dict as JSON)."""

    def __init__(self, connect: int, cam_id: str, meta: dict | bytes,
                 mesh: bool = False) -> None:
        """``mesh``: also listen on a free port, so that the nodes' gossip joins it to a
        node it did not connect to (it outlives the node it connected to)."""
        self.id = cam_id
        self.prefix = f"{SITE}/cam/{cam_id}"
        self.session = open_peer(connect=connect, listen=free_port() if mesh else None)
        payload = meta if isinstance(meta, bytes) else json.dumps(meta).encode()
        self.queryable = self.session.declare_queryable(
            f"{self.prefix}/meta", lambda q: q.reply(f"{self.prefix}/meta", payload))
        self.token = self.session.liveliness().declare_token(self.prefix)

    def measurement(self, name: str, t: float, x: float, y: float,
                    sigma: float | None = 0.002) -> None:
        self.put(f"robots/{name}", {"name": name, "valid": True, "t": t, "x": x, "y": y,
                                    "theta": 0.0, "sigma": sigma})

    def put(self, suffix: str, body: dict | bytes) -> None:
        self.session.put(f"{self.prefix}/{suffix}",
                         body if isinstance(body, bytes) else json.dumps(body).encode())

    def close(self) -> None:
        self.session.close()


def meta(cam_id: str, digest: str) -> dict:
    return {"camera": cam_id, "map_digest": digest, "map_name": "test map",
            "model": "built-in", "width": 640, "height": 480, "fx": 500.0, "fy": 500.0,
            "source": "test", "extent": [-1.0, 4.0, -1.0, 2.0]}
