"""``kmea bench estimators``: median time of one estimate of kmea, lmea and umeyama.

Synthetic frames, no camera: the marker positions of a map are put through a known
camera-to-world similarity and 2 mm of Gaussian noise, and each estimator runs on them.
33 markers = the RobotAtFactory floor; 1000 markers = a random floor of the same size
(with the same anchors). Also the leave-one-out of all markers (what the daemon runs every
frame for its live error figures), for kmea's batched version and the plain loop.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from functools import partial

import numpy as np

from kmea.estimators import get
from kmea.estimators.base import MarkerObservation
from kmea.estimators.loo import loo_errors
from kmea.geometry import rot_x, rot_z
from kmea.maps.files import Marker, MarkerMap, default_map


def _floor_map(n: int, seed: int = 0) -> MarkerMap:
    base = default_map()
    floor = {i: base[i] for i in base.ids if base[i].on_floor}
    if n <= len(floor):
        return MarkerMap(dict(list(floor.items())[:n]), reference_length=2.081)
    rng = np.random.default_rng(seed)
    markers = dict(floor)
    next_id = 100
    while len(markers) < n:
        p = np.array([rng.uniform(-0.84, 0.84), rng.uniform(-0.59, 0.59), 0.0])
        markers[next_id] = Marker(next_id, p, np.eye(3), 0.06)
        next_id += 1
    return MarkerMap(markers, dictionary="DICT_5X5_1000", reference_length=2.081)


def synthetic_frame(world_map: MarkerMap, noise_m: float = 0.002,
                    seed: int = 1) -> list[MarkerObservation]:
    """Observations of every marker of ``world_map`` from a camera 2 m above the floor."""
    rng = np.random.default_rng(seed)
    # cam2world: camera looking down (z_cam = -z_world), slightly tilted and turned.
    R_c2w = rot_z(0.3) @ rot_x(np.pi + 0.05)
    t_c2w = np.array([0.05, -0.02, 2.0])
    obs = []
    for mid in world_map.ids:
        mk = world_map[mid]
        p_cam = R_c2w.T @ (mk.position - t_c2w) + rng.normal(0.0, noise_m, 3)
        obs.append(MarkerObservation(mid, R_c2w.T @ mk.rotation, p_cam, length=mk.length))
    return obs


def _median_time(fn: Callable[[], object], reps: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def _rows(quick: bool) -> list[tuple[str, int, Callable[[], object], int]]:
    reps = {33: 30 if quick else 300, 1000: 5 if quick else 50}
    rows = []
    for n in (33, 1000):
        m = _floor_map(n)
        obs = synthetic_frame(m)
        for name in ("kmea", "lmea", "umeyama"):
            est = get(name)
            if not est.estimate(obs, m).ok:
                raise RuntimeError(f"{name} failed on the synthetic frame")
            rows.append((name, n, partial(est.estimate, obs, m), reps[n]))
        loo_reps = max(3, reps[n] // 10)
        rows.append(("kmea leave-one-out", n, partial(loo_errors, get("kmea"), obs, m),
                     loo_reps))
        if n == 33:  # the plain loop, for comparison (too slow to bother at 1000)
            rows.append(("umeyama leave-one-out", n,
                         partial(loo_errors, get("umeyama"), obs, m), loo_reps))
    return rows


def run(quick: bool = False) -> None:
    """Print the median time (ms) of one estimate for 33 and 1000 markers."""
    print(f"{'estimator':<22}{'markers':>8}{'median ms':>12}{'reps':>6}")
    for label, n, fn, reps in _rows(quick):
        t = _median_time(fn, reps)
        print(f"{label:<22}{n:>8}{t * 1e3:>12.3f}{reps:>6}", flush=True)
