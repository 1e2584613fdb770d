"""``kmea map [show|check|convert|survey] [FILE]``: look at, validate, convert or survey a map.

Without FILE the built-in RobotAtFactory 4.0 map is used. A CSV map takes its dictionary
and default marker length from ``--dictionary`` and ``--length``.

``kmea map survey --source SPEC --camera FILE --map FILE --out FILE.csv [--frames N]``
measures every marker the camera sees against the map (see :mod:`kmea.survey`).
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from kmea.estimators import DEFAULT_ALGORITHM
from kmea.maps.files import (
    DEFAULT_DICTIONARY,
    MapError,
    MarkerMap,
    _angles_deg,
    check_map,
    check_spread,
    default_map,
    load_map,
    save_map_toml,
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.description = (__doc__ or "").partition("\n")[0].replace("``", "")
    p.add_argument("action", nargs="?", choices=("show", "check", "convert", "survey"),
                   default="show", help="show the table (default), check the file, convert "
                   "CSV to TOML, or survey the markers a camera sees")
    p.add_argument("file", nargs="?", type=Path, metavar="FILE",
                   help="map file (.toml or .csv); default: the built-in RobotAtFactory 4.0 map")
    p.add_argument("-o", "--output", type=Path, help="convert: TOML file to write "
                   "(default: FILE with the suffix .toml)")
    p.add_argument("--force", action="store_true", help="convert: overwrite the output")
    p.add_argument("--dictionary", default=DEFAULT_DICTIONARY,
                   help=f"CSV maps: ArUco dictionary name (default {DEFAULT_DICTIONARY}: "
                        "RobotAtFactory's DICT_5X5_50 codes are its first 50)")
    p.add_argument("--length", type=float, default=0.06,
                   help="CSV maps: marker side where the file has no length, m (default 0.06)")
    p.add_argument("--origin-id", type=int, help="convert: origin marker id (default 13)")
    p.add_argument("--x-id", type=int, help="convert: +X marker id (default 16)")
    p.add_argument("--y-id", type=int, help="convert: +Y marker id (default 4)")
    p.add_argument("--reference-length", type=float,
                   help="convert: reference length of the MRE, m (default: floor diagonal)")
    p.add_argument("--name", help="convert: map name (default: the file's stem)")
    g = p.add_argument_group("survey")
    g.add_argument("--source", help="survey: frame source spec (images:DIR, video:PATH, "
                   "camera:0, picamera, sim:SCENE, ...)")
    g.add_argument("--camera", help="survey: camera calibration file (a simulated source "
                   "brings its own)")
    g.add_argument("--map", dest="map_file", help="survey: the map (default: FILE, else the "
                   "built-in one)")
    g.add_argument("--out", help="survey: CSV to write (map CSV format)")
    g.add_argument("--frames", type=int, default=30, help="survey: frames to average "
                   "(default 30)")
    g.add_argument("--algorithm", default=DEFAULT_ALGORITHM,
                   help=f"survey: estimator (default {DEFAULT_ALGORITHM})")
    g.add_argument("--level", type=float, default=0.9999,
                   help="survey: significance level of a disagreement (default 0.9999)")


def _load(args: argparse.Namespace) -> MarkerMap:
    if args.file is None:
        return default_map()
    return load_map(args.file, dictionary=args.dictionary, default_length=args.length)


def format_map(m: MarkerMap) -> str:
    """Metadata and marker table of ``m`` (metres; angles in degrees, R = Rx @ Ry @ Rz)."""
    ref = m.ref_length()
    x0, x1, y0, y1 = m.floor_extent()
    lines = [
        f"map        {m.name}  ({m.source})",
        f"dictionary {m.dictionary}",
        f"markers    {len(m)} ({sum(mk.on_floor for mk in m.markers.values())} on the floor)",
        f"anchors    origin {m.origin_id}, +X {m.x_id}, +Y {m.y_id}",
        f"floor      x {x0:+.3f} .. {x1:+.3f} m, y {y0:+.3f} .. {y1:+.3f} m",
        f"reference  {ref:.3f} m"
        + ("" if m.reference_length is not None else " (floor diagonal)"),
        "",
        f"{'id':>4} {'x m':>8} {'y m':>8} {'z m':>8} {'rx deg':>8} {'ry deg':>8} "
        f"{'rz deg':>8} {'len m':>6}",
    ]
    for mid in m.ids:
        mk = m[mid]
        rx, ry, rz = _angles_deg(mk.rotation)
        lines.append(f"{mid:>4} {mk.position[0]:>8.4f} {mk.position[1]:>8.4f} "
                     f"{mk.position[2]:>8.4f} {rx:>8.2f} {ry:>8.2f} {rz:>8.2f} "
                     f"{mk.length:>6.3f}")
    return "\n".join(lines)


def _convert(args: argparse.Namespace) -> int:
    if args.file is None:
        print("kmea map convert: give the CSV FILE to convert", file=sys.stderr)
        return 2
    m = _load(args)
    for attr in ("origin_id", "x_id", "y_id", "name"):
        v = getattr(args, attr)
        if v is not None:
            setattr(m, attr, v)
    if args.reference_length is not None:
        if not (math.isfinite(args.reference_length) and args.reference_length > 0):
            print("kmea map convert: --reference-length must be > 0 m", file=sys.stderr)
            return 2
        m.reference_length = args.reference_length
    out = args.output or args.file.with_suffix(".toml")
    if out.resolve() == args.file.resolve():
        print(f"kmea map convert: {out} is the input file; choose another with -o",
              file=sys.stderr)
        return 2
    if out.exists() and not args.force:
        print(f"kmea map convert: {out} exists (use --force to overwrite)", file=sys.stderr)
        return 1
    save_map_toml(m, out)
    load_map(out)  # the file we wrote must read back (anchors present, values valid)
    print(f"wrote {out}: {len(m)} markers")
    for w in check_map(m):
        print(f"warning: {w}")
    return 0


def _survey(args: argparse.Namespace) -> int:
    from kmea import estimators

    missing = [opt for opt, v in (("--source", args.source), ("--out", args.out)) if not v]
    if missing:
        print(f"kmea map survey: give {', '.join(missing)}", file=sys.stderr)
        return 2
    if args.algorithm not in estimators.available():
        print(f"kmea map survey: --algorithm: unknown {args.algorithm!r}; choose among "
              f"{', '.join(estimators.available())}", file=sys.stderr)
        return 2
    if not 0.5 < args.level < 1.0:
        print("kmea map survey: --level must be between 0.5 and 1", file=sys.stderr)
        return 2
    map_file = args.map_file or (str(args.file) if args.file else None)
    return _run_survey(args.source, args.camera, map_file, args.out, args.frames, args.algorithm,
                   args.level, dictionary=args.dictionary, length=args.length)


def run(args: argparse.Namespace) -> int:
    if args.action == "survey":
        return _survey(args)
    try:
        if args.action == "convert":
            return _convert(args)
        m = _load(args)
        check_spread(m)
        if args.action == "show":
            print(format_map(m))
            for w in check_map(m):
                print(f"warning: {w}")
            return 0
        warnings = check_map(m)
        for w in warnings:
            print(f"{m.source}: warning: {w}")
        print(f"{m.source}: OK, {len(m)} markers, {m.dictionary}"
              + (f", {len(warnings)} warning(s)" if warnings else ""))
        return 0
    except MapError as e:
        print(f"kmea map: {e}", file=sys.stderr)
        return 1


def _frames_from(source, n: int, errors: list[str]) -> Iterable[np.ndarray]:
    from kmea.vision.detection import as_gray

    got = 0
    while got < n:
        f = source.read()
        if f is None:
            return
        if f.image is None:
            errors.append(str(f.meta.get("error", "unreadable frame")))
            continue
        got += 1
        yield as_gray(f.image)


def _run_survey(source_spec: str, camera_file: str | None, map_file: str | None, out: str,
            frames: int,
            algorithm: str = DEFAULT_ALGORITHM, level: float = 0.9999,
            dictionary: str | None = None, length: float | None = None,
            quiet: bool = False) -> int:
    """``kmea map survey``; returns the exit code."""
    from kmea.maps.files import MapError, default_map, load_map
    from kmea.progress import Progress
    from kmea.sources.base import SourceError
    from kmea.sources.registry import open_source
    from kmea.survey import format_report, survey_frames, write_csv
    from kmea.vision.camera import CameraError, load_camera, model_for_frame

    if frames < 1:
        print("kmea map survey: --frames must be >= 1", file=sys.stderr)
        return 2
    try:
        kw = {}
        if dictionary:
            kw["dictionary"] = dictionary
        if length:
            kw["default_length"] = length
        world_map = default_map() if map_file is None else load_map(map_file, **kw)
        camera = load_camera(camera_file) if camera_file else None
    except (MapError, CameraError, OSError) as e:
        print(f"kmea map survey: {e}", file=sys.stderr)
        return 1
    try:
        source = open_source(source_spec)
    except (SourceError, ValueError) as e:
        print(f"kmea map survey: {e}", file=sys.stderr)
        return 1
    if camera is None:
        # A simulated source knows its camera; a real one needs its calibration file.
        camera = getattr(source, "camera", None)
        if camera is None:
            source.close()
            print(f"kmea map survey: {source_spec}: give --camera FILE (the calibration)",
                  file=sys.stderr)
            return 2
    errors: list[str] = []

    bar = Progress(frames, "kmea map survey", enabled=not quiet)

    def progress(k: int, seen: int) -> None:
        bar.update(k + 1 - bar.done, note=f"{seen} markers seen")

    try:
        first = next(iter(_frames_from(source, 1, errors)), None)
        if first is None:
            print(f"kmea map survey: {source_spec}: no frame", file=sys.stderr)
            return 1
        h, w = first.shape[:2]
        try:
            camera = model_for_frame(camera, w, h)
        except (CameraError, ValueError) as e:
            print(f"kmea map survey: {camera_file}: {e}", file=sys.stderr)
            return 1

        def all_frames():
            yield first
            yield from _frames_from(source, frames - 1, errors)

        survey = survey_frames(all_frames(), world_map, camera, algorithm, level,
                               progress=progress)
    finally:
        source.close()
        bar.close()
    for e in errors[:5]:
        print(f"kmea map survey: skipped frame: {e}", file=sys.stderr)
    write_csv(survey, out)
    print(format_report(survey))
    print(f"wrote {out}: {len(survey.markers)} markers")
    return 0

