"""What a recording costs: bytes a frame, bytes an hour at 30 frames/s, CPU a frame written.

    kmea bench recording-size [--frames N] [--candidates]

The same frames are written in every format (like with like): what a real daemon (in this
process, on the simulated floor: 1640x1232, 35-40 markers, two robots) hands its recorder,
in two cases:

- ``fast path``: the daemon's default on a live source (``detector.fixed_camera``): a fixed
  marker keeps its observation between the floor's refits, so most of a frame repeats the
  last one;
- ``every frame new``: ``detector.fixed_camera = false``: every corner and every pose is
  measured afresh, every number changes (the worst case for compression).

Formats: ``v1`` is the first format's writer (every marker's corners and flags, plain JSON
lines: what ``--record run.jsonl`` wrote before format version 2); ``v2 plain`` and ``v2
.zst`` are :class:`kmea.recordings.format.Recorder` today (``run.jsonl`` and ``run.jsonl.zst``).
``--candidates`` adds what was measured to choose: gzip (stdlib zlib, a sync flush every
frame) and MCAP chunks (the ``mcap`` package, zstd and lz4, 1 MB chunks: durable only when a
chunk closes). CPU is ``time.process_time`` of encoding, compressing and writing every frame
to a real file, divided by the frames (the median of ``--runs`` runs).
"""

from __future__ import annotations

import argparse
import json
import logging
import statistics
import sys
import tempfile
import time
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

from kmea.recordings.format import Recorder, _arr, _num
from kmea.wire.jsonsafe import to_jsonable
from kmead.config.layers import load_config
from kmead.outputs.totals import truth_record
from kmead.run.daemon import Daemon

FPS = 30.0
CASES = {"fast path": [], "every frame new": ["detector.fixed_camera=false"]}


class Run(NamedTuple):
    frames: list[tuple]
    camera: Any
    world_map: Any
    config: dict


def capture(frames: int, extra: list[str]) -> tuple[list[tuple], Any, Any, dict]:
    """The frames a real daemon (in this process, on the simulator) hands its recorder:
    (frames, camera, map, configuration). Each frame as ``Recorder.write_frame`` takes it."""
    logging.getLogger("kmead").setLevel(logging.WARNING)
    cfg = load_config(None, [*extra, 'network.telemetry="tcp://127.0.0.1:*"',
                             'network.control="tcp://127.0.0.1:*"'])
    d = Daemon(cfg, max_frames=frames)
    got: list[tuple] = []
    outputs = d._outputs

    def grab(res: Any) -> None:
        truth = res.meta.get("truth")
        got.append((res.index, res.timestamp, res.ids, res.corners, list(res.observations),
                    dict(res.diagnostics), truth_record(truth) if truth is not None else None))
        outputs(res)

    d._outputs = grab
    try:
        d.run()
    finally:
        d.close()
    return got, d.pipeline.camera, d.world_map, cfg.to_dict()


def v1_line(index, t, ids, corners, obs, diag, truth) -> bytes:
    """A frame as format version 1 wrote it (kmea/recordings/format.py before version 2)."""
    line = {"frame": int(index), "t": float(t), "ids": [int(i) for i in ids],
            "corners": [_arr(c) for c in corners],
            "markers": [{"id": int(o.id), "R": _arr(o.marker2cam_R), "t": _arr(o.marker2cam_t),
                         "corners": _arr(o.corners), "length": float(o.length),
                         "reproj": _num(o.reproj_error), "alt_R": _arr(o.alt_R),
                         "alt_t": _arr(o.alt_t), "alt_reproj": _num(o.alt_reproj_error),
                         "ambiguous": bool(o.ambiguous), "flipped": bool(o.flipped),
                         "suspect": bool(o.suspect)} for o in obs],
            "diag": to_jsonable(diag)}
    if truth is not None:
        line["truth"] = to_jsonable(truth)
    return (json.dumps(line, separators=(",", ":"), allow_nan=False) + "\n").encode()


def write_v1(out: Path, run: Run) -> int:
    header = Recorder(out, run.camera, run.world_map, "sim", run.config)  # its header line
    header.close()
    head = out.read_bytes().replace(b'"version":2', b'"version":1')
    with open(out, "wb", buffering=0) as f:
        f.write(head)
        for fr in run.frames:
            f.write(v1_line(*fr))
    return len(head)


def write_recorder(out: Path, run: Run) -> int:
    rec = Recorder(out, run.camera, run.world_map, "sim", run.config)
    head = rec.bytes
    for fr in run.frames:
        rec.write_frame(*fr)
    rec.close()
    return head


def write_gzip(out: Path, run: Run) -> int:
    from kmea.recordings.format import frame_to_json

    z = zlib.compressobj(6, zlib.DEFLATED, 31)
    with open(out, "wb", buffering=0) as f:
        for fr in run.frames:
            line = json.dumps(frame_to_json(*fr), separators=(",", ":")).encode() + b"\n"
            f.write(z.compress(line) + z.flush(zlib.Z_SYNC_FLUSH))
        f.write(z.flush())
    return 0  # no header written


def write_mcap(kind: str) -> Callable[[Path, Run], int]:
    def write(out: Path, run: Run) -> int:
        from mcap.writer import CompressionType, Writer

        from kmea.recordings.format import frame_to_json

        with open(out, "wb") as f:
            w = Writer(f, chunk_size=1 << 20, compression=getattr(CompressionType, kind))
            w.start("kmead-recording", "kmea")
            schema = w.register_schema("kmead.Frame", "jsonschema", b"{}")
            ch = w.register_channel("/frames", "json", schema)
            for fr in run.frames:
                ns = int(fr[1] * 1e9)
                w.add_message(ch, log_time=ns, publish_time=ns, data=json.dumps(
                    frame_to_json(*fr), separators=(",", ":")).encode())
            w.finish()
        return 0  # no header written
    return write


def measure(write, run: Run, out: Path, runs: int) -> tuple[float, float]:
    """(bytes a frame, CPU ms a frame) of writing the run's frames to ``out``; the header
    (once a file, about 8 KB) is not counted."""
    cpu = []
    for _ in range(runs):
        out.unlink(missing_ok=True)
        t0 = time.process_time()
        head = write(out, run)
        cpu.append((time.process_time() - t0) / len(run.frames) * 1e3)
    return (out.stat().st_size - head) / len(run.frames), statistics.median(cpu)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="kmea bench recording-size",
                                 description=(__doc__ or "").split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--candidates", action="store_true",
                    help="also gzip and MCAP (zstd, lz4), the formats measured to choose")
    args = ap.parse_args(argv)
    formats: dict[str, tuple[str, Callable]] = {
        "v1 (before)": (".jsonl", write_v1), "v2 plain": (".jsonl", write_recorder),
        "v2 .zst (now)": (".jsonl.zst", write_recorder)}
    if args.candidates:
        formats.update({"v2 gzip": (".jsonl.gz", write_gzip),
                        "v2 MCAP zstd": (".mcap", write_mcap("ZSTD")),
                        "v2 MCAP lz4": (".mcap", write_mcap("LZ4"))})
    print(f"{args.frames} frames of the simulated floor (1640x1232), written {args.runs} times; "
          f"hour = {FPS:g} frames/s x 3600 s")
    print(f"{'frames':16} {'format':15} {'bytes/frame':>11} {'GB/hour':>8} {'CPU ms/frame':>12}")
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        for case, extra in CASES.items():
            run = Run(*capture(args.frames, extra))
            markers = statistics.mean(len(f[4]) for f in run.frames)
            for name, (suffix, write) in formats.items():
                per, cpu = measure(write, run, tmp / f"out{suffix}", args.runs)
                print(f"{case:16} {name:15} {per:11.0f} {per * FPS * 3600 / 1e9:8.3f} "
                      f"{cpu:12.2f}")
            print(f"{'':16} ({markers:.1f} markers a frame)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
