"""``kmea print``: printable markers, the whole floor at 1:1, ChArUco boards (PNG or PDF).

Examples::

    kmea print marker 13 --size-mm 60 --out m13.pdf
    kmea print floor --dpi 150 --out floor.pdf            # the RobotAtFactory 4.0 floor
    kmea print charuco 7x5 --square-mm 30 --marker-mm 22 --out board.pdf
"""

from __future__ import annotations

import argparse
import re
import sys

from kmea.maps.model import DEFAULT_DICTIONARY

__all__ = ["add_arguments", "run"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.description = (__doc__ or "").splitlines()[0].split(": ", 1)[1]
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--dpi", type=float, default=None,
                        help="resolution (default 300; floor: 150)")
    common.add_argument("--out", default=None, metavar="FILE",
                        help="output .png (DPI stored) or .pdf (page size = print size)")
    sub = p.add_subparsers(dest="what", required=True, metavar="WHAT")
    m = sub.add_parser("marker", parents=[common], help="one ArUco marker")
    m.add_argument("id", type=int)
    m.add_argument("--dict", default=DEFAULT_DICTIONARY,
                   help=f"dictionary name or file (default {DEFAULT_DICTIONARY})")
    m.add_argument("--size-mm", type=float, default=None,
                   help="black square side (default: the marker's side in the map, else 60)")
    m.add_argument("--map", default=None, metavar="FILE",
                   help="map .toml/.csv whose size for the marker to use (default: the "
                        "built-in RobotAtFactory 4.0 map)")
    m.add_argument("--margin-mm", type=float, default=12.0, help="white margin (default 12)")
    f = sub.add_parser("floor", parents=[common], help="the map's floor markers at 1:1")
    f.add_argument("--map", default=None, metavar="FILE",
                   help="map .toml/.csv (default: the built-in RobotAtFactory 4.0 map)")
    f.add_argument("--dict", default=None,
                   help=f"dictionary of a CSV map (default {DEFAULT_DICTIONARY})")
    f.add_argument("--canvas", default="1.7x1.2", metavar="WxH",
                   help="canvas size in metres (default 1.7x1.2)")
    c = sub.add_parser("charuco", parents=[common], help="a ChArUco calibration board")
    c.add_argument("size", metavar="COLSxROWS", help="squares, e.g. 7x5")
    c.add_argument("--square-mm", type=float, default=30.0, help="square side (default 30)")
    c.add_argument("--marker-mm", type=float, default=22.0, help="marker side (default 22)")
    c.add_argument("--dict", default=DEFAULT_DICTIONARY, help="predefined dictionary")


def _err(msg: str) -> int:
    print(f"kmea print: error: {msg}", file=sys.stderr)
    return 2


def _marker_size(args: argparse.Namespace) -> tuple[float, str]:
    """The side to print (mm) and a line saying where it came from: --size-mm, else the
    marker's side in the map (a wall marker of the built-in map is 40 mm), else 60."""
    from kmea.maps.files import default_map, load_map

    if args.size_mm is not None:
        return args.size_mm, ""
    mp = load_map(args.map, dictionary=args.dict) if args.map else default_map()
    if args.id in mp:
        side = mp[args.id].length * 1000.0
        return side, f"marker {args.id}: {side:g} mm, its side in the map {mp.name}"
    return 60.0, f"marker {args.id}: not in the map {mp.name}: printed at 60 mm"


def run(args: argparse.Namespace) -> int:
    from kmea.vision.printing import charuco_page, floor_page, marker_page, save_printable

    try:
        if args.what == "marker":
            size_mm, note = _marker_size(args)
            page = marker_page(args.id, args.dict, size_mm, args.dpi or 300.0,
                               args.margin_mm)
            if note:
                print(note)
            out = args.out or f"marker_{args.id}.png"
        elif args.what == "floor":
            from kmea.maps.files import MapError, default_map, load_map

            try:
                mp = (load_map(args.map, dictionary=args.dict or DEFAULT_DICTIONARY)
                      if args.map else default_map())
            except MapError as e:
                return _err(str(e))
            m = re.fullmatch(r"\s*([\d.]+)\s*[xX]\s*([\d.]+)\s*", args.canvas)
            if not m:
                return _err(f"--canvas {args.canvas!r}: expected WxH in metres, e.g. 1.7x1.2")
            page = floor_page(mp, args.dpi or 150.0, (float(m.group(1)), float(m.group(2))))
            out = args.out or "floor.pdf"
        else:
            m = re.fullmatch(r"(\d+)[xX](\d+)", args.size)
            if not m:
                return _err(f"{args.size!r}: expected COLSxROWS squares, e.g. 7x5")
            page = charuco_page(int(m.group(1)), int(m.group(2)), args.square_mm,
                                args.marker_mm, args.dict, args.dpi or 300.0)
            out = args.out or f"charuco_{args.size}.pdf"
        path = save_printable(page, out)
    except ValueError as e:  # includes DictionaryError
        return _err(str(e))
    w_mm, h_mm = page.size_mm
    h, w = page.image.shape
    print(f"wrote {path}: {page.title}; {w}x{h} px at {page.dpi:g} dpi = "
          f"{w_mm:.1f} x {h_mm:.1f} mm (print at 100 %, no 'fit to page')")
    return 0
