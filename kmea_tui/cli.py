"""kmea-tui: the terminal UI on a running kmead, or on a recorded telemetry stream."""

from __future__ import annotations

import argparse
import asyncio
import re
import sys

from kmea.wire import protocol


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="kmea-tui",
        description="Terminal UI for kmead: markers, robots, statistics, floor map, "
                    "configuration, log and camera. Keys: 1-7 tabs, q quit (Ctrl+Q from a "
                    "text field), ? help.")
    p.add_argument("--telemetry", metavar="ENDPOINT",
                   help="the daemon's telemetry PUB socket (default: the newest kmead or kmea "
                        f"fuse running on this machine, else {protocol.DEFAULT_TELEMETRY})")
    p.add_argument("--control", metavar="ENDPOINT",
                   help="the daemon's control REP socket (default: as --telemetry, else "
                        f"{protocol.DEFAULT_CONTROL})")
    p.add_argument("--keys", metavar="DIR",
                   help="a kmead key directory (kmea keys init/add): connect with CURVE as "
                        "--client; needed when the daemon sets network.keys")
    p.add_argument("--client", default="operator", metavar="NAME",
                   help="the client key pair DIR/clients/NAME.key_secret (default %(default)s)")
    p.add_argument("--replay", metavar="FILE.jsonl",
                   help="show a recorded telemetry stream instead of a daemon")
    p.add_argument("--speed", type=float, default=1.0,
                   help="replay speed factor (default 1)")
    p.add_argument("--save-stream", metavar="FILE.jsonl",
                   help="record the daemon's telemetry to FILE for --replay (no UI)")
    p.add_argument("--seconds", type=float, default=5.0,
                   help="how long --save-stream records (default %(default)s s)")
    p.add_argument("--keep-frames", type=int, default=0, metavar="N",
                   help="--save-stream keeps only the last N frames (and every status, "
                        "event and log message); 0 keeps everything")
    p.add_argument("--screenshots", metavar="DIR",
                   help="with --replay: write an SVG of every tab (tui-TAB.svg) to DIR "
                        "after the whole recording was shown, then exit")
    p.add_argument("--size", default="80x24", metavar="COLSxROWS",
                   help="terminal size for --screenshots (default %(default)s)")
    p.add_argument("--rate", type=float, default=4.0, metavar="HZ",
                   help="table and map refreshes per second, at most (default %(default)s)")
    from kmea import __version__

    p.add_argument("--version", action="version", version=f"kmea-tui {__version__}")
    p.add_argument("--theme", default="auto",
                   help="Textual theme; 'auto' picks ansi-dark on 16-colour terminals "
                        "and textual-dark otherwise")
    return p


def _endpoints(args: argparse.Namespace) -> None:
    """Endpoints not given: the newest daemon announced on this machine
    (:mod:`kmea.wire.runtime`: ``make run`` binds free ports), else the defaults."""
    if args.telemetry is None and args.control is None:
        from kmea.wire.runtime import live_daemons

        found = live_daemons()
        if found:
            d = found[0]
            args.telemetry, args.control = d["telemetry"], d["control"]
            more = f" ({len(found) - 1} more running)" if len(found) > 1 else ""
            print(f"kmea-tui: {d.get('kind', 'kmead')} pid {d['pid']} on {d['telemetry']}"
                  f"{more}", file=sys.stderr)
            if args.keys is None and d.get("keys"):
                args.keys = d["keys"]
    if args.telemetry is None:
        args.telemetry = protocol.DEFAULT_TELEMETRY
    if args.control is None:
        args.control = protocol.DEFAULT_CONTROL


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.screenshots and not args.replay:
        print("kmea-tui: --screenshots needs --replay FILE", file=sys.stderr)
        return 2
    if not args.replay:
        _endpoints(args)
    from kmea.wire.curve_client import CurveKeyError, read_client_keys
    from kmea_tui.client import DaemonClient, RecordingClient, check_endpoint, record_stream

    if args.keys is not None:
        try:  # a missing or bad key file: one line, before any socket
            read_client_keys(args.keys, args.client)
        except CurveKeyError as e:
            print(f"kmea-tui: --keys: {e}", file=sys.stderr)
            return 2
    if args.save_stream:
        n = asyncio.run(record_stream(args.telemetry, args.control, args.save_stream,
                                      args.seconds, keep_frames=args.keep_frames,
                                      keys=args.keys, client=args.client))
        print(f"kmea-tui: wrote {n} messages to {args.save_stream}")
        return 0 if n else 1
    from kmea_tui.app import KmeaTui

    theme = None if args.theme == "auto" else args.theme
    if args.screenshots:
        from kmea_tui.app import save_screenshots

        m = re.fullmatch(r"(\d+)x(\d+)", args.size.strip().lower())
        if not m or int(m.group(1)) < 40 or int(m.group(2)) < 10:
            print(f"kmea-tui: --size {args.size!r}: give COLSxROWS, at least 40x10",
                  file=sys.stderr)
            return 2
        cols, rows = int(m.group(1)), int(m.group(2))
        try:
            files = asyncio.run(save_screenshots(args.replay, args.screenshots, (cols, rows),
                                                 theme or "textual-dark"))
        except ValueError as e:
            print(f"kmea-tui: {e}", file=sys.stderr)
            return 2
        print("\n".join(f"kmea-tui: wrote {f}" for f in files))
        return 0
    if args.replay:
        try:
            client: DaemonClient | RecordingClient = RecordingClient(
                args.replay, realtime=True, speed=args.speed, loop=True)
        except ValueError as e:
            print(f"kmea-tui: {e}", file=sys.stderr)
            return 2
    else:
        for opt, endpoint in (("--telemetry", args.telemetry), ("--control", args.control)):
            problem = check_endpoint(endpoint)
            if problem:
                print(f"kmea-tui: {opt} {endpoint!r}: {problem}", file=sys.stderr)
                return 2
        client = DaemonClient(args.telemetry, args.control, keys=args.keys, client=args.client)
    if not 0.5 <= args.rate <= 30:
        print("kmea-tui: --rate: give 0.5 to 30 refreshes per second", file=sys.stderr)
        return 2
    KmeaTui(client, theme=theme, ui_period=1.0 / args.rate).run()
    return 0


if __name__ == "__main__":
    sys.exit(main())
