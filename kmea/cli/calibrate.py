"""``kmea calibrate``: calibrate a camera from views of a chessboard or ChArUco board.

Example: ``kmea calibrate --source images:shots/ --board chessboard:9x7:0.025 --out cam.yml``.
Live sources (``camera:0``, ``picamera``) run until ``--max-views`` views are accepted or
Ctrl+C, then calibrate with what they have. An autofocus camera's lens position (what
the camera reports in its frames' metadata, ``picamera?lens_position=D`` to choose it) is
written beside the model as ``lens_position``: the calibration holds at that focus only
(:mod:`kmea.vision.lens`). See ``docs/camera.md``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

__all__ = ["add_arguments", "run"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.description = (__doc__ or "").partition("\n")[0].partition(": ")[2]
    p.add_argument("--source", required=True, metavar="SPEC",
                   help="images:DIR, video:PATH, camera:INDEX or picamera "
                        "(options after '?', e.g. camera:0?width=1280&height=960)")
    p.add_argument("--board", required=True, metavar="BOARD",
                   help="chessboard:COLSxROWS:SQUARE_M (inner corners) or "
                        "charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT (squares)")
    p.add_argument("--out", required=True, metavar="FILE",
                   help="camera file to write (.yml, .yaml, .xml, .json or .toml)")
    p.add_argument("--max-views", type=int, default=40, metavar="N",
                   help="stop after N accepted views (default 40)")
    p.add_argument("--min-views", type=int, default=8, metavar="N",
                   help="refuse to calibrate with fewer views (default 8)")
    p.add_argument("--max-frames", type=int, default=None, metavar="N",
                   help="stop after N frames (default: the end of a file source)")
    p.add_argument("--drop-outliers", action="store_true",
                   help="drop views whose error exceeds 2x the median view error, recalibrate")
    p.add_argument("--blur-threshold", type=float, default=30.0, metavar="V",
                   help="minimum variance of the Laplacian over the board (default 30; 0: off)")
    p.add_argument("--min-move", type=float, default=None, metavar="PX",
                   help="mean corner motion that makes a new view (default 2%% of the diagonal)")
    p.add_argument("--subpix-window", type=int, default=None, metavar="PX",
                   help="chessboard cornerSubPix half-window (default: half the corner spacing, "
                        "at most 11)")
    p.add_argument("--worst", type=int, default=5, metavar="N",
                   help="list the N worst views (default 5)")
    p.add_argument("-q", "--quiet", action="store_true", help="no per-frame lines")


def _err(msg: str) -> int:
    print(f"kmea calibrate: error: {msg}", file=sys.stderr)
    return 2


def run(args: argparse.Namespace) -> int:
    from kmea.sources.base import SourceError
    from kmea.sources.files import ImageFolderSource
    from kmea.sources.registry import open_source
    from kmea.vision.calibration import BoardError, Calibrator, parse_board
    from kmea.vision.camera import FILESTORAGE_SUFFIXES, CameraError, save_camera

    out = Path(args.out)
    if out.suffix.lower() not in (*FILESTORAGE_SUFFIXES, ".toml"):
        return _err(f"--out {out}: use .yml, .yaml, .xml, .json or .toml")
    if not out.parent.is_dir():
        return _err(f"--out {out}: folder {out.parent} does not exist")
    if args.max_views < 1 or args.min_views < 3:
        return _err("--max-views must be >= 1 and --min-views >= 3")
    try:
        board = parse_board(args.board)
    except BoardError as e:
        return _err(f"--board {e}")
    try:
        source = open_source(args.source)
    except SourceError as e:
        return _err(str(e))

    if args.subpix_window is not None and args.subpix_window < 1:
        return _err("--subpix-window must be >= 1")
    cal = Calibrator(board, blur_threshold=args.blur_threshold, min_move_px=args.min_move,
                     subpix_window=args.subpix_window)
    per_file = isinstance(source, ImageFolderSource)
    total = len(source) if hasattr(source, "__len__") else None  # type: ignore[arg-type]
    interrupted = False
    lens: list[float] = []  # dioptres, as each frame's metadata reports (autofocus cameras)
    with source:
        try:
            for frame in source:
                # one file per frame: its name; videos and cameras: the frame number
                name = Path(frame.meta["path"]).name if per_file and "path" in frame.meta \
                    else f"frame {frame.index}"
                check = cal.add(frame.image, name)
                if check.accepted and frame.meta.get("lens_position") is not None:
                    lens.append(float(frame.meta["lens_position"]))
                if not args.quiet and (check.accepted or not source.live):
                    where = f"[{frame.index + 1}/{total}]" if total else f"[{frame.index + 1}]"
                    detail = f" ({check.detail})" if check.detail else ""
                    if frame.error:
                        detail = f" ({frame.error})"
                    print(f"{where} {name}: {check.status}{detail}; views {len(cal.views)}/"
                          f"{cal.seen} seen, coverage {100 * cal.coverage():.0f}%", flush=True)
                elif not args.quiet and source.live and cal.seen % 30 == 0:
                    print(f"[{frame.index + 1}] views {len(cal.views)}/{cal.seen} seen, coverage "
                          f"{100 * cal.coverage():.0f}%; move the board (Ctrl+C to finish)",
                          flush=True)
                if len(cal.views) >= args.max_views:
                    print(f"reached --max-views {args.max_views}")
                    break
                if args.max_frames and cal.seen >= args.max_frames:
                    break
        except KeyboardInterrupt:
            interrupted = True
            print("\ninterrupted: calibrating with the views so far")
        except SourceError as e:
            print(f"kmea calibrate: warning: {e}; calibrating with the views so far",
                  file=sys.stderr)

    counts = ", ".join(f"{n} {s}" for s, n in sorted(cal.counts.items()))
    print(f"{cal.seen} frames: {counts}; coverage {100 * cal.coverage():.0f}% of the image")
    if len(cal.views) < args.min_views:
        print(f"kmea calibrate: error: {len(cal.views)} usable views, need --min-views "
              f"{args.min_views}", file=sys.stderr)
        return 130 if interrupted else 1
    try:
        res = cal.calibrate(drop_outliers=args.drop_outliers, min_views=args.min_views)
    except Exception as e:  # cv2.error on degenerate view sets
        print(f"kmea calibrate: error: calibration failed: {e}", file=sys.stderr)
        return 1
    m = res.model
    if res.dropped:
        names = ", ".join(f"{n} ({e:.2f} px)" for n, e in res.dropped)
        print(f"dropped {len(res.dropped)} outlier view(s): {names}; RMS before "
              f"{res.rms_all:.3f} px")
    print(f"calibrated {m.width}x{m.height} from {res.n_views} views: RMS reprojection error "
          f"{res.rms:.3f} px")
    print(f"  fx {m.fx:.2f}  fy {m.fy:.2f}  cx {m.cx:.2f}  cy {m.cy:.2f} (px)")
    print("  dist " + " ".join(f"{v:.4f}" for v in m.dist_coeffs) + " (k1 k2 p1 p2 k3)")
    worst = ", ".join(f"{n} {e:.2f} px" for n, e in res.view_errors[:max(args.worst, 0)])
    if worst:
        print(f"  worst views: {worst}")
    if res.rms > 1.0:
        print(f"warning: RMS {res.rms:.2f} px is high for a calibration (expect < 0.5 px): blurred "
              f"views, a wrong board size, or a --subpix-window wider than half the corner "
              f"spacing")
    print(f"note: the square size ({board.square:g} m) only scales the board poses "
          f"(extrinsics); the intrinsics above do not depend on it.")
    meta = {"rms": round(res.rms, 6), "nr_of_frames": res.n_views, "board": board.spec,
            "source": args.source}
    if lens:
        from kmea.vision.lens import LENS_KEY, LENS_TOL_DIOPTRE

        lens.sort()
        meta[LENS_KEY] = round(lens[len(lens) // 2], 4)
        print(f"  lens position {meta[LENS_KEY]:g} dioptres (the focus this calibration holds "
              f"at; kmead locks the lens there)")
        if lens[-1] - lens[0] > LENS_TOL_DIOPTRE:
            print(f"warning: the lens moved during calibration ({lens[0]:g}-{lens[-1]:g} "
                  f"dioptres): calibrate again with a fixed lens position "
                  f"(picamera?lens_position=D)")
    try:
        save_camera(m, out, meta=meta)
    except CameraError as e:
        return _err(str(e))
    print(f"wrote {out}")
    return 130 if interrupted else 0
