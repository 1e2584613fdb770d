"""Figures for the Zenoh output: latency frame -> Zenoh subscriber vs frame -> UDP datagram,
and the daemon's CPU per robot for the ROS 2 output.

    kmea bench zenoh-latency [--frames N] [--sends N]

Latency: a real kmead (subprocess) on the default floor (``sim``, paced at 30 frames/s like
a camera, default configuration, two robots) sends each robot's pose by UDP to this
process and publishes it on Zenoh to this process's session (peer, loopback TCP). Each
message carries the frame's capture time ``t`` (s since the epoch, the same clock here):
the delay is receive time - ``t``, for the UDP datagram, the binary pose
(``<site>/robots/<robot>/pose``) and the ROS 2 pose (``header.stamp``). Also the Zenoh
minus UDP arrival of the same message (robot, seq). Median and p99.

CPU: ``ZenohOutput.send`` for one robot message, timed with the calling thread's CPU
clock, in this process, with a subscriber connected (so the data really leaves): the ROS 2
output (PoseWithCovarianceStamped + /tf, CDR by rosbags, attachment) and the binary pose
alone; per message = per robot per frame, and as a share of one core at 30 frames/s.
"""

from __future__ import annotations

import argparse
import os
import socket
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from kmead.config.layers import load_config
from kmead.outputs import ros2_messages as msgs
from kmead.outputs.relay import RobotChannel, parse_datagram
from kmead.outputs.robot_pose_wire import unpack_pose
from kmead.outputs.zenoh import ZenohOutput

ROOT = Path(__file__).resolve().parents[2]  # the directory that holds kmead


def _free_port(kind: int = socket.SOCK_STREAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _stats(ms: list[float]) -> str:
    if not ms:
        return "no samples"
    a = np.asarray(ms)
    return (f"median {np.median(a):.2f} ms, p99 {np.percentile(a, 99):.2f} ms "
            f"(n = {len(a)})")


def latency(frames: int) -> None:
    zport = _free_port()
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("listen/endpoints", f'["tcp/127.0.0.1:{zport}"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(conf)
    lock = threading.Lock()
    udp_at: dict[tuple[str, int], tuple[float, float]] = {}  # (robot, seq) -> (recv, t)
    zen_at: dict[tuple[str, int], tuple[float, float]] = {}
    ros_ms: list[float] = []

    def on_binary(s) -> None:
        now = time.time()
        p = unpack_pose(s.payload.to_bytes())
        if p.valid:
            with lock:
                zen_at[(str(s.key_expr).split("/")[2], p.seq)] = (now, p.t)

    def on_ros(s) -> None:
        now = time.time()
        m: Any = msgs.decode(s.payload.to_bytes(), msgs.POSE_TYPE)  # a rosbags message
        with lock:
            ros_ms.append((now - m.header.stamp.sec - m.header.stamp.nanosec * 1e-9) * 1e3)

    subs = [session.declare_subscriber("kmea/robots/*/pose", on_binary),
            session.declare_subscriber("0/kmea/*/pose/**", on_ros)]
    socks, ports = [], []
    for _ in range(2):
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.bind(("127.0.0.1", 0))
        s.settimeout(0.5)
        socks.append(s)
        ports.append(s.getsockname()[1])
    stop = threading.Event()

    def udp_loop(s: socket.socket) -> None:
        while not stop.is_set():
            try:
                data = s.recv(2048)
            except TimeoutError:
                continue
            now = time.time()
            d = parse_datagram(data)
            if d["valid"]:
                with lock:
                    udp_at[(d["name"], d["seq"])] = (now, d["t"])

    threads = [threading.Thread(target=udp_loop, args=(s,), daemon=True) for s in socks]
    for t in threads:
        t.start()
    robots = ('robots=[{name="amr1", markers=[40, 41], height=0.2, length=0.06, '
              f'destinations=["udp:127.0.0.1:{ports[0]}"]}}, {{name="amr2", markers=[42], '
              f'height=0.2, length=0.06, destinations=["udp:127.0.0.1:{ports[1]}"]}}]')
    env = dict(os.environ, PYTHONPATH=f"{ROOT}{os.pathsep}" + os.environ.get("PYTHONPATH", ""))
    cmd = [sys.executable, "-m", "kmead.cli", "--headless", "--frames", str(frames),
           "--free-ports", "--status-every", "0", "--set", robots,
           "--set", "zenoh.enabled=true", "--set", f'zenoh.connect=["tcp/127.0.0.1:{zport}"]']
    print("kmead:", " ".join(a if " " not in a else repr(a) for a in cmd[1:]), flush=True)
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd="/tmp")
    time.sleep(1.0)  # the last samples in flight
    stop.set()
    for t in threads:
        t.join()
    for s in subs:
        s.undeclare()
    session.close()
    if proc.returncode != 0:
        sys.exit(f"kmead failed: {proc.stderr[-2000:]}")
    summary = [ln for ln in proc.stdout.splitlines() if "frames in" in ln or "latency" in ln]
    print("\n".join(summary))
    with lock:
        udp = [(r - t) * 1e3 for r, t in udp_at.values()]
        zen = [(r - t) * 1e3 for r, t in zen_at.values()]
        both = [(zen_at[k][0] - udp_at[k][0]) * 1e3 for k in udp_at if k in zen_at]
    print(f"frame -> UDP datagram:           {_stats(udp)}")
    print(f"frame -> Zenoh binary pose:      {_stats(zen)}")
    print(f"frame -> Zenoh ROS 2 pose:       {_stats(ros_ms)}")
    print(f"Zenoh binary minus UDP (same message): {_stats(both)}")


def cpu(sends: int) -> None:
    port = _free_port()
    for ros2, label in ((True, "ROS 2 output (pose + /tf) and binary pose"),
                        (False, "binary pose alone")):
        z = load_config(None, ["zenoh.enabled=true", f'zenoh.listen=["tcp/127.0.0.1:{port}"]',
                               f"zenoh.ros2={str(ros2).lower()}"], use_local=False)["zenoh"]
        out = ZenohOutput.open(z)
        sub_conf = zenoh.Config()
        sub_conf.insert_json5("connect/endpoints", f'["tcp/127.0.0.1:{port}"]')
        sub_conf.insert_json5("listen/endpoints", "[]")
        sub_conf.insert_json5("scouting/multicast/enabled", "false")
        sub_session = zenoh.open(sub_conf)
        # A channel, no Python callback: the subscriber takes no GIL from the timed thread.
        sub = sub_session.declare_subscriber("**", zenoh.handlers.RingChannel(100000))
        tr = RobotChannel("amr1", [40, 41], [], [], x=0.5, y=0.25, theta=1.0, sigma=0.003,
                        cov=np.diag([9e-6, 9e-6, 4e-4]),
                        extra={"vx": 0.1, "vy": 0.0, "omega": 0.2, "age": 0.0})
        time.sleep(1.0)  # the subscriber's declaration reaches the publisher
        for i in range(200):  # warm-up (publishers declared, caches)
            tr.seq = i
            out.send(tr, time.time(), True)
        per = []
        for i in range(sends):
            tr.seq = 200 + i
            c0 = time.thread_time()
            out.send(tr, time.time(), True)
            per.append((time.thread_time() - c0) * 1e6)
            time.sleep(1 / 300)  # not back to back: a frame loop's pace, ten robots
        time.sleep(0.5)
        got = sum(1 for _ in iter(sub.try_recv, None))
        med = statistics.median(per)
        print(f"CPU per robot per frame, {label}: median {med:.0f} us, mean "
              f"{statistics.fmean(per):.0f} us ({statistics.fmean(per) * 30 / 1e4:.2f} % of "
              f"a core at 30 frames/s); {got} samples received, errors {out.errors}")
        sub.undeclare()
        sub_session.close()
        out.close()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="kmea bench zenoh-latency",
                                 description=(__doc__ or "").split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=600)
    ap.add_argument("--sends", type=int, default=3000)
    a = ap.parse_args(argv)
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    latency(a.frames)
    cpu(a.sends)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
