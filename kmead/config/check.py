"""``kmead --check``: validate the configuration, map and camera without starting.

Runs start-up's own plan (:func:`kmead.config.plan.plan_startup`), so it refuses exactly what
start-up refuses, with the same line and exit code, and prints the effective
configuration (TOML) with the files it came from, then the warnings. Opens no camera and
binds no port. Exit 0 when kmead would start with this configuration, 2 (one line on
stderr naming the file and key) when it would not.
"""

from __future__ import annotations

import sys
from typing import TextIO

from kmead.config.layers import Config, ConfigError
from kmead.config.plan import plan_startup
from kmead.config.startup import EXIT_OK, StartupError


def effective_toml(cfg: Config) -> str:
    import tomli_w

    return tomli_w.dumps(cfg.to_dict())


def run_check(cfg: Config, out: TextIO | None = None, err: TextIO | None = None) -> int:
    """Print the effective configuration and the warnings; the exit code."""
    out = sys.stdout if out is None else out
    err = sys.stderr if err is None else err
    try:
        warnings = plan_startup(cfg).warnings
    except StartupError as e:
        print(f"kmead: {e}", file=err)
        return e.code
    except ConfigError as e:
        print(f"kmead: configuration error: {e}", file=err)
        return 2
    print("# kmead --check: the effective configuration", file=out)
    print(f"# files read, in order: {', '.join(cfg.files)}", file=out)
    print(f"# the Configuration tab's Save writes: {cfg.overlay_path}", file=out)
    print(effective_toml(cfg), file=out)
    for w in warnings:
        print(f"kmead: warning: {w}", file=err)
    print(f"kmead: configuration OK ({len(warnings)} warning{'s' * (len(warnings) != 1)})",
          file=err)
    return EXIT_OK
