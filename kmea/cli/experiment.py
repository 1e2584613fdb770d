"""``kmea experiment``: reproduce the paper's validation, Parts I-IV, or score a recording.

    kmea experiment I --samples 256 --jobs 2
    kmea experiment all --algorithms kmea,lmea --miscalibrate
    kmea experiment --replay run.jsonl

Writes into ``--out`` (default ``out/experiment``): ``part-X.md`` (the paper's table and the
per-marker metrics), ``part-X-markers.csv`` (per-marker metrics, metres),
``part-X-samples.csv`` (every estimate) and, with matplotlib, the figures. See
``docs/experiments.md``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from kmea.experiments.parts import PARTS, get_part

if TYPE_CHECKING:
    from kmea.progress import Progress

DEFAULT_ALGORITHMS = ("kmea", "lmea", "lmea-printed", "umeyama", "kmea-robust", "corner-pnp")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.description = "Reproduce the paper's validation, Parts I-IV, or score a recording."
    p.add_argument("part", nargs="?", metavar="PART",
                   help="I, II, III, IV (or 1-4) or 'all'; omit with --replay")
    p.add_argument("--samples", "-n", type=int, default=256,
                   help="frames per Part = samples per marker and algorithm (default 256)")
    p.add_argument("--algorithms", "-a", default=None,
                   help="comma-separated estimators (default: every registered one of "
                        f"{','.join(DEFAULT_ALGORITHMS)})")
    p.add_argument("--baseline", default="lmea", help="the %% change is against it (default lmea)")
    p.add_argument("--out", "-o", default="out/experiment", help="output directory")
    p.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    p.add_argument("--jobs", "-j", type=int, default=1, help="worker processes (default 1)")
    p.add_argument("--size", default="1640x1232",
                   help="rendered image size WxH, the Pi Camera v2 binned mode by default")
    p.add_argument("--miscalibrate", action="store_true",
                   help="give the estimators a slightly wrong calibration, as a real camera "
                        "has: focal length +2 %%, k1 +0.02 (see --focal-error, --k1-error)")
    p.add_argument("--focal-error", type=float, default=None, metavar="PCT",
                   help="focal length error the estimators believe, percent")
    p.add_argument("--k1-error", type=float, default=None, metavar="DK1",
                   help="error added to the first radial distortion coefficient")
    p.add_argument("--displacement-scale", type=float, default=1.0, metavar="K",
                   help="multiply the anchors' displacements of Parts III and IV by K")
    p.add_argument("--known-heights", action="store_true",
                   help="Part II: tell the estimators the raised markers' height, as the "
                        "daemon does for robots (the paper's algorithms do not)")
    p.add_argument("--floor-only", action="store_true",
                   help="give the estimators the floor markers only (wall markers are drawn "
                        "and detected but never references)")
    p.add_argument("--replay", metavar="FILE",
                   help="score a kmead recording instead (truth = the map's positions)")
    p.add_argument("--markers", default=None,
                   help="comma-separated ids to evaluate (default: the Part's; with --replay "
                        "every detected map marker but the map's origin/x/y anchors)")
    p.add_argument("--modes", default="plane-known,off-map",
                   help="evaluation modes, comma-separated, the first one primary: "
                        "plane-known (every estimator told the marker's plane), off-map "
                        "(the marker removed from the map); default both")
    p.add_argument("--iir", type=float, default=1.0, metavar="ALPHA",
                   help="apply the paper's IIR filter y = ALPHA x + (1 - ALPHA) y_prev to "
                        "every estimator's samples (default 1: off)")
    p.add_argument("--no-plots", action="store_true", help="skip the figures")
    p.add_argument("--quiet", "-q", action="store_true", help="no progress bar")


def _ids(text: str | None, what: str) -> tuple[int, ...] | None:
    if text is None:
        return None
    try:
        return tuple(int(t) for t in text.split(",") if t.strip())
    except ValueError:
        raise SystemExit(f"kmea experiment: {what}: expected comma-separated integers, "
                         f"got {text!r}") from None


def _algorithms(text: str | None) -> tuple[str, ...]:
    from kmea import estimators

    known = estimators.available()
    if text is None:
        return tuple(a for a in DEFAULT_ALGORITHMS if a in known)
    algs = tuple(a.strip() for a in text.split(",") if a.strip())
    for a in algs:
        if a not in known:
            raise SystemExit(f"kmea experiment: --algorithms: unknown {a!r}; "
                             f"choose among {', '.join(known)}")
    if not algs:
        raise SystemExit("kmea experiment: --algorithms: empty list")
    return algs


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise SystemExit(f"kmea experiment: --size: expected WxH, got {text!r}") from None
    if w < 64 or h < 48:
        raise SystemExit(f"kmea experiment: --size: {w}x{h} is too small")
    return w, h


def write_outputs(result, out: Path, plots: bool = True, quiet: bool = False,
                  others: dict | None = None) -> dict[str, Path | list[Path]]:
    """Write the Part's Markdown, CSVs and figures; returns name -> path.

    ``result`` is the primary mode's; ``others`` (mode -> result) the other modes', whose
    CSVs go to ``part-X-MODE-*.csv`` and whose tables join the Markdown.
    """
    from kmea.experiments import tables

    out.mkdir(parents=True, exist_ok=True)
    scores = tables.score(result)
    stem = f"part-{result.part}"
    markdown = out / f"{stem}.md"
    paths: dict[str, Path | list[Path]] = {
        "markdown": markdown,
        "csv": tables.write_csv(result, out / f"{stem}-markers.csv", scores),
        "samples": tables.write_samples_csv(result, out / f"{stem}-samples.csv"),
    }
    for mode, r in (others or {}).items():
        paths[f"csv-{mode}"] = tables.write_csv(r, out / f"{stem}-{mode}-markers.csv")
        paths[f"samples-{mode}"] = tables.write_samples_csv(r, out / f"{stem}-{mode}-samples.csv")
    markdown.write_text(
        tables.modes_markdown({result.mode: result, **(others or {})}) + "\n")
    if plots:
        from kmea.experiments import plots as plots_mod

        if plots_mod.have_matplotlib():
            paths["plots"] = plots_mod.write_plots(result, out, scores)
        elif not quiet:
            print("kmea experiment: matplotlib not installed (the 'plots' extra): no figures",
                  file=sys.stderr)
    return paths


def run(args: argparse.Namespace) -> int:
    from kmea.experiments.run import ExperimentConfig, run_modes
    from kmea.progress import Progress

    algorithms = _algorithms(args.algorithms)
    if args.baseline not in algorithms:
        print(f"kmea experiment: baseline {args.baseline!r} is not among the algorithms; "
              f"% change is against {algorithms[0]!r}", file=sys.stderr)
        args.baseline = algorithms[0]
    if args.samples < 1:
        raise SystemExit("kmea experiment: --samples must be >= 1")
    out = Path(args.out)
    markers = _ids(args.markers, "--markers")

    if args.replay:
        from kmea.experiments.replay import replay

        if args.part not in (None, "replay"):
            print("kmea experiment: PART is ignored with --replay", file=sys.stderr)
        bar = Progress(min(args.samples, _count_frames(args.replay)), "replay",
                       enabled=not args.quiet)
        return _run_and_write(
            lambda progress: replay(args.replay, algorithms, baseline=args.baseline,
                                    markers=markers, max_frames=args.samples,
                                    progress=progress),
            bar, out, args)

    if args.part is None:
        raise SystemExit("kmea experiment: give a PART (I, II, III, IV or all) or --replay FILE")
    names = list(PARTS) if args.part.lower() == "all" else [args.part]
    try:
        parts = [get_part(n) for n in names]
    except ValueError as e:
        raise SystemExit(f"kmea experiment: {e}") from None
    w, h = _size(args.size)
    default_f, default_k1 = (2.0, 0.02) if args.miscalibrate else (0.0, 0.0)
    focal = args.focal_error if args.focal_error is not None else default_f
    k1 = args.k1_error if args.k1_error is not None else default_k1
    modes = tuple(m.strip() for m in args.modes.split(",") if m.strip())
    from kmea.experiments.run import MODES

    bad = [m for m in modes if m not in MODES]
    if bad or not modes:
        raise SystemExit(f"kmea experiment: --modes: unknown {', '.join(bad) or '(none)'}; "
                         f"choose among {', '.join(MODES)}")
    if not 0.0 < args.iir <= 1.0:
        raise SystemExit("kmea experiment: --iir: ALPHA must be in (0, 1]")
    for spec in parts:
        spec = spec.scaled(args.displacement_scale)
        if markers is not None:
            from dataclasses import replace

            spec = replace(spec, evaluated=markers)
        cfg = ExperimentConfig(part=spec, algorithms=algorithms, baseline=args.baseline,
                               samples=args.samples, seed=args.seed, width=w, height=h,
                               focal_error=focal / 100.0, k1_error=k1,
                               known_heights=args.known_heights, floor_only=args.floor_only,
                               jobs=max(1, args.jobs), modes=modes, iir_alpha=args.iir)
        bar = Progress(cfg.samples, f"Part {spec.name}", enabled=not args.quiet)
        rc = _run_and_write(lambda progress, cfg=cfg: run_modes(cfg, progress=progress),
                            bar, out, args)
        if rc:
            return rc
    return 0


def _run_and_write(run, bar: Progress, out: Path, args: argparse.Namespace) -> int:
    """Run one experiment with its progress bar, then write and report its outputs."""
    try:
        result = run(bar.update)
    except ValueError as e:
        print(f"kmea experiment: {e}", file=sys.stderr)
        return 2
    finally:
        bar.close()
    others = {}
    if isinstance(result, dict):  # every mode of one Part: the first is the primary
        results = list(result.values())
        result, others = results[0], {r.mode: r for r in results[1:]}
    paths = write_outputs(result, out, plots=not args.no_plots, quiet=args.quiet,
                          others=others)
    _report(result, paths, others)
    return 0


def _count_frames(path: str) -> int:
    """Frame lines in a recording (for the progress bar; 0 when unreadable)."""
    try:
        with open(path, "rb") as f:
            return max(sum(1 for _ in f) - 1, 0)
    except OSError:
        return 0


def _report(result, paths: dict, others: dict | None = None) -> None:
    from kmea.experiments import tables

    print(tables.modes_markdown({result.mode: result, **(others or {})}, per_marker=False))
    written = [paths["markdown"], paths["csv"], paths["samples"],
               *(v for k, v in paths.items() if k.startswith(("csv-", "samples-"))),
               *paths.get("plots", [])]
    print("Written: " + ", ".join(str(p) for p in written))
    print()
