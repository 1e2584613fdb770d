"""``kmea experiment --replay FILE``: the same tables from a kmead recording.

The recording (``kmea/recordings/format.py``: JSON lines, a header with the camera model and
the map, then one line per frame with every per-marker pose) is re-estimated with each
algorithm, each evaluated marker left out of the references. The truth is the map's
position of each marker, so only markers in the map are scored: a real floor whose markers
were surveyed. The mode is
"plane-known" (see :mod:`kmea.experiments.run`): each evaluated marker is left out of the
references and every estimator is told its surveyed plane.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from kmea import estimators as est_registry
from kmea.experiments.run import FrameResult, RunResult, collect, estimate_frame

__all__ = ["replay"]


def replay(path: str | Path, algorithms: Sequence[str], baseline: str = "lmea",
           markers: Sequence[int] | None = None, max_frames: int | None = None,
           progress: Callable[[int], None] | None = None) -> RunResult:
    """Score the recording at ``path``.

    markers: ids to evaluate; default every map marker detected at least once, except the
    map's origin, x and y anchors (LMEA's references, never evaluated in the paper).
    max_frames: stop after this many frames (None: all).
    progress: called with 1 after each frame is estimated.
    """
    from kmea.sources.base import SourceError
    from kmea.sources.replay import ReplaySource

    try:
        src = ReplaySource(path)
    except SourceError as e:
        raise ValueError(str(e)) from None
    world_map, camera = src.world_map, src.camera
    frames_obs = []
    try:
        while max_frames is None or len(frames_obs) < max_frames:
            fr = src.read()
            if fr is None:
                break
            if "error" in fr.meta:
                raise ValueError(fr.meta["error"])
            frames_obs.append((fr.index, fr.meta["replay"][2]))
    finally:
        src.close()
    if not frames_obs:
        raise ValueError(f"{path}: the recording has no frames")
    if markers is None:
        seen = {o.id for _, obs in frames_obs for o in obs}
        anchors = {world_map.origin_id, world_map.x_id, world_map.y_id}
        markers = tuple(sorted(i for i in seen if i in world_map and i not in anchors))
    else:
        missing = [i for i in markers if i not in world_map]
        if missing:
            raise ValueError(f"--markers: {missing} not in the recording's map "
                             "(the truth is the map position)")
        markers = tuple(markers)
    if not markers:
        raise ValueError(f"{path}: no map marker to evaluate in the recording")
    ests = {a: est_registry.get(a) for a in algorithms}
    # "plane-known" mode: every estimator is told each evaluated marker's surveyed plane.
    planes = {m: float(world_map[m].position[2]) for m in markers
              if world_map[m].rotation[2, 2] > 1.0 - 1e-9}
    results: list[FrameResult] = []
    for k, (_, obs) in enumerate(frames_obs):
        results.append(estimate_frame(k, obs, ests, world_map, markers,
                                      camera=camera.intrinsics, planes=planes))
        if progress:
            progress(1)
    samples, heights, failures, rejected = collect(results, algorithms, markers)
    truth = {m: np.asarray(world_map[m].position[:2], dtype=float) for m in markers}
    return RunResult(
        title=f"Replay of {Path(path).name}", part="replay", algorithms=tuple(algorithms),
        baseline=baseline, markers=markers, truth=truth, samples=samples,
        frames=len(frames_obs), reference_length=world_map.ref_length(), failures=failures,
        rejected=rejected, heights=heights,
        settings={"recording": str(path), "camera": f"{camera.width}x{camera.height}",
                  "map": world_map.name})
