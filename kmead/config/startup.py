"""Start-up: exit codes, the configured source, map and camera, with one-line errors.

Everything here runs once, before the first frame; a problem raises :class:`StartupError`
whose ``code`` is the process exit code.
"""

from __future__ import annotations

import logging
from typing import Any

from kmea.maps.files import DEFAULT_DICTIONARY, MarkerMap, default_map, load_map
from kmea.sources.base import FrameSource, SourceError
from kmea.sources.registry import open_source, parse_source_spec
from kmea.vision.camera import CameraError, CameraModel, pi_camera_v2
from kmea.vision.lens import load_lens_position
from kmead.config.layers import Config

EXIT_OK, EXIT_RUNTIME, EXIT_CONFIG = 0, 1, 2


class StartupError(Exception):
    """The daemon cannot start; ``code`` is the exit code (2: configuration, 1: other)."""

    def __init__(self, message: str, code: int = EXIT_CONFIG) -> None:
        super().__init__(message)
        self.code = code


def source_options(cfg: Config, prefix: str) -> dict[str, Any]:
    """The ``[source]`` keys that apply to a source of this prefix, as open_source options."""
    s = cfg["source"]
    opts: dict[str, Any] = {}
    if prefix in ("camera", "picamera", "sim") and s["width"] and s["height"]:
        opts.update(width=s["width"], height=s["height"])
    if prefix in ("camera", "picamera") and s["fps"]:
        opts["fps"] = s["fps"]
    if prefix == "picamera" and cfg["camera"]["max_exposure_ms"]:
        opts["max_exposure_ms"] = cfg["camera"]["max_exposure_ms"]
    if prefix == "picamera" and cfg["camera"]["file"]:
        # The calibration's focus: an autofocus camera's lens is locked there.
        try:
            lens = load_lens_position(cfg["camera"]["file"])
        except CameraError as e:
            raise StartupError(f"camera: {e}") from None
        if lens is not None:
            opts["lens_position"] = lens
    if prefix in ("images", "video", "camera"):
        opts["gray"] = True  # detection works on grey: convert once at decode time
    base, _, query = cfg["source"]["spec"].partition("?")
    if is_paced_sim(cfg) and base in ("sim:wide", "sim:wide-cam1") and "clock=" not in query:
        # The wide scene's cameras, paced: the robots move on the Unix time, so cameras
        # started separately (one kmead each) show them at the same place (docs/fusion.md).
        opts["clock"] = "wall"
    return opts


def open_configured_source(cfg: Config) -> FrameSource:
    """The source of ``source.spec`` (``StartupError`` when it cannot be opened)."""
    spec = cfg["source"]["spec"]
    try:
        prefix = parse_source_spec(spec).prefix
        return open_source(spec, **source_options(cfg, prefix))
    except SourceError as e:
        raise StartupError(f"source: {e}", EXIT_RUNTIME) from None


def is_paced_sim(cfg: Config) -> bool:
    """The simulator delivering at ``source.fps`` (a live source) rather than flat out."""
    return parse_source_spec(cfg["source"]["spec"]).prefix == "sim" and cfg["source"]["fps"] > 0


def configured_map(cfg: Config, source: FrameSource | None) -> MarkerMap:
    """The map file of the configuration, else the source's map, else the default map
    (``MapError`` for a bad file)."""
    path = cfg["map"]["file"]
    if path:
        return load_map(path, dictionary=cfg["detector"]["dictionary"] or DEFAULT_DICTIONARY,
                        default_length=cfg["detector"]["marker_length"])
    m = getattr(source, "world_map", None)
    return m if isinstance(m, MarkerMap) else default_map()


def fit_camera(cfg: Config, cam: CameraModel | None, source: FrameSource) -> CameraModel:
    """The configured camera, else the source's, else a Pi Camera v2; at the frame size."""
    size = getattr(source, "size", None)
    if cam is None:
        cam = getattr(source, "camera", None)
        if not isinstance(cam, CameraModel):
            scene = getattr(source, "scene", None)
            cam = getattr(scene, "camera", None)
        if not isinstance(cam, CameraModel):
            cam = pi_camera_v2()
    if size and (cam.width, cam.height) != tuple(size):
        configured = (cfg["source"]["width"], cfg["source"]["height"])
        if cfg["camera"]["file"] and tuple(size) != configured:  # else the plan said it
            logging.getLogger("kmead").warning(
                "camera: %s is for %dx%d; rescaled to the frame size %dx%d (calibrate at "
                "this size for the best accuracy)", cfg["camera"]["file"], cam.width,
                cam.height, *size)
        try:
            cam = cam.scaled_to(*size)
        except CameraError as e:
            raise StartupError(f"camera: {cfg['camera']['file'] or 'default camera'}: "
                               f"{e}") from None
    return cam
