"""Estimators: from camera-frame marker poses to world poses. See :mod:`kmea.estimators.base`.

``get(name)`` returns an estimator instance by name; ``available()`` lists the names.
"""

from __future__ import annotations

from importlib import import_module

from kmea.estimators.base import (
    Estimate,
    EstimateWithLoo,
    Estimator,
    MarkerEstimate,
    MarkerObservation,
)
from kmea.geometry.camera import CameraIntrinsics

__all__ = [
    "DEFAULT_ALGORITHM",
    "PAPER_ONLY",
    "CameraIntrinsics",
    "Estimate",
    "EstimateWithLoo",
    "Estimator",
    "MarkerEstimate",
    "MarkerObservation",
    "available",
    "get",
]

# name -> "module:Class"; modules are imported on first use.
_REGISTRY: dict[str, str] = {
    "kmea": "kmea.estimators.kmea:KMEA",
    "lmea": "kmea.estimators.lmea:LMEA",
    "lmea-printed": "kmea.estimators.lmea:LMEAPrinted",
    "umeyama": "kmea.estimators.umeyama:Umeyama",
    "kmea-robust": "kmea.estimators.robust:KMEARobust",
    "corner-pnp": "kmea.estimators.corner_pnp:CornerPnP",
}


#: The estimator the daemon uses unless configured otherwise (see docs/accuracy.md, "The
#: default estimator": the most accurate within the frame budget, on data it was not tuned on).
DEFAULT_ALGORITHM = "corner-pnp"


def register(name: str, target: str) -> None:
    """Register an estimator class as ``"module:Class"`` under ``name``."""
    _REGISTRY[name] = target


#: Estimators kept to reproduce the paper, not to run a floor: ``lmea-printed`` replicates
#: a typo of its Algorithm 1 (docs/accuracy.md). ``kmea experiment`` runs them; the daemon,
#: its configuration and the UI do not offer them.
PAPER_ONLY = frozenset({"lmea-printed"})


def available(live: bool = False) -> list[str]:
    """Names of the registered estimators; ``live``: those a daemon may run (without
    :data:`PAPER_ONLY`)."""
    return [n for n in _REGISTRY if not (live and n in PAPER_ONLY)]


def get(name: str, **options: object) -> Estimator:
    """A new estimator instance; ``ValueError`` naming the choices for an unknown name."""
    try:
        target = _REGISTRY[name]
    except KeyError:
        raise ValueError(f"unknown algorithm {name!r}; "
                         f"choose one of {', '.join(_REGISTRY)}") from None
    module, cls = target.split(":")
    return getattr(import_module(module), cls)(**options)
