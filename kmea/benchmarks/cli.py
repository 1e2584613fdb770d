"""``kmea bench [NAME ...]``: benchmarks that print figures (never asserted in tests).

Each benchmark is a function ``run(quick: bool) -> None`` that prints its own table.
"""

from __future__ import annotations

import argparse
import inspect
from collections.abc import Callable
from importlib import import_module

# name -> "module:function"
BENCHES: dict[str, str] = {
    "estimators": "kmea.benchmarks.estimators:run",
    "estimator-cost": "kmea.benchmarks.robust:run",
    "detection": "kmea.benchmarks.detection:run",
    "render": "kmea.benchmarks.render:run",
    "pipeline": "kmea.benchmarks.pipeline:run",
    "tracking": "kmea.benchmarks.tracking:run",
    "fusion": "kmea.benchmarks.fusion:run",
    "fixed-camera": "kmea.benchmarks.fixed_camera:run",
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    every = {**BENCHES, **(p.get_default("daemon_benches") or {})}
    p.add_argument("names", nargs="*", metavar="NAME",
                   help=f"benchmarks to run (default: all): {', '.join(every)}")
    p.add_argument("--quick", action="store_true", help="fewer repetitions")
    p.add_argument("--frames", type=int, default=None, metavar="N",
                   help="frames for the benchmarks that take a count (pipeline: 90 by "
                        "default; 1640x1232 frames are pre-rendered, ~6 MB each)")


def run(args: argparse.Namespace) -> int:
    """Run the named benchmarks; ``args.daemon_benches`` (name -> function or
    "module:function", set by the ``kmea`` front door) adds the daemon's own."""
    benches: dict[str, Callable[..., None] | str] = {**BENCHES,
                                                      **getattr(args, "daemon_benches", {})}
    names = args.names or list(benches)
    for name in names:
        if name not in benches:
            print(f"kmea bench: unknown benchmark {name!r}; choose from {', '.join(benches)}")
            return 2
    for name in names:
        target = benches[name]
        if isinstance(target, str):
            module, func = target.split(":")
            target = getattr(import_module(module), func)
        print(f"== {name} ==", flush=True)
        frames = getattr(args, "frames", None)
        if frames is not None and "frames" in inspect.signature(target).parameters:
            target(quick=args.quick, frames=frames)
        else:
            target(quick=args.quick)
    return 0
