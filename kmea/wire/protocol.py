"""The wire protocol between kmead and its clients (see ``docs/protocol.md``).

Telemetry: ZeroMQ PUB, multipart ``[topic, body]``; topic is ASCII, body is UTF-8 JSON
with ``"v": PROTOCOL_VERSION``. Control: ZeroMQ REQ/REP, one JSON object each way.
No pickle anywhere. Every body has ONE declared type below (a ``TypedDict``: the JSON
object's keys and value types); :func:`check_body` checks a decoded body against the type
of its topic, so a client (and the tests) find out when the daemon's messages and the
declared types disagree. This module imports only the standard library (and
:mod:`kmea.wire.jsonsafe`, which is stdlib-only too): the terminal UI imports it and nothing
else from ``kmea``.

Units: metres, radians, seconds. ``float | None``: JSON has no NaN/inf, those are ``null``.
"""

from __future__ import annotations

import json
import types
import typing
from collections.abc import Callable
from typing import Any, TypedDict, Union

from kmea.wire.jsonlimits import MAX_DEPTH, JsonLimitError, safe_loads
from kmea.wire.jsonsafe import to_jsonable

# 2: markers[].moved/moved_offset/moved_frames/moved_threshold (the daemon's "moved" decision
#    with its evidence), markers[].rejection (was "displacement"), status.algorithms;
#    markers[].plane/plane_stat (added fields: old clients ignore them).
PROTOCOL_VERSION = 2

# Telemetry topics. Subscribers filter by prefix (TOPIC_ROBOT_PREFIX gets every robot).
TOPIC_FRAME = "frame"
TOPIC_MARKERS = "markers"
TOPIC_ROBOTS = "robots"
TOPIC_ROBOT_PREFIX = "robot."
TOPIC_STATS = "stats"
TOPIC_STATUS = "status"
TOPIC_EVENT = "event"
TOPIC_LOG = "log"
TOPIC_CAMERA = "camera"  # thumbnails, only while a client holds a camera_watch lease

DEFAULT_TELEMETRY = "tcp://127.0.0.1:5555"
DEFAULT_CONTROL = "tcp://127.0.0.1:5556"

MAX_MESSAGE_BYTES = 1 << 20
# Control requests are small (the largest is a robots list); bigger ones are refused unread.
MAX_REQUEST_BYTES = 64 << 10


class ProtocolError(ValueError):
    """A message that does not follow the protocol; the text says which field."""


def robot_topic(name: str) -> str:
    """The telemetry topic of one robot's relay messages (``robot.<name>``)."""
    return f"{TOPIC_ROBOT_PREFIX}{name}"


# ---------------------------------------------------------------------------------- bodies
class FrameBody(TypedDict):
    """``frame``: one processed frame (every frame)."""

    t: float
    frame: int
    source: str
    algorithm: str
    ok: bool
    reason: str
    n_detected: int
    n_refs: int
    fps: float
    dropped: int
    timings_ms: dict[str, float]  # capture, detect, pose, estimate, loo, filter, robots, ...
    flips: int
    ambiguous: int
    suspect: int
    bad_frames: int
    scale: float | None
    rejected: list[int]


class _MarkerRowBase(TypedDict):
    """The fields every ``markers`` row has."""

    id: int
    in_map: bool
    detected: bool
    x: float | None
    y: float | None
    z: float | None
    yaw: float | None
    map_x: float | None
    map_y: float | None
    map_z: float | None
    error: float | None  # leave-one-out error of this frame (m)
    ambiguous: bool
    flipped: bool
    suspect: bool
    rejected: bool  # a robust estimator left it out of this frame's references
    rejection: float | None  # ... and how far it disagreed with the map (m)
    reference: bool
    moved: bool  # the daemon's decision (kmea.stats.moved), with its evidence:
    moved_offset: float | None  # median displacement figure over the window (m)
    moved_frames: int  # figures in the window
    moved_threshold: float | None  # the marker's threshold now (m)


class MarkerRow(_MarkerRowBase, total=False):
    """One marker of a ``markers`` body. World frame, metres, radians. The daemon sends
    every field; ``plane`` and ``plane_stat`` were added later (recordings before them
    lack them)."""

    plane: str | None  # unknown-plane markers: "floor", "plane N" or "free" (else None)
    plane_stat: float | None  # ... the likelihood-ratio statistic of that plane


class MarkersBody(TypedDict):
    """``markers``: every map marker and every detected marker (every frame)."""

    t: float
    frame: int
    algorithm: str
    markers: list[MarkerRow]


class _RobotRowExtra(TypedDict, total=False):
    """Optional fields of a ``robots`` row, sent by a fusion node (``kmea fuse``): the
    tracking filter's world velocity (m/s) and turn rate (rad/s), ``source`` (the cameras
    that saw the robot recently, "cam0+cam1") and ``sources`` (camera -> s since its last
    measurement). A daemon sends the velocity in ``robot.<name>`` only.

    ``refused`` (the destinations whose datagrams the receiving host refused among the
    robot's last messages: nothing listens on that port) and ``send_refused`` (how many of
    ``send_errors`` were such refusals): added later, recordings before them lack
    them."""

    refused: list[str]
    send_refused: int

    vx: float | None
    vy: float | None
    omega: float | None
    source: str
    sources: dict[str, float]


class RobotRow(_RobotRowExtra):
    """One configured robot of a ``robots`` body."""

    name: str
    markers: list[int]
    x: float | None
    y: float | None
    theta: float | None
    sigma: float | None
    valid: bool
    age_s: float | None
    stale: bool
    destinations: list[str]
    sent: int
    seq: int
    send_errors: int


class RobotsBody(TypedDict):
    """``robots``: every configured robot (every frame)."""

    t: float
    frame: int
    robots: list[RobotRow]


class _RawMeasurementTime(TypedDict, total=False):
    """t: the instant the measurement stands for (s; its markers' mid-exposure), also with
    ``filter.predict`` on, when the message's own ``t`` is the send time (older recordings
    lack it)."""

    t: float


class RawMeasurement(_RawMeasurementTime):
    """A robot measurement before the tracking filter (m, rad; sigma m or None)."""

    x: float
    y: float
    theta: float
    sigma: float | None


class _RobotMessageExtra(TypedDict, total=False):
    """Optional fields of a valid ``robot.<name>`` message with the tracking filter: world
    velocity vx, vy (m/s), turn rate omega (rad/s), age (s predicted past the measurement),
    raw (the measurement, what a fusion node fuses); from a fusion node, source and
    t_capture (the newest measurement's time, s) instead of raw."""

    vx: float
    vy: float
    omega: float
    age: float
    raw: RawMeasurement
    source: str
    t_capture: float


class RobotMessage(_RobotMessageExtra):
    """``robot.<name>``: one relay message (the UDP datagram's fields)."""

    name: str
    seq: int
    t: float
    x: float | None
    y: float | None
    theta: float | None
    valid: bool
    sigma: float | None


class MarkerStats(TypedDict):
    """Window statistics of one map marker's leave-one-out errors (m; mre in %)."""

    id: int
    n: int
    rmse: float | None
    std: float | None
    mae: float | None
    maxae: float | None
    mre: float | None


class StatsBody(TypedDict):
    """``stats``: window statistics (at most 5 Hz)."""

    t: float
    frame: int | None
    algorithm: str
    window: int
    mean_error: float | None
    max_error: float | None
    markers: list[MarkerStats]


class _OutputError(TypedDict, total=False):
    # Why the output stopped on its own (a write error, the free-space floor), None when it
    # did not; optional: daemons before it (and their recordings) do not send it.
    error: str | None


class LoggingState(_OutputError):
    active: bool
    path: str | None
    rows: int
    bytes: int


class RecordingState(_OutputError):
    active: bool
    path: str | None
    frames: int
    bytes: int


class CameraInfo(TypedDict):
    width: int
    height: int
    fx: float
    fy: float


class MapInfo(TypedDict, total=False):
    """The map's name and marker count (always), and ``extent``: [xmin, xmax, ymin, ymax]
    of its floor markers' centres, m (what the UI's map outline shows before, or without,
    any marker estimate: a fusion node); a fusion node, which has no markers telemetry, also
    sends ``markers``, so its map draws their ids."""

    name: str
    n: int
    extent: list[float]
    markers: list[list[float]]  # a fusion node: [id, x, y, z] of every map marker, m


class InputState(TypedDict):
    """A fusion node's camera (found on Zenoh): its id, key, state (waiting for its
    metadata, used, refused with a reason, silent, gone), counters, seconds since its last
    message, median delay (arrival - capture time, s), its clock's estimated offset against
    the node's (s, positive: ahead; None before a few messages)."""

    label: str
    key: str
    state: str
    reason: str | None
    received: int
    measurements: int
    bad: int
    bad_fields: dict[str, int]  # refused messages by the field that was wrong
    dropped_old: int
    silent_s: float | None
    delay_s: float | None
    clock_offset_s: float | None


class FusionState(TypedDict):
    """A fusion node's tracking counters and the latency it adds (ms)."""

    accepted: int
    rejected: int
    reacquired: int
    dropped_old: int
    latency_ms_p50: float | None
    latency_ms_p99: float | None
    node: str  # this node's id (its Zenoh session id)
    role: str  # starting, standby or active (the one that speaks to the robots)
    map_digest: str | None  # the map every camera must have (None: no camera yet)
    overflow: int  # samples dropped because the node fell behind
    strangers: int  # samples of cameras the node does not know (no token) or has no room for


class _StatusExtra(TypedDict, total=False):
    """A fusion node's ``status`` (``kmea fuse``) also has its inputs and counters.
    ``state`` is only in the last status a daemon sends, at shutdown: ``"stopped"`` (a UI
    then says "daemon stopped" instead of showing frozen data as live)."""

    inputs: list[InputState]
    fusion: FusionState
    state: str


class StatusBody(_StatusExtra):
    """``status``: the daemon's state (every ``network.status_period_s``)."""

    t: float
    uptime: float
    source: str
    config_file: str
    config_files: list[str]
    algorithm: str
    algorithms: list[str]  # the estimators this daemon can run (estimator.algorithm)
    logging: LoggingState
    recording: RecordingState
    camera: CameraInfo
    map: MapInfo
    frames: int
    dropped: int
    bad_frames: int
    telemetry: str
    control: str


class CameraOutline(TypedDict):
    """One marker outline of a ``camera`` body: corners in full-frame pixels (OpenCV:
    pixel centres at integer coordinates; TL, TR, BR, BL). kind: detected | suspect |
    rejected | expected (a map marker in view that was not detected)."""

    id: int
    kind: str
    corners: list[list[float]]


class CameraBody(TypedDict):
    """``camera``: a greyscale thumbnail while a client holds a ``camera_watch`` lease.

    data: base64 of ``width * height`` bytes, row-major (encoding "gray8"). focus: variance
    of the Laplacian over the detected markers' regions, or None.
    """

    t: float
    frame: int
    width: int
    height: int
    full_width: int
    full_height: int
    encoding: str
    data: str
    focus: float | None
    markers: list[CameraOutline]


class EventBody(TypedDict):
    """``event``: something a technician must see. level: info | warning | error."""

    t: float
    level: str
    text: str


class LogBody(TypedDict):
    """``log``: one of the daemon's log lines."""

    t: float
    level: str
    logger: str
    text: str


class _RequestBase(TypedDict):
    cmd: str


class ControlRequest(_RequestBase, total=False):
    """A control request: ``cmd`` and that command's arguments (docs/protocol.md)."""

    key: str
    value: Any
    path: str
    width: int  # camera_watch: thumbnail size, pixels
    height: int
    lease_s: float  # camera_watch: seconds
    overlay: bool  # snapshot
    limit: int  # get_log


class _ReplyBase(TypedDict):
    ok: bool


class ControlReply(_ReplyBase, total=False):
    """A control reply: ``ok`` with ``cmd`` and the command's fields, or ``error``."""

    cmd: str
    error: str


class StateReply(TypedDict):
    """The reply to ``get_state``; ``frame`` is ``{}`` before the first frame."""

    ok: bool
    cmd: str
    status: StatusBody
    frame: dict[str, Any]
    stats: StatsBody


class _ConfigReplyExtra(TypedDict, total=False):
    advanced: list[str]  # section.key of the keys config.toml and the UI's form leave out


class ConfigReply(_ConfigReplyExtra):
    """The reply to ``get_config``: the effective configuration as the TOML file's tables."""

    ok: bool
    cmd: str
    config: dict[str, Any]
    config_file: str | None
    config_files: list[str]
    overlay_file: str
    live_keys: list[str]


TOPIC_TYPES: dict[str, type] = {
    TOPIC_FRAME: FrameBody, TOPIC_MARKERS: MarkersBody, TOPIC_ROBOTS: RobotsBody,
    TOPIC_STATS: StatsBody, TOPIC_STATUS: StatusBody, TOPIC_EVENT: EventBody,
    TOPIC_LOG: LogBody, TOPIC_CAMERA: CameraBody,
}
REPLY_TYPES: dict[str, type] = {"get_state": StateReply, "get_config": ConfigReply}


def body_type(topic: str) -> type | None:
    """The declared body type of ``topic`` (``robot.<name>`` -> :class:`RobotMessage`)."""
    if topic.startswith(TOPIC_ROBOT_PREFIX):
        return RobotMessage
    return TOPIC_TYPES.get(topic)


# ----------------------------------------------------------------------- type checking
# Each declared type is compiled once into a checker function; a mismatch unwinds as
# _Mismatch collecting the field path, so a well-formed body costs no string formatting.
Checker = Callable[[Any, bool], None]


class _Mismatch(Exception):
    def __init__(self, expected: str, value: Any) -> None:
        super().__init__()
        self.path: list[str] = []
        self.expected = expected
        self.got = "null" if value is None else type(value).__name__


def _is_typeddict(tp: Any) -> bool:
    return isinstance(tp, type) and issubclass(tp, dict) and hasattr(tp, "__required_keys__")


def _type_name(tp: Any) -> str:
    if tp is type(None):
        return "null"
    if isinstance(tp, type):
        return "object" if _is_typeddict(tp) else tp.__name__
    origin = typing.get_origin(tp)
    if origin in (Union, types.UnionType):
        return " or ".join(_type_name(a) for a in typing.get_args(tp))
    return getattr(origin, "__name__", str(tp))


_COMPILED: dict[Any, Checker] = {}


def _compile(tp: Any) -> Checker:
    got = _COMPILED.get(tp)
    if got is None:
        got = _COMPILED[tp] = _build(tp)
    return got


def _build(tp: Any) -> Checker:
    name = _type_name(tp)
    if tp is Any:
        return lambda v, exact: None
    if tp is float:
        def check_float(v: Any, exact: bool) -> None:
            if type(v) is not float and type(v) is not int:
                raise _Mismatch(name, v)
        return check_float
    if tp in (int, str, bool, type(None)):
        def check_exact(v: Any, exact: bool, _t: type = tp) -> None:
            if type(v) is not _t:
                raise _Mismatch(name, v)
        return check_exact
    if _is_typeddict(tp):
        return _build_typeddict(tp)
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin in (Union, types.UnionType):
        options = [_compile(a) for a in args if a is not type(None)]
        nullable = type(None) in args

        def check_union(v: Any, exact: bool) -> None:
            if v is None and nullable:
                return
            for c in options:
                try:
                    c(v, exact)
                    return
                except _Mismatch:
                    continue
            raise _Mismatch(name, v)
        return check_union
    if origin is list:
        item = _compile(args[0])

        def check_list(v: Any, exact: bool) -> None:
            if type(v) is not list:
                raise _Mismatch(name, v)
            for i, x in enumerate(v):
                try:
                    item(x, exact)
                except _Mismatch as e:
                    e.path.insert(0, f"[{i}]")
                    raise
        return check_list
    if origin is dict:
        value = _compile(args[1])

        def check_dict(v: Any, exact: bool) -> None:
            if type(v) is not dict:
                raise _Mismatch(name, v)
            for k, x in v.items():
                try:
                    value(x, exact)
                except _Mismatch as e:
                    e.path.insert(0, f".{k}")
                    raise
        return check_dict
    raise TypeError(f"protocol type {tp!r} not supported")  # pragma: no cover


def _build_typeddict(td: type) -> Checker:
    fields: dict[str, Checker] = {}
    hints = typing.get_type_hints(td)
    required = frozenset(td.__required_keys__)

    def check_fields_(v: Any, exact: bool) -> None:
        if type(v) is not dict:
            raise _Mismatch("object", v)
        if not fields:  # compiled on first use: nested types may refer to each other
            fields.update({k: _compile(t) for k, t in hints.items()})
        if not required <= v.keys():
            e = _Mismatch("", None)
            e.path.append(f".{min(required - v.keys())}")
            e.expected = "missing"
            raise e
        for k, x in v.items():
            c = fields.get(k)
            if c is None:
                if exact and k != "v":
                    e = _Mismatch("", None)
                    e.path.append(f".{k}")
                    e.expected = f"not in {td.__name__}"
                    raise e
                continue
            try:
                c(x, exact)
            except _Mismatch as e:
                e.path.insert(0, f".{k}")
                raise
    return check_fields_


def check_fields(body: dict[str, Any], td: type, where: str = "", exact: bool = False) -> None:
    """Check ``body`` against the TypedDict ``td``: required keys present, every declared
    key's value of its type (an int is a float, a bool is not an int). ``exact``: also refuse
    keys ``td`` does not declare (the tests use it; clients accept added fields).
    ``ProtocolError`` names the field (``where`` is put in front of its path)."""
    try:
        _compile(td)(body, exact)
    except _Mismatch as e:
        path = (where + "".join(e.path)).lstrip(".")
        if e.expected == "missing" or e.expected.startswith("not in "):
            raise ProtocolError(f"field {path!r}: {e.expected}") from None
        raise ProtocolError(f"field {path!r}: expected {e.expected}, got {e.got}") from None


def check_body(topic: str, body: dict[str, Any], exact: bool = False) -> dict[str, Any]:
    """``body`` if it has the declared type of ``topic``, else ``ProtocolError`` naming the
    topic and the field. Topics without a declared type are refused."""
    td = body_type(topic)
    if td is None:
        raise ProtocolError(f"topic {topic!r}: unknown")
    try:
        check_fields(body, td, exact=exact)
    except ProtocolError as e:
        raise ProtocolError(f"{topic}: {e}") from None
    return body


# ----------------------------------------------------------------------- encode / decode
def _numpy_default(obj: Any) -> Any:
    if hasattr(obj, "tolist"):  # numpy arrays and scalars (not float subclasses)
        return obj.tolist()
    raise TypeError(type(obj).__name__)


def encode_body(body: dict[str, Any] | Any) -> bytes:
    """JSON bytes of ``body`` with the protocol version added (NaN/inf sent as null)."""
    try:
        # Fast path (the sender thread's main cost): bodies without NaN/inf and with str or
        # int keys encode to the same bytes as the cleaned copy, without the Python walk.
        return json.dumps({"v": PROTOCOL_VERSION, **body}, separators=(",", ":"),
                          allow_nan=False, default=_numpy_default).encode()
    except (TypeError, ValueError):
        pass
    clean = to_jsonable(body)
    if not isinstance(clean, dict):
        raise TypeError(f"a body must be a JSON object, not {type(body).__name__}")
    return json.dumps({"v": PROTOCOL_VERSION, **clean}, separators=(",", ":"),
                      allow_nan=False).encode()


def encode(topic: str, body: dict[str, Any] | Any) -> list[bytes]:
    """Multipart frames ``[topic, body]`` for a PUB socket."""
    return [topic.encode("ascii"), encode_body(body)]


def decode_body(data: bytes, max_bytes: int = MAX_MESSAGE_BYTES,
                max_depth: int = MAX_DEPTH) -> dict[str, Any]:
    """Parse one JSON body and check its version; ``ProtocolError`` names the problem.

    Refused (:mod:`kmea.wire.jsonlimits`): more than ``max_bytes``, nesting deeper than
    ``max_depth``, not UTF-8 JSON, NaN or Infinity; then anything but an object, and a ``v``
    other than exactly the integer :data:`PROTOCOL_VERSION` (``true`` or ``2.0`` are not
    versions).
    """
    try:
        body = safe_loads(data, max_bytes, max_depth)
    except JsonLimitError as e:
        raise ProtocolError(str(e)) from None
    if not isinstance(body, dict):
        raise ProtocolError("body must be a JSON object")
    v = body.get("v")
    if type(v) is not int or v != PROTOCOL_VERSION:
        shown = repr(v) if len(repr(v)) < 40 else repr(v)[:37] + "..."
        raise ProtocolError(f"field 'v': protocol version {shown} not supported "
                            f"(expected the integer {PROTOCOL_VERSION})")
    return body


def decode(frames: list[bytes], typed: bool = True) -> tuple[str, dict[str, Any]]:
    """Inverse of :func:`encode`; ``typed``: also :func:`check_body` against the topic's
    declared type."""
    if len(frames) != 2:
        raise ProtocolError(f"expected 2 frames [topic, body], got {len(frames)}")
    try:
        topic = frames[0].decode("ascii")
    except UnicodeDecodeError:
        raise ProtocolError("topic is not ASCII") from None
    body = decode_body(frames[1])
    if typed:
        check_body(topic, body)
    return topic, body
