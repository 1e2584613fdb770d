"""``kmea bench estimator-cost``: cost per frame of every estimator for 33 markers.

One synthetic frame of the RobotAtFactory floor: the nominal Pi Camera v2 1.35 m above the
floor centre looking down, the 33 floor markers' corners projected with 0.15 px of Gaussian
noise, per-marker poses from ``cv2.solvePnP`` (IPPE_SQUARE). For each estimator: the median
time of one estimate; of one estimate plus the leave-one-out of all markers, as the daemon
runs them every frame (``Estimator.estimate_with_loo``: KMEA's batched fast path, the
definition's loop for the others); and of the plain loop of N estimates with one marker
excluded each. Frames cycle
through 4 noise draws so no call reuses the previous one's work.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable

import cv2
import numpy as np

from kmea.estimators import get
from kmea.estimators.base import MarkerObservation
from kmea.geometry import check_distortion as dist14
from kmea.geometry import marker_corners_local, project
from kmea.maps.files import MarkerMap, default_map
from kmea.vision.camera import CameraModel, pi_camera_v2

NAMES = ("kmea", "lmea", "umeyama", "kmea-robust", "corner-pnp")


def floor_frame(noise_px: float = 0.15, seed: int = 0
                ) -> tuple[list[MarkerObservation], MarkerMap, CameraModel]:
    """Observations of the 33 floor markers from 1.35 m above the floor centre."""
    full = default_map()
    m = MarkerMap({i: full[i] for i in full.ids if full[i].on_floor}, reference_length=2.081)
    cam = pi_camera_v2()
    x0, x1, y0, y1 = m.floor_extent()
    R = np.diag([1.0, -1.0, -1.0])  # world2cam: looking down
    t = -R @ np.array([(x0 + x1) / 2, (y0 + y1) / 2, 1.35])
    rng = np.random.default_rng(seed)
    obs = []
    for i in m.ids:
        uv = project(m[i].corners_world() @ R.T + t, cam.camera_matrix, dist14(cam.dist_coeffs))
        uv = uv + rng.normal(0.0, noise_px, uv.shape)
        _, rv, tv = cv2.solvePnP(marker_corners_local(m[i].length), uv, cam.camera_matrix,
                                  cam.dist_coeffs, flags=cv2.SOLVEPNP_IPPE_SQUARE)
        obs.append(MarkerObservation(i, cv2.Rodrigues(rv)[0], tv.reshape(3), corners=uv,
                                     length=m[i].length))
    return obs, m, cam


def _median_ms(fn: Callable[[list[MarkerObservation]], object],
               frames: list[list[MarkerObservation]], reps: int) -> tuple[float, float]:
    """(median wall time, mean CPU time of this process) in ms of ``fn(frame)``, cycling
    through different frames so that no call can reuse the previous one's work. The CPU
    time is the figure to trust on a busy machine."""
    fn(frames[-1])
    times = []
    c0 = time.process_time()
    for k in range(reps):
        t0 = time.perf_counter()
        fn(frames[k % len(frames)])
        times.append(time.perf_counter() - t0)
    cpu = (time.process_time() - c0) / reps
    return statistics.median(times) * 1e3, cpu * 1e3


def run(quick: bool = False) -> None:
    frames = [floor_frame(seed=s)[0] for s in range(4)]
    _, m, cam = floor_frame()
    K = cam.intrinsics
    reps = 6 if quick else 40
    print(f"{len(frames[0])} markers, ms per frame ({reps} frames): median wall / mean CPU")
    print(f"{'estimator':<13} {'estimate':>13} {'+ LOO (daemon)':>15} {'LOO as N estimates':>19}")
    for name in NAMES:
        est = get(name)
        one = _median_ms(lambda f, est=est: est.estimate(f, m, camera=K), frames, reps)

        def daemon(f, est=est) -> None:  # what kmead does every frame with stats.loo on
            est.estimate_with_loo(f, m, camera=K)

        def loop(f, est=est) -> None:
            for o in f:
                est.estimate(f, m, exclude=(o.id,), camera=K)

        both = _median_ms(daemon, frames, reps)
        plain = _median_ms(loop, frames, max(4, reps // 8))
        print(f"{name:<13} {one[0]:>6.2f} /{one[1]:>5.2f} {both[0]:>7.2f} /{both[1]:>6.2f} "
              f"{plain[0]:>10.1f} /{plain[1]:>7.1f}")
