"""A venue day in miniature: a real kmead with everything attached, for a given time.

Runs ``kmead --headless`` (default source: the simulated floor at its configured pace) with
a CSV log, a recording and the two default robots sending their datagrams to real UDP
listeners on loopback, one ZeroMQ subscriber that reads everything (the terminal UI's
load) and ``--idle`` subscribers that never read (a stuck client must not grow the daemon).
Every ``--every`` seconds it prints the daemon's RSS, frames, datagrams and bytes written;
at the end (SIGINT to the daemon, as Ctrl-C) the figures: RSS over time, datagrams vs
frames, ``seq`` gaps, the longest gap between two datagrams of a robot, bytes per hour of
the log and the recording, and the daemon's exit code. Prints figures; no asserts.

    .venv/bin/python benchmarks/soak.py --minutes 60
    .venv/bin/python benchmarks/soak.py --minutes 2 --set source.width=820 --set source.height=616
"""

from __future__ import annotations

import argparse
import os
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

from kmea import protocol as P

ROBOTS = (("amr1", "[40, 41]", "separation = 0.10\n"), ("amr2", "[42]", ""))


@dataclass
class RobotCount:
    """What one robot's UDP listener saw."""

    datagrams: int = 0
    valid: int = 0
    gaps: int = 0  # missing seq numbers
    repeats: int = 0  # seq not increasing
    longest_gap_s: float = 0.0  # between two valid datagrams
    last_seq: int | None = None
    last_t: float | None = None  # monotonic arrival of the last valid datagram
    bad: int = 0  # datagrams that did not parse

    def take(self, data: bytes, now: float) -> None:
        fields = parse_datagram(data)
        if fields is None or "seq" not in fields:
            self.bad += 1
            return
        seq = int(fields["seq"])
        self.datagrams += 1
        self.valid += fields.get("valid") == "1"
        if self.last_seq is not None:
            if seq > self.last_seq + 1:
                self.gaps += seq - self.last_seq - 1
            elif seq <= self.last_seq:
                self.repeats += 1
        self.last_seq = seq
        if fields.get("valid") != "1":  # the stop message, or stale: not a gap in service
            return
        if self.last_t is not None:
            self.longest_gap_s = max(self.longest_gap_s, now - self.last_t)
        self.last_t = now


def parse_datagram(data: bytes) -> dict[str, str] | None:
    """``name=amr1;seq=17;...`` -> {"name": "amr1", "seq": "17", ...}; None if not that form."""
    try:
        text = data.decode("ascii")
    except UnicodeDecodeError:
        return None
    out: dict[str, str] = {}
    for part in text.split(";"):
        key, sep, value = part.partition("=")
        if not sep or not key:
            return None
        out[key] = value
    return out


def rss_mb(pid: int) -> float | None:
    """Resident set size of a process in MB (10^6 bytes), from /proc; None if gone."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return None
    m = re.search(r"^VmRSS:\s+(\d+) kB", status, re.MULTILINE)
    return int(m.group(1)) * 1024 / 1e6 if m else None


@dataclass
class Listener:
    """A UDP listener on a free loopback port, counting in a thread."""

    name: str
    count: RobotCount = field(default_factory=RobotCount)
    sock: socket.socket = field(default_factory=lambda: socket.socket(socket.AF_INET,
                                                                      socket.SOCK_DGRAM))

    def __post_init__(self) -> None:
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.2)
        self.port = self.sock.getsockname()[1]
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self.stop.is_set():
            try:
                data = self.sock.recv(65536)
            except TimeoutError:
                continue
            except OSError:
                return
            self.count.take(data, time.monotonic())


def site_config(ports: dict[str, int]) -> str:
    """The default robots, each sending to its listener (``[[robots]]`` replaces the list)."""
    out = []
    for name, markers, extra in ROBOTS:
        out.append(f'[[robots]]\nname = "{name}"\nmarkers = {markers}\nheight = 0.20\n'
                   f'length = 0.06\n{extra}destinations = ["udp:127.0.0.1:{ports[name]}"]\n')
    return "\n".join(out)


def connectable(endpoint: str) -> str:
    return endpoint.replace("://0.0.0.0:", "://127.0.0.1:").replace("://*:", "://127.0.0.1:")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=60.0)
    ap.add_argument("--every", type=float, default=60.0, help="seconds between sample lines")
    ap.add_argument("--idle", type=int, default=10, help="subscribers that never read")
    ap.add_argument("--source", default="sim")
    ap.add_argument("--record-name", default="recording.jsonl",
                    help="recording file name (its suffix chooses the format)")
    ap.add_argument("--dir", help="keep the log and recording here (default: a temp dir)")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE")
    args = ap.parse_args(argv)

    workdir = Path(args.dir) if args.dir else Path(tempfile.mkdtemp(prefix="kmea-soak-"))
    workdir.mkdir(parents=True, exist_ok=True)
    listeners = {name: Listener(name) for name, _, _ in ROBOTS}
    site = workdir / "soak.toml"
    site.write_text(site_config({n: li.port for n, li in listeners.items()}))
    log_path, rec_path = workdir / "log.csv", workdir / args.record_name
    cmd = [sys.executable, "-m", "kmead.cli", "--config", str(site), "--headless",
           "--free-ports", "--status-every", "0", "--source", args.source,
           "--log", str(log_path), "--record", str(rec_path)]
    for s in args.set:
        cmd += ["--set", s]
    env = {**os.environ, "XDG_CONFIG_HOME": str(workdir / "home")}
    proc = subprocess.Popen(cmd, cwd=workdir, env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    stderr: list[str] = []
    reader = threading.Thread(target=lambda: stderr.extend(proc.stderr or []), daemon=True)
    reader.start()

    deadline = time.monotonic() + 120.0
    endpoint = None
    while endpoint is None and time.monotonic() < deadline and proc.poll() is None:
        endpoint = next((m.group(1) for line in list(stderr)
                         if (m := re.search(r"telemetry (tcp://\S+?),", line))), None)
        time.sleep(0.05)
    if endpoint is None:
        proc.kill()
        print("soak: kmead did not start:\n" + "".join(stderr[-20:]), file=sys.stderr)
        return 1

    ctx = zmq.Context()
    ui = ctx.socket(zmq.SUB)
    ui.setsockopt(zmq.SUBSCRIBE, b"")
    ui.connect(connectable(endpoint))
    idle = []
    for _ in range(args.idle):
        s = ctx.socket(zmq.SUB)
        s.setsockopt(zmq.SUBSCRIBE, b"")
        s.setsockopt(zmq.RCVHWM, 1000)
        s.connect(connectable(endpoint))
        idle.append(s)

    ui_state = {"frames": 0, "last_frame": None, "dropped": 0, "messages": 0}
    ui_stop = threading.Event()

    def read_ui() -> None:
        poller = zmq.Poller()
        poller.register(ui, zmq.POLLIN)
        while not ui_stop.is_set():
            if not poller.poll(200):
                continue
            parts = ui.recv_multipart()
            ui_state["messages"] += 1
            try:
                topic, body = P.decode(parts)
            except Exception:  # a soak counts, it does not judge the protocol
                continue
            if topic == P.TOPIC_FRAME:
                ui_state["frames"] += 1
                ui_state["last_frame"] = body["frame"]
                ui_state["dropped"] = body["dropped"]

    ui_thread = threading.Thread(target=read_ui, daemon=True)
    ui_thread.start()

    def size(p: Path) -> int:
        # rotated parts share the stem and the suffix (soak.csv, soak-2.csv, ...)
        return sum(f.stat().st_size for f in p.parent.glob(f"{p.stem}*{p.suffix}")
                   if f.is_file())

    t0 = time.monotonic()
    end = t0 + args.minutes * 60.0
    samples: list[tuple[float, float | None]] = []
    print("  min   RSS MB   frames  datagrams(amr1/amr2)  log MB  recording MB", flush=True)
    next_sample = t0
    while proc.poll() is None and time.monotonic() < end:
        now = time.monotonic()
        if now >= next_sample:
            rss = rss_mb(proc.pid)
            samples.append(((now - t0) / 60.0, rss))
            c = [listeners[n].count.datagrams for n, _, _ in ROBOTS]
            print(f"{(now - t0) / 60:5.1f}  {rss or 0:7.1f}  {ui_state['frames']:7d}  "
                  f"{c[0]:9d}/{c[1]:<9d}  {size(log_path) / 1e6:8.1f}  "
                  f"{size(rec_path) / 1e6:10.1f}", flush=True)
            next_sample += args.every
        time.sleep(min(1.0, max(0.05, next_sample - time.monotonic())))
    elapsed = time.monotonic() - t0
    samples.append((elapsed / 60.0, rss_mb(proc.pid)))
    early_exit = proc.poll()
    if early_exit is None:
        proc.send_signal(signal.SIGINT)
    try:
        rc = proc.wait(60.0)
    except subprocess.TimeoutExpired:
        proc.kill()
        rc = proc.wait()
    time.sleep(0.5)  # the last datagrams (valid=0 at stop) reach the listeners
    ui_stop.set()
    for li in listeners.values():
        li.stop.set()
    ui_thread.join(2.0)
    for s in [ui, *idle]:
        s.close(0)
    ctx.term()

    hours = elapsed / 3600.0
    frames = (ui_state["last_frame"] or 0) + 1 if ui_state["last_frame"] is not None else 0
    print(f"\nsoak: {elapsed / 60:.1f} min, source {args.source}, {args.idle} idle subscribers,"
          f" kmead exit {rc}" + (" (exited before the end)" if early_exit is not None else ""))
    print(f"frames: {frames} processed (telemetry frame index), {ui_state['frames']} frame "
          f"messages read by the UI subscriber, {ui_state['dropped']} dropped by capture, "
          f"{frames / elapsed:.1f} frames/s")
    for name, li in listeners.items():
        c = li.count
        per_frame = c.datagrams / max(frames, 1)
        print(f"{name}: {c.datagrams} datagrams ({c.valid} valid, {per_frame:.3f} per frame)"
              f", seq gaps {c.gaps}, out of order {c.repeats}, unparsable {c.bad}, "
              f"longest gap between valid datagrams {c.longest_gap_s * 1e3:.0f} ms")
    rss = [r for _, r in samples if r is not None]
    if rss:
        after5 = [r for m, r in samples if r is not None and m >= 5.0]
        print("RSS MB: start {:.1f}, max {:.1f}, end {:.1f}{}".format(
            rss[0], max(rss), rss[-1],
            f", growth after minute 5: {after5[-1] - after5[0]:+.1f}" if len(after5) > 1 else ""))
    for label, p in (("CSV log", log_path), ("recording", rec_path)):
        b = size(p)
        print(f"{label}: {b / 1e6:.1f} MB in {elapsed / 60:.1f} min = {b / hours / 1e9:.3f} GB/hour"
              f" ({b / max(frames, 1) / 1e3:.2f} KB/frame)")
    print(f"files in {workdir}")
    tail = [line for line in stderr if "Traceback" in line or "ERROR" in line]
    if tail:
        print(f"kmead errors on stderr: {len(tail)}; first: {tail[0].strip()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
