"""A fixed live camera: track the markers instead of detecting them, reuse what did not change.

- :mod:`~kmea.fixed_camera.detector`: :class:`FixedCameraDetector`, detection that tracks
  what it knows, built of :mod:`~kmea.fixed_camera.codes` (a marker's code read at known
  corners), :mod:`~kmea.fixed_camera.floor` (the fixed markers' check, drift and bumps),
  :mod:`~kmea.fixed_camera.follow` (the moving markers) and
  :mod:`~kmea.fixed_camera.discovery` (full detections for new markers, run where the
  caller says: the library starts no thread);
- :mod:`~kmea.fixed_camera.session`: :class:`FixedCameraSession`, what the pipeline keeps
  across frames (:mod:`~kmea.fixed_camera.reuse`: poses and leave-one-out errors reused,
  the floor of the last camera fit, robots placed before the poses).

Used by :class:`kmea.pipeline.Pipeline` with ``settings.fixed_camera`` (live sources).
"""

from kmea.fixed_camera.codes import CodeSampler, code_scores, marker_codes, verify_codes
from kmea.fixed_camera.detector import FixedCameraDetector
from kmea.fixed_camera.discovery import Background, Inline, Jobs
from kmea.fixed_camera.reuse import IncrementalLoo, IncrementalPoses
from kmea.fixed_camera.session import FixedCameraSession
from kmea.fixed_camera.tracks import FixedCameraConfig

__all__ = ["Background", "CodeSampler", "FixedCameraConfig", "FixedCameraDetector",
           "FixedCameraSession", "IncrementalLoo", "IncrementalPoses", "Inline", "Jobs",
           "code_scores", "marker_codes", "verify_codes"]
