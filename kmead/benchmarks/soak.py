"""Soak: a real kmead for a given time with everything a venue day has, and what it did.

    kmea bench soak --minutes 60 [--idle 10] [--every 60] [--source sim]

One ``kmead --headless`` process (the simulated floor by default, two robots) with a CSV log
and a compressed recording, its robots' datagrams going to a real UDP listener here, a real
ZeroMQ subscriber that reads every telemetry topic (the terminal UI's part) and ``--idle``
subscribers that connect and never read (a UI left open on a frozen laptop). Printed every
``--every`` seconds: the daemon's RSS, frames, datagrams, the files' sizes; at the end: RSS
over the run, datagrams against frames, ``seq`` gaps per robot, the longest silence between
two datagrams of a robot, and the bytes written per hour by the log and by the recording.

``--minutes 2`` is a smoke run; the figures worth quoting come from an hour (the first
minutes include start-up: compare RSS from the second sample on).
"""

from __future__ import annotations

import argparse
import contextlib
import re
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import zmq

from kmea.wire import protocol as P
from kmead.outputs.relay import parse_datagram

ROBOTS = {"amr1": "[40, 41]", "amr2": "[42]"}  # the simulated floor's robots


@dataclass
class RobotStats:
    """The datagrams of one robot, in arrival order: counts, ``seq`` gaps, longest silence."""

    count: int = 0
    valid: int = 0
    missing: int = 0  # seq numbers skipped (a gap of k missing datagrams adds k)
    gaps: int = 0  # places where seq jumped
    out_of_order: int = 0  # seq not above the last one
    longest_s: float = 0.0  # longest time between two datagrams (arrival clock)
    longest_at: float = 0.0  # when that silence ended (arrival clock)
    last_seq: int | None = None
    last_t: float | None = None

    def add(self, seq: int, valid: bool, arrival: float) -> None:
        self.count += 1
        self.valid += valid
        if self.last_seq is not None:
            if seq > self.last_seq + 1:
                self.gaps += 1
                self.missing += seq - self.last_seq - 1
            elif seq <= self.last_seq:
                self.out_of_order += 1
        if self.last_t is not None and arrival - self.last_t > self.longest_s:
            self.longest_s, self.longest_at = arrival - self.last_t, arrival
        self.last_seq = seq if self.last_seq is None else max(seq, self.last_seq)
        self.last_t = arrival


@dataclass
class Listener:
    """Counts every datagram per robot on a real UDP socket (its own thread)."""

    sock: socket.socket
    robots: dict[str, RobotStats] = field(default_factory=dict)
    bad: int = 0

    def run(self, stop: threading.Event) -> None:
        self.sock.settimeout(0.2)
        while not stop.is_set():
            try:
                data = self.sock.recv(2048)
            except TimeoutError:
                continue
            now = time.monotonic()
            try:
                d = parse_datagram(data)
            except (KeyError, ValueError, UnicodeDecodeError):
                self.bad += 1
                continue
            self.robots.setdefault(d["name"], RobotStats()).add(d["seq"], d["valid"], now)


def rss_kb(status_text: str) -> int | None:
    """VmRSS (kB) from the text of /proc/PID/status; None when absent (process gone)."""
    for line in status_text.splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    return None


def summary_counts(text: str) -> dict[str, int]:
    """Frames, dropped and bad frames from kmead's exit summary (its stdout); {} without."""
    m = re.search(r"kmead summary: (\d+) frames", text)
    if not m:
        return {}
    out = {"frames": int(m.group(1))}
    for key in ("dropped", "bad"):
        k = re.search(rf"{key} frames: (\d+)", text)
        if k:
            out[key] = int(k.group(1))
    return out


def per_hour(n_bytes: int, seconds: float) -> float:
    return n_bytes / seconds * 3600 if seconds > 0 else 0.0


def _free_port(kind: int = socket.SOCK_STREAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _site(udp_port: int, telemetry: str, control: str) -> str:
    robots = "".join(f'\n[[robots]]\nname = "{n}"\nmarkers = {m}\nheight = 0.0\n'
                     f'destinations = ["udp:127.0.0.1:{udp_port}"]\n' for n, m in ROBOTS.items())
    return (f'[network]\ntelemetry = "{telemetry}"\ncontrol = "{control}"\n'
            f"{robots}")


def _sizes(d: Path) -> tuple[int, int]:
    """Bytes of the CSV log and of every part of the recording."""
    log = sum(p.stat().st_size for p in d.glob("run*.csv"))
    rec = sum(p.stat().st_size for p in d.glob("run*.jsonl.zst"))
    return log, rec


def _rss(pid: int) -> int | None:
    try:
        return rss_kb(Path(f"/proc/{pid}/status").read_text())
    except OSError:
        return None


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="kmea bench soak",
                                 description=(__doc__ or "").split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=60.0)
    ap.add_argument("--idle", type=int, default=10, help="subscribers that never read")
    ap.add_argument("--every", type=float, default=60.0, help="seconds between samples")
    ap.add_argument("--source", default="sim")
    ap.add_argument("--dir", help="where the files go (default: a temporary directory)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="passed to kmead")
    args = ap.parse_args(argv)
    with contextlib.ExitStack() as stack:
        d = Path(args.dir) if args.dir else Path(stack.enter_context(tempfile.TemporaryDirectory()))
        d.mkdir(parents=True, exist_ok=True)
        return soak(args, d)


def soak(args: argparse.Namespace, d: Path) -> int:
    udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    udp.bind(("127.0.0.1", 0))
    udp.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
    telemetry = f"tcp://127.0.0.1:{_free_port()}"
    control = f"tcp://127.0.0.1:{_free_port()}"
    (d / "site.toml").write_text(_site(udp.getsockname()[1], telemetry, control))
    cmd = [sys.executable, "-m", "kmead.cli", "--config", str(d / "site.toml"), "--headless",
           "--source", args.source, "--log", str(d / "run.csv"),
           "--record", str(d / "run.jsonl.zst"), "--status-every", "30",
           *[x for kv in args.set for x in ("--set", kv)]]
    out = open(d / "kmead.out", "w")  # noqa: SIM115 - closed below
    err = open(d / "kmead.err", "w")  # noqa: SIM115 - closed below
    proc = subprocess.Popen(cmd, cwd=d, stdout=out, stderr=err)
    stop = threading.Event()
    listener = Listener(udp)
    threading.Thread(target=listener.run, args=(stop,), daemon=True).start()
    ctx = zmq.Context()
    ui = ctx.socket(zmq.SUB)
    ui.setsockopt(zmq.SUBSCRIBE, b"")
    ui.connect(telemetry)
    idle = []
    for _ in range(args.idle):
        s = ctx.socket(zmq.SUB)
        s.setsockopt(zmq.SUBSCRIBE, b"")
        s.connect(telemetry)
        idle.append(s)
    topics: dict[str, int] = {}
    status: dict = {}
    t0 = time.monotonic()
    end = t0 + args.minutes * 60
    next_sample = t0 + args.every
    samples: list[tuple[float, int | None]] = []
    print(f"soak: kmead pid {proc.pid}, {args.minutes:g} min, files in {d}; "
          f"{args.idle} idle subscribers", flush=True)
    print(f"{'min':>6} {'RSS MB':>7} {'frames':>7} {'datagrams':>9} {'log MB':>7} "
          f"{'rec MB':>7}", flush=True)
    try:
        while time.monotonic() < end and proc.poll() is None:
            if ui.poll(100):
                topic, body = P.decode(ui.recv_multipart())
                topics[topic] = topics.get(topic, 0) + 1
                if topic == P.TOPIC_STATUS:
                    status = body
            now = time.monotonic()
            if now >= next_sample or now >= end:
                next_sample += args.every
                rss = _rss(proc.pid)
                samples.append(((now - t0) / 60, rss))
                log_b, rec_b = _sizes(d)
                n = sum(r.count for r in listener.robots.values())
                print(f"{(now - t0) / 60:6.1f} {(rss or 0) / 1024:7.1f} "
                      f"{status.get('frames', 0):7d} {n:9d} {log_b / 1e6:7.1f} "
                      f"{rec_b / 1e6:7.1f}", flush=True)
    finally:
        elapsed = time.monotonic() - t0
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        try:
            code = proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            code = proc.wait()
        time.sleep(0.5)  # the last datagrams (valid=0 at stop)
        stop.set()
        for s in (ui, *idle):
            s.close(linger=0)
        ctx.term()
        out.close()
        err.close()
    report(d, elapsed, code, samples, status, listener, topics, t0)
    return 0 if code == 0 else 1


def report(d: Path, elapsed: float, code: int, samples: list[tuple[float, int | None]],
           status: dict, listener: Listener, topics: dict[str, int], t0: float) -> None:
    log_b, rec_b = _sizes(d)
    counts = summary_counts((d / "kmead.out").read_text())
    frames = counts["frames"] if "frames" in counts else int(status.get("frames", 0))
    rss = [r for _, r in samples if r]
    print(f"\nsoak: {elapsed / 60:.1f} min, kmead exit code {code}, {frames} frames "
          f"({frames / elapsed:.1f}/s; dropped {counts.get('dropped', '?')}, bad "
          f"{counts.get('bad', '?')}: kmead's summary)")
    if rss:
        later = rss[1:] or rss
        print(f"RSS: first sample {rss[0] / 1024:.1f} MB, last {rss[-1] / 1024:.1f} MB, max "
              f"{max(rss) / 1024:.1f} MB; from the second sample on {min(later) / 1024:.1f}-"
              f"{max(later) / 1024:.1f} MB")
    for name, r in sorted(listener.robots.items()):
        print(f"robot {name}: {r.count} datagrams ({r.valid} valid) for {frames} frames; seq "
              f"gaps {r.gaps} ({r.missing} missing), out of order {r.out_of_order}; longest "
              f"silence {r.longest_s * 1e3:.0f} ms (ending {(r.longest_at - t0) / 60:.2f} min "
              "in)")
    if listener.bad:
        print(f"unparsable datagrams: {listener.bad}")
    print(f"written: CSV log {log_b / 1e6:.1f} MB ({per_hour(log_b, elapsed) / 1e6:.0f} MB/h), "
          f"recording {rec_b / 1e6:.1f} MB ({per_hour(rec_b, elapsed) / 1e6:.0f} MB/h, "
          f"{len(list(d.glob('run*.jsonl.zst')))} part(s))")
    print("UI subscriber received: " + ", ".join(f"{t} {n}" for t, n in sorted(topics.items())))


if __name__ == "__main__":
    sys.exit(main())
