"""The sampling loop of ``kmea experiment``.

One sample of an evaluated marker is one frame: render (fresh sensor noise), detect, estimate
each marker's camera-frame pose, then run every algorithm without that marker. Frames do not
depend on the marker, the algorithm or the evaluation mode, so N frames are rendered and
detected once per Part and serve every evaluated marker, algorithm and mode (N samples each).

Two evaluation modes (``MODES``), so that every estimator gets the same information:

- ``plane-known``: the marker is left out of the references, and every estimator is told
  its plane (its surveyed height; for Part II its support's height) through
  ``plane_heights``: the Kabsch-family estimators slide it along its camera ray onto that
  plane, corner-pnp intersects its corner rays with it. What a surveyed floor marker or a
  configured robot gives.
- ``off-map``: the marker is removed from the estimators' map entirely (a newly laid
  marker, a robot nobody configured): no reference, no plane. Each estimator does what it
  does with an unknown marker (KMEA: its own PnP pose moved by the alignment, as in the
  paper; corner-pnp: its plane inferred from the map's planes, or free).

Optionally (``iir_alpha`` < 1) every estimator's samples of a marker go through the paper's
first-order IIR filter (:class:`kmea.robots.iir.PoseFilter`) in frame order, as the paper ran
both of its algorithms.
``--jobs`` spreads the frames over processes; each worker does render, detection and every
estimate of its frames, so the results do not depend on the number of jobs.
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from multiprocessing import get_context
from typing import Any

import numpy as np

from kmea import estimators as est_registry
from kmea.estimators.base import Estimator, MarkerObservation
from kmea.experiments import simscene
from kmea.experiments.setup import MODES, ExperimentConfig
from kmea.geometry.camera import CameraIntrinsics
from kmea.maps.files import MarkerMap

__all__ = [
    "MODES",
    "ExperimentConfig",
    "FrameResult",
    "RunResult",
    "estimate_frame",
    "iir_filter",
    "run_modes",
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
    heights: (algorithm, marker id) -> (n,) the estimated z of those samples, metres.
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
    heights: dict[tuple[str, int], np.ndarray] = field(default_factory=dict)
    mode: str = "plane-known"

    def n(self, algorithm: str, marker: int) -> int:
        return len(self.samples.get((algorithm, marker), ()))


# ------------------------------------------------------------------ estimation (shared)

def estimate_frame(
    index: int,
    observations: Sequence[MarkerObservation],
    estimators: Mapping[str, Estimator],
    world_map: MarkerMap,
    evaluated: Collection[int],
    camera: CameraIntrinsics | None = None,
    plane_heights: Mapping[int, float] | None = None,
    never_reference: Collection[int] = (),
    mode: str = "plane-known",
    planes: Mapping[int, float] | None = None,
    maps_without: Mapping[int, MarkerMap] | None = None,
) -> FrameResult:
    """Run every estimator on the evaluated markers detected in this frame, in ``mode``
    (see the module docstring; ``never_reference`` are never references either).

    "plane-known": ``Estimator.estimate_with_loo`` (the one leave-one-out definition: each
    marker left out of the references) with each evaluated marker's plane height from
    ``planes`` added to ``plane_heights``. "off-map": one estimate per marker with the map
    without it (``maps_without``: evaluated id -> that map, built here when absent).
    ``rejected`` comes from each estimator's full estimate (the first marker's, off-map).
    """
    if mode not in MODES:
        raise ValueError(f"unknown evaluation mode {mode!r}; choose one of {', '.join(MODES)}")
    detected = tuple(sorted(o.id for o in observations))
    res = FrameResult(index=index, detected=detected)
    present = [m for m in evaluated if m in set(detected)]
    base_heights = dict(plane_heights or {})
    for name, estimator in estimators.items():
        if mode == "plane-known":
            ph = {**base_heights, **{m: float(planes[m]) for m in present
                                     if planes and m in planes}}
            both = estimator.estimate_with_loo(observations, world_map,
                                               exclude=never_reference, camera=camera,
                                               plane_heights=ph or None, loo_ids=present)
            if both.estimate.rejected:
                res.rejected[name] = {int(i): float(d)
                                      for i, d in both.estimate.rejected.items()}
            for m in present:
                if m in both.loo_positions:
                    res.positions[(name, m)] = np.asarray(both.loo_positions[m], dtype=float)
                else:
                    res.failures[(name, m)] = both.loo_failures.get(m, "not estimated")
            continue
        for k, m in enumerate(present):
            wm = (maps_without or {}).get(m) or _without(world_map, m)
            ph = {i: h for i, h in base_heights.items() if i != m}
            e = estimator.estimate(observations, wm, exclude=set(never_reference),
                                   camera=camera, plane_heights=ph or None)
            if k == 0 and e.rejected:
                res.rejected[name] = {int(i): float(d) for i, d in e.rejected.items()}
            if not e.ok:
                res.failures[(name, m)] = e.reason or "not estimated"
            elif m not in e.markers:
                res.failures[(name, m)] = "marker missing from the estimate"
            else:
                res.positions[(name, m)] = np.asarray(e.markers[m].position, dtype=float)
    return res


def _without(world_map: MarkerMap, marker: int) -> MarkerMap:
    """``world_map`` without ``marker`` (itself when the marker is not in it)."""
    if marker not in world_map:
        return world_map
    from dataclasses import replace

    return replace(world_map, markers={i: m for i, m in world_map.markers.items()
                                       if i != marker}, extra=dict(world_map.extra))


def iir_filter(samples: np.ndarray, alpha: float, fps: float = 30.0) -> np.ndarray:
    """The paper's first-order IIR filter over one marker's samples (n, 3) in frame order:
    y_k = alpha x_k + (1 - alpha) y_(k-1) (:class:`kmea.robots.iir.PoseFilter`, one definition
    for the daemon and the experiments)."""
    from kmea.robots.iir import PoseFilter

    if alpha >= 1.0 or len(samples) == 0:
        return samples
    f = PoseFilter(alpha, reset_after_s=1e9)  # one track: never reset
    return np.array([f.update(0, k / fps, p, 0.0)[0] for k, p in enumerate(samples)])


def collect(frames: Sequence[FrameResult], algorithms: Sequence[str],
            markers: Sequence[int], iir_alpha: float = 1.0) -> tuple[dict, dict, dict, dict]:
    """Gather per-frame results into samples (x, y), heights (z), failure counts, rejections;
    ``iir_alpha`` < 1 filters each (algorithm, marker) series in frame order first."""
    frames = sorted(frames, key=lambda f: f.index)
    samples, heights, failures = {}, {}, {}
    rejected: dict[str, dict[int, list[float]]] = {a: {} for a in algorithms}
    for a in algorithms:
        for m in markers:
            pts = [f.positions[(a, m)] for f in frames if (a, m) in f.positions]
            arr = iir_filter(np.array(pts, dtype=float).reshape(-1, 3), iir_alpha)
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

_WORKER: dict[str, Any] = {}  # simscene.build's state, plus estimators and maps_without


def _setup(config: ExperimentConfig) -> dict[str, Any]:
    """Per-process state: scene, renderer, detector, estimators (built once per config)."""
    key = repr(config)
    if _WORKER.get("key") == key:
        return _WORKER
    _WORKER.clear()
    _WORKER.update(simscene.build(config))
    _WORKER["estimators"] = {a: est_registry.get(a) for a in config.algorithms}
    emap = _WORKER["estimator_map"]
    _WORKER["maps_without"] = {m: _without(emap, m) for m in config.part.evaluated}
    _WORKER["key"] = key
    return _WORKER


def _process(config: ExperimentConfig, indices: Sequence[int]) -> dict[str, list[FrameResult]]:
    st = _setup(config)
    out: dict[str, list[FrameResult]] = {m: [] for m in config.modes}
    for i in indices:
        obs = simscene.observe(st, i)
        for mode in config.modes:
            out[mode].append(estimate_frame(
                i, obs, st["estimators"], st["estimator_map"], config.part.evaluated,
                camera=st["believed"].intrinsics, plane_heights=st["plane_heights"] or None,
                never_reference=st["never_reference"], mode=mode, planes=st["planes"],
                maps_without=st["maps_without"]))
    return out


def run_simulation(config: ExperimentConfig,
                   progress: Callable[[int], None] | None = None) -> RunResult:
    """Render, detect and estimate ``config.samples`` frames of ``config.part``; the result of
    the first of ``config.modes``."""
    return run_modes(config, progress)[config.modes[0]]


def run_modes(config: ExperimentConfig,
              progress: Callable[[int], None] | None = None) -> dict[str, RunResult]:
    """Render, detect and estimate ``config.samples`` frames of ``config.part`` once, and
    score them in every mode of ``config.modes``: mode -> result."""
    for a in config.algorithms:
        if a not in est_registry.available():
            raise ValueError(f"unknown algorithm {a!r}; choose among "
                             f"{', '.join(est_registry.available())}")
    if not config.modes or any(m not in MODES for m in config.modes):
        raise ValueError(f"evaluation modes must be among {', '.join(MODES)}, "
                         f"got {', '.join(config.modes) or 'none'}")
    if not 0.0 < config.iir_alpha <= 1.0:
        raise ValueError(f"IIR filter alpha must be in (0, 1], got {config.iir_alpha}")
    info = simscene.describe(config)
    chunks = [list(range(s, min(s + config.chunk, config.samples)))
              for s in range(0, config.samples, config.chunk)]
    frames: dict[str, list[FrameResult]] = {m: [] for m in config.modes}

    def add(got: dict[str, list[FrameResult]]) -> None:
        for m, fr in got.items():
            frames[m].extend(fr)
        if progress:
            progress(len(next(iter(got.values()))))

    if config.jobs <= 1 or len(chunks) <= 1:
        for c in chunks:
            add(_process(config, c))
    else:
        # spawn, not fork: a forked OpenCV/numpy process with threads is not safe.
        with ProcessPoolExecutor(max_workers=config.jobs, mp_context=get_context("spawn")) as ex:
            futures = [ex.submit(_process, config, c) for c in chunks]
            for fut in futures:
                add(fut.result())
    markers = tuple(config.part.evaluated)
    out: dict[str, RunResult] = {}
    for mode in config.modes:
        samples, heights, failures, rejected = collect(frames[mode], config.algorithms,
                                                       markers, config.iir_alpha)
        settings = {
            "mode": mode,
            "samples": config.samples, "seed": config.seed,
            "image": f"{config.width}x{config.height}",
            "focal_error": config.focal_error, "k1_error": config.k1_error,
            **({"iir_alpha": config.iir_alpha} if config.iir_alpha < 1.0 else {}),
            **({"known_heights": True} if config.known_heights and config.part.raised else {}),
            **({"map": "floor markers only"} if config.floor_only else {}),
            **info["settings"],
        }
        out[mode] = RunResult(
            title=f"Part {config.part.name}: {config.part.title} ({mode})",
            part=config.part.name, algorithms=tuple(config.algorithms),
            baseline=config.baseline, markers=markers, truth=info["truth"], samples=samples,
            frames=config.samples, reference_length=info["reference_length"],
            failures=failures, rejected=rejected, settings=settings, heights=heights,
            mode=mode)
    return out
