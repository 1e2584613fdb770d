"""``kmea bench [NAME ...]``: every benchmark of KMEA, by name (figures, never asserted in
tests). ``kmea bench --list`` names them, one line each.

Benchmarks live in two packages, split by layer: the library's here (:mod:`kmea.benchmarks`,
numpy and OpenCV only, :data:`BENCHES`) and the daemon's in ``kmead/benchmarks/`` (the
daemon, sockets, Zenoh, subprocesses; its table is added by the ``kmea`` front door in
``kmead/tools/kmea_cli.py``, as ``args.daemon_benches``): one table of name ->
(``"module:function"``, one-line description) each, one dispatcher.

Two kinds of function:

- ``run(quick: bool[, frames: int])`` prints its table; ``--quick`` and ``--frames`` reach
  it (``--frames`` only when it has that parameter). ``kmea bench`` alone runs every one.
- ``main(argv) -> int`` (a function named ``main``) has its own options
  (``kmea bench NAME --help``): everything after its name is its command line. It runs
  alone and only by name (some take minutes or an hour).
"""

from __future__ import annotations

import argparse
import inspect
from collections.abc import Callable, Mapping
from importlib import import_module
from typing import Any

# "module:function", or the function itself (tests).
Target = str | Callable[..., Any]

# The library's benchmarks: name -> ("module:function", one-line description).
BENCHES: dict[str, tuple[Target, str]] = {
    "estimators": ("kmea.benchmarks.estimators:run",
                   "median time of one estimate of kmea, lmea and umeyama"),
    "estimator-cost": ("kmea.benchmarks.robust:run",
                       "cost per frame of every estimator for 33 markers"),
    "detection": ("kmea.benchmarks.detection:run",
                  "ArUco detection time, one thread, on rendered frames"),
    "render": ("kmea.benchmarks.render:run",
               "simulator speed on one core, corner fidelity vs truth"),
    "pipeline": ("kmea.benchmarks.pipeline:run",
                 "detection variants and the library pipeline, one thread"),
    "tracking": ("kmea.benchmarks.tracking:run",
                 "the tracking filter against the paper's IIR filter"),
    "fusion": ("kmea.benchmarks.fusion:run",
               "two cameras, one picture, on the simulated wide scene"),
    "fixed-camera": ("kmea.benchmarks.fixed_camera:run",
                     "nothing lost with the tracking detector (1640x1232 sim)"),
    "frame-path": ("kmea.benchmarks.frame_path:main",
                   "the frame path up to the robots' datagrams, CPU time"),
    "corner-pnp-frame": ("kmea.benchmarks.corner_pnp_frame:main",
                         "corner-pnp's estimate on a fixed camera, CPU a frame"),
    "motion": ("kmea.benchmarks.motion:main",
               "robot poses at 0.5-1.5 m/s under the rolling shutter"),
    "tracking-ablation": ("kmea.benchmarks.tracking_ablation:main",
                          "the tracking filter's mechanisms, each removed alone"),
}


def takes_argv(target: Target) -> bool:
    """A ``main(argv)`` benchmark (its own options, run alone), known without importing."""
    name = target.rpartition(":")[2] if isinstance(target, str) else target.__name__
    return name == "main"


def _resolve(target: Target) -> Callable[..., Any]:
    if isinstance(target, str):
        module, func = target.split(":")
        return getattr(import_module(module), func)
    return target


def _every(args_or_parser: Any) -> dict[str, tuple[Target, str]]:
    extra = (args_or_parser.get_default("daemon_benches")
             if isinstance(args_or_parser, argparse.ArgumentParser)
             else getattr(args_or_parser, "daemon_benches", None))
    return {**BENCHES, **(extra or {})}


def listing(benches: Mapping[str, tuple[Target, str]]) -> str:
    """One line a benchmark: its name, ``*`` when it has its own options, what it measures."""
    cells = {name: name + (" *" if takes_argv(t) else "")
             for name, (t, _) in benches.items()}
    width = max(map(len, cells.values()), default=0)
    return "\n".join(f"  {cells[name]:<{width}}  {help_}"
                     for name, (_, help_) in benches.items())


def add_arguments(p: argparse.ArgumentParser) -> None:
    every = _every(p)
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.description = ("Run benchmarks by name (default: every one not marked *).\n"
                     "A benchmark marked * has its own options (kmea bench NAME --help)\n"
                     "and runs alone: kmea bench NAME [OPTIONS].")
    p.epilog = "benchmarks (* its own options):\n" + listing(every)
    p.add_argument("--list", action="store_true",
                   help="name every benchmark with what it measures, and stop")
    p.add_argument("--quick", action="store_true", help="fewer repetitions")
    p.add_argument("--frames", type=int, default=None, metavar="N",
                   help="frames for the benchmarks that take a count (pipeline: 90 by "
                        "default; 1640x1232 frames are pre-rendered, ~6 MB each)")
    p.add_argument("names", nargs=argparse.REMAINDER, metavar="NAME ...",
                   help="benchmarks to run (below); after one marked *, its options")


def run(args: argparse.Namespace) -> int:
    """Run the named benchmarks; ``args.daemon_benches`` (name -> ("module:function",
    description) or (function, description), set by the ``kmea`` front door) adds the
    daemon's own."""
    benches = _every(args)
    if getattr(args, "list", False):
        print(listing(benches))
        return 0
    tokens: list[str] = list(args.names or [])
    if tokens and tokens[0] in benches and takes_argv(benches[tokens[0]][0]):
        name = tokens[0]
        if args.quick or args.frames is not None:
            print(f"kmea bench: {name} has its own options, after its name "
                  f"(kmea bench {name} --help)")
            return 2
        return int(_resolve(benches[name][0])(tokens[1:]) or 0)
    # The run(quick[, frames]) benchmarks: names, then --quick / --frames anywhere.
    inner = argparse.ArgumentParser(prog="kmea bench")
    inner.add_argument("names", nargs="*")
    inner.add_argument("--quick", action="store_true")
    inner.add_argument("--frames", type=int, default=None)
    more = inner.parse_args(tokens)
    quick = bool(args.quick or more.quick)
    frames = more.frames if more.frames is not None else getattr(args, "frames", None)
    names = more.names or [n for n, (t, _) in benches.items() if not takes_argv(t)]
    for name in names:
        if name not in benches:
            print(f"kmea bench: unknown benchmark {name!r}; choose from {', '.join(benches)}")
            return 2
        if takes_argv(benches[name][0]):
            print(f"kmea bench: {name} has its own options and runs alone: "
                  f"kmea bench {name} [OPTIONS]")
            return 2
    for name in names:
        target = _resolve(benches[name][0])
        print(f"== {name} ==", flush=True)
        if frames is not None and "frames" in inspect.signature(target).parameters:
            target(quick=quick, frames=frames)
        else:
            target(quick=quick)
    return 0
