"""The simulated scene of each Part, and one frame's observations.

Truth versus what the estimators are told:

- the renderer draws the *true* scene: Part III/IV anchors displaced (``Scene.misplaced``:
  the map does not know), Part II markers lifted on 20 cm supports (``raised``);
- the estimators get the *nominal* map (the anchors keep their surveyed poses: that is the
  point of Parts III and IV) and, optionally, a slightly wrong calibration;
- Part II's raised markers are treated like robot markers: removed from the estimators' map
  (they are not where the map says, so they must never be references). As in the paper,
  every estimator then places them from their own PnP pose. With ``known_heights`` their
  height is given as ``plane_heights``, as the daemon does for a robot's top plate: the
  Kabsch-family estimators slide each along its camera ray to that height, corner-pnp
  intersects its corner rays with that plane.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np

from kmea.experiments.setup import ExperimentConfig, miscalibrated
from kmea.maps.files import MarkerMap, default_map

__all__ = ["build", "build_scene", "describe", "observe"]


def build_scene(config: ExperimentConfig):
    """The true :class:`kmea.sim.Scene` of ``config.part`` (no robots, default effects)."""
    from kmea.sim import get_scene, look_at, raised_overrides, scenario1_camera

    spec = config.part
    world_map = default_map()
    name = {1: "scenario1", 2: "scenario2"}[spec.scenario]
    overrides: dict[int, np.ndarray] = {}
    for mid, h in spec.raised.items():
        overrides.update(raised_overrides(world_map, [mid], h))
    misplaced = {mid: ((d.dx, d.dy, 0.0), (0.0, 0.0, math.degrees(d.dyaw)))
                 for mid, d in spec.displaced.items()}
    if spec.scenario == 1:
        cam2world = scenario1_camera(spec.camera_height)
    else:
        cam2world = look_at(spec.camera_position, spec.camera_target)
    return get_scene(name, world_map=world_map, width=config.width, height=config.height,
                     seed=config.seed, overrides=overrides, misplaced=misplaced,
                     cam2world=cam2world)


def estimator_map(config: ExperimentConfig, nominal: MarkerMap) -> MarkerMap:
    """The map the estimators get: nominal, minus Part II's raised markers (and minus the wall
    markers with ``floor_only``)."""
    if not config.part.raised and not config.floor_only:
        return nominal
    markers = {i: m for i, m in nominal.markers.items()
               if i not in config.part.raised and (m.on_floor or not config.floor_only)}
    return replace(nominal, markers=markers, extra=dict(nominal.extra))


def build(config: ExperimentConfig) -> dict[str, Any]:
    """Everything a worker needs to turn a frame index into observations."""
    from kmea.pipeline import MarkerObserver
    from kmea.sim import Renderer
    from kmea.vision.detection import DetectorConfig, MarkerDetector

    scene = build_scene(config)
    nominal = scene.world_map
    emap = estimator_map(config, nominal)
    lengths = {i: m.length for i, m in nominal.markers.items()}
    believed = miscalibrated(scene.camera, config.focal_error, config.k1_error)
    return {
        "scene": scene,
        "renderer": Renderer(scene),
        "observer": MarkerObserver(MarkerDetector(DetectorConfig(dictionary=nominal.dictionary)),
                                   believed, emap, lengths),
        "believed": believed,
        "estimator_map": emap,
        "plane_heights": ({int(i): float(h) for i, h in config.part.raised.items()}
                          if config.known_heights else {}),
        "planes": evaluated_planes(config, nominal),
        "never_reference": (),
    }


def evaluated_planes(config: ExperimentConfig, nominal: MarkerMap) -> dict[int, float]:
    """Evaluated id -> height (m) of its true plane: its surveyed height, plus its support's
    for Part II (what "plane-known" mode tells every estimator). Only horizontal markers."""
    out = {}
    for m in config.part.evaluated:
        if m in nominal and nominal[m].rotation[2, 2] > 1.0 - 1e-9:
            out[m] = float(nominal[m].position[2]) + float(config.part.raised.get(m, 0.0))
    return out


def observe(state: dict[str, Any], index: int) -> list:
    """Render frame ``index`` (fresh sensor noise), detect, and estimate every marker's
    camera-frame pose with the believed calibration."""
    return state["observer"].observe(state["renderer"].render(index).image)


def describe(config: ExperimentConfig) -> dict[str, Any]:
    """Truth of the evaluated markers (true x, y, metres), the MRE reference length, and the
    settings worth printing. Builds the scene only (no rendering)."""
    scene = build_scene(config)
    true = scene.static_markers()
    spec = config.part
    truth = {m: np.asarray(true[m].position[:2], dtype=float) for m in spec.evaluated}
    cam = scene.cam_position
    settings: dict[str, Any] = {
        "camera": f"scenario {spec.scenario} at ({cam[0]:.2f}, {cam[1]:.2f}, {cam[2]:.2f}) m",
    }
    if spec.raised:
        hs = sorted({round(h, 3) for h in spec.raised.values()})
        settings["raised"] = f"{len(spec.raised)} markers by {', '.join(map(str, hs))} m"
    if spec.displaced:
        settings["displaced"] = "; ".join(f"{i}: {d.describe()}"
                                          for i, d in sorted(spec.displaced.items()))
    return {"truth": truth, "reference_length": scene.world_map.ref_length(),
            "settings": settings}

