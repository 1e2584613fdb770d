"""``kmea bench pipeline``: detection variants and the library pipeline, one thread.

On pre-rendered 1640x1232 simulator frames (scene "default", two robots; rendering not
counted): bare ``detectMarkers`` with the default parameters and with one 13 px
threshold window, the fast detector (:mod:`kmea.vision.fastdetect`), then
:class:`kmea.pipeline.Pipeline` (detection, pose, estimator, leave-one-out, filter, robots)
with the normal and the fast detector. The daemon's figures with its threads, files and
sockets are ``kmea bench daemon``.
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


def bare_detection(images: list[np.ndarray], params: dict, dictionary: str
                   ) -> tuple[float, list[set]]:
    """Frames/s of bare ``detectMarkers`` and the ids found in each frame."""
    from kmea.vision.detection import DetectorConfig, MarkerDetector

    raw = MarkerDetector(DetectorConfig(dictionary, parameters=params))._detector
    raw.detectMarkers(images[0])  # warm-up
    found = []
    t0 = time.perf_counter()
    for f in images:
        _, ids, _ = raw.detectMarkers(f)
        found.append(set() if ids is None else set(ids.ravel().tolist()))
    return len(images) / (time.perf_counter() - t0), found


def pipeline_rate(frames, scene, settings: PipelineSettings) -> tuple[float, dict[str, float]]:
    """Frames/s of :meth:`Pipeline.process` and its mean stage times (ms)."""
    p = Pipeline(scene.camera, scene.effective_map(), settings)
    sums: dict[str, float] = {}
    t0 = time.perf_counter()
    for f in frames:
        res = p.process(FrameInput(f.index, f.timestamp, f.image))
        for k, v in res.timings.items():
            sums[k] = sums.get(k, 0.0) + v
    rate = len(frames) / (time.perf_counter() - t0)
    return rate, {k: v / len(frames) for k, v in sums.items()}


def run(quick: bool = False) -> None:
    import cv2

    from kmea.vision.detection import DetectorConfig
    from kmea.vision.fastdetect import FastDetector

    n = 20 if quick else 90
    t0 = time.perf_counter()
    frames, scene = render(n)
    images = [f.image for f in frames]
    print(f"pre-rendered {n} frames {scene.size[0]}x{scene.size[1]} (default scene, 2 robots) "
          f"in {time.perf_counter() - t0:.1f} s (not counted); cv2 threads "
          f"{cv2.getNumThreads()}, {len(os.sched_getaffinity(0))} cores")
    dic = scene.world_map.dictionary
    bare, full_sets = bare_detection(images, {}, dic)
    print(f"bare detectMarkers, default parameters: {bare:6.1f} frames/s, "
          f"{np.mean([len(s) for s in full_sets]):.1f} markers/frame")
    tuned, tuned_sets = bare_detection(images, TUNED, dic)
    lost = sum(len(a - b) for a, b in zip(full_sets, tuned_sets, strict=True))
    print(f"bare detectMarkers, one 13 px window only: {tuned:6.1f} frames/s, {lost} of "
          f"{sum(len(s) for s in full_sets)} markers of the default detection lost")
    fast = FastDetector(DetectorConfig(dic))
    t0 = time.perf_counter()
    fast_sets = [set(fast.detect(f).ids.tolist()) for f in images]
    fast_rate = n / (time.perf_counter() - t0)
    lost = sum(len(a - b) for a, b in zip(full_sets, fast_sets, strict=True))
    print(f"fast detection (detector.fast): {fast_rate:6.1f} frames/s, {fast.fast} fast / "
          f"{fast.full} full frames, {lost} markers of the default detection lost")
    robots = tuple(scene.robot_specs())
    for label, fast_on in (("default detection", False), ("fast detection", True)):
        rate, ms = pipeline_rate(frames, scene, PipelineSettings(fast=fast_on, robots=robots))
        total = sum(ms.values())
        print(f"library pipeline, {label}: {rate:6.1f} frames/s = {rate / bare * 100:5.1f} % "
              "of bare default detection; stage ms/frame: "
              + ", ".join(f"{k} {v:.2f}" for k, v in ms.items() if k != "capture")
              + f"; all stages {total:.2f} ms")
