"""``kmea bench detection``: ArUco detection time, one thread, on rendered RobotAtFactory frames.

Frames come from the simulator (``kmea.sim``, scene "default": the Pi Camera v2 1.35 m above
the floor, the two default robots moving) at 640x480, 1280x960 and 1640x1232. For each
resolution and corner refinement (sub-pixel / none): the median detection time per frame,
how many of the visible markers (nothing hides them, all corners in the image) were found,
false ids, the corner error against the exact rendered corners, and the time of the
per-marker poses (both IPPE solutions + the scene choice) for the markers found, with the
number of poses the scene flipped (lowest-error IPPE solution rejected) and left ambiguous.
"""

from __future__ import annotations

import statistics
import time

import cv2
import numpy as np

from kmea.maps.files import default_map
from kmea.pipeline import MarkerObserver
from kmea.vision.detection import DetectorConfig, MarkerDetector

RESOLUTIONS = ((640, 480), (1280, 960), (1640, 1232))


def _frames(width: int, height: int, n: int):
    from kmea.sim import Renderer, get_scene

    scene = get_scene("default", width=width, height=height, seed=1)
    renderer = Renderer(scene)
    # Frames spread over the robots' loops (the sim runs at its own fps).
    return [renderer.render(i * 25) for i in range(n)], scene.camera


def run(quick: bool = False) -> None:
    n_frames, reps = (3, 3) if quick else (8, 7)
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    world_map = default_map()
    lengths = {40: 0.06, 41: 0.06, 42: 0.06}
    try:
        print(f"one thread, {n_frames} rendered frames per resolution (scene 'default'), "
              f"median of {reps} runs per frame; OpenCV {cv2.__version__}")
        print("detect ms: wall clock; cpu ms and poses ms: this thread's CPU time (robust to "
              "other load)")
        print(f"{'resolution':>10} {'refine':>7} {'detect ms':>9} {'cpu ms':>6} "
              f"{'found/visible':>13} {'false':>5} {'corner err px (median / p95)':>29} "
              f"{'poses ms':>8} "
              f"{'flipped':>7} {'ambiguous':>9}")
        for w, h in RESOLUTIONS:
            frames, camera = _frames(w, h, n_frames)
            for refine in ("subpix", "none"):
                observer = MarkerObserver(MarkerDetector(DetectorConfig(world_map.dictionary,
                                                                        refine)),
                                          camera, world_map, lengths)
                times, cpu_times, pose_times, errs = [], [], [], []
                found = visible = false = flipped = ambiguous = 0
                for f in frames:
                    truth = f.truth
                    t_frame, c_frame = [], []
                    for _ in range(reps):
                        c0, t0 = time.thread_time(), time.perf_counter()
                        ids_found, corners_found = observer.detect(f.pixels)
                        t_frame.append(time.perf_counter() - t0)
                        c_frame.append(time.thread_time() - c0)
                    times.append(statistics.median(t_frame))
                    cpu_times.append(statistics.median(c_frame))
                    ids = set(ids_found.tolist())
                    visible += len(truth.visible)
                    found += len(ids & truth.visible)
                    false += len(ids - set(truth.corners))
                    for mid, c in zip(ids_found.tolist(), corners_found, strict=True):
                        if mid in truth.corners:
                            errs.append(np.linalg.norm(c - truth.corners[mid], axis=1))
                    t_pose = []
                    for _ in range(reps):
                        c0 = time.thread_time()
                        _, diag = observer.poses(ids_found, corners_found)
                        t_pose.append(time.thread_time() - c0)
                    flipped += diag["n_flipped"]
                    ambiguous += diag["n_ambiguous"]
                    pose_times.append(statistics.median(t_pose))
                e = np.concatenate(errs) if errs else np.array([np.nan])
                pose = f"{statistics.median(pose_times) * 1e3:8.2f}"
                print(f"{w:>5}x{h:<4} {refine:>7} {statistics.median(times) * 1e3:9.1f} "
                      f"{statistics.median(cpu_times) * 1e3:6.1f} "
                      f"{found:>6}/{visible:<6} {false:>5} "
                      f"{np.median(e):>14.2f} / {np.percentile(e, 95):<12.2f} {pose} "
                      f"{flipped:>7} {ambiguous:>9}", flush=True)
    finally:
        cv2.setNumThreads(threads)
