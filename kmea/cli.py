"""kmea: the tools (map, calibrate, print, experiment, bench, fuse, doctor, keys, export,
snapshot).

Each subcommand lives in its own module exposing ``add_arguments(parser)`` and
``run(args) -> int``; they are imported only when used, so a missing optional
dependency of one tool never breaks another.
"""

from __future__ import annotations

import argparse
import sys
from importlib import import_module

# name -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "map": ("kmea.map_cli", "show, check or convert a marker map"),
    "calibrate": ("kmea.vision.calibrate_cli", "calibrate a camera from board views"),
    "print": ("kmea.vision.print_cli", "printable markers, floor and ChArUco boards"),
    "experiment": ("kmea.experiments.cli", "reproduce the paper's validation, Parts I-IV"),
    "bench": ("kmea.bench", "benchmarks that print figures"),
    # Daemon-side tools (sockets, UDP, files, the Pi), imported only when run: the one place
    # the library reaches into the daemon.
    "fuse": ("kmead.fusion", "fuse several cameras' robot poses (docs/fusion.md)"),
    "doctor": ("kmead.doctor", "check a Raspberry Pi install: versions, camera, ports, files"),
    "export": ("kmead.mcap_export", "a recording as MCAP for Foxglove (foxglove extra)"),
    "snapshot": ("kmead.snapshot_cli", "save a running kmead's camera frame as PNG"),
    "keys": ("kmead.keys_cli", "make CURVE keys for kmead and its clients (docs/security.md)"),
}


def main(argv: list[str] | None = None) -> int:
    from kmea import __version__

    parser = argparse.ArgumentParser(prog="kmea", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"kmea {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    modules = {}
    argv = sys.argv[1:] if argv is None else argv
    for name, (module, help_) in COMMANDS.items():
        p = sub.add_parser(name, help=help_)
        # Only the chosen command's module is imported (and so its dependencies).
        if argv and argv[0] == name:
            modules[name] = import_module(module)
            modules[name].add_arguments(p)
    args = parser.parse_args(argv)
    if args.command == "bench":
        args.daemon_benches = _daemon_benches()
    try:
        return int(modules[args.command].run(args) or 0)
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        # `kmea map show | head`: the reader left; say nothing more.
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0


def _daemon_benches() -> dict:
    """The daemon's benchmarks (threads, sockets, files), when kmead is installed: the front
    door is the one place of the library that may reach the daemon."""
    try:
        from kmead import bench
    except ImportError:
        return {}
    from kmead import fusion_bench

    return {"daemon": bench.run_daemon, "latency": bench.run_latency,
            "fusion-node": fusion_bench.run, "tui": bench.run_tui}


if __name__ == "__main__":
    sys.exit(main())
