"""kmea snapshot: ask a running kmead to save its camera frame as PNG (control "snapshot").

The daemon writes the full-resolution frame into its data directory (its working
directory) and replies the path; nothing is sent back over the network but that path.
"""

from __future__ import annotations

import argparse
import sys

DEFAULT_CONTROL = "tcp://127.0.0.1:5556"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.description = ("Ask a running kmead to save the last camera frame, full resolution, "
                     "as PNG in its data directory (its working directory).")
    p.add_argument("--overlay", action="store_true",
                   help="draw the marker outlines, ids and focus figure on the image")
    p.add_argument("--control", default=DEFAULT_CONTROL, metavar="ENDPOINT",
                   help="the daemon's control socket (default %(default)s)")
    p.add_argument("--timeout", type=float, default=5.0, metavar="SECONDS",
                   help="wait this long for the reply (default %(default)g s)")


def run(args: argparse.Namespace) -> int:
    import zmq

    from kmea.wire import protocol as P

    ctx = zmq.Context.instance()
    s = ctx.socket(zmq.REQ)
    s.setsockopt(zmq.LINGER, 0)
    try:
        s.connect(args.control)
    except zmq.ZMQError as e:
        print(f"kmea snapshot: --control {args.control!r}: {e}", file=sys.stderr)
        return 2
    try:
        s.send(P.encode_body({"cmd": "snapshot", "overlay": bool(args.overlay)}))
        if not s.poll(int(args.timeout * 1000), zmq.POLLIN):
            print(f"kmea snapshot: no reply from {args.control} within {args.timeout:g} s "
                  "(is kmead running? its control socket on?)", file=sys.stderr)
            return 1
        reply = P.decode_body(s.recv())
    except P.ProtocolError as e:
        print(f"kmea snapshot: bad reply: {e}", file=sys.stderr)
        return 1
    finally:
        s.close(linger=0)
    if not reply.get("ok"):
        print(f"kmea snapshot: {reply.get('error', 'refused')}", file=sys.stderr)
        return 1
    print(f"saved {reply.get('path')} (frame {reply.get('frame')})")
    return 0
