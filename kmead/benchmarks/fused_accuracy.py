"""How good the fused stream is: the fusion node's poses against the simulator's truth.

    kmea bench fused-accuracy [--speeds 0.25 1.5] [--seconds 40] [--width 820]

Two camera processes (``kmead --source "sim:wide?camera=N&clock=wall..."``, Zenoh on) and one
``kmea fuse`` on this machine, on a private loopback Zenoh port; the robots are UDP
listeners here. The wall-clock simulator draws every frame's robots at the Unix time it
stamps the frame with (:class:`kmea.sim.motion.WallClock`), so the truth of a pose is the
scene's path at the pose's own ``t``, whichever process drew it.

For each speed it reports, per region of the floor, the position and heading RMSE against
truth of:

- ``fused``: every ``valid=1`` datagram the node sent, at its ``t``;
- ``camN raw``: that camera's measurements (``<site>/cam/camN/robots/<robot>``, the pose
  before any tracking filter) at their ``t``;
- ``camN filt``: the same measurements through the tracking filter a camera alone runs
  (:class:`kmea.robots.tracking.Tracker`, the default configuration): what that camera's
  own stream would have been.

Regions, by which cameras measured the robot within ``--window`` s of a pose's ``t``:
``one`` (one camera), ``overlap`` (both), ``handover`` (within 0.5 s of the set changing).
The first ``--settle`` s after the node's first datagram are left out (its tracks start).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from kmead.outputs.relay import parse_datagram

ROOT = Path(__file__).resolve().parents[2]
SITE = "kmeabench"
ROBOTS = (("amr1", "[40, 41]"), ("amr2", "[42]"))


def _free_port(kind: int = socket.SOCK_STREAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass
class Stream:
    """Poses (t, x, y, theta) of one robot from one source."""

    t: list[float] = field(default_factory=list)
    x: list[float] = field(default_factory=list)
    y: list[float] = field(default_factory=list)
    theta: list[float] = field(default_factory=list)
    sigma: list[float | None] = field(default_factory=list)

    def add(self, t: float, x: float, y: float, theta: float,
            sigma: float | None = None) -> None:
        self.t.append(t)
        self.x.append(x)
        self.y.append(y)
        self.theta.append(theta)
        self.sigma.append(sigma)


def _zenoh_sets(zport: int, extra: list[str]) -> list[str]:
    return ["--set", "zenoh.enabled=true", "--set", f'zenoh.site="{SITE}"',
            "--set", f'zenoh.connect=["tcp/127.0.0.1:{zport}"]',
            "--set", 'zenoh.listen=["tcp/127.0.0.1:0"]', "--set", "zenoh.ros2=false",
            "--set", "zenoh.lease_s=1.0", *extra]


def _robots(ports: dict[str, int]) -> str:
    return "robots=[" + ", ".join(
        f'{{name="{n}", markers={m}, height=0.2, destinations=["udp:127.0.0.1:{ports[n]}"]}}'
        for n, m in ROBOTS) + "]"


def run_once(speed: float, seconds: float, width: int, settle: float, window: float,
             fps: float = 30.0,
             ) -> tuple[dict[str, dict[str, list[float]]], dict[str, float]]:
    """One run at ``speed`` m/s with the cameras asked for ``fps`` frames/s: ({region:
    {stream: [pos rmse mm, heading rmse mrad, n]}}, {camera: the frame rate it achieved,
    from the median interval of its measurements of a robot})."""
    import zenoh

    from kmea.robots.tracking import Tracker
    from kmea.sim.scenes import scene_from_spec

    height = round(width * 1232 / 1640)
    zport = _free_port()
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{zport}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(conf)
    lock = threading.Lock()
    raw: dict[tuple[str, str], Stream] = defaultdict(Stream)

    def on_measurement(s) -> None:
        parts = str(s.key_expr).split("/")  # <site>/cam/<id>/robots/<robot>
        try:
            m = json.loads(s.payload.to_bytes())
        except ValueError:
            return
        if m.get("valid"):
            with lock:
                raw[(parts[2], parts[4])].add(m["t"], m["x"], m["y"], m["theta"],
                                              m.get("sigma"))

    sub = session.declare_subscriber(f"{SITE}/cam/*/robots/*", on_measurement)
    udp = {n: socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for n, _ in ROBOTS}
    ports = {}
    for n, s in udp.items():
        s.bind(("127.0.0.1", 0))
        s.settimeout(0.2)
        ports[n] = s.getsockname()[1]
    fused: dict[str, Stream] = defaultdict(Stream)
    stop = threading.Event()

    def listen(name: str, s: socket.socket) -> None:
        while not stop.is_set():
            try:
                data = s.recv(2048)
            except OSError:
                continue
            d = parse_datagram(data)
            if d["valid"]:
                fused[name].add(d["t"], d["x"], d["y"], d["theta"])

    threads = [threading.Thread(target=listen, args=(n, s), daemon=True)
               for n, s in udp.items()]
    for t in threads:
        t.start()
    epoch = time.time()
    env = dict(os.environ, PYTHONPATH=f"{ROOT}{os.pathsep}" + os.environ.get("PYTHONPATH", ""))
    procs = []
    with tempfile.TemporaryDirectory() as tmp:
        try:
            for cam in (0, 1):
                spec = (f"sim:wide?camera={cam}&clock=wall&epoch={epoch}&speed={speed}"
                        f"&width={width}&height={height}")
                procs.append(subprocess.Popen(
                    [sys.executable, "-m", "kmead.cli", "--headless", "--free-ports",
                     "--status-every", "0", "--source", spec, "--set", f"source.fps={fps}",
                     *_zenoh_sets(zport, ["--set", _robots({n: _free_port(socket.SOCK_DGRAM)
                                                            for n, _ in ROBOTS})])],
                    cwd=tmp, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
            procs.append(subprocess.Popen(
                [sys.executable, "-m", "kmead.tools.fuse", "--headless",
                 *_zenoh_sets(zport, ["--set", 'network.telemetry=""', "--set",
                                      'network.control=""', "--set", _robots(ports)])],
                cwd=tmp, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
            deadline = time.monotonic() + 120
            while time.monotonic() < deadline and not all(fused[n].t for n, _ in ROBOTS):
                time.sleep(0.2)
            if not all(fused[n].t for n, _ in ROBOTS):
                raise RuntimeError("the fusion node sent no pose within 120 s")
            t_first = time.time()
            time.sleep(seconds + settle)
        finally:
            for p in procs:
                if p.poll() is None:
                    p.send_signal(signal.SIGINT)
            for p in procs:
                try:
                    p.wait(20)
                except subprocess.TimeoutExpired:
                    p.kill()
            stop.set()
            for t in threads:
                t.join(2)
            sub.undeclare()
            session.close()
            for s in udp.values():
                s.close()
    truth_scene = scene_from_spec(f"sim:wide?speed={speed}")
    t_from = t_first + settle
    errs: dict[str, dict[str, list[tuple[float, float]]]] = defaultdict(lambda: defaultdict(list))
    with lock:
        raw_copy = {k: v for k, v in raw.items()}
    for name, _ in ROBOTS:
        seen = {cam: np.asarray(raw_copy[(cam, name)].t) for cam in ("cam0", "cam1")
                if (cam, name) in raw_copy}
        streams = {"fused": fused[name]}
        for cam in ("cam0", "cam1"):
            st = raw_copy.get((cam, name))
            if st is None:
                continue
            streams[f"{cam} raw"] = st
            tracker, filt = Tracker(), Stream()
            # With the sigma the camera sent, as its kmead's own filter and the node take it.
            for t, x, y, th, sg in sorted(zip(st.t, st.x, st.y, st.theta, st.sigma,
                                              strict=True), key=lambda r: r[0]):
                out = tracker.update(name, t, x, y, th, sg)
                if out.state is not None and out.kind != "rejected":
                    filt.add(t, out.state.x, out.state.y, out.state.theta)
            streams[f"{cam} filt"] = filt
        for label, st in streams.items():
            for t, x, y, th in zip(st.t, st.x, st.y, st.theta, strict=True):
                if t < t_from:
                    continue
                tx, ty, tth = truth_scene.robot_poses(t - epoch)[name]
                d_th = (th - tth + math.pi) % (2 * math.pi) - math.pi
                errs[_region(seen, t, window)][label].append((math.hypot(x - tx, y - ty), d_th))
    rates: dict[str, float] = {}
    for cam in ("cam0", "cam1"):
        gaps = np.concatenate([np.diff(np.asarray(raw_copy[(cam, n)].t)) for n, _ in ROBOTS
                               if (cam, n) in raw_copy] or [np.zeros(0)])
        gaps = gaps[(gaps > 0) & (gaps < 0.5)]
        rates[cam] = 1.0 / float(np.median(gaps)) if gaps.size else 0.0
    table: dict[str, dict[str, list[float]]] = {}
    for reg, by in errs.items():
        table[reg] = {}
        for label, e in by.items():
            a = np.asarray(e)
            table[reg][label] = [1e3 * math.sqrt(float(np.mean(a[:, 0] ** 2))),
                                 1e3 * math.sqrt(float(np.mean(a[:, 1] ** 2))), len(a)]
    return table, rates


def _region(seen: dict[str, np.ndarray], t: float, window: float) -> str:
    """``one``, ``overlap`` or ``handover`` (module docstring) for a pose at ``t``."""
    def cams_at(u: float) -> frozenset[str]:
        return frozenset(c for c, ts in seen.items()
                         if ts.size and np.min(np.abs(ts - u)) <= window)
    now = cams_at(t)
    if any(cams_at(t + d) != now for d in (-0.5, -0.25, 0.25, 0.5)):
        return "handover"
    return "overlap" if len(now) == 2 else "one"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="kmea bench fused-accuracy", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--speeds", type=float, nargs="+", default=[0.25, 1.5])
    ap.add_argument("--seconds", type=float, default=40.0, help="measured per speed")
    ap.add_argument("--settle", type=float, default=3.0)
    ap.add_argument("--width", type=int, default=820, help="camera width (px; 4:3)")
    ap.add_argument("--fps", type=float, default=30.0,
                    help="frame rate asked of the cameras (source.fps; default 30, kmead's)")
    ap.add_argument("--window", type=float, default=0.1,
                    help="s: a camera measured the robot this close to a pose's t")
    args = ap.parse_args(argv)
    print(f"fused accuracy: 2 cameras (sim:wide, {args.width} px wide, clock=wall) + 1 fusion "
          f"node, {args.seconds:.0f} s per speed; RMSE against truth at each pose's t")
    print("speed m/s | region   | stream    | pos RMSE mm | heading RMSE mrad |     n")
    for speed in args.speeds:
        table, rates = run_once(speed, args.seconds, args.width, args.settle, args.window,
                                args.fps)
        print(f"{speed:9.2f} | cameras asked for {args.fps:g} frames/s, achieved: "
              + ", ".join(f"{c} {r:.1f}" for c, r in rates.items()))
        for reg in ("one", "overlap", "handover"):
            for label in ("fused", "cam0 raw", "cam0 filt", "cam1 raw", "cam1 filt"):
                v = table.get(reg, {}).get(label)
                if v is not None:
                    print(f"{speed:9.2f} | {reg:8s} | {label:9s} | {v[0]:11.2f} | "
                          f"{v[1]:17.2f} | {int(v[2]):5d}")
        sys.stdout.flush()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
