"""Regenerate the UI's recorded test stream from a real daemon run.

    .venv/bin/python scripts/record_telemetry.py            # writes tests/data/telemetry_sim.jsonl

Starts ``kmead`` (a subprocess, headless, the simulated floor with a moved marker and two
robots, paced so a subscriber sees every message), records its telemetry with the UI's own
client (typed decoding, :func:`kmea.wire.protocol.decode`) up to frame ``--last``, asks it for
``get_config`` and ``get_state`` (the replay's header), stops it and keeps the last
``--keep`` frames (:func:`kmea_tui.client.trim_messages`). The daemon runs full detection
on every frame (``detector.fixed_camera = false``; see :func:`start_daemon`). Every message
in the file came from the daemon unchanged (floats rounded to 6 digits). After
regenerating, update the snapshots (``pytest tests/test_tui_snapshots.py
tests/test_tui_suspect.py --snapshot-update``) and look at them.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from kmea.wire import protocol  # noqa: E402
from kmea_tui.client import DaemonClient, trim_messages  # noqa: E402

SCENE = "sim:misplaced?robots=true"
OUT = ROOT / "tests" / "data" / "telemetry_sim.jsonl"


def start_daemon(cwd: Path, scene: str, fps: float) -> tuple[subprocess.Popen, str, str]:
    """kmead on ``scene``; returns the process and its bound telemetry/control endpoints."""
    err = open(cwd / "kmead.err", "w")  # noqa: SIM115 - closed with the process
    cmd = [sys.executable, "-m", "kmead.cli", "--source", scene, "--headless",
           "--log", "out/run.csv",
           "--set", 'network.telemetry="tcp://127.0.0.1:*"',
           "--set", 'network.control="tcp://127.0.0.1:*"',
           "--set", f"source.fps={fps}", "--set", "network.status_period_s=1.0",
           # Full detection on every frame: the stream shows the suspect flag (frame 32:
           # amr2's plate over a corner of marker 25), which the fixed-camera path (the
           # default for a paced source) never has to raise for a floor marker - it
           # reports one at its reference corners, or not at all until it is seen cleanly
           # (tests/test_fixed_camera_suspect.py).
           "--set", "detector.fixed_camera=false"]
    proc = subprocess.Popen(cmd, cwd=cwd, stdout=subprocess.DEVNULL, stderr=err)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        text = (cwd / "kmead.err").read_text()
        m = re.search(r"telemetry (tcp://\S+), control (tcp://\S+)", text)
        if m:
            return proc, m.group(1), m.group(2)
        if proc.poll() is not None:
            raise RuntimeError(f"kmead exited with {proc.returncode}:\n{text}")
        time.sleep(0.05)
    proc.kill()
    raise RuntimeError("kmead did not report its endpoints")


async def record(telemetry: str, control: str, last: int,
                 timeout: float) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """Messages up to the ``frame`` message of frame ``last``, then the header replies."""
    client = DaemonClient(telemetry, control, timeout=5.0)
    await client.open()
    records: list[dict[str, Any]] = []
    t_last: float | None = None
    try:
        end = time.monotonic() + timeout
        done = False
        while not done:
            if time.monotonic() > end:
                raise RuntimeError(f"frame {last} not seen within {timeout:g} s")
            for topic, body in await client.recv(0.1):
                if body.get("frame") is not None and body["frame"] > last:
                    continue
                t = time.monotonic()
                records.append({"topic": topic, "body": body,
                                "dt": 0.0 if t_last is None else round(t - t_last, 4)})
                t_last = t
                if topic == protocol.TOPIC_FRAME and body["frame"] == last:
                    done = True
                    break
        header: dict[str, Any] = {"telemetry": telemetry}
        for cmd in ("get_config", "get_state"):
            reply = await client.request(cmd)
            if not reply.get("ok"):
                raise RuntimeError(f"{cmd}: {reply.get('error')}")
            header[cmd] = reply
        if client.bad_messages:
            raise RuntimeError(f"{client.bad_messages} messages did not follow the protocol: "
                               f"{client.last_error}")
    finally:
        client.close()
    return header, records


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, default=OUT, help="default %(default)s")
    p.add_argument("--scene", default=SCENE, help="simulator source (default %(default)s)")
    p.add_argument("--last", type=int, default=32, help="last frame recorded (default 32: "
                   "a robot's plate hides a corner of marker 25)")
    p.add_argument("--keep", type=int, default=5, help="frames kept (default %(default)s)")
    p.add_argument("--fps", type=float, default=5.0,
                   help="the daemon's pace, frames/s (default %(default)s)")
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        proc, telemetry, control = start_daemon(Path(tmp), args.scene, args.fps)
        try:
            header, records = asyncio.run(record(telemetry, control, args.last,
                                                 timeout=60 + 3 * args.last / args.fps))
        finally:
            proc.terminate()
            proc.wait(timeout=30)
    records = trim_messages(records, args.keep)
    lines = [json.dumps({"header": header}, separators=(",", ":"))]
    lines += [json.dumps(r, separators=(",", ":")) for r in records]
    args.out.write_text("\n".join(lines) + "\n", encoding="utf-8")
    print(f"wrote {len(records)} messages (frames {args.last - args.keep + 1}-{args.last}) "
          f"to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
