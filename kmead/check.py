"""``kmead --check``: validate the configuration, map and camera without starting.

Reads every file the configuration names and prints the effective configuration (TOML)
with the files it came from, then the warnings (a map id the dictionary cannot hold, a
camera file made for another resolution, an unwritable log path, ...). Opens no camera and
binds no port. Exit 0 when kmead would start with this configuration, 2 (one line on
stderr naming the file and key) when it would not.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import TextIO

from kmead.config import Config, ConfigError

EXIT_OK, EXIT_CONFIG = 0, 2


class CheckError(ValueError):
    """kmead would not start; one line naming the file or key."""


def _writable(path: str) -> bool:
    """Whether kmead could create (or append to) ``path``: tried for real in the first
    existing folder (a temporary file, removed at once), since permission bits say
    nothing for root and nothing about read-only or virtual file systems."""
    import tempfile

    p = Path(path).expanduser().resolve()
    if p.exists():
        return p.is_file() and os.access(p, os.W_OK)
    d = p.parent
    while not d.exists() and d != d.parent:
        d = d.parent  # kmead creates the missing folders below it
    if not d.is_dir():
        return False
    try:
        with tempfile.TemporaryFile(dir=d):
            pass
    except OSError:
        return False
    return d == p.parent or _mkdir_ok(d)


def _mkdir_ok(d: Path) -> bool:
    import tempfile

    try:
        tempfile.TemporaryDirectory(dir=d).cleanup()
    except OSError:
        return False
    return True


def check_config(cfg: Config) -> list[str]:
    """The warnings for ``cfg``; ``CheckError`` for what would stop kmead from starting."""
    from kmea.maps import MapError, check_map, default_map, load_map
    from kmea.vision.camera import CameraError, load_camera

    warnings: list[str] = []
    spec = cfg["source"]["spec"]
    prefix = spec.split(":", 1)[0].split("?", 1)[0]
    # Map: the configured file, else the default map (a source's own map is known only
    # once it is opened: replay and sim say so).
    path = cfg["map"]["file"]
    try:
        if path:
            world_map = load_map(path, dictionary=cfg["detector"]["dictionary"] or "DICT_5X5_100",
                                 default_length=cfg["detector"]["marker_length"])
        else:
            world_map = default_map()
    except MapError as e:
        raise CheckError(f"map: {e}") from None
    where = path or "the built-in map"
    for w in check_map(world_map):
        warnings.append(f"map {where}: {w}")
    # Camera file: loads, and its size against the configured capture size.
    cam_file = cfg["camera"]["file"]
    if cam_file:
        try:
            cam = load_camera(cam_file)
        except CameraError as e:
            raise CheckError(f"camera: {e}") from None
        w, h = cfg["source"]["width"], cfg["source"]["height"]
        if w and h and (cam.width, cam.height) != (w, h):
            if cam.width * h != cam.height * w:
                raise CheckError(f"camera: {cam_file}: made for {cam.width}x{cam.height}, "
                                 f"source.width/height {w}x{h} has another aspect ratio")
            warnings.append(f"camera: {cam_file} is for {cam.width}x{cam.height}; it will be "
                            f"rescaled to the capture size {w}x{h}")
    # Source files (no camera is opened).
    if prefix in ("video", "images", "replay"):
        target = spec.split(":", 1)[1]
        if not Path(target).exists():
            raise CheckError(f"key 'source.spec': {spec}: no such "
                             f"{'folder' if prefix == 'images' else 'file'}")
        if prefix == "replay":
            from kmea.recording import RecordingError, read_header

            try:
                read_header(target)
            except RecordingError as e:
                raise CheckError(f"key 'source.spec': {e}") from None
    elif prefix in ("picamera", "camera"):
        warnings.append(f"source: {spec} is a live camera: not opened by --check")
    for key in ("csv", "record"):
        p = cfg["log"][key]
        if p and not _writable(p):
            raise CheckError(f"key 'log.{key}': cannot write {p}")
    net = cfg["network"]
    for key in ("telemetry", "control"):
        ep = net[key]
        if ep.startswith("tcp://") and not ep.startswith(("tcp://127.", "tcp://localhost")):
            warnings.append(f"network.{key}: {ep} is reachable from other machines")
    if cfg.data.get("foxglove", {}).get("enabled"):
        try:
            import foxglove  # noqa: F401
        except ImportError:
            raise CheckError("key 'foxglove.enabled': the foxglove extra is not installed "
                             "(pip install 'kmea[foxglove]')") from None
    return warnings


def effective_toml(cfg: Config) -> str:
    import tomli_w

    return tomli_w.dumps(cfg.to_dict())


def run_check(cfg: Config, out: TextIO | None = None, err: TextIO | None = None) -> int:
    """Print the effective configuration and the warnings; the exit code."""
    out = sys.stdout if out is None else out
    err = sys.stderr if err is None else err
    try:
        warnings = check_config(cfg)
    except (CheckError, ConfigError) as e:
        print(f"kmead: check failed: {e}", file=err)
        return EXIT_CONFIG
    print("# kmead --check: the effective configuration", file=out)
    print(f"# files read, in order: {', '.join(cfg.files)}", file=out)
    print(f"# the Configuration tab's Save writes: {cfg.overlay_path}", file=out)
    print(effective_toml(cfg), file=out)
    for w in warnings:
        print(f"kmead: warning: {w}", file=err)
    print(f"kmead: configuration OK ({len(warnings)} warning{'s' * (len(warnings) != 1)})",
          file=err)
    return EXIT_OK
