"""kmea: KMEA's tools (each COMMAND has its own --help).

The ``kmea`` command: the library's front door (:mod:`kmea.cli`) with the daemon-side tools
(sockets, UDP, files, the Pi) and the daemon's benchmarks added. It lives here, above both
layers, so that the library never imports the daemon.
"""

from __future__ import annotations

import sys

from kmea import cli
from kmead.benchmarks import BENCHES

# name -> (module, one-line help), imported only when run.
DAEMON_COMMANDS: dict[str, tuple[str, str]] = {
    "fuse": ("kmead.tools.fuse", "fuse several cameras' robot poses (docs/fusion.md)"),
    "doctor": ("kmead.tools.doctor",
               "check a Raspberry Pi install: versions, camera, ports, files"),
    "export": ("kmead.viewers.mcap_export", "a recording as MCAP for Foxglove (foxglove extra)"),
    "snapshot": ("kmead.tools.snapshot_cli", "save a running kmead's camera frame as PNG"),
    "keys": ("kmead.tools.keys_cli",
             "make CURVE keys for kmead and its clients (docs/security.md)"),
}


# The daemon's benchmarks (kmead/benchmarks/) for ``kmea bench``, beside the library's.
DAEMON_BENCHES = BENCHES


def main(argv: list[str] | None = None) -> int:
    return cli.main(argv, {**cli.COMMANDS, **DAEMON_COMMANDS}, DAEMON_BENCHES,
                    (__doc__ or "").splitlines()[0])


if __name__ == "__main__":
    sys.exit(main())
