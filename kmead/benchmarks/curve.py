"""Telemetry throughput and latency over loopback TCP, plain and with CURVE, in one run.

    kmea bench curve [--messages N] [--size BYTES] [--rate HZ]

Both modes use the daemon's own set-up: a PUB socket made a CURVE server by
``kmead.net.keys.CurveServer`` (ZAP handler, key directory from ``kmead.net.keys.init_keys``) and a
SUB client connected with ``kmead.net.keys.connect_client``; the plain mode the same sockets
without keys. Each mode runs in its own pair of ZeroMQ contexts (publisher, subscriber).

- throughput: N messages of ``--size`` bytes (default: a 50-marker ``markers`` body, the
  largest message the daemon sends every frame) published back to back; messages received
  per second, first send to last receive;
- latency: messages published at ``--rate`` Hz, each carrying its send time
  (``time.perf_counter``, one process, one clock); p50 / p99 / max of receive - send.

Plain and CURVE alternate ``--runs`` times and the medians are printed, so both modes see
the same machine load.
"""

from __future__ import annotations

import argparse
import json
import statistics
import struct
import sys
import tempfile
import threading
import time
from pathlib import Path

import zmq

from kmead.net.keys import CurveServer, connect_client, init_keys


def _markers_body(n: int = 50) -> bytes:
    """About the size of the daemon's per-frame ``markers`` body for ``n`` markers."""
    rows = [{"id": i, "in_map": True, "detected": True, "x": 0.123456, "y": 0.654321,
             "z": 0.0, "yaw": 1.2345, "map_x": 0.12, "map_y": 0.65, "map_z": 0.0,
             "error": 0.00123, "ambiguous": False, "flipped": False, "suspect": False,
             "rejected": False, "displacement": None, "reference": True} for i in range(n)]
    return json.dumps({"v": 1, "t": 0.0, "frame": 0, "algorithm": "kmea",
                       "markers": rows}).encode()


class _Pair:
    """PUB (daemon side) and SUB (client side) on loopback, with or without CURVE."""

    def __init__(self, keys: Path | None) -> None:
        self.pub_ctx, self.sub_ctx = zmq.Context(), zmq.Context()
        self.curve = CurveServer(self.pub_ctx, keys) if keys else None
        self.pub = self.pub_ctx.socket(zmq.PUB)
        self.pub.setsockopt(zmq.SNDHWM, 0)
        self.pub.setsockopt(zmq.LINGER, 0)
        if self.curve:
            self.curve.secure(self.pub, "telemetry")
        endpoint = f"tcp://127.0.0.1:{self.pub.bind_to_random_port('tcp://127.0.0.1')}"
        if keys:
            self.sub = connect_client(self.sub_ctx, endpoint, keys, "operator", zmq.SUB)
        else:
            self.sub = self.sub_ctx.socket(zmq.SUB)
            self.sub.setsockopt(zmq.LINGER, 0)
            self.sub.connect(endpoint)
        self.sub.setsockopt(zmq.RCVHWM, 0)
        self.sub.setsockopt(zmq.SUBSCRIBE, b"")
        # Slow joiner: publish until the subscription is through.
        end = time.monotonic() + 5
        while time.monotonic() < end:
            self.pub.send_multipart([b"hello", b""])
            if self.sub.poll(20):
                while self.sub.poll(0):
                    self.sub.recv_multipart()
                return
        raise RuntimeError("subscriber never connected")

    def close(self) -> None:
        self.sub.close(0)
        self.pub.close(0)
        if self.curve:
            self.curve.stop()
        self.sub_ctx.term()
        self.pub_ctx.term()


def throughput(pair: _Pair, body: bytes, n: int) -> float:
    """Messages per second, first send to last receive."""
    done = threading.Event()
    t_last = [0.0]

    def receive() -> None:
        for _ in range(n):
            pair.sub.recv_multipart()
        t_last[0] = time.perf_counter()
        done.set()

    th = threading.Thread(target=receive)
    th.start()
    t0 = time.perf_counter()
    for _ in range(n):
        pair.pub.send_multipart([b"markers", body])
    if not done.wait(120):
        raise RuntimeError("messages lost")
    th.join()
    return n / (t_last[0] - t0)


def latency(pair: _Pair, body: bytes, n: int, rate: float) -> list[float]:
    """One-way latencies (ms) of ``n`` messages published at ``rate`` Hz."""
    out: list[float] = []

    def receive() -> None:
        for _ in range(n):
            _, msg = pair.sub.recv_multipart()
            out.append((time.perf_counter() - struct.unpack("d", msg[:8])[0]) * 1e3)

    th = threading.Thread(target=receive)
    th.start()
    period = 1.0 / rate
    t_next = time.perf_counter()
    for _ in range(n):
        while time.perf_counter() < t_next:
            time.sleep(min(period / 4, 0.001))
        pair.pub.send_multipart([b"markers", struct.pack("d", time.perf_counter()) + body])
        t_next += period
    th.join(60)
    return out


def _pct(xs: list[float], q: float) -> float:
    return statistics.quantiles(xs, n=100, method="inclusive")[int(q) - 1] if len(xs) > 1 \
        else xs[0]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="kmea bench curve",
                                description=(__doc__ or "").split("\n\n")[0])
    p.add_argument("--messages", type=int, default=20000, help="throughput messages")
    p.add_argument("--latency-messages", type=int, default=2000)
    p.add_argument("--rate", type=float, default=500.0, help="latency send rate, Hz")
    p.add_argument("--runs", type=int, default=3,
                   help="plain and CURVE alternate this many times; medians are printed")
    p.add_argument("--size", type=int, default=0,
                   help="message size in bytes (default: a 50-marker markers body)")
    args = p.parse_args(argv)
    bodies = ([("custom", b"x" * args.size)] if args.size else
              [("frame", _markers_body(1)[:600]), ("markers", _markers_body())])
    print(f"telemetry PUB -> SUB over tcp://127.0.0.1, pyzmq {zmq.__version__}, "
          f"libzmq {zmq.zmq_version()}; latency at {args.rate:g} Hz; median of "
          f"{args.runs} alternating runs")
    print(f"{'message':<9} {'bytes':>6} {'mode':<6} {'msgs/s':>8} {'MB/s':>6} {'p50 ms':>7} "
          f"{'p99 ms':>7} {'max ms':>7}")
    with tempfile.TemporaryDirectory() as tmp:
        keys = Path(tmp) / "keys"
        init_keys(keys)
        for label, body in bodies:
            runs: dict[str, list[tuple[float, float, float, float]]] = {"plain": [],
                                                                         "curve": []}
            for _ in range(args.runs):  # alternate, so both see the same machine load
                for mode, k in (("plain", None), ("curve", keys)):
                    pair = _Pair(k)
                    try:
                        rate = throughput(pair, body, args.messages)
                        lat = latency(pair, body, args.latency_messages, args.rate)
                    finally:
                        pair.close()
                    runs[mode].append((rate, _pct(lat, 50), _pct(lat, 99), max(lat)))
            for mode, rs in runs.items():
                rate, p50, p99, worst = (statistics.median(c) for c in zip(*rs, strict=True))
                print(f"{label:<9} {len(body):>6} {mode:<6} {rate:>8.0f} "
                      f"{rate * len(body) / 1e6:>6.1f} {p50:>7.3f} {p99:>7.3f} {worst:>7.3f}",
                      flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
