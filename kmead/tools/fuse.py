"""``kmea fuse``: the fusion node's command line (options, logging, serving, summary).

The node itself is :class:`kmead.fusion.node.FusionNode`; this front-end builds it from the
configuration and serves it as kmead is served (:func:`kmead.tools.host.serve`).
"""

from __future__ import annotations

from typing import Any

from kmead.config.layers import ConfigError
from kmead.config.startup import StartupError
from kmead.fusion.node import FusionNode


def add_arguments(p: Any) -> None:
    """``kmea fuse`` options (as for kmead)."""
    p.add_argument("--config", metavar="FILE", help="configuration file overlaid on the default")
    p.add_argument("--set", metavar="SECTION.KEY=VALUE", action="append", default=[],
                   help="override any configuration key; VALUE is TOML (repeatable)")
    p.add_argument("--log", metavar="FILE.csv", help="CSV log of every fused pose (log.csv)")
    p.add_argument("--map", metavar="FILE", help="the floor's map: cameras with another are "
                                                 "refused (map.file; default: the first "
                                                 "camera's)")
    p.add_argument("--headless", action="store_true", help="no terminal UI")
    p.add_argument("--frames", metavar="N", type=int, help="stop after N fused outputs")


def run(args: Any) -> int:
    """Run the fusion node; exit codes as kmead's (0 done, 1 runtime failure, 2 config)."""
    import sys

    from kmead.cli import stderr_logging
    from kmead.config.layers import load_config

    if args.frames is not None and args.frames < 1:
        print("kmea fuse: --frames: must be >= 1", file=sys.stderr)
        return 2
    try:
        overrides = {k: v for k, v in (("log.csv", args.log), ("map.file", args.map)) if v}
        cfg = load_config(args.config, args.set, overrides or None)
        # Joining the site takes a few seconds: say so at once (kmead does the same).
        print(f"kmea fuse: starting (joining the Zenoh site {cfg['zenoh']['site']!r})...",
              file=sys.stderr, flush=True)
        with stderr_logging(cfg["log"]["level"]):
            node = FusionNode(cfg, max_outputs=args.frames)
    except ConfigError as e:
        print(f"kmea fuse: configuration error: {e}", file=sys.stderr)
        return 2
    except StartupError as e:  # Zenoh cannot open its session
        print(f"kmea fuse: {e}", file=sys.stderr)
        return e.code
    except OSError as e:
        print(f"kmea fuse: {e}", file=sys.stderr)
        return 1
    with stderr_logging(cfg["log"]["level"]):
        return _serve(node, args)


def _serve(node: FusionNode, args: Any) -> int:
    """The node's run (with the UI or headless), then its summary; closes the node."""
    import sys

    from kmead.tools.host import serve

    print(f"kmea fuse: telemetry {node.telemetry.bound if node.telemetry else 'off'}, control "
          f"{node.control.bound if node.control else 'off'}", file=sys.stderr, flush=True)
    ui = not args.headless and sys.stdout.isatty() and sys.stdin.isatty()
    code = serve(node, ui, f"fusing on zenoh site {node.site!r}", kind="kmea fuse")
    summary = node.summary()
    print(summary, flush=True)
    return code


def main(argv: list[str] | None = None) -> int:
    """``python -m kmead.tools.fuse [options]``: ``kmea fuse`` in a process of its own (the
    fusion-node benchmark starts it so)."""
    import argparse
    import sys

    p = argparse.ArgumentParser(prog="kmea fuse", description=add_arguments.__doc__)
    add_arguments(p)
    return run(p.parse_args(sys.argv[1:] if argv is None else argv))


if __name__ == "__main__":
    raise SystemExit(main())
