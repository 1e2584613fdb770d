"""``kmea keys``: make the CURVE key directory of kmead, and a site's TLS (docs/security.md).

``kmea keys init DIR`` writes the daemon's pair and a first operator; ``kmea keys add DIR
NAME [--viewer]`` adds a client. The contract is described in :mod:`kmea.wire.curve_client`.
``kmea keys site DIR --cameras ... --nodes ... --robots ...`` makes a site's CA, one
certificate per peer and Zenoh's access control (:mod:`kmead.config.site_tls`).
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

from kmea.wire.curve_client import CurveKeyError
from kmead.config.site_tls import SiteTlsError, make_site
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
    p = sub.add_parser("site", help="a Zenoh site's CA, a certificate per camera, fusion node "
                                    "and robot, and its access control (acl.json5)")
    p.add_argument("dir", metavar="DIR")
    p.add_argument("--site", default="kmea", help="zenoh.site (default kmea)")
    p.add_argument("--cameras", nargs="*", default=[], metavar="ID",
                   help="camera ids (each its certificate's name and its zenoh key part)")
    p.add_argument("--nodes", nargs="*", default=[], metavar="ID", help="fusion node ids")
    p.add_argument("--robots", nargs="*", default=[], metavar="NAME",
                   help="robots that subscribe over TLS")
    p.add_argument("--hosts", nargs="*", default=[], metavar="HOST",
                   help="host names and addresses peers connect to (in every certificate)")
    p.add_argument("--ros-domain", type=int, default=0, help="zenoh.ros_domain (default 0)")
    p.add_argument("--ros-namespace", default="/kmea",
                   help="zenoh.ros_namespace (default /kmea)")


def _site(args: Any) -> int:
    try:
        files = make_site(args.dir, args.site, args.cameras, args.nodes, args.robots,
                          args.hosts, args.ros_domain, args.ros_namespace)
    except (SiteTlsError, OSError) as e:
        print(f"kmea keys site: {e}", file=sys.stderr)
        return 2
    for f in files:
        print(f"wrote {f}")
    d = Path(args.dir).resolve()
    print(f"next: on each peer NAME set [zenoh] tls_ca = \"{d / 'ca.pem'}\", tls_cert = "
          f"\"NAME.pem\", tls_key = \"NAME.key\", acl = \"{d / 'acl.json5'}\" (copy "
          "ca.pem, acl.json5 and its own two files only; ca.key stays here: docs/security.md)")
    return 0


def run(args: Any) -> int:
    if args.keys_command == "site":
        return _site(args)
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
