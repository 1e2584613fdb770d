"""``kmea bench [NAME ...]``: benchmarks that print figures (never asserted in tests).

Each benchmark is a function ``run(quick: bool) -> None`` that prints its own table.
"""

from __future__ import annotations

import argparse
from importlib import import_module

# name -> "module:function"
BENCHES: dict[str, str] = {
    "estimators": "kmea.benchmarks.estimators:run",
    "estimator-cost": "kmea.benchmarks.robust:run",
    "detection": "kmea.benchmarks.detection:run",
    "render": "kmea.benchmarks.render:run",
    "pipeline": "kmead.bench:run_pipeline",
    "latency": "kmead.bench:run_latency",
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("names", nargs="*", metavar="NAME",
                   help=f"benchmarks to run (default: all): {', '.join(BENCHES)}")
    p.add_argument("--quick", action="store_true", help="fewer repetitions")


def run(args: argparse.Namespace) -> int:
    names = args.names or list(BENCHES)
    for name in names:
        if name not in BENCHES:
            print(f"kmea bench: unknown benchmark {name!r}; choose from {', '.join(BENCHES)}")
            return 2
    for name in names:
        module, func = BENCHES[name].split(":")
        print(f"== {name} ==", flush=True)
        getattr(import_module(module), func)(quick=args.quick)
    return 0
