"""``kmea bench pipeline``: detection variants and the library pipeline, one thread.

On pre-rendered 1640x1232 simulator frames (scene "default", two robots; rendering not
counted): bare ``detectMarkers`` with the default parameters and with one 13 px
threshold window, then :class:`kmea.pipeline.Pipeline` (detection, pose, estimator,
leave-one-out, filter, robots) with full detection, then with tracking for a fixed camera
(:mod:`kmea.fixed_camera`) against full detection of every frame, with the default
estimator and with ``corner-pnp``, back to back on the same frames. Times are wall-clock
and CPU (``time.process_time``: every thread of the process, OpenCV's worker threads
included; the tracking detector's discoveries run in the calling thread),
per frame and as a share of bare ``detectMarkers``: the one timed at the start and, for
each tracking run, one timed just before it (this machine's speed drifts by tens of percent
within a minute; the adjacent one compares like with like). The daemon's figures with its
threads, files and sockets are ``kmea bench daemon``.
"""

from __future__ import annotations

import os
import time

import numpy as np

from kmea.pipeline import FrameInput, Pipeline, PipelineSettings

TUNED = {"adaptiveThreshWinSizeMin": 13, "adaptiveThreshWinSizeMax": 13}


def render(n: int):
    """``n`` rendered frames of the default scene (:class:`kmea.sim.renderer.SimFrame`) and
    the scene."""
    from kmea.sim.renderer import Renderer
    from kmea.sim.scenes import get_scene

    scene = get_scene("default")
    r = Renderer(scene)
    return [r.render(i) for i in range(n)], scene


def bare_detection(images: list[np.ndarray], params: dict, dictionary: str,
                   cpu: list[float] | None = None) -> tuple[float, list[set]]:
    """Frames/s of bare ``detectMarkers`` and the ids found in each frame; ``cpu`` gets the
    CPU ms per frame appended."""
    from kmea.vision.detection import DetectorConfig, MarkerDetector

    raw = MarkerDetector(DetectorConfig(dictionary, parameters=params))._detector
    raw.detectMarkers(images[0])  # warm-up
    found = []
    c0 = time.process_time()
    t0 = time.perf_counter()
    for f in images:
        _, ids, _ = raw.detectMarkers(f)
        found.append(set() if ids is None else set(ids.ravel().tolist()))
    if cpu is not None:
        cpu.append((time.process_time() - c0) / len(images) * 1e3)
    return len(images) / (time.perf_counter() - t0), found


def pipeline_rate(frames, scene, settings: PipelineSettings, out: dict | None = None
                  ) -> tuple[float, dict[str, float]]:
    """Frames/s of :meth:`Pipeline.process` and its mean stage times (ms). ``out`` gets
    ``cpu_ms`` (CPU per frame, all threads), ``results`` and the ``pipeline``."""
    p = Pipeline(scene.camera, scene.effective_map(), settings)
    sums: dict[str, float] = {}
    results = []
    c0, m0 = time.process_time(), time.thread_time()
    t0 = time.perf_counter()
    marks = [(t0, c0, m0)]  # per frame boundary: wall, CPU of all threads, main thread
    for f in frames:
        res = p.process(FrameInput(f.index, f.timestamp, f.image))
        marks.append((time.perf_counter(), time.process_time(), time.thread_time()))
        results.append(res)
        for k, v in res.timings.items():
            sums[k] = sums.get(k, 0.0) + v
    rate = len(frames) / (time.perf_counter() - t0)
    cpu = (time.process_time() - c0) / len(frames) * 1e3
    main = (time.thread_time() - m0) / len(frames) * 1e3
    p.close()
    if out is not None:
        out.update(cpu_ms=cpu, main_cpu_ms=main, results=results, pipeline=p,
                   marks=np.asarray(marks))
    return rate, {k: v / len(frames) for k, v in sums.items()}


# Frames of start-up (1 s at 30 frames/s) left out of the steady-state figures.
STEADY_FROM = 30


def compare_tracking(frames, scene, bare_fps: float, bare_cpu: float, algorithms) -> None:
    """Full detection of every frame vs tracking, per estimator, on the same frames: time
    per frame (wall, CPU) as a share of bare detection, markers and robots found, and the
    leave-one-out error of the floor (accuracy)."""
    robots = tuple(scene.robot_specs())
    truth = [f.truth for f in frames]
    images = [f.image for f in frames]
    dic = scene.world_map.dictionary
    for algo in algorithms:
        row = {}
        for label, tracking in (("full detection", False), ("tracking", True)):
            out: dict = {}
            if tracking:
                adjacent = _adjacent_bare(images, dic)
            rate, ms = pipeline_rate(frames, scene, PipelineSettings(
                algorithm=algo, robots=robots, fixed_camera=tracking), out)
            res = out["results"]
            loo = [e for r in res for e in r.loo.values()]
            n_robot_frames = sum(len(r.robots) for r in res)
            # A robot is visible when one of its markers is (truth: corners and centre seen).
            visible = sum(sum(1 for spec in robots if set(spec.markers) & t.visible)
                          for t in truth)
            det = out["pipeline"].detector
            extra = ""
            if tracking:
                inc = out["pipeline"]
                extra = (f"; {det.followed_frames} followed / {det.full} full frames, "
                         f"{det.background} background full detections, poses "
                         f"{inc.session.poses.posed} computed / {inc.session.poses.reused} reused, "
                         f"leave-one-out {inc.session.loo.computed} computed / "
                         f"{inc.session.loo.reused} reused")
            wall = 1e3 / rate
            row[label] = (wall, out["cpu_ms"])
            print(f"{algo}, {label}: {wall:6.2f} ms/frame wall = "
                  f"{wall / (1e3 / bare_fps) * 100:5.1f} % of bare detection, "
                  f"{out['cpu_ms']:6.2f} ms/frame CPU = {out['cpu_ms'] / bare_cpu * 100:5.1f} % "
                  f"of bare detection's CPU (main thread {out['main_cpu_ms']:.2f} ms); "
                  f"{np.mean([len(r.ids) for r in res]):.1f} "
                  f"markers/frame, robot poses {n_robot_frames} (robots visible "
                  f"{visible}); floor leave-one-out error mean "
                  f"{np.mean(loo) * 1e3 if loo else float('nan'):.2f} mm, max "
                  f"{np.max(loo) * 1e3 if loo else float('nan'):.2f} mm; stage ms/frame: "
                  + ", ".join(f"{k} {v:.2f}" for k, v in ms.items() if k != "capture")
                  + extra)
            if tracking:
                _print_steady(f"{algo}, tracking", out["marks"], bare_fps, bare_cpu)
                _print_adjacent(f"{algo}, tracking", out["marks"], adjacent)
        (fw, fc), (tw, tc) = row["full detection"], row["tracking"]
        print(f"{algo}: tracking / full detection = {tw / fw:.2f} (wall), {tc / fc:.2f} (CPU)")
        # The library's default robot filter is the paper's IIR; the daemon's configuration
        # defaults to the tracking filter (kmea.robots.tracking), whose update runs per robot per
        # frame: the same tracking run with it.
        out = {}
        adjacent = _adjacent_bare(images, dic)
        rate, _ = pipeline_rate(frames, scene, PipelineSettings(
            algorithm=algo, robots=robots, fixed_camera=True, filter_kind="kalman"), out)
        wall = 1e3 / rate
        print(f"{algo}, tracking, robots' tracking filter (filter.kind = kalman): "
              f"{wall:6.2f} ms/frame wall = {wall / (1e3 / bare_fps) * 100:5.1f} % of bare "
              f"detection, {out['cpu_ms']:6.2f} ms/frame CPU = "
              f"{out['cpu_ms'] / bare_cpu * 100:5.1f} % of bare detection's CPU (main thread "
              f"{out['main_cpu_ms']:.2f} ms)")
        _print_steady(f"{algo}, tracking, robots' tracking filter", out["marks"], bare_fps,
                      bare_cpu)
        _print_adjacent(f"{algo}, tracking, robots' tracking filter", out["marks"], adjacent)


def _adjacent_bare(images: list[np.ndarray], dictionary: str) -> float:
    """Bare ``detectMarkers`` (default parameters) on the same frames, timed just before a
    run (wall ms a frame): this machine's speed drifts by tens of percent over a minute, so
    the run is also compared with the detection timed next to it."""
    fps, _ = bare_detection(images, {}, dictionary)
    return 1e3 / fps


def _print_adjacent(label: str, marks: np.ndarray, bare_ms: float) -> None:
    """The run's wall time per frame (whole run and from STEADY_FROM on) against the bare
    detection timed just before it (``bare_ms``)."""
    n = len(marks) - 1
    whole = (marks[-1, 0] - marks[0, 0]) / n * 1e3
    text = f"{label}, against bare detection timed just before it ({bare_ms:.2f} ms/frame): " \
           f"{whole / bare_ms * 100:5.1f} %"
    if n > 2 * STEADY_FROM:
        steady = (marks[-1, 0] - marks[STEADY_FROM, 0]) / (n - STEADY_FROM) * 1e3
        text += f" (frames {STEADY_FROM}-{n - 1}: {steady / bare_ms * 100:5.1f} %)"
    print(text)


def _print_steady(label: str, marks: np.ndarray, bare_fps: float, bare_cpu: float) -> None:
    """The run's figures from frame STEADY_FROM on (``marks``: :func:`pipeline_rate`'s frame
    boundaries). A live camera runs for hours: the first second (the cold first frame, the
    floor's references averaged, markers uncovered for the first time) is start-up; the
    rest is what every later second costs."""
    n = len(marks) - 1
    if n <= 2 * STEADY_FROM:
        return
    k = n - STEADY_FROM
    sw, sc, sm = ((marks[-1, j] - marks[STEADY_FROM, j]) / k * 1e3 for j in range(3))
    print(f"{label}, steady state (frames {STEADY_FROM}-{n - 1}): {sw:6.2f} ms/frame wall = "
          f"{sw / (1e3 / bare_fps) * 100:5.1f} % of bare detection, {sc:6.2f} ms/frame CPU = "
          f"{sc / bare_cpu * 100:5.1f} % of bare detection's CPU (main thread {sm:.2f} ms)")


def run(quick: bool = False, frames: int | None = None) -> None:
    import cv2

    n = frames if frames is not None else 20 if quick else 90
    if n < 2:
        raise SystemExit("kmea bench pipeline: --frames must be at least 2")
    t0 = time.perf_counter()
    rendered, scene = render(n)
    images = [f.pixels for f in rendered]
    print(f"pre-rendered {n} frames {scene.size[0]}x{scene.size[1]} (default scene, 2 robots) "
          f"in {time.perf_counter() - t0:.1f} s (not counted); cv2 threads "
          f"{cv2.getNumThreads()}, {len(os.sched_getaffinity(0))} cores")
    dic = scene.world_map.dictionary
    cpu: list[float] = []
    bare, full_sets = bare_detection(images, {}, dic, cpu)
    print(f"bare detectMarkers, default parameters: {bare:6.1f} frames/s "
          f"({1e3 / bare:.2f} ms/frame wall, {cpu[0]:.2f} ms/frame CPU), "
          f"{np.mean([len(s) for s in full_sets]):.1f} markers/frame")
    tuned, tuned_sets = bare_detection(images, TUNED, dic)
    lost = sum(len(a - b) for a, b in zip(full_sets, tuned_sets, strict=True))
    print(f"bare detectMarkers, one 13 px window only: {tuned:6.1f} frames/s, {lost} of "
          f"{sum(len(s) for s in full_sets)} markers of the default detection lost")
    robots = tuple(scene.robot_specs())
    rate, ms = pipeline_rate(rendered, scene, PipelineSettings(robots=robots))
    total = sum(ms.values())
    print(f"library pipeline, default detection: {rate:6.1f} frames/s = "
          f"{rate / bare * 100:5.1f} % of bare default detection; stage ms/frame: "
          + ", ".join(f"{k} {v:.2f}" for k, v in ms.items() if k != "capture")
          + f"; all stages {total:.2f} ms")
    compare_tracking(rendered, scene, bare, cpu[0], ("kmea", "corner-pnp"))
