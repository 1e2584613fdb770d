"""Figures for the fusion node on Zenoh: time to drop a killed and a frozen camera, and the
failover between two fusion nodes (the time it takes and the largest gap a robot saw).

    kmea bench fusion-zenoh [--lease S]

Everything on this machine, on loopback, as in the field: each fusion node is
``kmea fuse --headless`` in its own process (a Zenoh peer; the first listens on a port, the
others connect to it), each camera a process of its own playing a camera of the site (its
liveliness token, its metadata, 30 measurements/s of one robot and the heartbeat, as a
``kmead`` sends them), so that it can be killed (SIGKILL) and frozen (SIGSTOP). The robot is
a UDP listener here.

- Camera dropped: from the signal to the node's "camera ...: gone" / "silent" line (its
  telemetry ``log`` topic). Killed: the token goes with the TCP connection. Frozen (the
  process stopped): its Zenoh lease runs out (``zenoh.lease_s``). Stuck (the process and
  its session alive, its frame loop not): the node's data timeout, the lease too.
- Failover: two nodes, the camera, the robot. The active node is killed (SIGKILL) and
  restarted (a standby now); then the new active one is frozen (SIGSTOP, then SIGCONT after
  3 leases). Failover time: from
  the signal to the first datagram from the other node; the largest gap: between two
  datagrams the robot got, over the whole run; voices: the datagrams that came from a node
  while the other one was speaking (a second voice; 0 expected).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]  # the directory that holds kmead
SITE = "kmea"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def camera_main(port: int, cam_id: str, lease: float) -> None:
    """A camera of the site (a process of its own): SIGUSR1 stops its 'frame loop' (the
    session and its token stay). Its session as kmead's (kmead.outputs.zenoh_session: Zenoh's
    lease 3/4 of zenoh.lease_s)."""
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("transport/link/tx/lease", str(max(1, int(lease * 750))))
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    # A port of its own too: the nodes' gossip tells each other where it is, so the
    # camera stays connected to a standby node when the node it connected to dies.
    conf.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    z = zenoh.open(conf)
    prefix = f"{SITE}/cam/{cam_id}"
    meta = json.dumps({"camera": cam_id, "map_digest": "bench", "map_name": "bench",
                       "model": "bench", "width": 640, "height": 480, "fx": 500.0,
                       "fy": 500.0, "source": "bench"}).encode()
    # (kept: a token or queryable dropped is undeclared)
    kept = (z.declare_queryable(f"{prefix}/meta", lambda q: q.reply(f"{prefix}/meta", meta)),
            z.liveliness().declare_token(prefix))
    pub = z.declare_publisher(f"{prefix}/robots/amr1")
    beat = z.declare_publisher(f"{prefix}/frame")
    stuck = threading.Event()
    signal.signal(signal.SIGUSR1, lambda *_: stuck.set())
    k = 0
    while True:
        if not stuck.is_set():
            t = time.time()
            pub.put(json.dumps({"name": "amr1", "valid": True, "t": t, "x": 0.5 + 1e-4 * k,
                                "y": 0.3, "theta": 0.0, "sigma": 0.002}).encode())
            beat.put(json.dumps({"t": t, "frames": k}).encode())
            k += 1
        time.sleep(1 / 30)
    del kept


class Node:
    """``kmea fuse --headless`` in its own process; its stderr lines (with the time this
    process read them, every 5 ms) in :attr:`lines`."""

    def __init__(self, tmp: Path, name: str, lease: float, zport: int, listen: bool,
                 udp_port: int) -> None:
        self.err = open(tmp / f"{name}.err", "w+")  # noqa: SIM115 (closed in stop())
        # The first node listens on zport, the others on a port of their own and connect to
        # it (then Zenoh's gossip meshes every peer: a node's death leaves the rest joined).
        zset = f'zenoh.listen=["tcp/127.0.0.1:{zport}"]' if listen \
            else f'zenoh.listen=["tcp/127.0.0.1:{_free_port()}"]'
        zcon = [] if listen else ["--set", f'zenoh.connect=["tcp/127.0.0.1:{zport}"]']
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "kmead.tools.fuse", "--headless",
             "--set", 'network.telemetry=""',
             "--set", 'network.control=""', "--set", 'log.level="info"',
             "--set", f"zenoh.lease_s={lease}", "--set", "zenoh.ros2=false", "--set", zset, *zcon,
             "--set", "relay.stale_after_s=5.0",
             "--set", f'robots=[{{name="amr1", markers=[40, 41], height=0.2, '
                      f'destinations=["udp:127.0.0.1:{udp_port}"]}}]'],
            stdout=subprocess.DEVNULL, stderr=self.err, cwd=tmp,
            env=dict(os.environ, PYTHONPATH=str(ROOT)))
        self.lines: list[tuple[float, str]] = []
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self) -> None:
        with open(self.err.name) as f:
            buf = ""
            while not self._stop.is_set():
                chunk = f.read()
                if not chunk:
                    time.sleep(0.005)
                    continue
                buf += chunk
                *done, buf = buf.split("\n")
                now = time.time()
                self.lines.extend((now, line) for line in done)

    def wait_for(self, text: str, after: float = 0.0, timeout: float = 60.0) -> float:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            for t, line in list(self.lines):
                if t >= after and text in line:
                    return t
            if self.proc.poll() is not None:
                self.err.seek(0)
                raise RuntimeError(f"node exited: {self.err.read()[-400:]}")
            time.sleep(0.01)
        raise RuntimeError(f"no {text!r} within {timeout} s")

    def stop(self) -> None:
        self._stop.set()
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGCONT)
            self.proc.terminate()
        self.proc.wait(timeout=30)
        self.thread.join(timeout=5)
        self.err.close()


def _camera(zport: int, cam_id: str, lease: float) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "kmead.benchmarks.fusion_zenoh", "--camera",
                             str(zport), cam_id, str(lease)],
                            env=dict(os.environ, PYTHONPATH=str(ROOT)))


def drops(lease: float) -> None:
    zport = _free_port()
    with tempfile.TemporaryDirectory() as tmp:
        node = Node(Path(tmp), "node", lease, zport, True, _free_port())
        cams = []
        try:
            node.wait_for("fusion node")
            print(f"camera dropped (zenoh.lease_s = {lease:g} s):")
            for cam_id, how, sig, expect in (
                    ("killed", "killed (SIGKILL)", signal.SIGKILL, "gone"),
                    ("frozen", "frozen (SIGSTOP)", signal.SIGSTOP, ": "),
                    ("stuck", "frame loop stuck (SIGUSR1: session alive)", signal.SIGUSR1,
                     "silent")):
                cam = _camera(zport, cam_id, lease)
                cams.append(cam)
                node.wait_for(f"camera {cam_id}: used")
                time.sleep(1.0)
                t0 = time.time()
                cam.send_signal(sig)
                t1 = node.wait_for(f"camera {cam_id}: " + ("" if expect == ": " else expect),
                                   after=t0)
                line = next(text for t, text in node.lines
                            if t == t1 and f"camera {cam_id}" in text)
                print(f"  {how:44s} {(t1 - t0) * 1e3:7.0f} ms   ({line})", flush=True)
        finally:
            for cam in cams:
                cam.send_signal(signal.SIGCONT)
                cam.kill()
                cam.wait()
            node.stop()


def failover(lease: float) -> None:
    zport = _free_port()
    udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    udp.bind(("127.0.0.1", 0))
    udp.settimeout(0.1)
    got: list[tuple[float, int, bool]] = []  # (arrival, sender port, valid)
    stop = threading.Event()

    def listen() -> None:
        while not stop.is_set():
            try:
                data, addr = udp.recvfrom(2048)
            except TimeoutError:
                continue
            got.append((time.time(), addr[1], b"valid=1" in data))

    th = threading.Thread(target=listen, daemon=True)
    th.start()
    with tempfile.TemporaryDirectory() as tmp:
        a = Node(Path(tmp), "a", lease, zport, True, udp.getsockname()[1])
        cam = _camera(zport, "cam0", lease)
        nodes = [a]
        try:
            a.wait_for("active: this node speaks")
            b = Node(Path(tmp), "b", lease, zport, False, udp.getsockname()[1])
            nodes.append(b)
            b.wait_for("standby:")
            time.sleep(2.0)
            print(f"failover (zenoh.lease_s = {lease:g} s; the robot gets 30 poses/s):")
            t0 = time.time()
            a.proc.send_signal(signal.SIGKILL)
            b.wait_for("active: this node speaks", after=t0)
            a2 = Node(Path(tmp), "a2", lease, zport, True, udp.getsockname()[1])
            nodes.append(a2)  # restarted: a standby now, it must not take the voice
            a2.wait_for("standby:")
            time.sleep(2.0)
            t1 = time.time()
            b.proc.send_signal(signal.SIGSTOP)  # frozen: the other node must take over
            a2.wait_for("active: this node speaks", after=t1)
            time.sleep(3 * lease)
            t2 = time.time()
            b.proc.send_signal(signal.SIGCONT)  # it comes back: must not speak again
            b.wait_for("stepped down", after=t2)
            time.sleep(2.0)
        finally:
            stop.set()
            th.join(timeout=2)
            cam.kill()
            cam.wait()
            for n in nodes:
                n.stop()
            udp.close()
    valid = [(t, p) for t, p, v in got if v]
    ports = []
    for _, p in valid:
        if not ports or ports[-1] != p:
            ports.append(p)

    def first_from_other(after: float, port_before: int) -> float:
        return next(t for t, p in valid if t > after and p != port_before) - after

    port_a = next(p for t, p in valid if t < t0)
    port_b = next(p for t, p in valid if t0 < t < t1 and p != port_a)
    gaps = [(valid[i + 1][0] - valid[i][0], valid[i][0]) for i in range(len(valid) - 1)]
    print(f"  active killed (SIGKILL): the standby spoke after "
          f"{first_from_other(t0, port_a) * 1e3:.0f} ms")
    print("  active frozen (SIGSTOP), the killed node restarted as standby meanwhile: it "
          f"spoke after {first_from_other(t1, port_b) * 1e3:.0f} ms")
    late_b = sum(1 for t, p in valid if t > t2 and p == port_b)
    print(f"  the frozen node resumed (SIGCONT): {late_b} datagrams from it afterwards "
          "(it stepped down before sending)")
    print(f"  voices in turn: {len(ports)} (a change of speaker each: A, B, A again)")
    print(f"  largest gap a robot saw: {max(gaps)[0] * 1e3:.0f} ms; "
          f"{len(valid)} valid poses over {valid[-1][0] - valid[0][0]:.1f} s")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="kmea bench fusion-zenoh",
                                description=(__doc__ or "").split("\n\n")[0])
    p.add_argument("--lease", type=float, default=1.0, help="zenoh.lease_s (s)")
    p.add_argument("--camera", nargs=3, metavar=("PORT", "ID", "LEASE"),
                   help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.camera:
        camera_main(int(args.camera[0]), args.camera[1], float(args.camera[2]))
        return 0
    drops(args.lease)
    failover(args.lease)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
