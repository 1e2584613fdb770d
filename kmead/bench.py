"""Daemon benchmarks (``kmea bench daemon`` / ``kmea bench latency``): figures, no asserts.

daemon: frames/s of the whole daemon (detection, pose, estimator, leave-one-out, filter,
robots, relay, CSV, telemetry) on pre-rendered 1640x1232 simulator frames (rendering not
counted), beside the rate of bare ``detectMarkers`` on the same frames, with 1 and 2
detection threads (``detector.workers``). The library's own figures (detection variants,
the pipeline in one thread) are ``kmea bench pipeline`` (:mod:`kmea.benchmarks.pipeline`).
latency: frame-to-UDP-datagram latency at 30 frames/s from the paced simulator, measured by
a real UDP receiver (arrival time minus the datagram's capture timestamp).
"""

from __future__ import annotations

import socket
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from kmea.benchmarks.pipeline import bare_detection, render
from kmea.sim.source import SimSource
from kmea.vision.sources import register_source
from kmead.config import load_config
from kmead.daemon import Daemon
from kmead.relay import parse_datagram

NET = ['network.telemetry="tcp://127.0.0.1:*"', 'network.control="tcp://127.0.0.1:*"']


_BENCH: dict = {}
# The pre-rendered frames, served by the simulator source (rendering not counted).
register_source("bench", lambda rest, **o: SimSource(_BENCH["scene"], rendered=_BENCH["frames"]))


def _daemon_fps(tmp: str, sets: list[str]) -> tuple[float, dict, Daemon]:
    """Frames/s of a whole daemon on the pre-rendered frames, and mean stage times (ms)."""
    d = Daemon(load_config(None, ["source.spec=bench", *NET,
                                  f'log.csv="{Path(tmp) / "bench.csv"}"', *sets]))
    try:
        d.run()
    finally:
        d.close()
    t = d.totals
    return t.frames / (t.t_end - t.t_start), {k: v / t.frames for k, v in t.timing_sums.items()}, d


def run_daemon(quick: bool = False) -> None:
    n = 20 if quick else 90
    frames, scene = render(n)
    _BENCH.update(frames=frames, scene=scene)
    bare, _ = bare_detection([f.image for f in frames], {}, scene.world_map.dictionary)
    print(f"{n} pre-rendered frames {scene.size[0]}x{scene.size[1]}; bare detectMarkers "
          f"{bare:6.1f} frames/s")
    with tempfile.TemporaryDirectory() as tmp:
        for label, sets in (("main thread only (workers=0)", ["detector.workers=0"]),
                            ("detection thread ahead (workers=1)", ["detector.workers=1"]),
                            ("two detection threads (workers=2)", ["detector.workers=2"]),
                            ("fast detection, workers=0", ["detector.workers=0",
                                                           "detector.fast=true"]),
                            ("fast detection, workers=1", ["detector.workers=1",
                                                           "detector.fast=true"])):
            fps, ms, d = _daemon_fps(tmp, sets)
            rest = ms["total"] - ms["detect"] - ms["capture"]
            print(f"pipeline, {label}: {fps:6.1f} frames/s = {fps / bare * 100:5.1f} % of bare "
                  f"default detection; markers seen {len(d.totals.markers_seen)}; stage "
                  "ms/frame: " + ", ".join(f"{k} {v:.2f}" for k, v in ms.items()
                                           if k != "capture")
                  + f"; non-detection stages {rest:.2f} ms = {rest / ms['total'] * 100:.0f} %")


def run_latency(quick: bool = False) -> None:
    n = 60 if quick else 300
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(0.5)
    port = rx.getsockname()[1]
    lat: list[float] = []
    stop = threading.Event()

    def receive() -> None:
        while not stop.is_set():
            try:
                data = rx.recv(256)
            except TimeoutError:
                continue
            m = parse_datagram(data)
            if m["valid"]:
                lat.append((time.time() - m["t"]) * 1e3)

    robots = (f'robots=[{{name="amr1", markers=[40, 41], destinations=["udp:127.0.0.1:{port}"]}},'
              f' {{name="amr2", markers=[42], destinations=["udp:127.0.0.1:{port}"]}}]')
    for (w, h), workers in (((640, 480), 0), ((640, 480), 1), ((1640, 1232), 0),
                            ((1640, 1232), 1)):
        lat.clear()
        stop.clear()
        th = threading.Thread(target=receive, daemon=True)
        th.start()
        cfg = load_config(None, ["source.spec=sim", "source.fps=30", f"source.width={w}",
                                 f"source.height={h}", f"detector.workers={workers}", robots,
                                 *NET])
        d = Daemon(cfg, max_frames=n)
        try:
            d.run()
        finally:
            d.close()
            stop.set()
            th.join()
        t = d.totals
        a = np.asarray(lat)
        print(f"sim {w}x{h} paced at 30 frames/s, detector.workers={workers}: "
              f"{t.frames} frames processed, "
              f"{d.capture.captured if d.capture else 0} captured, "
              f"{d.dropped} dropped; frame-to-datagram latency over {a.size} datagrams: "
              f"median {np.median(a):.1f} ms, p99 {np.percentile(a, 99):.1f} ms")
    rx.close()
