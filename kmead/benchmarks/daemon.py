"""The daemon's own benchmarks (``kmea bench daemon`` / ``latency`` / ``tui``): figures, no
asserts.

daemon: frames/s of the whole daemon (detection, pose, estimator, leave-one-out, filter,
robots, relay, CSV, telemetry) on pre-rendered 1640x1232 simulator frames (rendering not
counted), beside the rate of bare ``detectMarkers`` on the same frames, with 1 and 2
detection threads (``detector.workers``). The library's own figures (detection variants,
the pipeline in one thread) are ``kmea bench pipeline`` (:mod:`kmea.benchmarks.pipeline`).
latency: frame-to-UDP-datagram latency at 1640x1232 and 30 frames/s, full detection vs
tracking, measured by a UDP listener process (arrival time minus the datagram's ``t``).
tui: CPU of ``kmea-tui`` at 120x40 on each tab, and the daemon's frame rate with the UI
connected and without.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from kmea.benchmarks.pipeline import bare_detection, render
from kmea.sources.registry import register_source
from kmea.sources.sim import SimSource
from kmead.config.layers import load_config
from kmead.run.daemon import Daemon

NET = ['network.telemetry="tcp://127.0.0.1:*"', 'network.control="tcp://127.0.0.1:*"']


_BENCH: dict = {}
# The pre-rendered frames, served by the simulator source (rendering not counted).
register_source("bench", lambda rest, **o: SimSource(_BENCH["scene"], rendered=_BENCH["frames"]))
# The same, served in real time at the scene's 30 frames/s (a live source).
register_source("bench-live", lambda rest, **o: SimSource(_BENCH["scene"], realtime=True,
                                                          rendered=_BENCH["frames"]))


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
    bare, _ = bare_detection([f.pixels for f in frames], {}, scene.world_map.dictionary)
    print(f"{n} pre-rendered frames {scene.size[0]}x{scene.size[1]}; bare detectMarkers "
          f"{bare:6.1f} frames/s")
    with tempfile.TemporaryDirectory() as tmp:
        for label, sets in (("main thread only (workers=0)", ["detector.workers=0"]),
                            ("detection thread ahead (workers=1)", ["detector.workers=1"]),
                            ("two detection threads (workers=2)", ["detector.workers=2"])):
            fps, ms, d = _daemon_fps(tmp, sets)
            rest = ms["total"] - ms["detect"] - ms["capture"]
            print(f"pipeline, {label}: {fps:6.1f} frames/s = {fps / bare * 100:5.1f} % of bare "
                  f"default detection; markers seen {len(d.totals.markers_seen)}; stage "
                  "ms/frame: " + ", ".join(f"{k} {v:.2f}" for k, v in ms.items()
                                           if k != "capture")
                  + f"; non-detection stages {rest:.2f} ms = {rest / ms['total'] * 100:.0f} %")


# The UDP listener of ``kmea bench latency``: a process of its own (measured outside the
# daemon). Prints its port, records arrival time - the datagram's t (ms) of every valid
# datagram until stdin closes, then prints them as JSON.
LISTENER = r"""
import json, selectors, socket, sys, time
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.bind(("127.0.0.1", 0))
print(s.getsockname()[1], flush=True)
sel = selectors.DefaultSelector()
sel.register(s, selectors.EVENT_READ)
sel.register(sys.stdin, selectors.EVENT_READ)
lat = []
while True:
    for key, _ in sel.select():
        if key.fileobj is s:
            data = s.recv(512)
            now = time.time()
            f = dict(p.split("=", 1) for p in data.decode("ascii").split(";"))
            if f.get("valid") == "1":
                lat.append((float(f["t"]), (now - float(f["t"])) * 1e3))
        elif not sys.stdin.readline():
            print(json.dumps(lat), flush=True)
            sys.exit(0)
"""


def _listen() -> tuple[subprocess.Popen, int]:
    proc = subprocess.Popen([sys.executable, "-c", LISTENER], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    if proc.stdout is None:  # cannot happen with stdout=PIPE
        raise RuntimeError("kmea bench: the listener has no stdout pipe")
    return proc, int(proc.stdout.readline())


def _collect(proc: subprocess.Popen) -> np.ndarray:
    """(N, 2): each valid datagram's time ``t`` (s) and its latency (ms), as recorded."""
    out, _ = proc.communicate("", timeout=30)  # stdin closed: the listener reports
    return np.asarray(json.loads(out.strip().splitlines()[-1]), dtype=float).reshape(-1, 2)


# A daemon's first second is start-up (the first frame is a full detection, the floor's
# references settle): the steady-state figures leave it out.
STEADY_S = 1.0


def run_latency(quick: bool = False) -> None:
    """Frame-to-datagram latency at 1640x1232 and 30 frames/s: full detection of every
    frame, then tracking (the default for live sources), back to back on the same
    pre-rendered frames served in real time (the paced simulator without its rendering
    time); a UDP listener process takes arrival time minus the datagram's ``t``. Run it
    under ``taskset -c 0`` for the one-core (Pi stand-in) figures."""
    n = 90 if quick else 240
    frames, scene = render(n)
    _BENCH.update(frames=frames, scene=scene)
    cores = len(os.sched_getaffinity(0))
    print(f"{n} pre-rendered frames {scene.size[0]}x{scene.size[1]} served at 30 frames/s "
          f"(default scene, 2 moving robots); {cores} core(s)")
    rows = {}
    for label, sets in (("full detection every frame (detector.fixed_camera=false)",
                         ["detector.fixed_camera=false"]),
                        ("tracking (default)", [])):
        proc, port = _listen()
        robots = (f'robots=[{{name="amr1", markers=[40, 41], '
                  f'destinations=["udp:127.0.0.1:{port}"]}}, {{name="amr2", markers=[42], '
                  f'destinations=["udp:127.0.0.1:{port}"]}}]')
        cfg = load_config(None, ["source.spec=bench-live", robots, *NET, *sets])
        d = Daemon(cfg, max_frames=n - 2)
        c0 = time.process_time()
        try:
            d.run()
        finally:
            d.close()
        cpu = time.process_time() - c0
        got = _collect(proc)
        a = got[:, 1]
        steady = got[got[:, 0] >= got[:, 0].min() + STEADY_S, 1] if len(got) else a
        t = d.totals
        wall = t.t_end - t.t_start
        fps = t.frames / wall if wall > 0 else 0.0
        med, p99 = (np.median(a), np.percentile(a, 99)) if a.size else (math.nan, math.nan)
        rows[label] = (med, p99, fps)
        print(f"{label}: {t.frames} frames processed of {d.capture.captured if d.capture else 0}"
              f" captured, {d.dropped} dropped, {fps:.1f} frames/s, CPU "
              f"{cpu / max(1, t.frames) * 1e3:.1f} ms/frame; frame-to-datagram latency over "
              f"{a.size} datagrams: median {med:.1f} ms, p99 {p99:.1f} ms, max "
              f"{a.max() if a.size else math.nan:.1f} ms; from {STEADY_S:g} s on "
              f"({steady.size} datagrams): median "
              f"{np.median(steady) if steady.size else math.nan:.1f} ms, p99 "
              f"{np.percentile(steady, 99) if steady.size else math.nan:.1f} ms")
    (fm, fp, _), (tm, tp, _) = rows.values()
    print(f"tracking / full detection: median {tm / fm:.2f}, p99 {tp / fp:.2f}")


def _cpu_seconds(pid: int) -> float:
    """utime + stime of process ``pid`` (all its threads), seconds (Linux /proc)."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rpartition(")")[2].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _frames_in(d: Daemon, seconds: float) -> float:
    """The daemon's frame rate over the next ``seconds`` (frames/s)."""
    f0, t0 = d.totals.frames, time.perf_counter()
    time.sleep(seconds)
    return (d.totals.frames - f0) / (time.perf_counter() - t0)


def run_tui(quick: bool = False) -> None:
    """CPU of ``kmea-tui`` at 120x40 on each tab (a process of its own in a pseudo-terminal,
    attached to a daemon on the paced pre-rendered frames at 30 frames/s), and the daemon's
    frame rate without the UI and with it, in the same run."""
    import fcntl
    import pty
    import shutil
    import struct
    import termios
    import threading

    exe = shutil.which("kmea-tui") or str(Path(sys.executable).with_name("kmea-tui"))
    if not Path(exe).exists():
        print("kmea-tui not installed: no UI figures")
        return
    settle, window = (1.5, 3.0) if quick else (3.0, 8.0)
    frames, scene = render(60 if quick else 150)
    # Loop the pre-rendered frames for as long as the run lasts (robots jump back at the
    # loop: the tracking detector re-finds them, as after an occlusion).
    n = int(30 * (4 * settle + 8 * (settle + window) + 20))
    _BENCH.update(frames=[frames[i % len(frames)] for i in range(n)], scene=scene)
    cfg = load_config(None, ["source.spec=bench-live", *NET])
    d = Daemon(cfg)
    runner = threading.Thread(target=d.run, daemon=True)
    runner.start()
    try:
        time.sleep(settle)
        alone = _frames_in(d, window)
        print(f"daemon alone: {alone:.1f} frames/s (1640x1232, 30 frames/s paced, tracking)")
        telemetry, control = d.telemetry, d.control
        if telemetry is None or control is None:  # NET binds both
            raise RuntimeError("kmea bench: the daemon has no telemetry or control socket")
        pid, fd = pty.fork()
        if pid == 0:  # the UI, in a 120x40 pseudo-terminal
            os.execv(exe, [exe, "--telemetry", telemetry.bound, "--control", control.bound])
        fcntl.ioctl(fd, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 120, 0, 0))
        stop = threading.Event()

        def drain() -> None:  # the terminal's side: read (and drop) what the UI draws
            while not stop.is_set():
                try:
                    if not os.read(fd, 65536):
                        return
                except OSError:
                    return

        reader = threading.Thread(target=drain, daemon=True)
        reader.start()
        time.sleep(settle * 2)
        rates = []
        for key, tab in (("1", "Markers"), ("2", "Robots"), ("3", "Statistics"), ("4", "Map"),
                         ("5", "Config"), ("6", "Log")):
            os.write(fd, key.encode())
            time.sleep(settle)
            c0, t0 = _cpu_seconds(pid), time.perf_counter()
            fps = _frames_in(d, window)
            cpu = (_cpu_seconds(pid) - c0) / (time.perf_counter() - t0) * 100
            rates.append(fps)
            print(f"kmea-tui 120x40, tab {tab}: {cpu:5.1f} % of a core; daemon {fps:.1f} "
                  f"frames/s with the UI attached")
        with_ui = float(np.mean(rates))
        os.write(fd, b"q")
        time.sleep(0.5)
        stop.set()
        with contextlib.suppress(ChildProcessError, OSError):
            os.kill(pid, 15)
            os.waitpid(pid, 0)
        os.close(fd)
        # Without the UI again after it quit: the machine's load drifts over the run, so the
        # baseline is the mean of the windows before and after the UI.
        time.sleep(settle)
        after = _frames_in(d, window)
        print(f"daemon alone after the UI quit: {after:.1f} frames/s")
        without = (alone + after) / 2
        print(f"daemon frame rate with the UI / without: {with_ui:.1f} / {without:.1f} = "
              f"{with_ui / without:.3f}")
    finally:
        d.stop()
        runner.join(timeout=5)
        d.close()
