"""``python -m kmea.sim``: write rendered frames (PNG) and their truth (JSON lines).

Example: ``python -m kmea.sim "sim:default?width=640&height=480" --frames 90 --out /tmp/sim``
writes ``frame_000000.png`` ... and ``truth.jsonl`` (one line per frame: index, t seconds,
robots {name: [x, y, theta]} in m and rad, visible ids, corners {id: 4 x [u, v]} px,
markers {id: 4 x 4 marker2world}).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2

from kmea.sim.renderer import FrameTruth, Renderer
from kmea.sim.scenes import available_scenes, scene_from_spec
from kmea.wire.jsonsafe import to_jsonable


def truth_record(index: int, truth: FrameTruth) -> dict:
    """A JSON-ready dict of one frame's truth."""
    return to_jsonable({
        "index": index, "t": truth.t, "robots": truth.robots, "visible": truth.visible,
        "corners": dict(sorted(truth.corners.items())),
        "markers": dict(sorted(truth.markers.items())), "cam2world": truth.cam2world})


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m kmea.sim",
                                description=(__doc__ or "").partition("\n")[0])
    p.add_argument("spec", nargs="?", default="sim",
                   help="scene spec: sim, sim:NAME, sim:NAME?key=value&... (scenes: "
                        f"{', '.join(available_scenes())})")
    p.add_argument("--frames", type=int, default=30, help="number of frames (default 30)")
    p.add_argument("--start", type=int, default=0, help="first frame index (default 0)")
    p.add_argument("--step", type=int, default=1, help="index step (default 1)")
    p.add_argument("--out", type=Path, required=True, help="output folder (created)")
    args = p.parse_args(argv)
    if args.frames < 1 or args.start < 0 or args.step < 1:
        p.error("--frames and --step must be >= 1, --start >= 0")
    try:
        scene = scene_from_spec(args.spec)
    except ValueError as e:
        print(f"python -m kmea.sim: {e}", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    r = Renderer(scene)
    with open(args.out / "truth.jsonl", "w") as f:
        for k in range(args.frames):
            i = args.start + k * args.step
            frame = r.render(i)
            cv2.imwrite(str(args.out / f"frame_{i:06d}.png"), frame.pixels)
            f.write(json.dumps(truth_record(i, frame.truth)) + "\n")
    print(f"{args.frames} frames of {scene.name} ({scene.size[0]}x{scene.size[1]}) in {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
