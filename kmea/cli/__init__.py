"""kmea: the library's tools (each COMMAND has its own --help).

Each subcommand lives in its own module exposing ``add_arguments(parser)`` and
``run(args) -> int``; they are imported only when used, so a missing optional
dependency of one tool never breaks another. The ``kmea`` command (``kmead.tools.kmea_cli``) is
this front door with the daemon-side tools added (fuse, doctor, keys, export, snapshot and
the daemon's benchmarks): the library never reaches into the daemon.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Mapping
from importlib import import_module

# name -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "map": ("kmea.cli.map", "show, check or convert a marker map"),
    "calibrate": ("kmea.cli.calibrate", "calibrate a camera from board views"),
    "print": ("kmea.cli.printouts", "printable markers, floor and ChArUco boards"),
    "experiment": ("kmea.cli.experiment", "reproduce the paper's validation, Parts I-IV"),
    "bench": ("kmea.cli.bench", "every benchmark, by name (kmea bench --list)"),
}


def main(argv: list[str] | None = None,
         commands: Mapping[str, tuple[str, str]] | None = None,
         extra_benches: Mapping[str, tuple[str, str]] | None = None,
         description: str | None = None) -> int:
    """Run one subcommand. ``commands``: name -> (module, help), by default the library's
    :data:`COMMANDS`; ``extra_benches``: more benchmarks for ``bench`` to offer (name ->
    ("module:function", description); the daemon's, from ``kmead.tools.kmea_cli``)."""
    from kmea import __version__

    parser = argparse.ArgumentParser(prog="kmea",
                                     description=description or (__doc__ or "").partition("\n")[0])
    parser.add_argument("--version", action="version", version=f"kmea {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    modules = {}
    argv = sys.argv[1:] if argv is None else argv
    for name, (module, help_) in (COMMANDS if commands is None else commands).items():
        p = sub.add_parser(name, help=help_)
        if name == "bench":
            p.set_defaults(daemon_benches=dict(extra_benches or {}))
        # Only the chosen command's module is imported (and so its dependencies).
        if argv and argv[0] == name:
            modules[name] = import_module(module)
            modules[name].add_arguments(p)
    args = parser.parse_args(argv)
    try:
        return int(modules[args.command].run(args) or 0)
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        # `kmea map show | head`: the reader left; say nothing more.
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0


if __name__ == "__main__":
    sys.exit(main())
