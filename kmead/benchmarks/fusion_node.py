"""``kmea bench fusion-node``: what one fusion node carries, and the latency it adds.

The node runs as it would in the field (``kmea fuse --headless`` in its own process, a Zenoh
peer listening on a loopback port). This process plays C cameras (one Zenoh session each,
with the camera's liveliness token and metadata, sending measurements of R robots each at
``fps`` on ``<site>/cam/<id>/robots/<robot>``, capture time = the Unix time of sending) and
the robots (one UDP listener). Latency = UDP arrival - the measurement's time: the Zenoh
hop, the fusion and the UDP hop, i.e. what fusion adds between a camera's daemon and a
robot. CPU = the node
process's user + system time over the wall time (100 % = one core). Loads stay within the
configuration's MAX_ROBOTS robots per node; beyond the node's capacity by a faster rate.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from kmead.config.checks import MAX_ROBOTS
from kmead.outputs.relay import parse_datagram


def _cpu_s(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        parts = f.read().rsplit(")", 1)[1].split()
    return (int(parts[11]) + int(parts[12])) / os.sysconf("SC_CLK_TCK")


def _load(cameras: int, robots: int, fps: float, seconds: float) -> dict:
    import zenoh

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        zport = probe.getsockname()[1]
    meta = json.dumps({"camera": "c", "map_digest": "bench", "map_name": "bench",
                       "model": "bench", "width": 640, "height": 480, "fx": 500.0,
                       "fy": 500.0, "source": "bench",
                       "extent": [0.0, 64.0, 0.0, 1.0]}).encode()  # the robots' floor
    sessions, pubs, kept = [], [], []
    for c in range(cameras):
        conf = zenoh.Config()
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{zport}"]))
        conf.insert_json5("listen/endpoints", "[]")
        conf.insert_json5("scouting/multicast/enabled", "false")
        z = zenoh.open(conf)
        prefix = f"kmea/cam/c{c}"
        # (kept: a token or queryable dropped is undeclared)
        kept.append((z.declare_queryable(f"{prefix}/meta",
                                         lambda q, k=prefix: q.reply(f"{k}/meta", meta)),
                     z.liveliness().declare_token(prefix)))
        sessions.append(z)
        pubs.append([z.declare_publisher(f"{prefix}/robots/r{c}_{k}") for k in range(robots)])
    udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    udp.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)
    udp.bind(("127.0.0.1", 0))
    udp.settimeout(0.2)
    port = udp.getsockname()[1]
    names = [f"r{c}_{k}" for c in range(cameras) for k in range(robots)]
    toml = [f'[[robots]]\nname = "{n}"\nmarkers = [{i}]\n'
            f'destinations = ["udp:127.0.0.1:{port}"]\n' for i, n in enumerate(names)]
    with tempfile.TemporaryDirectory() as tmp, open(Path(tmp) / "node.err", "w+") as err:
        cfg = Path(tmp) / "fuse.toml"
        cfg.write_text("\n".join(toml))
        proc = subprocess.Popen(
            [sys.executable, "-m", "kmead.tools.fuse", "--config", str(cfg), "--headless",
             "--set", 'network.telemetry="tcp://127.0.0.1:*"', "--set", 'network.control=""',
             "--set", 'log.level="error"', "--set", "zenoh.lease_s=0.5",
             "--set", "zenoh.ros2=false", "--set", f'zenoh.listen=["tcp/127.0.0.1:{zport}"]'],
            stdout=subprocess.DEVNULL, stderr=err)
        lat: list[float] = []
        got = [0]
        heard: set[str] = set()
        stop = threading.Event()

        def listen() -> None:
            while not stop.is_set():
                try:
                    data = udp.recv(512)
                except TimeoutError:
                    continue
                now = time.time()
                m = parse_datagram(data)
                heard.add(m["name"])
                if m["valid"]:
                    got[0] += 1
                    lat.append(now - m["t"])

        th = threading.Thread(target=listen, daemon=True)
        th.start()
        try:
            # Measure once every camera's robots reach the UDP listener (the node found
            # the cameras, took their metadata and is active): a fixed start-up wait is
            # too short on a loaded machine, and every message before it is lost.
            deadline = time.monotonic() + 60.0
            first = {f"r{c}_0" for c in range(cameras)}
            while not first <= heard:
                if proc.poll() is not None:
                    # A node that did not start (e.g. a configuration it refuses) would
                    # show as every message lost: say why instead.
                    err.seek(0)
                    lines = err.read().strip().splitlines() or ["(no output)"]
                    raise RuntimeError(f"the fusion node exited with {proc.returncode}: "
                                       f"{lines[-1]}")
                if time.monotonic() > deadline:
                    raise RuntimeError("the fusion node relayed nothing within 60 s")
                for c, ps in enumerate(pubs):
                    ps[0].put(json.dumps({"name": f"r{c}_0", "valid": True, "t": time.time(),
                                          "x": 0.0, "y": 0.1 * c, "theta": 0.0,
                                          "sigma": 0.002}).encode())
                time.sleep(0.05)
            period = 1.0 / fps
            cpu0, w0 = _cpu_s(proc.pid), time.monotonic()
            sent = 0
            lat.clear()
            got[0] = 0
            k = 0
            next_t = time.monotonic()
            while time.monotonic() - w0 < seconds:
                t = time.time()
                for c, ps in enumerate(pubs):
                    for r in range(robots):
                        n = names[c * robots + r]
                        ps[r].put(json.dumps({
                            "name": n, "valid": True, "t": t, "x": 0.001 * k * 0.03 + r,
                            "y": 0.1 * c, "theta": 0.0, "sigma": 0.002}).encode())
                        sent += 1
                k += 1
                next_t += period
                delay = next_t - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            wall = time.monotonic() - w0
            time.sleep(0.3)
            cpu = (_cpu_s(proc.pid) - cpu0) / wall
        finally:
            stop.set()
            proc.terminate()
            proc.wait(timeout=10)
            th.join(timeout=2)
            udp.close()
            for z in sessions:
                z.close()
    lat.sort()
    return {"sent_per_s": sent / wall, "fused_per_s": got[0] / wall, "cpu": cpu,
            "p50": lat[len(lat) // 2] * 1e3 if lat else float("nan"),
            "p99": lat[min(len(lat) - 1, int(0.99 * len(lat)))] * 1e3 if lat else float("nan"),
            "lost": 1.0 - got[0] / max(sent, 1)}


def run(quick: bool = False) -> None:
    # Cameras, robots per camera, frames/s. A node takes at most MAX_ROBOTS robots (the
    # configuration's bound), so the loads beyond its capacity come from a faster rate.
    loads = [(2, 2, 30.0), (4, 10, 30.0), (8, 8, 30.0), (8, 8, 60.0), (8, 8, 120.0)]
    assert all(c * r <= MAX_ROBOTS for c, r, _ in loads)
    if quick:
        loads = loads[:3]
    seconds = 2.0 if quick else 5.0
    print(f"one fusion node ({os.cpu_count()} cores here), {seconds:g} s per load; every "
          "message a measurement of one robot; latency = UDP arrival - capture time")
    ms = loop_cost()
    print(f"the node's loop: {ms:.3f} ms of CPU per measurement (8 cameras x 8 robots, "
          f"its thread's clock): about {1000 / ms:.0f} measurements/s per core",
          flush=True)
    print(f"  {'cameras':>7} {'robots':>6} {'fps':>4} {'msgs/s in':>10} {'fused/s':>8} "
          f"{'lost':>6} {'CPU':>6} {'p50 ms':>7} {'p99 ms':>7}")
    for c, r, fps in loads:
        a = _load(c, r, fps, seconds)
        print(f"  {c:7d} {c * r:6d} {fps:4.0f} {a['sent_per_s']:10.0f} {a['fused_per_s']:8.0f} "
              f"{a['lost'] * 100:5.1f}% {a['cpu'] * 100:5.0f}% {a['p50']:7.2f} {a['p99']:7.2f}",
              flush=True)


def loop_cost(cameras: int = 8, robots: int = 8, n: int = 20000) -> float:
    """The node's loop CPU per measurement (ms, its thread's CPU clock): ``n`` measurements
    of ``cameras`` x ``robots`` already queued, handled as the loop handles them (decode,
    checks, Kalman update, datagram, telemetry, CSV off). Independent of the machine's other
    load, unlike the wall-clock table above."""
    from kmead.config.layers import load_config
    from kmead.fusion.node import FusionNode

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        zport = probe.getsockname()[1]
    names = [f"r{c}_{k}" for c in range(cameras) for k in range(robots)]
    robots_toml = "[" + ", ".join(f'{{name="{nm}", markers=[{i}], destinations='
                                  f'["udp:127.0.0.1:9"]}}' for i, nm in enumerate(names)) + "]"
    cfg = load_config(None, ['network.telemetry="tcp://127.0.0.1:*"', 'network.control=""',
                             'log.level="error"', f"robots={robots_toml}", "zenoh.ros2=false",
                             f'zenoh.listen=["tcp/127.0.0.1:{zport}"]'])
    node = FusionNode(cfg)
    try:
        meta = json.dumps({"camera": "c", "map_digest": "b", "map_name": "b", "model": "b",
                           "width": 640, "height": 480, "fx": 1.0, "fy": 1.0,
                           "source": "b", "extent": [0.0, 64.0, 0.0, 1.0]}).encode()
        for c in range(cameras):
            node.handle("camera", f"kmea/cam/c{c}", True, 0.0)
            node.handle("meta", f"c{c}", meta, 0.0)
        node.election.role = "active"
        node.relay.muted = False  # type: ignore[union-attr]
        items = []
        t0 = time.time() - 0.2  # Unix time, as the cameras stamp it (none in the future)
        for k in range(n // len(names)):
            for i, nm in enumerate(names):
                c = i // robots
                items.append((f"kmea/cam/c{c}/robots/{nm}", json.dumps({
                    "name": nm, "valid": True, "t": t0 + k / 3000, "x": 0.001 * k + i,
                    "y": 0.1 * c, "theta": 0.0, "sigma": 0.002}).encode()))
        t0 = time.thread_time()
        for key, payload in items:
            node.handle("data", key, payload, time.perf_counter())
        return (time.thread_time() - t0) / len(items) * 1e3
    finally:
        node.close()
