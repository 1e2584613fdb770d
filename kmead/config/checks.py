"""The checks that configuration keys are declared with (kmead.config.schema): types,
ranges, names, endpoints, robots.

The same check runs for the configuration files, ``--set`` and a live ``set`` request
(``remote=True`` adds the rules for a request that came over the network: a dictionary
must be a predefined name, never a file path). A bad value raises :class:`ConfigError`
with one line naming where it came from, the key and the problem; no check can raise
anything else, whatever the value (huge integers, NaN, nested tables, wrong types).

Ranges are the values that mean something: past them a value is a mistake or an attack
(``stats.window = 10**30`` once overflowed ``deque(maxlen=...)`` and stopped the daemon;
``perspectiveRemovePixelPerCell = 2000`` grew memory by 385 MB).
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from kmea.maps.aruco_names import MAX_MARKER_ID

__all__ = [
    "MAX_DESTINATIONS",
    "MAX_ROBOTS",
    "ConfigError",
    "Key",
    "check_destination",
    "check_robot_name",
    "choice",
    "integer",
    "number",
    "off_or_number",
    "parse_destination",
    "same_file",
    "validate_robots",
]


class ConfigError(ValueError):
    """A bad configuration file or value; the message is one line naming file and key."""


class Check(Protocol):
    """``check(value, where, remote=False) -> normalised value``; raises ConfigError."""

    def __call__(self, v: Any, where: str, remote: bool = False, /) -> Any: ...


@dataclass(frozen=True)
class Key:
    """One ``section.key``: ``default`` (what config.toml holds), ``check(value, where,
    remote) -> normalised value``, ``summary`` (one line, the docs' table), ``doc`` (the
    comment above it in config.toml; "" = the comment above an earlier key covers it) and
    ``live`` (a running daemon may change it; the others need a restart)."""

    default: Any
    check: Check
    summary: str
    doc: str = ""
    live: bool = False


MAX_ROBOTS = 64
MAX_DESTINATIONS = 8
MAX_TEXT = 4096  # file names, endpoints, source specs


def shown(v: Any, n: int = 60) -> str:
    """``repr`` cut to a readable length (a hostile value can be megabytes long)."""
    try:
        r = v if isinstance(v, str) and n > 60 else repr(v)
    except Exception:  # a value whose repr fails (huge int digits, recursion)
        r = f"<{type(v).__name__}>"
    return r if len(r) <= n else r[:n - 3] + "..."


def _got(v: Any) -> str:
    """What a wrong value is, in TOML's words: a string that holds a number says it is a
    string (the quotes are the mistake), not just its repr."""
    if isinstance(v, bool):
        return f"the boolean {str(v).lower()}"
    if isinstance(v, str):
        try:
            float(v)
        except ValueError:
            return f"the string {shown(v)}"
        return f"the string {shown(v)} (a number is written without quotes: {shown(v)[1:-1]})"
    if isinstance(v, (int, float)):
        return f"the number {shown(v)}"
    if isinstance(v, (list, tuple)):
        return f"an array {shown(v)}"
    if isinstance(v, dict):
        return f"a table {shown(v)}"
    return shown(v)


def text_value(v: Any, where: str, remote: bool = False) -> str:
    if not isinstance(v, str):
        raise ConfigError(f"{where}: expected a string, got {_got(v)}")
    if len(v) > MAX_TEXT or "\x00" in v:
        raise ConfigError(f"{where}: string too long or with a NUL character")
    return v


def flag(v: Any, where: str, remote: bool = False) -> bool:
    if not isinstance(v, bool):
        raise ConfigError(f"{where}: expected true or false, got {_got(v)}")
    return v


def _real(v: Any, where: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ConfigError(f"{where}: expected a number, got {_got(v)}")
    try:
        x = float(v)
    except OverflowError:
        raise ConfigError(f"{where}: number out of range, got {shown(v)}") from None
    if not math.isfinite(x):
        raise ConfigError(f"{where}: expected a finite number, got {shown(v)}")
    return x


def number(lo: float, hi: float, lo_open: bool = False, unit: str = "") -> Check:
    """A finite float in [lo, hi] (``(lo, hi]`` when ``lo_open``)."""
    def check(v: Any, where: str, remote: bool = False) -> float:
        x = _real(v, where)
        if (x <= lo if lo_open else x < lo) or x > hi:
            left = "(" if lo_open else "["
            raise ConfigError(f"{where}: must be in {left}{lo:g}, {hi:g}]{unit}, got {shown(v)}")
        return x
    check.lo, check.hi, check.lo_open = lo, hi, lo_open  # type: ignore[attr-defined]
    check.text = f"{'(' if lo_open else '['}{lo:g}, {hi:g}]{unit}"  # type: ignore[attr-defined]
    return check


def off_or_number(lo: float, hi: float, unit: str = "") -> Check:
    """0 (off) or a finite float in [lo, hi]: a limit that is either off or means something
    (a recording part of 0.001 MB would be a new file every frame)."""
    inner = number(lo, hi, unit=unit)

    def check(v: Any, where: str, remote: bool = False) -> float:
        x = _real(v, where)
        if x == 0:
            return 0.0
        try:
            return inner(v, where, remote)
        except ConfigError:
            raise ConfigError(f"{where}: must be 0 (off) or in [{lo:g}, {hi:g}]{unit}, "
                              f"got {shown(v)}") from None
    check.text = f"0 (off) or [{lo:g}, {hi:g}]{unit}"  # type: ignore[attr-defined]
    return check


def integer(lo: int, hi: int) -> Check:
    """An integer (not a bool, not a float) in [lo, hi]."""
    def check(v: Any, where: str, remote: bool = False) -> int:
        if isinstance(v, bool) or not isinstance(v, int):
            raise ConfigError(f"{where}: expected an integer, got {_got(v)}")
        if not lo <= v <= hi:
            raise ConfigError(f"{where}: must be an integer in [{lo}, {hi}], got {shown(v)}")
        return int(v)
    check.text = f"integer [{lo}, {hi}]"  # type: ignore[attr-defined]
    return check


def choice(*options: str) -> Check:
    def check(v: Any, where: str, remote: bool = False) -> str:
        if not isinstance(v, str) or v not in options:
            raise ConfigError(f"{where}: must be one of {', '.join(options)}; got {shown(v)}")
        return v
    check.text = " | ".join(options)  # type: ignore[attr-defined]
    return check


# ---------------------------------------------------------------------------- strings

def source_spec(v: Any, where: str, remote: bool = False) -> str:
    from kmea.sources.base import SourceError  # the one spec grammar:
    from kmea.sources.registry import parse_source_spec

    s = text_value(v, where)
    try:
        parse_source_spec(s, check=True)
    except SourceError as e:
        raise ConfigError(f"{where}: {shown(str(e), 200)}; use sim, sim:SCENE, picamera, "
                          "camera:INDEX, video:PATH, images:DIR or replay:FILE") from None
    return s


def algorithm_name(v: Any, where: str, remote: bool = False) -> str:
    s = text_value(v, where)
    from kmea import estimators

    if s not in estimators.available(live=True):
        paper = " (it reproduces the paper: kmea experiment)" if s in estimators.PAPER_ONLY else ""
        raise ConfigError(f"{where}: unknown algorithm {shown(s)}{paper}; choose one of "
                          f"{', '.join(estimators.available(live=True))}")
    return s


def dictionary_name(v: Any, where: str, remote: bool = False) -> str:
    s = text_value(v, where)
    if s == "":
        return s
    from kmea.maps.aruco_names import canonical_name
    from kmea.vision.dictionary import get_dictionary

    if remote:
        # Over the network a name only: a path would read files and tell whether they exist.
        if canonical_name(s) is None:
            raise ConfigError(f"{where}: over control the dictionary must be a predefined "
                              f"name such as DICT_5X5_100, got {shown(s)}")
        return s
    try:
        get_dictionary(s)
    except ValueError as e:
        raise ConfigError(f"{where}: {e}") from None
    return s


_ENDPOINT_RE = re.compile(r"^(tcp://(\[[0-9A-Fa-f:.]+\]|[^:/\[\]\s]+):(\d{1,5}|\*)|ipc://\S+|"
                          r"inproc://\S+)$")


def zmq_endpoint(v: Any, where: str, remote: bool = False) -> str:
    s = text_value(v, where)
    m = _ENDPOINT_RE.match(s) if s else None
    if s and (not m or (m.group(3) and m.group(3) != "*" and not 0 < int(m.group(3)) < 65536)):
        raise ConfigError(f"{where}: expected a ZeroMQ endpoint like tcp://127.0.0.1:5555 "
                          f"(or \"\" for off), got {shown(s)}")
    return s


# A probability a filter turns into a chi-square quantile or an odds ratio: 1e-300 or
# 1 - 1e-17 (== 1.0 in a float) is no probability anyone means, and breaks the arithmetic.
def probability_value(v: Any, where: str, remote: bool = False) -> float:
    x = _real(v, where)
    if not probability_value.lo <= x <= probability_value.hi:  # type: ignore[attr-defined]
        raise ConfigError(f"{where}: must be a probability in [1e-06, 1 - 1e-09], got "
                          f"{shown(v)}")
    return x


probability_value.lo, probability_value.hi = 1e-6, 1 - 1e-9  # type: ignore[attr-defined]
probability_value.text = "[1e-06, 1 - 1e-09]"  # type: ignore[attr-defined]


# ---------------------------------------------------------------------------- detector


def detector_parameters(v: Any, where: str, remote: bool = False) -> dict:
    """The library's detector-parameter rule (:func:`kmea.vision.detection.check_parameters`)
    as a :class:`ConfigError`."""
    from kmea.vision.detection import check_parameters

    try:
        return check_parameters(v, where)
    except ValueError as e:
        raise ConfigError(str(e)) from None


# ---------------------------------------------------------------------------- robots

ROBOT_KEYS = ("name", "markers", "height", "length", "separation", "destinations")
_NAME_RE = re.compile(r"^[A-Za-z0-9_-]{1,32}$")
# A hostname (RFC 1123 labels) or a dotted IPv4 literal: what goes to getaddrinfo, nothing
# a shell or a file name could make use of.
_LABEL_RE = re.compile(r"^[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?$")
_IPV4_RE = re.compile(r"^\d{1,3}(\.\d{1,3}){3}$")
_UDP_RE = re.compile(r"^udp:([^:]{1,253}):(\d{1,5})$")


def check_robot_name(v: Any, where: str) -> str:
    """A short identifier: it goes into datagrams, topics and CSV rows."""
    s = text_value(v, where)
    if not _NAME_RE.match(s):
        raise ConfigError(f"{where}: 1-32 letters, digits, '_' or '-' (it goes in datagrams "
                          f"and topics), got {shown(s)}")
    return s


def _host_ok(host: str) -> bool:
    if _IPV4_RE.match(host):
        return all(0 <= int(p) <= 255 for p in host.split("."))
    if host[-1:].isdigit() and host.replace(".", "").isdigit():
        return False  # "1.2.3" is neither an IPv4 literal nor a hostname
    return len(host) <= 253 and all(_LABEL_RE.match(x) for x in host.split("."))


def parse_destination(d: Any, where: str) -> tuple[str, int]:
    """``"udp:HOST:PORT"`` -> (host, port); HOST a hostname or an IPv4 literal, PORT 1-65535."""
    m = _UDP_RE.match(d) if isinstance(d, str) else None
    if not m or not _host_ok(m.group(1)) or not 0 < int(m.group(2)) < 65536:
        raise ConfigError(f"{where}: destination must be \"udp:HOST:PORT\" (a hostname or IPv4 "
                          f"address, port 1-65535), got {shown(d)}")
    return m.group(1), int(m.group(2))


def check_destination(d: Any, where: str) -> str:
    parse_destination(d, where)
    return d


def _robot(row: Any, where: str) -> dict:
    if not isinstance(row, dict):
        raise ConfigError(f"{where}: expected a table with {', '.join(ROBOT_KEYS)}")
    bad = sorted(str(k) for k in set(row) - set(ROBOT_KEYS))
    if bad:
        raise ConfigError(f"{where}: unknown key {shown(bad[0])} (robot keys: "
                          f"{', '.join(ROBOT_KEYS)})")
    from kmea.robots.poses import ROBOT_DEFAULTS, robot_from_table  # the one robot validation

    for k in ("name", "markers"):
        if k not in row:
            raise ConfigError(f"{where}: missing key {k!r}")
    # The ranges first (robot_from_table checks signs, not sizes, and prints values whole).
    check_robot_name(row["name"], f"{where}.name")
    markers = row["markers"]
    ids = [markers] if isinstance(markers, int) and not isinstance(markers, bool) else markers
    if (not isinstance(ids, list) or len(ids) not in (1, 2)
            or any(isinstance(m, bool) or not isinstance(m, int) or not 0 <= m <= MAX_MARKER_ID
                   for m in ids)):
        raise ConfigError(f"{where}.markers: expected one marker id or a pair [left, right], "
                          f"ids 0-{MAX_MARKER_ID}, got {shown(row['markers'])}")
    for key, hi in (("height", 10.0), ("length", 1.0), ("separation", 10.0)):
        number(0 if key == "height" else 1e-4, hi, unit=" m")(
            row.get(key, ROBOT_DEFAULTS[key]), f"{where}.{key}")
    try:
        spec = robot_from_table(row, where)
    except ValueError as e:
        raise ConfigError(str(e)) from None
    name, markers = spec.name, list(spec.markers)
    height, length, separation = spec.height, spec.length, spec.separation
    dests = row.get("destinations", [])
    if not isinstance(dests, list) or len(dests) > MAX_DESTINATIONS:
        raise ConfigError(f"{where}.destinations: expected a list of at most {MAX_DESTINATIONS} "
                          "like [\"udp:127.0.0.1:9001\"]")
    for i, d in enumerate(dests):
        parse_destination(d, f"{where}.destinations[{i}]")
    return {"name": name, "markers": [int(m) for m in markers], "height": height,
            "length": length, "separation": separation, "destinations": list(dests)}


def validate_robots(rows: Any, where: str, remote: bool = False) -> list[dict]:
    """The ``[[robots]]`` list: at most MAX_ROBOTS, unique names, each marker once."""
    if not isinstance(rows, list):
        raise ConfigError(f"{where}: expected an array of tables [[robots]]")
    if len(rows) > MAX_ROBOTS:
        raise ConfigError(f"{where}: at most {MAX_ROBOTS} robots, got {len(rows)}")
    out = [_robot(r, f"{where}[{i}]") for i, r in enumerate(rows)]
    names: set[str] = set()
    ids: dict[int, str] = {}
    for i, r in enumerate(out):
        if r["name"] in names:
            raise ConfigError(f"{where}[{i}].name: duplicate robot name {r['name']!r}")
        names.add(r["name"])
        for m in r["markers"]:
            if m in ids:
                raise ConfigError(f"{where}[{i}].markers: marker {m} already belongs to "
                                  f"robot {ids[m]!r}")
            ids[m] = r["name"]
    return out


# ---------------------------------------------------------------------------- zenoh

MAX_ZENOH_ENDPOINTS = 16
PROTOCOLS = ("tcp", "tls", "udp", "quic")
# proto/host:port; host a name, an IPv4 literal or a bracketed IPv6 literal. Zenoh's
# "#iface=..." metadata and other suffixes are refused: nothing but an address goes in.
_ZENOH_ENDPOINT_RE = re.compile(r"^(tcp|tls|udp|quic)/"
                                r"(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9.-]{1,253}):(\d{1,5})$")
_SITE_RE = re.compile(r"^[A-Za-z0-9_-]{1,32}$")
# ROS 2 name tokens (rcl's rules): a letter or '_' first, then letters, digits, '_'.
ROS_TOKEN_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]{0,62}$")


def zenoh_endpoint(v: Any, where: str) -> str:
    s = text_value(v, where)
    m = _ZENOH_ENDPOINT_RE.match(s)
    if not m or not 0 <= int(m.group(3)) < 65536:
        raise ConfigError(f"{where}: expected a Zenoh endpoint like tcp/127.0.0.1:7447 or "
                          f"tls/host.example:7447 ({', '.join(PROTOCOLS)}), got {shown(s)}")
    return s


def zenoh_endpoints(v: Any, where: str, remote: bool = False) -> list[str]:
    if not isinstance(v, list) or len(v) > MAX_ZENOH_ENDPOINTS:
        raise ConfigError(f"{where}: expected a list of at most {MAX_ZENOH_ENDPOINTS} Zenoh "
                          "endpoints like [\"tcp/127.0.0.1:7447\"]")
    return [zenoh_endpoint(e, f"{where}[{i}]") for i, e in enumerate(v)]


def site_name(v: Any, where: str, remote: bool = False) -> str:
    """The site: the first chunk of every key (``<site>/robots/<robot>/pose``)."""
    s = text_value(v, where)
    if not _SITE_RE.match(s):
        raise ConfigError(f"{where}: 1-32 letters, digits, '_' or '-' (it is the first part "
                          f"of every Zenoh key), got {shown(s)}")
    return s


def camera_id(v: Any, where: str, remote: bool = False) -> str:
    """This camera's id in ``<site>/cam/<id>``; ``""``: derived (kmead.outputs.zenoh_camera)."""
    s = text_value(v, where)
    if s and not _SITE_RE.match(s):
        raise ConfigError(f"{where}: \"\" or 1-32 letters, digits, '_' or '-' (the camera's "
                          f"part of its Zenoh keys), got {shown(s)}")
    return s


def ros_namespace(v: Any, where: str, remote: bool = False) -> str:
    """``""`` (the root) or ``/a/b``: tokens of ROS names, a leading slash, none trailing."""
    s = text_value(v, where)
    if s in ("", "/"):
        return ""
    if not s.startswith("/") or not all(ROS_TOKEN_RE.match(t) for t in s[1:].split("/")):
        raise ConfigError(f"{where}: a ROS 2 namespace like \"/kmea\" (tokens of letters, "
                          f"digits and '_', not starting with a digit), got {shown(s)}")
    return s


def frame_id(v: Any, where: str, remote: bool = False) -> str:
    """A tf2 frame id: tokens separated by '/', no leading slash (tf2 refuses one)."""
    s = text_value(v, where)
    if not s or s.startswith("/") or not all(ROS_TOKEN_RE.match(t) for t in s.split("/")):
        raise ConfigError(f"{where}: a tf2 frame id like \"map\" (no leading '/'), "
                          f"got {shown(s)}")
    return s



def check_intrinsics(fx: float, fy: float, cx: float, cy: float, width: int, height: int,
                     where: str) -> None:
    """The library's intrinsics rule (:func:`kmea.geometry.camera.check_intrinsics`), as a
    :class:`ConfigError` naming ``where``."""
    from kmea.geometry.camera import check_intrinsics as check

    try:
        check(fx, fy, cx, cy, width, height)
    except ValueError as e:
        raise ConfigError(f"{where}: {e}") from None


def same_file(a: str | Path, b: str | Path) -> bool:
    """True when two paths name the same file (resolved; existing or not)."""
    try:
        pa, pb = Path(a), Path(b)
        if pa.exists() and pb.exists():
            return os.path.samefile(pa, pb)
        return pa.resolve() == pb.resolve()
    except (OSError, ValueError):
        return False
