#!/usr/bin/env python3
"""hostile_camera.py ROW: play a hostile peer against a fusion node on this machine's
loopback mesh (the way the docs' cameras meet: the rendezvous tcp/127.0.0.1:7447), and send
one kind of message the node must refuse.

Start the docs' three processes first (docs/fusion.md, "Try it on the simulator"), with the
robots' destinations on a UDP listener, then e.g.::

    python scripts/hostile_camera.py x1e300             # as camera cam0, robot amr1
    python scripts/hostile_camera.py strangers --count 64

What the node did shows in its log (one event per camera and field), its ``status``
(``inputs[].bad``, ``fusion.strangers``) and what the robots get. ROW is one of
:data:`ROWS`. The messages go under an existing camera's key (``--camera``, default cam0):
whoever may publish on the site can do that, so the node checks every message on its own.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

# name -> (what it sends, how many by default)
ROWS = {
    "x1e300": ("x = 1e300", 6),
    "x1e100": ("x = 1e100", 6),
    "x1e308": ("x = 1e308", 1),
    "xdigits": ("x as a 401-digit JSON integer", 1),
    "future3600": ("one measurement stamped 3,600 s ahead", 1),
    "future20": ("one measurement stamped 20 s ahead", 1),
    "far100": ("a pose 100 m away", 10),
    "sigma": ("a sigma of 0.678 m", 5),
    "strangers": ("data-only messages under invented camera ids", 64),
}


def payload(row: str, robot: str, at: tuple[float, float]) -> bytes:
    now = time.time()
    body = {"name": robot, "valid": True, "t": now, "x": at[0], "y": at[1], "theta": 0.0,
            "sigma": 0.002}
    if row.startswith("x1e"):
        body["x"] = float(row[1:])
    elif row.startswith("future"):
        body["t"] = now + float(row.removeprefix("future"))
    elif row == "far100":
        body["x"], body["y"] = at[0] + 100.0, at[1] + 100.0
    elif row == "sigma":
        body["sigma"] = 0.678
    text = json.dumps(body)
    if row == "xdigits":
        text = text.replace(f'"x": {json.dumps(at[0])}', '"x": 1' + "0" * 400)
    return text.encode()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("row", choices=sorted(ROWS))
    p.add_argument("--count", type=int, help="messages (default: the row's)")
    p.add_argument("--camera", default="cam0", help="the camera id to send as (default cam0)")
    p.add_argument("--robot", default="amr1")
    p.add_argument("--at", default="1.0,0.3", help="where the robot stands: X,Y (m)")
    p.add_argument("--site", default="kmea")
    p.add_argument("--connect", default="tcp/127.0.0.1:7447")
    args = p.parse_args(argv)
    import zenoh

    at = tuple(float(v) for v in args.at.split(","))
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("connect/endpoints", json.dumps([args.connect]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(conf)
    try:
        time.sleep(1.0)  # the mesh's gossip: the node's subscriptions reach this session
        n = args.count or ROWS[args.row][1]
        for k in range(n):
            # Strangers send a plausible measurement: only their id is invented.
            cam = f"ghost{k}" if args.row == "strangers" else args.camera
            data = payload(args.row, args.robot, (at[0], at[1]))
            session.put(f"{args.site}/cam/{cam}/robots/{args.robot}", data)
            time.sleep(0.03)
        time.sleep(0.5)
    finally:
        session.close()
    who = "ghost0..." if args.row == "strangers" else args.camera
    print(f"sent {n} x {ROWS[args.row][0]} as {who}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
