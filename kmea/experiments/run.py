"""The sampling loop of ``kmea experiment``.

One sample of an evaluated marker is one frame: render (fresh sensor noise), detect, estimate
each marker's camera-frame pose, then run every algorithm with that marker left out of the
references. Frames do not depend on the marker or the algorithm, so N frames are rendered and
detected once per Part and serve every evaluated marker and algorithm (N samples each).
``--jobs`` spreads the frames over processes; each worker does render, detection and every
estimate of its frames, so the results do not depend on the number of jobs.
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from multiprocessing import get_context

import numpy as np

from kmea import estimators as est_registry
from kmea.estimators.base import CameraIntrinsics, MarkerObservation
from kmea.experiments import simscene
from kmea.experiments.setup import ExperimentConfig, miscalibrated
from kmea.maps import MarkerMap

__all__ = [
    "ExperimentConfig",
    "FrameResult",
    "RunResult",
    "estimate_frame",
    "miscalibrated",
    "run_simulation",
]


@dataclass
class FrameResult:
    """Estimates of one frame.

    positions: (algorithm, marker id) -> (3,) world position, metres, for each evaluated
        marker that was detected and estimated.
    failures: (algorithm, marker id) -> reason, when it was detected but not estimated.
    detected: ids detected in the frame.
    rejected: algorithm -> {reference id: disagreement with the map, m} (robust estimators),
        from the estimate that left out the first evaluated marker detected.
    """

    index: int
    positions: dict[tuple[str, int], np.ndarray] = field(default_factory=dict)
    failures: dict[tuple[str, int], str] = field(default_factory=dict)
    detected: tuple[int, ...] = ()
    rejected: dict[str, dict[int, float]] = field(default_factory=dict)


@dataclass
class RunResult:
    """Everything a Part produced; the tables and plots are computed from it.

    truth: marker id -> (2,) true world x, y, metres.
    samples: (algorithm, marker id) -> (n, 2) estimated x, y of the n frames where that
        marker was detected and estimated, metres, in frame order.
    frames: number of frames (N); ``n < frames`` means some frames gave no estimate.
    rejected: algorithm -> reference id -> list of disagreements (m), one per frame it was
        rejected in.
    """

    title: str
    part: str
    algorithms: tuple[str, ...]
    baseline: str
    markers: tuple[int, ...]
    truth: dict[int, np.ndarray]
    samples: dict[tuple[str, int], np.ndarray]
    frames: int
    reference_length: float
    failures: dict[tuple[str, int], dict[str, int]] = field(default_factory=dict)
    rejected: dict[str, dict[int, list[float]]] = field(default_factory=dict)
    settings: dict[str, object] = field(default_factory=dict)
    heights: dict[int, np.ndarray] = field(default_factory=dict)

    def n(self, algorithm: str, marker: int) -> int:
        return len(self.samples.get((algorithm, marker), ()))


# ------------------------------------------------------------------ estimation (shared)

def estimate_frame(
    index: int,
    observations: Sequence[MarkerObservation],
    estimators: Mapping[str, object],
    world_map: MarkerMap,
    evaluated: Collection[int],
    camera: CameraIntrinsics | None = None,
    plane_heights: Mapping[int, float] | None = None,
    never_reference: Collection[int] = (),
) -> FrameResult:
    """Run every estimator once per evaluated marker detected in this frame, that marker
    left out of the references (with ``never_reference`` too)."""
    detected = tuple(sorted(o.id for o in observations))
    res = FrameResult(index=index, detected=detected)
    present = [m for m in evaluated if m in set(detected)]
    for name, estimator in estimators.items():
        for k, m in enumerate(present):
            e = estimator.estimate(observations, world_map, exclude={m, *never_reference},
                                   camera=camera, plane_heights=plane_heights)
            if k == 0 and e.rejected:
                res.rejected[name] = {int(i): float(d) for i, d in e.rejected.items()}
            if not e.ok:
                res.failures[(name, m)] = e.reason or "not estimated"
            elif m not in e.markers:
                res.failures[(name, m)] = "marker missing from the estimate"
            else:
                res.positions[(name, m)] = np.asarray(e.markers[m].position, dtype=float)
    return res


def collect(frames: Sequence[FrameResult], algorithms: Sequence[str],
            markers: Sequence[int]) -> tuple[dict, dict, dict, dict]:
    """Gather per-frame results into samples (x, y), heights (z), failure counts, rejections."""
    frames = sorted(frames, key=lambda f: f.index)
    samples, heights, failures = {}, {}, {}
    rejected: dict[str, dict[int, list[float]]] = {a: {} for a in algorithms}
    for a in algorithms:
        for m in markers:
            pts = [f.positions[(a, m)] for f in frames if (a, m) in f.positions]
            arr = np.array(pts, dtype=float).reshape(-1, 3)
            samples[(a, m)] = arr[:, :2].copy()
            heights[(a, m)] = arr[:, 2].copy()
            reasons: dict[str, int] = {}
            for f in frames:
                if (a, m) in f.failures:
                    r = f.failures[(a, m)]
                    reasons[r] = reasons.get(r, 0) + 1
                elif m not in f.detected:
                    reasons["not detected"] = reasons.get("not detected", 0) + 1
            failures[(a, m)] = reasons
    for f in frames:
        for a, rej in f.rejected.items():
            for i, d in rej.items():
                rejected.setdefault(a, {}).setdefault(i, []).append(d)
    return samples, heights, failures, rejected


# ------------------------------------------------------------------ simulation

_WORKER: dict[str, object] = {}


def _setup(config: ExperimentConfig) -> dict[str, object]:
    """Per-process state: scene, renderer, detector, estimators (built once per config)."""
    key = repr(config)
    if _WORKER.get("key") == key:
        return _WORKER
    _WORKER.clear()
    _WORKER.update(simscene.build(config))
    _WORKER["estimators"] = {a: est_registry.get(a) for a in config.algorithms}
    _WORKER["key"] = key
    return _WORKER


def _process(config: ExperimentConfig, indices: Sequence[int]) -> list[FrameResult]:
    st = _setup(config)
    out = []
    for i in indices:
        obs = simscene.observe(st, i)
        out.append(estimate_frame(
            i, obs, st["estimators"], st["estimator_map"], config.part.evaluated,
            camera=st["believed"].intrinsics, plane_heights=st["plane_heights"] or None,
            never_reference=st["never_reference"]))
    return out


def run_simulation(config: ExperimentConfig,
                   progress: Callable[[int], None] | None = None) -> RunResult:
    """Render, detect and estimate ``config.samples`` frames of ``config.part``."""
    for a in config.algorithms:
        if a not in est_registry.available():
            raise ValueError(f"unknown algorithm {a!r}; choose among "
                             f"{', '.join(est_registry.available())}")
    info = simscene.describe(config)
    chunks = [list(range(s, min(s + config.chunk, config.samples)))
              for s in range(0, config.samples, config.chunk)]
    frames: list[FrameResult] = []
    if config.jobs <= 1 or len(chunks) <= 1:
        for c in chunks:
            frames.extend(_process(config, c))
            if progress:
                progress(len(c))
    else:
        # spawn, not fork: a forked OpenCV/numpy process with threads is not safe.
        with ProcessPoolExecutor(max_workers=config.jobs, mp_context=get_context("spawn")) as ex:
            futures = [ex.submit(_process, config, c) for c in chunks]
            for fut in futures:
                got = fut.result()
                frames.extend(got)
                if progress:
                    progress(len(got))
    markers = tuple(config.part.evaluated)
    samples, heights, failures, rejected = collect(frames, config.algorithms, markers)
    settings = {
        "samples": config.samples, "seed": config.seed,
        "image": f"{config.width}x{config.height}",
        "focal_error": config.focal_error, "k1_error": config.k1_error,
        **({"known_heights": True} if config.known_heights and config.part.raised else {}),
        **({"map": "floor markers only"} if config.floor_only else {}),
        **info["settings"],
    }
    return RunResult(
        title=f"Part {config.part.name}: {config.part.title}",
        part=config.part.name, algorithms=tuple(config.algorithms), baseline=config.baseline,
        markers=markers, truth=info["truth"], samples=samples, frames=config.samples,
        reference_length=info["reference_length"], failures=failures, rejected=rejected,
        settings=settings, heights=heights)
