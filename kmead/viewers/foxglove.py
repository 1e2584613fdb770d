"""Foxglove: the live WebSocket server and the MCAP messages (optional extra ``foxglove``).

One :class:`FoxgloveLog` turns what the daemon knows about a frame (:class:`FrameView`)
into Foxglove schema messages on these channels of a ``foxglove.Context``:

=====================  ==================  ===============================================
topic                  schema              content
=====================  ==================  ===============================================
/camera/image          CompressedImage     the frame, JPEG, rate-limited, only when watched
/camera/calibration    CameraCalibration   the camera model (K, D, size), with each image
/camera/annotations    ImageAnnotations    marker outlines and ids (green detected, yellow
                                           suspect ``?``, red rejected, cyan expected but
                                           unseen ``(id)``)
/floor/map             SceneUpdate         the floor and the surveyed map markers with ids
/floor/markers         SceneUpdate         this frame's estimated marker poses
/floor/robots          SceneUpdate         robots: a box and an arrow at each pose
/robots/poses          PosesInFrame        every robot pose seen this frame, frame "world"
/tf                    FrameTransforms     world -> camera (the estimate's cam2world) and
                                           world -> robot/NAME
=====================  ==================  ===============================================

The same class writes an MCAP file (:mod:`kmead.viewers.mcap_export`) or feeds
:class:`FoxgloveServer`, the live WebSocket server (subprotocol ``foxglove.sdk.v1``).
Units: metres, radians, image pixels; the world frame is ``world`` (x right, y up, z up);
the camera frame ``camera`` is OpenCV's (x right, y down, z forward).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import cv2
import foxglove
import numpy as np
from foxglove.channels import (
    CameraCalibrationChannel,
    CompressedImageChannel,
    FrameTransformsChannel,
    ImageAnnotationsChannel,
    PosesInFrameChannel,
    SceneUpdateChannel,
)
from foxglove.messages import (
    ArrowPrimitive,
    CameraCalibration,
    Color,
    CompressedImage,
    CubePrimitive,
    FrameTransform,
    FrameTransforms,
    ImageAnnotations,
    Point2,
    PointsAnnotation,
    PointsAnnotationType,
    Pose,
    PosesInFrame,
    Quaternion,
    SceneEntity,
    SceneUpdate,
    TextAnnotation,
    TextPrimitive,
    Timestamp,
    Vector3,
)
from foxglove.websocket import ServerListener  # (foxglove re-exports it, not statically)

from kmea.maps.files import MarkerMap
from kmea.vision.camera import CameraModel
from kmea.vision.overlay import OverlayMarker

log = logging.getLogger("kmead")

WORLD = "world"
CAMERA = "camera"
TOPICS = ("/camera/image", "/camera/calibration", "/camera/annotations", "/floor/map",
          "/floor/markers", "/floor/robots", "/robots/poses", "/tf")

_RGBA = {"detected": (0.1, 0.85, 0.1, 1.0), "suspect": (1.0, 0.85, 0.0, 1.0),
         "rejected": (0.95, 0.1, 0.1, 1.0), "expected": (0.0, 0.8, 1.0, 1.0)}


@dataclass
class RobotView:
    """One robot: world x, y (m), heading theta (rad); valid = seen this frame."""

    name: str
    x: float | None
    y: float | None
    theta: float | None
    valid: bool = True


@dataclass
class MarkerView:
    """An estimated marker: world position (3,), m; yaw, rad; kind as in OverlayMarker."""

    id: int
    position: np.ndarray
    yaw: float
    kind: str = "detected"


@dataclass
class FrameView:
    """What one frame shows.

    t: unix seconds (or the recording's clock); image: (H, W) uint8 grey or (H, W, 3)
    BGR, None when there is none (replay); outlines: pixel outlines (detected and expected);
    markers: world estimates; cam2world: (4, 4) similarity or None.
    """

    t: float
    frame: int
    image: np.ndarray | None = None
    # A list, or a function giving it: computed only when annotations go out.
    outlines: list[OverlayMarker] | Callable[[], list[OverlayMarker]] = field(
        default_factory=list)
    markers: list[MarkerView] = field(default_factory=list)
    robots: list[RobotView] = field(default_factory=list)
    cam2world: np.ndarray | None = None


def quaternion_xyzw(R: np.ndarray) -> tuple[float, float, float, float]:
    """Unit quaternion (x, y, z, w) of a (3, 3) rotation matrix (Shepperd's method)."""
    R = np.asarray(R, dtype=float)
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        w, x, y, z = 0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, \
            (R[1, 0] - R[0, 1]) / s
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        w, x, y, z = (R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, \
            (R[0, 2] + R[2, 0]) / s
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        w, x, y, z = (R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, \
            (R[1, 2] + R[2, 1]) / s
    else:
        s = 2.0 * math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        w, x, y, z = (R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, \
            (R[1, 2] + R[2, 1]) / s, 0.25 * s
    return x, y, z, w


def quaternion(R: np.ndarray) -> Quaternion:
    x, y, z, w = quaternion_xyzw(R)
    return Quaternion(x=x, y=y, z=z, w=w)


def _yaw_q(theta: float) -> Quaternion:
    return Quaternion(x=0.0, y=0.0, z=math.sin(theta / 2), w=math.cos(theta / 2))


def _color(kind: str) -> Color:
    r, g, b, a = _RGBA.get(kind, _RGBA["detected"])
    return Color(r=r, g=g, b=b, a=a)


def _stamp(t: float) -> Timestamp:
    return Timestamp.from_epoch_secs(max(0.0, t))


class FoxgloveLog:
    """The channels of one context and the messages for them (see the module docstring).

    world_map: the marker map (the static scene); camera: the model at the frame size.
    image_hz: at most this many images a second (0 = every frame); image_width: images
    wider than this are shrunk first (0 = full size); jpeg_quality: 1-100.
    """

    def __init__(self, context: foxglove.Context, world_map: MarkerMap, camera: CameraModel,
                 image_hz: float = 5.0, image_width: int = 960, jpeg_quality: int = 80
                 ) -> None:
        self.context = context
        self.world_map = world_map
        self.camera = camera
        self.image_hz = image_hz
        self.image_width = image_width
        self.jpeg_quality = jpeg_quality
        self._last_image = -math.inf
        self.counts: dict[str, int] = {}  # topic -> messages logged
        c = context
        self.image = CompressedImageChannel("/camera/image", context=c)
        self.calibration = CameraCalibrationChannel("/camera/calibration", context=c)
        self.annotations = ImageAnnotationsChannel("/camera/annotations", context=c)
        self.map_scene = SceneUpdateChannel("/floor/map", context=c)
        self.marker_scene = SceneUpdateChannel("/floor/markers", context=c)
        self.robot_scene = SceneUpdateChannel("/floor/robots", context=c)
        self.poses = PosesInFrameChannel("/robots/poses", context=c)
        self.tf = FrameTransformsChannel("/tf", context=c)

    def close(self) -> None:
        for ch in (self.image, self.calibration, self.annotations, self.map_scene,
                   self.marker_scene, self.robot_scene, self.poses, self.tf):
            ch.close()

    def _log(self, channel, message, log_time: int | None = None) -> None:
        channel.log(message, log_time=log_time)
        topic = channel.topic()
        self.counts[topic] = self.counts.get(topic, 0) + 1

    # ------------------------------------------------------------------ static scene
    def map_update(self, t: float) -> SceneUpdate:
        """The floor (a thin grey slab over the markers' extent) and every map marker."""
        wm = self.world_map
        x0, x1, y0, y1 = wm.floor_extent()
        pad = 2 * wm.default_length
        stamp = _stamp(t)
        floor = SceneEntity(
            timestamp=stamp, frame_id=WORLD, id="floor",
            cubes=[CubePrimitive(
                pose=Pose(position=Vector3(x=(x0 + x1) / 2, y=(y0 + y1) / 2, z=-0.002),
                          orientation=Quaternion(x=0, y=0, z=0, w=1)),
                size=Vector3(x=x1 - x0 + 2 * pad, y=y1 - y0 + 2 * pad, z=0.002),
                color=Color(r=0.55, g=0.55, b=0.55, a=1.0))])
        entities = [floor]
        for mid, mk in sorted(wm.markers.items()):
            q = quaternion(mk.rotation)
            p = mk.position
            entities.append(SceneEntity(
                timestamp=stamp, frame_id=WORLD, id=f"map/{mid}",
                cubes=[CubePrimitive(pose=Pose(position=Vector3(x=p[0], y=p[1], z=p[2]),
                                               orientation=q),
                                     size=Vector3(x=mk.length, y=mk.length, z=0.001),
                                     color=Color(r=0.05, g=0.05, b=0.05, a=1.0))],
                texts=[TextPrimitive(pose=Pose(position=Vector3(x=p[0], y=p[1],
                                                                z=p[2] + 0.01),
                                               orientation=q),
                                     billboard=True, font_size=14.0, scale_invariant=True,
                                     color=Color(r=1, g=1, b=1, a=1), text=str(mid))]))
        return SceneUpdate(entities=entities)

    def log_map(self, t: float, log_time: int | None = None) -> None:
        self._log(self.map_scene, self.map_update(t), log_time=log_time)

    # ------------------------------------------------------------------ per frame
    def calibration_message(self, t: float) -> CameraCalibration:
        cam = self.camera
        K = np.asarray(cam.camera_matrix, dtype=float)
        D = [float(v) for v in np.asarray(cam.dist_coeffs, dtype=float).reshape(-1)]
        model = "plumb_bob" if len(D) <= 5 else "rational_polynomial"
        D = (D + [0.0] * 8)[:5 if model == "plumb_bob" else 8]
        P = np.hstack([K, np.zeros((3, 1))])
        return CameraCalibration(timestamp=_stamp(t), frame_id=CAMERA, width=cam.width,
                                 height=cam.height, distortion_model=model, D=D,
                                 K=K.reshape(-1).tolist(), R=np.eye(3).reshape(-1).tolist(),
                                 P=P.reshape(-1).tolist())

    def annotations_message(self, t: float, outlines: Sequence[OverlayMarker],
                            scale: float = 1.0) -> ImageAnnotations:
        """Outlines (LINE_LOOP) and id labels; ``scale`` maps frame pixels to the image
        sent (when it was shrunk). Foxglove pixels have the origin at the top-left corner
        of the top-left pixel: OpenCV coordinates + 0.5."""
        stamp = _stamp(t)
        points, texts = [], []
        for m in outlines:
            c = _color(m.kind)
            q = (np.asarray(m.corners, dtype=float).reshape(4, 2) + 0.5) * scale
            points.append(PointsAnnotation(
                timestamp=stamp, type=PointsAnnotationType.LineLoop,
                points=[Point2(x=float(x), y=float(y)) for x, y in q], outline_color=c,
                thickness=1.0 if m.kind == "expected" else 2.0))
            label = {"expected": f"({m.id})", "suspect": f"{m.id}?"}.get(m.kind, str(m.id))
            cx, cy = q.mean(axis=0)
            texts.append(TextAnnotation(timestamp=stamp, position=Point2(x=float(cx),
                                                                           y=float(cy)),
                                        text=label, font_size=14.0, text_color=c,
                                        background_color=Color(r=0, g=0, b=0, a=0.6)))
        return ImageAnnotations(points=points, texts=texts)

    def image_message(self, t: float, image: np.ndarray) -> tuple[CompressedImage, float]:
        """(JPEG message, scale from frame pixels to the image sent)."""
        h, w = image.shape[:2]
        scale = 1.0
        if self.image_width and w > self.image_width:
            scale = self.image_width / w
            image = cv2.resize(image, (self.image_width, max(1, round(h * scale))),
                               interpolation=cv2.INTER_AREA)
        ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
        if not ok:
            raise ValueError("JPEG encoding failed")
        return CompressedImage(timestamp=_stamp(t), frame_id=CAMERA, data=buf.tobytes(),
                               format="jpeg"), scale

    def markers_update(self, t: float, markers: Sequence[MarkerView]) -> SceneUpdate:
        stamp = _stamp(t)
        L = self.world_map.default_length
        cubes = [CubePrimitive(pose=Pose(position=Vector3(x=float(m.position[0]),
                                                          y=float(m.position[1]),
                                                          z=float(m.position[2]) + 0.003),
                                         orientation=_yaw_q(m.yaw)),
                               size=Vector3(x=L * 0.8, y=L * 0.8, z=0.004),
                               color=_color(m.kind)) for m in markers]
        # One entity replaced every frame: markers no longer seen disappear.
        return SceneUpdate(entities=[SceneEntity(timestamp=stamp, frame_id=WORLD,
                                                 id="estimates", cubes=cubes)])

    def robots_update(self, t: float, robots: Sequence[RobotView]) -> SceneUpdate:
        stamp = _stamp(t)
        entities = []
        for r in robots:
            if r.x is None or r.y is None or r.theta is None:
                continue
            c = Color(r=0.8, g=0.2, b=0.8, a=1.0 if r.valid else 0.3)
            pose = Pose(position=Vector3(x=r.x, y=r.y, z=0.05), orientation=_yaw_q(r.theta))
            entities.append(SceneEntity(
                timestamp=stamp, frame_id=WORLD, id=f"robot/{r.name}",
                cubes=[CubePrimitive(pose=pose, size=Vector3(x=0.18, y=0.14, z=0.1), color=c)],
                arrows=[ArrowPrimitive(pose=Pose(position=Vector3(x=r.x, y=r.y, z=0.11),
                                                 orientation=_yaw_q(r.theta)),
                                       shaft_length=0.12, shaft_diameter=0.015,
                                       head_length=0.05, head_diameter=0.04, color=c)],
                texts=[TextPrimitive(pose=Pose(position=Vector3(x=r.x, y=r.y, z=0.2),
                                               orientation=Quaternion(x=0, y=0, z=0, w=1)),
                                     billboard=True, font_size=14.0, scale_invariant=True,
                                     color=c, text=r.name if r.valid else f"{r.name} (stale)")]))
        return SceneUpdate(entities=entities)

    def poses_message(self, t: float, robots: Sequence[RobotView]) -> PosesInFrame:
        poses = [Pose(position=Vector3(x=r.x, y=r.y, z=0.0), orientation=_yaw_q(r.theta))
                 for r in robots
                 if r.valid and r.x is not None and r.y is not None and r.theta is not None]
        return PosesInFrame(timestamp=_stamp(t), frame_id=WORLD, poses=poses)

    def transforms_message(self, t: float, cam2world: np.ndarray | None,
                           robots: Sequence[RobotView]) -> FrameTransforms:
        stamp = _stamp(t)
        out = []
        if cam2world is not None and np.all(np.isfinite(cam2world)):
            A = np.asarray(cam2world, dtype=float)[:3, :3]
            s = float(np.cbrt(np.linalg.det(A)))
            if s > 0:
                tr = np.asarray(cam2world, dtype=float)[:3, 3]
                out.append(FrameTransform(timestamp=stamp, parent_frame_id=WORLD,
                                          child_frame_id=CAMERA,
                                          translation=Vector3(x=tr[0], y=tr[1], z=tr[2]),
                                          rotation=quaternion(A / s)))
        for r in robots:
            if r.valid and r.x is not None and r.y is not None and r.theta is not None:
                out.append(FrameTransform(timestamp=stamp, parent_frame_id=WORLD,
                                          child_frame_id=f"robot/{r.name}",
                                          translation=Vector3(x=r.x, y=r.y, z=0.0),
                                          rotation=_yaw_q(r.theta)))
        return FrameTransforms(transforms=out)

    def log_frame(self, view: FrameView, log_time: int | None = None) -> bool:
        """Log one frame on every channel somebody listens to; True if an image went out.

        The image (the costly part: JPEG) only when ``/camera/image`` has a sink and at
        most ``image_hz`` times a second of ``view.t``.
        """
        t = view.t
        sent = False
        scale = 1.0
        if view.image is not None and self.image.has_sinks() and \
                (self.image_hz <= 0 or t - self._last_image >= 1.0 / self.image_hz):
            msg, scale = self.image_message(t, view.image)
            self._log(self.image, msg, log_time=log_time)
            self._last_image = t
            sent = True
        if self.calibration.has_sinks() and (sent or view.image is None):
            self._log(self.calibration, self.calibration_message(t), log_time=log_time)
        if self.annotations.has_sinks() and (sent or view.image is None):
            # With an image, annotations go with it (same timestamp, same scale).
            outlines = view.outlines() if callable(view.outlines) else view.outlines
            self._log(self.annotations, self.annotations_message(t, outlines, scale),
                      log_time=log_time)
        if self.marker_scene.has_sinks():
            self._log(self.marker_scene, self.markers_update(t, view.markers), log_time=log_time)
        if self.robot_scene.has_sinks():
            self._log(self.robot_scene, self.robots_update(t, view.robots), log_time=log_time)
        if self.poses.has_sinks():
            self._log(self.poses, self.poses_message(t, view.robots), log_time=log_time)
        if self.tf.has_sinks():
            self._log(self.tf, self.transforms_message(t, view.cam2world, view.robots),
                        log_time=log_time)
        return sent


class _Listener(ServerListener):
    """Re-sends the static map scene when a client subscribes to it."""

    def __init__(self) -> None:
        self.map_wanted = threading.Event()
        self.clients: set[int] = set()

    def on_subscribe(self, client, channel) -> None:
        self.clients.add(client.id)
        if channel.topic == "/floor/map":
            self.map_wanted.set()

    def on_unsubscribe(self, client, channel) -> None:
        pass


class FoxgloveServer:
    """The live Foxglove WebSocket server of a running daemon.

    Binds ``host:port`` (port 0: any free port, see :attr:`port`); ``OSError`` when it
    cannot. :meth:`publish` is called once per processed frame and costs little while
    nobody is connected (the channels have no sink).
    """

    def __init__(self, world_map: MarkerMap, camera: CameraModel, host: str = "127.0.0.1",
                 port: int = 8765, image_hz: float = 5.0, image_width: int = 960) -> None:
        self.context = foxglove.Context()
        self._listener = _Listener()
        try:
            self.server = foxglove.start_server(name="kmead", host=host, port=port,
                                                context=self.context,
                                                server_listener=self._listener)
        except RuntimeError as e:  # the SDK reports a bind failure as RuntimeError
            raise OSError(f"foxglove: cannot serve on {host}:{port}: {e}") from None
        self.host = host
        self.log = FoxgloveLog(self.context, world_map, camera, image_hz, image_width)
        self._last_map = -math.inf

    @property
    def port(self) -> int:
        return self.server.port

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def set_map(self, world_map: MarkerMap) -> None:
        self.log.world_map = world_map
        self._listener.map_wanted.set()

    def set_camera(self, camera: CameraModel) -> None:
        self.log.camera = camera

    def publish(self, view: FrameView) -> None:
        """Log one frame; a failure is logged, never raised (the daemon goes on)."""
        try:
            now = time.monotonic()
            # The map is static: on subscription, and every 5 s for panels that missed it.
            if self._listener.map_wanted.is_set() or now - self._last_map >= 5.0:
                self._listener.map_wanted.clear()
                self._last_map = now
                if self.log.map_scene.has_sinks():
                    self.log.log_map(view.t)
            self.log.log_frame(view)
        except Exception as e:  # a broken message must not stop localization
            log.warning("foxglove: frame %d not published: %s: %s", view.frame,
                        type(e).__name__, e)

    def close(self) -> None:
        self.server.stop()
        self.log.close()
