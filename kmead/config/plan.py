"""The start-up plan: every check that decides whether kmead may start, opening nothing.

One function, :func:`plan_startup`, judges a configuration: its map, camera file, source
spec (a sim scene that exists, an image folder with a decodable image, a recording whose
header reads), the detector's dictionary against the robots' markers, the pipeline's
settings, the data directory and log paths, and the network's exposure and keys. Start-up
(:class:`kmead.run.daemon.Daemon`) runs it first and then opens the source and binds the
sockets; ``kmead --check`` runs it and stops. So both give the same verdict, the same line
and the same exit code (2) for every configuration problem; what only opening can find (a
camera in use, a port taken) is exit 1 at run time and not judged here.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

from kmea.maps.files import MapError, MarkerMap, check_map, check_spread, default_map
from kmea.sources.base import SourceError
from kmea.sources.registry import parse_source_spec
from kmea.vision.camera import CameraError, CameraModel, load_camera, pi_camera_v2
from kmea.vision.lens import load_lens_position
from kmea.wire.destinations import THIS_MACHINE_ONLY, this_machine_only
from kmead.config.checks import check_intrinsics
from kmead.config.layers import Config, ConfigError
from kmead.config.startup import StartupError, configured_map


@dataclass
class StartupPlan:
    """What :func:`plan_startup` found.

    world_map: the map kmead will use (the map file, else the source's own, else the
    built-in one). camera: the camera file's model (None: the source's, else a Pi Camera
    v2, at the frame size). preview_camera: the camera the checks were made with (the
    file's, else the simulator's, else a Pi Camera v2). prefix: the source kind.
    warnings: one line each, as start-up logs them.
    """

    world_map: MarkerMap
    camera: CameraModel | None
    preview_camera: CameraModel
    prefix: str
    warnings: list[str] = field(default_factory=list)


def plan_startup(cfg: Config) -> StartupPlan:
    """Judge ``cfg`` as start-up does, opening no camera and binding no port.

    Raises :class:`StartupError` (code 2, one line naming the file or key) for anything
    that would stop kmead from starting.
    """
    warnings: list[str] = []
    spec = cfg["source"]["spec"]
    try:
        prefix = parse_source_spec(spec, check=True).prefix
    except SourceError as e:
        raise StartupError(f"key 'source.spec': {e}") from None
    camera = _camera_file(cfg)
    source_map, source_camera = _source_preview(cfg, prefix)
    world_map = _configured_map(cfg) or source_map or default_map()
    where = cfg["map"]["file"] or world_map.source or "the built-in map"
    try:
        check_spread(world_map)
    except MapError as e:
        raise StartupError(f"map: {e}") from None
    warnings += [f"map {where}: {w}" for w in check_map(world_map)]
    preview = camera or source_camera or pi_camera_v2()
    warnings += _camera_size(cfg, preview)
    check_camera(cfg, preview)
    warnings += _dictionary_ids(cfg, world_map)
    problem = robot_ids_problem(cfg, world_map, cfg["robots"])
    if problem:
        raise StartupError(problem)
    _pipeline_settings(cfg, preview, world_map)
    _outputs(cfg)
    warnings += network_exposure(cfg)
    if cfg.data.get("foxglove", {}).get("enabled"):
        try:
            import foxglove  # noqa: F401
        except ImportError:
            raise StartupError("key 'foxglove.enabled': the foxglove extra is not installed "
                               "(pip install 'kmea[foxglove]')") from None
    if prefix == "picamera":
        _exposure(cfg)
    if prefix in ("picamera", "camera") and this_machine_only(cfg["robots"]):
        dests = ", ".join(d for r in cfg["robots"] for d in r["destinations"])
        warnings.append(f"robots: {THIS_MACHINE_ONLY} ({dests}): set each [[robots]] "
                        "destinations to its robot's address, e.g. [\"udp:192.168.1.21:9001\"] "
                        "(docs/pi.md, Robots)")
    warnings += zenoh_plan(cfg)
    if prefix in ("picamera", "camera"):
        warnings.append(f"source: {spec} is a live camera: not opened by --check "
                        "(opened at start)")
    return StartupPlan(world_map, camera, preview, prefix, warnings)


def _exposure(cfg: Config) -> None:
    """camera.max_exposure_ms must fit in a frame at source.fps (the Pi camera's default 30
    frames/s when 0): the camera could not honour it."""
    ms = float(cfg["camera"]["max_exposure_ms"])
    fps = float(cfg["source"]["fps"]) or 30.0
    if ms > 1e3 / fps:
        raise StartupError(f"key 'camera.max_exposure_ms': {ms:g} ms is longer than a frame "
                           f"at {fps:g} frames/s (source.fps: {1e3 / fps:.1f} ms)")


# ---------------------------------------------------------------------- files

def _camera_file(cfg: Config) -> CameraModel | None:
    path = cfg["camera"]["file"]
    if not path:
        return None
    try:
        model = load_camera(path)
        load_lens_position(path)  # a bad lens_position stops kmead as a bad matrix does
    except CameraError as e:
        raise StartupError(f"camera: {e}") from None
    return model


def _configured_map(cfg: Config) -> MarkerMap | None:
    if not cfg["map"]["file"]:
        return None
    try:
        return configured_map(cfg, None)
    except MapError as e:
        raise StartupError(f"map: {e}") from None


def _source_preview(cfg: Config, prefix: str) -> tuple[MarkerMap | None, CameraModel | None]:
    """The map and camera a file or simulated source brings, read without opening it; a
    source that could not be opened is a configuration error naming ``source.spec``."""
    spec = cfg["source"]["spec"]
    rest = parse_source_spec(spec).rest
    if prefix == "sim":
        from kmea.sim.scenes import scene_from_spec
        from kmea.sources.sim import split_bump

        try:
            scene = scene_from_spec(split_bump(spec)[0])
        except (ValueError, TypeError) as e:
            raise StartupError(f"key 'source.spec': {spec}: {e}") from None
        return scene.effective_map(), scene.camera
    if prefix == "replay":
        from kmea.recordings.format import RecordingError, read_header

        if not Path(rest).is_file():
            raise StartupError(f"key 'source.spec': {spec}: no such file")
        try:
            header = read_header(rest)
        except RecordingError as e:
            raise StartupError(f"key 'source.spec': {e}") from None
        return _header_map(spec, header), None
    if prefix == "images":
        _check_image_folder(spec, Path(rest))
    elif prefix == "video":
        _check_video(spec, Path(rest))
    return None, None


def _header_map(spec: str, header: dict) -> MarkerMap | None:
    from kmea.recordings.format import map_from_json

    try:
        return map_from_json(header["map"])
    except (KeyError, TypeError, ValueError, MapError) as e:
        raise StartupError(f"key 'source.spec': {spec}: the recording's map: {e}") from None


def _check_image_folder(spec: str, folder: Path) -> None:
    import cv2

    from kmea.sources.base import IMAGE_SUFFIXES

    if not folder.is_dir():
        raise StartupError(f"key 'source.spec': {spec}: no such folder")
    names = sorted(p for p in folder.iterdir()
                   if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
    if not names:
        raise StartupError(f"key 'source.spec': {spec}: no image files "
                           f"({', '.join(IMAGE_SUFFIXES)})")
    # Reading stops at the first decodable image, usually the first one.
    for p in names:
        if cv2.imread(str(p), cv2.IMREAD_REDUCED_GRAYSCALE_8) is not None:
            return
    raise StartupError(f"key 'source.spec': {spec}: none of the {len(names)} image files "
                       "can be decoded")


def _check_video(spec: str, path: Path) -> None:
    import cv2

    if not path.is_file():
        raise StartupError(f"key 'source.spec': {spec}: no such file")
    cap = cv2.VideoCapture(str(path))
    try:
        if not cap.isOpened():
            raise StartupError(f"key 'source.spec': {spec}: cannot open as a video")
    finally:
        cap.release()


# ---------------------------------------------------------------------- camera and ids

def _camera_size(cfg: Config, cam: CameraModel) -> list[str]:
    w, h = cfg["source"]["width"], cfg["source"]["height"]
    cam_file = cfg["camera"]["file"]
    if not (cam_file and w and h) or (cam.width, cam.height) == (w, h):
        return []
    try:
        cam.scaled_to(w, h)  # as start-up will
    except CameraError as e:
        raise StartupError(f"camera: {cam_file}: {e}") from None
    return [f"camera: {cam_file} is for {cam.width}x{cam.height}; rescaled to the frame size "
            f"{w}x{h} (calibrate at this size for the best accuracy)"]


def check_camera(cfg: Config, cam: CameraModel) -> None:
    """Intrinsics a camera can have (``StartupError`` naming the camera file)."""
    try:
        check_intrinsics(cam.fx, cam.fy, float(cam.camera_matrix[0, 2]),
                         float(cam.camera_matrix[1, 2]), cam.width, cam.height,
                         f"camera: {cfg['camera']['file'] or 'default camera'}")
    except ConfigError as e:
        raise StartupError(str(e)) from None


def dictionary_size(cfg: Config, world_map: MarkerMap) -> tuple[str, int | None]:
    """The detector's dictionary and its size (None for a custom dictionary file)."""
    from kmea.maps.aruco_names import PREDEFINED, canonical_name

    name = cfg["detector"]["dictionary"] or world_map.dictionary
    known = canonical_name(name)
    return name, PREDEFINED[known] if known else None


def robot_ids_problem(cfg: Config, world_map: MarkerMap, robots: list[dict]) -> str | None:
    """A robot marker the map places (on the floor or a wall: the robot would be reported
    where that marker is fixed), or one the detector's dictionary cannot hold, as one line,
    else None."""
    for r in robots:
        placed = [m for m in r["markers"] if m in world_map]
        if placed:
            where = "on the floor" if world_map[placed[0]].on_floor else "in the scene"
            return (f"robots: robot {r['name']!r} marker {placed[0]} is a marker the map "
                    f"{world_map.name!r} places {where}: a robot needs markers of its own")
    name, size = dictionary_size(cfg, world_map)
    if size is None:  # a custom dictionary file: its ids are not checked here
        return None
    for r in robots:
        bad = [m for m in r["markers"] if m >= size]
        if bad:
            return (f"robots: robot {r['name']!r} marker {bad[0]} is outside {name} "
                    f"(ids 0-{size - 1}): it could never be found")
    return None


def _dictionary_ids(cfg: Config, world_map: MarkerMap) -> list[str]:
    """Map ids a dictionary set in the configuration cannot hold (the map's own dictionary
    is judged by check_map)."""
    name, size = dictionary_size(cfg, world_map)
    if size is None or name == world_map.dictionary:
        return []
    family = _family(name)
    if family != _family(world_map.dictionary):
        # DICT_5X5_50 and DICT_5X5_100 share their codes; DICT_6X6_250 shares none of them.
        return [f"key 'detector.dictionary': {name} is not the family of the map's "
                f"{world_map.dictionary} ({world_map.source}): markers printed from the map's "
                "dictionary are never detected with it; leave it \"\" (the map's) or use "
                "the map's family"]
    big = [i for i in world_map.ids if i >= size]
    if not big:
        return []
    shown = ", ".join(map(str, big[:10])) + (" ..." if len(big) > 10 else "")
    return [f"map {world_map.source}: ids {shown} are outside {name} (ids 0-{size - 1}) "
            "and can never be detected"]


def _family(name: str) -> str:
    """``DICT_5X5_100`` -> ``DICT_5X5``: dictionaries of one family share their first codes."""
    head, _, tail = name.rpartition("_")
    return head if head.startswith("DICT_") and tail.isdigit() else name


def _pipeline_settings(cfg: Config, cam: CameraModel, world_map: MarkerMap) -> None:
    """Detector parameters, dictionary and estimator options: built once, then dropped."""
    from kmea.pipeline import Pipeline, PipelineSettings

    try:
        Pipeline(cam, world_map, PipelineSettings.from_config(cfg.data))
    except ValueError as e:
        raise StartupError(f"{cfg.files[-1]}: detector: {e}") from None


# ---------------------------------------------------------------------- outputs, network

def writable(path: str) -> bool:
    """Whether kmead could create (or append to) ``path``: tried for real in the first
    existing folder (a temporary file, removed at once), since permission bits say
    nothing for root and nothing about read-only or virtual file systems."""
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
        if d != p.parent:
            tempfile.TemporaryDirectory(dir=d).cleanup()
    except OSError:
        return False
    return True


def _outputs(cfg: Config) -> None:
    log_dir = cfg["log"]["dir"]
    if log_dir and not writable(str(Path(log_dir).expanduser() / ".kmead-check")):
        raise StartupError(f"key 'log.dir': data directory {log_dir}: cannot create or "
                           "write it")
    csv, record = cfg["log"]["csv"], cfg["log"]["record"]
    if csv and record and (Path(csv).expanduser().resolve()
                           == Path(record).expanduser().resolve()):
        raise StartupError(f"key 'log.record': {record} is the file the CSV log writes")
    for key, p in (("csv", csv), ("record", record)):
        if p and not writable(p):
            raise StartupError(f"key 'log.{key}': cannot write {p}")


def same_endpoint(a: str, b: str) -> bool:
    """Whether two ZeroMQ endpoints would bind the same place: the same ``ipc://`` path,
    or TCP on the same port (not ``*``) on the same or a wildcard address."""
    if a.startswith("ipc://") or b.startswith("ipc://"):
        return a == b
    ha, _, pa = a.removeprefix("tcp://").rpartition(":")
    hb, _, pb = b.removeprefix("tcp://").rpartition(":")
    if pa != pb or pa == "*":
        return False
    wild = ("*", "0.0.0.0", "[::]", "::")
    alias = {"localhost": "127.0.0.1", "[::1]": "127.0.0.1"}
    ha, hb = alias.get(ha, ha), alias.get(hb, hb)
    return ha == hb or ha in wild or hb in wild


def network_exposure(cfg: Config) -> list[str]:
    """Keys (CURVE on both sockets) or loopback only, or an explicit insecure = true; the
    key directory is read as start-up reads it. The warnings (a reachable insecure socket);
    :class:`StartupError` when the sockets may not be opened so. The daemon (through
    :func:`plan_startup`) and the fusion node judge their sockets with it."""
    from kmead.config.keyring import KeyRing, KeysError, exposure

    net = cfg["network"]
    if net["telemetry"] and net["control"] and same_endpoint(net["telemetry"], net["control"]):
        raise StartupError(f"key 'network.control': {net['control']} is the endpoint of "
                           "network.telemetry: give each socket its own")
    error, warning = exposure({"network.telemetry": net["telemetry"],
                               "network.control": net["control"]},
                              net["keys"], net["insecure"])
    if error:
        raise StartupError(error)
    if net["keys"]:
        try:
            KeyRing(net["keys"])
        except KeysError as e:
            raise StartupError(str(e)) from None
    return [warning] if warning else []


def zenoh_plan(cfg: Config, z: dict | None = None) -> list[str]:
    """``[zenoh]`` (or ``z``, the section as a fusion node uses it): the extra installed,
    the exposure rule (:func:`zenoh_exposure`), the certificate files readable, robot names
    that can be ROS 2 topic tokens. Warnings."""
    from kmead.config.site_tls import SiteTlsError, certificate_name, load_acl
    from kmead.config.zenoh import ros_token_problem, zenoh_exposure

    z = cfg.data.get("zenoh", {}) if z is None else z
    if not z.get("enabled"):
        return []
    try:
        import rosbags  # noqa: F401
        import zenoh  # noqa: F401
    except ImportError:
        raise StartupError("key 'zenoh.enabled': the zenoh extra is not installed "
                           "(pip install 'kmea[zenoh]')") from None
    error, warning = zenoh_exposure(z)
    if error:
        raise StartupError(error)
    for key in ("tls_ca", "tls_cert", "tls_key"):
        path = z[key]
        if path and not os.access(Path(path).expanduser(), os.R_OK):
            raise StartupError(f"key 'zenoh.{key}': cannot read {path}")
    if z.get("acl"):
        if not z["tls_cert"]:
            raise StartupError("key 'zenoh.acl': access control is keyed by the peers' "
                               "certificates: it needs zenoh.tls_ca, tls_cert and tls_key")
        try:
            load_acl(z["acl"])
        except SiteTlsError as e:
            raise StartupError(f"key 'zenoh.acl': {e}") from None
    if z["tls_cert"]:
        try:
            name = certificate_name(z["tls_cert"])
        except SiteTlsError as e:
            raise StartupError(f"key 'zenoh.tls_cert': {e}") from None
        if z.get("camera") and z["camera"] != name:
            raise StartupError(f"key 'zenoh.camera': {z['camera']!r} is not this camera's "
                               f"certificate name {name!r}: with TLS a camera's id is its "
                               "certificate's common name (leave zenoh.camera empty)")
    if z["ros2"]:
        for r in cfg["robots"]:
            if (problem := ros_token_problem(r["name"])) is not None:
                raise StartupError(f"robots: {problem}")
    return [warning] if warning else []
