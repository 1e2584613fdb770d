"""``kmea bench voice-seams``: what a robot hears at every seam of a site (docs/fusion.md,
"One voice per robot").

The docs' own set-up on one machine, each a process of its own on loopback: two cameras
(``kmead --source "sim:wide?camera=N&clock=wall"``, 820x616 unless told), fusion nodes
started, stopped in order (SIGINT), killed (SIGKILL) and frozen (SIGSTOP), a camera killed
and started again. The robots are a UDP listener and a Zenoh subscriber of the binary pose
(``<site>/robots/*/pose``). Per seam and robot, over the window from the seam's signal to
a few seconds after:

- **silence**: the longest time between two valid messages a robot received (while a
  camera sees it: a robot nobody sees is silent by nature, the table says so);
- **seq**: pairs of consecutive messages whose ``seq`` did not increase (UDP and binary);
- **jumps**: messages whose error against the simulator's truth (at the message's ``t``)
  changed from the previous message by more than 3 (and 10) times the message's sigma, per
  1,000 messages;
- **voices**: changes of the UDP sender (each a handover; two voices at once would show as
  many).
"""

from __future__ import annotations

import argparse
import itertools
import math
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

__all__ = ["main"]

ROBOTS = ("amr1", "amr2")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _robots_toml(udp: int) -> str:
    dest = f'destinations=["udp:127.0.0.1:{udp}"]'
    return (f'robots=[{{name="amr1", markers=[40, 41], height=0.2, {dest}}}, '
            f'{{name="amr2", markers=[42], height=0.2, {dest}}}]')


@dataclass
class Msg:
    at: float  # monotonic arrival
    port: int
    seq: int
    t: float
    x: float
    y: float
    valid: bool
    sigma: float


@dataclass
class Robot:
    """Everything the robots received."""

    udp: dict[str, list[Msg]] = field(default_factory=lambda: {n: [] for n in ROBOTS})
    binary: dict[str, list[tuple[float, int]]] = field(
        default_factory=lambda: {n: [] for n in ROBOTS})
    lock: threading.Lock = field(default_factory=threading.Lock)


class Site:
    def __init__(self, lease: float, speed: float, width: int, height: int,
                 tmp: Path) -> None:
        self.lease, self.speed, self.width, self.height = lease, speed, width, height
        self.tmp = tmp
        self.zport = _free_port()
        self.epoch = time.time()
        self.procs: dict[str, subprocess.Popen] = {}
        self.robot = Robot()
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.1)
        self.port = self.sock.getsockname()[1]
        self.done = threading.Event()
        self.thread = threading.Thread(target=self._listen, daemon=True)
        self.thread.start()
        self.session = None

    def _listen(self) -> None:
        from kmead.outputs.relay import parse_datagram

        while not self.done.is_set():
            try:
                data, addr = self.sock.recvfrom(2048)
            except TimeoutError:
                continue
            m = parse_datagram(data)
            if m["name"] in ROBOTS:
                with self.robot.lock:
                    self.robot.udp[m["name"]].append(Msg(
                        time.monotonic(), addr[1], m["seq"], m["t"], m["x"], m["y"],
                        m["valid"], m.get("sigma", 0.0)))

    def listen_zenoh(self) -> None:
        import zenoh

        from kmead.outputs.robot_pose_wire import unpack_pose

        conf = zenoh.Config()
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("connect/endpoints", f'["tcp/127.0.0.1:{self.zport}"]')
        conf.insert_json5("scouting/multicast/enabled", "false")
        self.session = zenoh.open(conf)

        def on_pose(s: object) -> None:
            key = str(s.key_expr).split("/")  # type: ignore[attr-defined]
            p = unpack_pose(s.payload.to_bytes())  # type: ignore[attr-defined]
            if len(key) == 4 and key[2] in ROBOTS:
                with self.robot.lock:
                    self.robot.binary[key[2]].append((time.monotonic(), p.seq))
        self.sub = self.session.declare_subscriber("kmea/robots/*/pose", on_pose)

    def _spawn(self, name: str, argv: list[str]) -> None:
        err = open(self.tmp / f"{name}.err", "w")  # noqa: SIM115 (the process owns it)
        self.procs[name] = subprocess.Popen(
            [sys.executable, *argv], stdout=subprocess.DEVNULL, stderr=err, cwd=self.tmp,
            env=dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path)))

    def camera(self, cam: int, first: bool) -> None:
        where = (f'zenoh.listen=["tcp/127.0.0.1:{self.zport}"]' if first else
                 f'zenoh.connect=["tcp/127.0.0.1:{self.zport}"]')
        self._spawn(f"cam{cam}", [
            "-m", "kmead.cli", "--headless", "--free-ports", "--status-every", "0",
            "--source", f"sim:wide?camera={cam}&clock=wall&epoch={self.epoch}"
                        f"&speed={self.speed}",
            "--set", f"source.width={self.width}", "--set", f"source.height={self.height}",
            "--set", 'log.level="info"', "--set", "zenoh.enabled=true",
            "--set", f"zenoh.lease_s={self.lease}", "--set", "zenoh.ros2=false",
            "--set", "relay.extra_fields=true", "--set", where,
            "--set", _robots_toml(self.port)])

    def node(self, name: str) -> None:
        self._spawn(name, [
            "-m", "kmead.tools.fuse", "--headless", "--set", 'network.telemetry=""',
            "--set", 'network.control=""', "--set", 'log.level="info"',
            "--set", f"zenoh.lease_s={self.lease}", "--set", "zenoh.ros2=false",
            "--set", "relay.extra_fields=true",
            "--set", f'zenoh.connect=["tcp/127.0.0.1:{self.zport}"]',
            "--set", f'zenoh.listen=["tcp/127.0.0.1:{_free_port()}"]',
            "--set", _robots_toml(self.port)])

    def said(self, name: str, text: str) -> bool:
        return text in (self.tmp / f"{name}.err").read_text()

    def signal(self, name: str, sig: int) -> None:
        self.procs[name].send_signal(sig)

    def wait(self, cond, what: str, timeout: float = 120.0) -> None:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if cond():
                return
            time.sleep(0.02)
        raise SystemExit(f"voice-seams: timed out waiting for {what}")

    def speaker(self, name: str) -> int | None:
        with self.robot.lock:
            ms = [m for m in self.robot.udp[name] if m.valid]
        return ms[-1].port if ms else None

    def close(self) -> None:
        for p in self.procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGCONT)
                p.kill()
            p.wait(timeout=60)
        self.done.set()
        self.thread.join(timeout=10)
        self.sock.close()
        if self.session is not None:
            self.session.close()


def _truth(speed: float, epoch: float):
    from kmea.sim.scenes import get_scene

    paths = {r.name: r.path for r in get_scene("wide", speed=speed).robots}
    return lambda name, t: paths[name].pose(t - epoch)


def _window(site: Site, name: str, a: float, b: float, truth) -> dict:
    with site.robot.lock:
        msgs = [m for m in site.robot.udp[name] if a <= m.at < b]
        binary = [s for at, s in site.robot.binary[name] if a <= at < b]
    valid = [m for m in msgs if m.valid]
    gaps = [(q.at - p.at) for p, q in itertools.pairwise(valid)]
    seq_bad = sum(q.seq <= p.seq for p, q in itertools.pairwise(msgs))
    seq_bad += sum(q <= p for p, q in itertools.pairwise(binary))
    j3 = j10 = 0
    worst = step = 0.0
    prev = None
    for m in valid:
        tx, ty, _ = truth(name, m.t)
        e = (m.x - tx, m.y - ty)
        if prev is not None and m.sigma > 0:
            d = math.hypot(e[0] - prev[0], e[1] - prev[1])
            k = d / m.sigma
            j3 += k > 3
            j10 += k > 10
            worst = max(worst, k)
            step = max(step, d)
        prev = e
    switches = sum(q.port != p.port for p, q in itertools.pairwise(valid))
    seams = [q.at - p.at for p, q in itertools.pairwise(valid) if q.port != p.port]
    steady = sorted(q.at - p.at for p, q in itertools.pairwise(valid) if q.port == p.port)
    return {"n": len(valid), "silence": max(gaps, default=math.inf), "seq_bad": seq_bad,
            "j3": j3, "j10": j10, "worst": worst, "voices": switches, "step": step,
            "seam": max(seams, default=math.nan),
            "period": steady[len(steady) // 2] if steady else math.nan}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="kmea bench voice-seams",
                                description="what a robot hears at every seam of a site")
    p.add_argument("--lease", type=float, default=3.0, help="zenoh.lease_s (default 3)")
    p.add_argument("--speed", type=float, default=0.25, help="robots' speed, m/s")
    p.add_argument("--width", type=int, default=820)
    p.add_argument("--height", type=int, default=616)
    p.add_argument("--settle", type=float, default=6.0,
                   help="s after each seam that count in its window")
    p.add_argument("--dump", metavar="FILE.json", help="every message received, for study")
    p.add_argument("--logs", metavar="DIR", help="keep the processes' logs there")
    a = p.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        site = Site(a.lease, a.speed, a.width, a.height, Path(a.logs or tmp))
        try:
            rows = _run(site, a.settle)
        finally:
            site.close()
    truth = _truth(a.speed, site.epoch)
    print(f"voice-seams: lease {a.lease:g} s, robots at {a.speed:g} m/s, cameras "
          f"{a.width}x{a.height}")
    print("| seam | robot | messages | period ms (median) | silence at the handover ms | "
          "longest silence ms | seq back/repeat | jumps > 3 sigma per 1,000 | > 10 sigma | "
          "largest sigma | largest step mm | speaker changes |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for label, t0, t1 in rows:
        for name in ROBOTS:  # from 1 s before the seam: the handover's first gap too
            w = _window(site, name, t0 - 1.0, t1, truth)
            per = 1000.0 * w["j3"] / w["n"] if w["n"] else 0.0
            print(f"| {label} | {name} | {w['n']} | {w['period'] * 1e3:.0f} | "
                  f"{w['seam'] * 1e3:.0f} | {w['silence'] * 1e3:.0f} | {w['seq_bad']} | "
                  f"{per:.1f} | {w['j10']} | {w['worst']:.1f} | {w['step'] * 1e3:.1f} | "
                  f"{w['voices']} |")
    if a.dump:
        import json

        with open(a.dump, "w") as f:
            json.dump({"epoch": site.epoch, "speed": a.speed, "rows": rows,
                       "udp": {n: [m.__dict__ for m in ms] for n, ms in site.robot.udp.items()},
                       "binary": site.robot.binary}, f)
    return 0


def _run(site: Site, settle: float) -> list[tuple[str, float, float]]:
    rows: list[tuple[str, float, float]] = []
    now = time.monotonic
    site.camera(0, True)
    site.wait(lambda: site.said("cam0", "zenoh: camera cam0"), "camera 0")
    site.camera(1, False)
    site.listen_zenoh()
    site.wait(lambda: all(site.speaker(n) for n in ROBOTS), "both robots heard")
    cams = {site.speaker(n) for n in ROBOTS}
    t = now()
    time.sleep(2 * settle)
    cams |= {m.port for n in ROBOTS for m in site.robot.udp[n]}
    rows.append(("cameras alone (their own hand-overs)", t, now()))

    def speaking(not_in: set) -> bool:
        return all(site.speaker(n) not in not_in for n in ROBOTS)

    t = now()
    site.node("a")
    site.wait(lambda: speaking(cams), "node a speaking")
    time.sleep(settle)
    rows.append(("node start (cameras -> node)", t, now()))
    known = {m.port for n in ROBOTS for m in site.robot.udp[n]}
    site.node("b")
    site.wait(lambda: site.said("b", "standby:"), "node b standby")
    time.sleep(1.0)
    t = now()
    site.signal("a", signal.SIGINT)
    site.wait(lambda: speaking(known), "node b speaking")
    time.sleep(settle)
    rows.append(("orderly stop, a standby (node -> node)", t, now()))
    t = now()
    site.signal("b", signal.SIGINT)
    site.wait(lambda: all(site.speaker(n) in cams for n in ROBOTS), "cameras back")
    time.sleep(settle)
    rows.append(("orderly stop, no standby (node -> cameras)", t, now()))
    known = {m.port for n in ROBOTS for m in site.robot.udp[n]}
    site.node("c")
    site.wait(lambda: speaking(known), "node c speaking")
    known = {m.port for n in ROBOTS for m in site.robot.udp[n]}
    site.node("d")
    site.wait(lambda: site.said("d", "standby:"), "node d standby")
    time.sleep(1.0)
    t = now()
    site.signal("c", signal.SIGKILL)
    site.wait(lambda: speaking(known), "node d speaking")
    time.sleep(settle)
    rows.append(("active node killed (node -> node)", t, now()))
    t = now()
    site.signal("d", signal.SIGSTOP)
    time.sleep(site.lease + settle)
    rows.append(("active node frozen, no standby (node -> cameras)", t, now()))
    t = now()
    site.signal("d", signal.SIGCONT)
    time.sleep(settle)
    rows.append(("frozen node resumed", t, now()))
    site.signal("d", signal.SIGKILL)
    site.wait(lambda: all(site.speaker(n) in cams for n in ROBOTS), "cameras back")
    time.sleep(settle)
    t = now()
    site.signal("cam1", signal.SIGKILL)
    time.sleep(settle)
    rows.append(("camera 1 killed, no node", t, now()))
    t = now()
    site.camera(1, False)
    time.sleep(2 * settle)
    rows.append(("camera 1 started again, no node", t, now()))
    return rows
