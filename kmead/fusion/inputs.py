"""What a camera sends the fusion node, checked once where it enters: the schema of a
camera's metadata, measurement and heartbeat (types, finite, physical ranges), and each
camera's clock offset against the node's.

Everything received over Zenoh is hostile. A message that fails is counted on its camera
(``bad``) and reported in one event per camera and field; nothing here raises to the node's
loop. The ranges (docs/fusion.md, "What it checks"):

- position within the extent of the map's markers plus ``fusion.margin_m``;
- sigma in [0.1 mm, ``fusion.max_sigma_m``] (a smaller one, e.g. two markers that agree
  exactly, is taken as 0.1 mm: the filter floors it far above anyway);
- time no later than the node's own Unix clock plus ``fusion.max_future_s`` (the lower
  bound, ``fusion.max_age_s`` behind the fusion clock, is :class:`kmea.robots.fusion.Fusion`'s).

Clocks: arrival (the node's clock) minus capture time is the network and processing delay
plus the clock offset; over a camera's last :data:`CLOCK_WINDOW` messages its low
percentile is the delay's least part, so the camera's clock offset is estimated as minus
that (positive: the camera is ahead). Beyond ``fusion.clock_warn_s`` an event names the
camera and the offset; beyond ``fusion.max_clock_offset_s`` the camera is refused until it is
back within.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from kmea.robots.fusion import Measurement
from kmea.wire.jsonlimits import safe_loads

__all__ = ["CLOCK_MIN", "CLOCK_WINDOW", "MAX_META_BYTES", "MAX_SAMPLE_BYTES", "MIN_SIGMA_M",
           "BadField", "Limits", "admit", "check_meta", "clock_offset", "measurement_from",
           "number"]

MAX_META_BYTES = 4096
MAX_SAMPLE_BYTES = 1024  # a measurement or heartbeat; larger ones are bad
MIN_SIGMA_M = 1e-4
MAX_COORD_M = 1e4  # an extent in metadata beyond this is no floor
CLOCK_WINDOW = 50  # messages the clock offset is estimated over
CLOCK_MIN = 5  # messages before a camera's offset is judged
CLOCK_QUANTILE = 0.1  # low enough to leave out the processing delay, high enough that a
# few hostile timestamps cannot move it


class BadField(ValueError):
    """A message refused: ``field`` names what was wrong."""

    def __init__(self, field: str, text: str) -> None:
        super().__init__(text)
        self.field = field


def number(v: Any, field: str, lo: float = -math.inf, hi: float = math.inf) -> float:
    """``v`` as a finite float in [lo, hi]; :class:`BadField` otherwise (also for an integer
    too large for a float, or a bool)."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise BadField(field, f"field {field!r}: expected a number, got {_shown(v)}")
    try:
        x = float(v)
    except OverflowError:
        raise BadField(field, f"field {field!r}: a number out of range") from None
    if not math.isfinite(x):
        raise BadField(field, f"field {field!r}: expected a finite number, got {_shown(v)}")
    if not lo <= x <= hi:
        raise BadField(field, f"field {field!r}: {x:.6g} outside [{lo:.6g}, {hi:.6g}]")
    return x


def _shown(v: Any) -> str:
    text = repr(v)
    return text if len(text) <= 40 else text[:37] + "..."


@dataclass(frozen=True)
class Limits:
    """The ranges a measurement must be in: the floor (xmin, xmax, ymin, ymax, m, the
    margin included), the largest sigma (m), how far ahead of the node's clock (s)."""

    extent: tuple[float, float, float, float]
    max_sigma_m: float
    max_future_s: float

    @classmethod
    def of(cls, fusion: dict, extent: tuple[float, float, float, float]) -> Limits:
        """From the ``[fusion]`` section and the markers' extent (the margin added)."""
        m = float(fusion["margin_m"])
        x0, x1, y0, y1 = extent
        return cls((x0 - m, x1 + m, y0 - m, y1 + m), float(fusion["max_sigma_m"]),
                   float(fusion["max_future_s"]))


def check_meta(payload: bytes) -> dict:
    """A camera's metadata (kmead.outputs.zenoh_camera.meta_body), checked; ValueError names
    what is wrong. ``extent`` (the markers' xmin, xmax, ymin, ymax) is optional."""
    body = safe_loads(payload, MAX_META_BYTES, 4)
    if not isinstance(body, dict):
        raise ValueError("metadata: expected a JSON object")
    for k in ("camera", "map_digest", "map_name", "model", "source"):
        if not isinstance(body.get(k), str) or len(body[k]) > 256:
            raise ValueError(f"metadata field {k!r}: expected a string")
    for k in ("width", "height"):
        v = body.get(k)
        if isinstance(v, bool) or not isinstance(v, int) or not 0 < v < 100000:
            raise ValueError(f"metadata field {k!r}: expected a size in pixels")
    ext = body.get("extent")
    if ext is not None:
        if not isinstance(ext, list) or len(ext) != 4:
            raise ValueError("metadata field 'extent': expected [xmin, xmax, ymin, ymax]")
        x0, x1, y0, y1 = (number(v, "extent", -MAX_COORD_M, MAX_COORD_M) for v in ext)
        if x0 > x1 or y0 > y1:
            raise ValueError("metadata field 'extent': expected [xmin, xmax, ymin, ymax]")
        body["extent"] = (x0, x1, y0, y1)
    return body


def measurement_from(label: str, body: dict, names: set[str],
                     limits: Limits | None = None) -> Measurement | None:
    """A measurement from a ``robot.NAME`` body (its ``raw`` measurement when the camera's
    daemon filters with the tracking filter), None for a valid=0 (stale) message;
    :class:`BadField` names the bad field. ``limits``: the position and sigma ranges (the
    time's is :func:`admit`'s: it needs the clock)."""
    name = body.get("name")
    if not isinstance(name, str) or name not in names:
        raise BadField("name", f"field 'name': unknown robot {_shown(name)}")
    valid = body.get("valid")
    if not isinstance(valid, bool):
        raise BadField("valid", "field 'valid': expected true or false")
    if not valid:
        return None
    raw = body.get("raw")
    # A daemon with the tracking filter sends its filtered pose and the measurement ("raw"):
    # fuse the measurement (filtering filtered poses again would count the noise twice).
    src = {**body, **raw} if isinstance(raw, dict) else body
    x0, x1, y0, y1 = limits.extent if limits else (-math.inf, math.inf, -math.inf, math.inf)
    t = number(src.get("t"), "t")
    x = number(src.get("x"), "x", x0, x1)
    y = number(src.get("y"), "y", y0, y1)
    theta = number(src.get("theta"), "theta", -4 * math.pi, 4 * math.pi)
    sigma = src.get("sigma")
    if sigma is not None:
        sigma = max(number(sigma, "sigma", 0.0, limits.max_sigma_m if limits else math.inf),
                    MIN_SIGMA_M)
    return Measurement(label, name, t, x, y, theta, sigma)


def clock_offset(delays: Any) -> float | None:
    """The camera's clock minus the node's (s; positive: ahead), from its recent delays
    (arrival minus capture time); None before :data:`CLOCK_MIN` of them."""
    if len(delays) < CLOCK_MIN:
        return None
    d = sorted(delays)
    return -d[int(CLOCK_QUANTILE * (len(d) - 1))]


def admit(cam: Any, parts: list[str], payload: bytes, now_wall: float, names: set[str],
          limits: Limits, cfg: dict, event: Callable[[str, str], None]) -> Measurement | None:
    """One sample of camera ``cam`` (kmead.fusion.cameras.Camera) on key ``parts``, checked:
    the measurement to fuse, or None (a heartbeat, a valid=0, another node's robot, or
    refused: counted on the camera, one event per camera and field). Watches the camera's
    clock (``cfg``: the ``[fusion]`` section)."""
    try:
        body = safe_loads(payload, MAX_SAMPLE_BYTES, 2)
        if not isinstance(body, dict):
            raise BadField("body", "expected a JSON object")
        if parts[3] == "frame" and len(parts) == 4:
            _clock(cam, number(body.get("t"), "t"), now_wall, limits, cfg, event)
            return None
        if parts[3] != "robots" or len(parts) != 5 or body.get("name") != parts[4]:
            raise BadField("key", f"key {'/'.join(parts)!r}: not <site>/cam/<id>/robots/"
                                  "<its name>")
        if parts[4] not in names:  # another node's robot (a region of its own)
            cam.ignored += 1
            return None
        m = measurement_from(cam.label, body, names, limits)
        if m is not None:
            _clock(cam, m.t, now_wall, limits, cfg, event)
        return m
    except BadField as e:
        _bad(cam, e.field, str(e), event)
    except ValueError as e:  # JsonLimitError: size, depth, NaN
        _bad(cam, "body", str(e), event)
    return None


def _bad(cam: Any, field: str, text: str, event: Callable[[str, str], None]) -> None:
    cam.bad += 1
    cam.bad_fields[field] = cam.bad_fields.get(field, 0) + 1
    if cam.bad_fields[field] == 1:
        event("warning", f"camera {cam.label}: message refused: {text} (further ones with "
                         f"a bad {field!r} are only counted)")


def _clock(cam: Any, t: float, now_wall: float, limits: Limits, cfg: dict,
           event: Callable[[str, str], None]) -> None:
    """Record the message's delay, judge the camera's clock; :class:`BadField` for a time
    ahead of the node's clock by more than ``limits.max_future_s``."""
    cam.delays.append(now_wall - t)
    cam.clock.append(now_wall - t)
    off = clock_offset(cam.clock)
    if off is not None:
        cam.clock_offset_s = off
        _judge_clock(cam, off, cfg, event)
    if t > now_wall + limits.max_future_s:
        raise BadField("t", f"field 't': {t - now_wall:.3f} s ahead of the node's clock "
                            f"(more than fusion.max_future_s {limits.max_future_s:g} s)")


def _judge_clock(cam: Any, off: float, cfg: dict, event: Callable[[str, str], None]) -> None:
    side = "ahead of" if off > 0 else "behind"
    warn, refuse = float(cfg["clock_warn_s"]), float(cfg["max_clock_offset_s"])
    if abs(off) > warn and not cam.clock_warned:
        cam.clock_warned = True
        event("warning", f"camera {cam.label}: its clock is {abs(off):.3f} s {side} the "
                         f"node's (more than fusion.clock_warn_s {warn:g} s; behind includes "
                         "its processing delay)")
    elif abs(off) <= warn / 2 and cam.clock_warned:  # hysteresis: one event per excursion
        cam.clock_warned = False
        event("info", f"camera {cam.label}: its clock agrees with the node's again "
                      f"({off:+.3f} s)")
    if abs(off) > refuse and cam.state == "used":
        cam.state, cam.clock_refused = "refused", True
        cam.reason = (f"its clock is {abs(off):.3f} s {side} the node's (more than "
                      f"fusion.max_clock_offset_s {refuse:g} s)")
        event("warning", f"camera {cam.label}: refused: {cam.reason}")
    elif abs(off) <= refuse and cam.clock_refused and cam.state == "refused":
        cam.state, cam.reason, cam.clock_refused = "used", None, False
        event("info", f"camera {cam.label}: its clock is back within "
                      f"{refuse:g} s ({off:+.3f} s): used")
