"""``kmea bench render``: simulator speed on one core and corner fidelity against its truth.

Speed: frames per second of the default scene (two robots) at 640x480 and 1640x1232, with
OpenCV limited to one thread (numpy's element-wise work is single-threaded). Fidelity:
OpenCV ArUco detection with sub-pixel refinement on rendered default frames; corners of the
visible markers 30 px inside the image and >= 20 px wide, against the exact projected truth.
"""

from __future__ import annotations

import math
import time

import cv2
import numpy as np

from kmea.sim import Renderer, get_scene

SIZES = ((640, 480), (1640, 1232))


def _speed(width: int, height: int, frames: int) -> tuple[float, float, float]:
    """(static build s, frames/s wall clock, frames/s of process CPU time)."""
    c0 = time.process_time()
    r = Renderer(get_scene("default", width=width, height=height))
    build = time.process_time() - c0
    r.render(0)  # noise bank, first frame
    w0, c0 = time.perf_counter(), time.process_time()
    for i in range(1, frames + 1):
        r.render(i)
    wall, cpu = time.perf_counter() - w0, time.process_time() - c0
    return build, frames / wall, frames / cpu


def _fidelity(width: int, height: int, indices: list[int]) -> tuple[int, int, float, np.ndarray]:
    """(markers expected, found, corner RMS px, mean offset (2,) px) over frames ``indices``."""
    r = Renderer(get_scene("default", width=width, height=height))
    p = cv2.aruco.DetectorParameters()
    p.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    p.cornerRefinementMaxIterations = 50
    p.cornerRefinementMinAccuracy = 0.01
    det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_5X5_100), p)
    errs, expected, found_n = [], 0, 0
    for i in indices:
        f = r.render(i)
        corners, ids, _ = det.detectMarkers(f.pixels)
        found = {} if ids is None else {int(k): c.reshape(4, 2)
                                        for k, c in zip(ids.ravel(), corners, strict=True)}
        for mid in f.truth.visible:
            c = f.truth.corners[mid]
            side = np.linalg.norm(c - np.roll(c, 1, axis=0), axis=1).min()
            if (c.min() < 30 or c[:, 0].max() > width - 31 or c[:, 1].max() > height - 31
                    or side < 20):
                continue
            expected += 1
            if mid in found:
                found_n += 1
                errs.append(found[mid] - c)
    e = np.concatenate(errs) if errs else np.zeros((0, 2))
    rms = math.sqrt(float((e ** 2).sum(axis=1).mean())) if len(e) else math.nan
    return expected, found_n, rms, e.mean(axis=0) if len(e) else np.full(2, math.nan)


def run(quick: bool = False) -> None:
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        frames = 30 if quick else 150
        print(f"default scene, two robots, {frames} frames, one core")
        print(f"{'size':>10} {'static s':>9} {'fps wall':>9} {'fps cpu':>8}")
        for w, h in SIZES:
            build, fps_wall, fps_cpu = _speed(w, h, frames)
            print(f"{f'{w}x{h}':>10} {build:9.2f} {fps_wall:9.1f} {fps_cpu:8.1f}", flush=True)
        indices = [0, 150, 300] if quick else list(range(0, 450, 45))
        print(f"corner fidelity (ArUco SUBPIX vs truth, {len(indices)} frames)")
        print(f"{'size':>10} {'found':>9} {'rms px':>7} {'mean dx':>8} {'mean dy':>8}")
        for w, h in SIZES:
            n, k, rms, mean = _fidelity(w, h, indices)
            found = f"{k}/{n}"
            print(f"{f'{w}x{h}':>10} {found:>9} {rms:7.3f} {mean[0]:8.4f} {mean[1]:8.4f}",
                  flush=True)
    finally:
        cv2.setNumThreads(threads)
