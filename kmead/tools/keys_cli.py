"""``kmea keys``: make the CURVE key directory of kmead (see docs/security.md).

``kmea keys init DIR`` writes the daemon's pair and a first operator; ``kmea keys add DIR
NAME [--viewer]`` adds a client. The contract is described in :mod:`kmea.wire.curve_client`.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

from kmea.wire.curve_client import CurveKeyError
from kmead.net.keys import add_client, init_keys


def add_arguments(parser: Any) -> None:
    """``kmea keys init DIR`` / ``kmea keys add DIR NAME [--viewer]``."""
    sub = parser.add_subparsers(dest="keys_command", required=True, metavar="ACTION")
    p = sub.add_parser("init", help="make a key directory: the daemon's pair and an operator")
    p.add_argument("dir", metavar="DIR")
    p = sub.add_parser("add", help="add a client key pair (an operator unless --viewer)")
    p.add_argument("dir", metavar="DIR")
    p.add_argument("name", metavar="NAME")
    p.add_argument("--viewer", action="store_true", help="may only watch telemetry")


def run(args: Any) -> int:
    try:
        if args.keys_command == "init":
            files = init_keys(args.dir)
        else:
            files = add_client(args.dir, args.name, args.viewer)
    except (CurveKeyError, OSError) as e:
        print(f"kmea keys: {e}", file=sys.stderr)
        return 2
    for f in files:
        print(f"wrote {f}")
    if args.keys_command == "init":
        d = Path(args.dir)
        print(f"next: set [network] keys = \"{d.resolve()}\" in the daemon's config; copy "
              f"{d / 'server.key'} and {d / 'clients' / 'operator.key_secret'} to the "
              "operator's laptop (docs/security.md)")
    else:
        print(f"copy {files[1]} and {Path(args.dir) / 'server.key'} to that client only")
    return 0
