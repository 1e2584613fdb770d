"""Opening a frame source from a spec string (see ``docs/camera.md``): the one spec grammar
and the table of source kinds.

- ``images:DIR``   image files in DIR, in natural name order (``img2`` before ``img10``);
- ``video:PATH``   a video file read with ``cv2.VideoCapture``; ends cleanly;
- ``camera:INDEX`` a V4L2/OpenCV camera; options ``width``, ``height``, ``fps``;
- ``picamera``     the Raspberry Pi camera through picamera2 (imported only when opened):
  greyscale Y plane of a YUV420 stream; options ``width``, ``height``, ``fps``;
- ``sim:SCENE``    the simulator (:func:`kmea.sources.sim.open_sim`);
- ``replay:FILE``  a recording's detections and poses (:func:`kmea.sources.replay.open_replay`);
- anything added with :func:`register_source`.

Options come as keyword arguments of :func:`open_source` or after a ``?`` in the spec:
``camera:0?width=1280&height=960&fps=30``.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from kmea.sources.base import FrameSource, SourceError, SourceOptionError
from kmea.sources.camera import CameraSource
from kmea.sources.files import ImageFolderSource, VideoSource
from kmea.sources.picamera import PiCameraSource
from kmea.sources.replay import open_replay
from kmea.sources.sim import open_sim

__all__ = ["SourceSpec", "open_source", "parse_source_spec", "register_source",
           "source_prefixes"]


SourceFactory = Callable[..., FrameSource]
_REGISTRY: dict[str, SourceFactory] = {}


def register_source(prefix: str, factory: SourceFactory) -> None:
    """Make ``open_source("PREFIX:REST", **opts)`` call ``factory(REST, **opts)``.

    For sources outside the library (tests, site plug-ins). Registering a prefix again
    replaces the factory; a registered prefix wins over a built-in one.
    """
    if not re.fullmatch(r"[a-z][a-z0-9_-]*", prefix):
        raise ValueError(f"source prefix {prefix!r}: use lower-case letters, digits, - and _")
    _REGISTRY[prefix] = factory


def source_prefixes() -> list[str]:
    """Every prefix :func:`open_source` accepts (built in and registered), sorted."""
    return sorted({*_BUILTIN, *_REGISTRY})


_BOOL = {"1": True, "true": True, "yes": True, "on": True,
         "0": False, "false": False, "no": False, "off": False}


def _parse_value(text: str) -> Any:
    if text.lower() in _BOOL:
        return _BOOL[text.lower()]
    for conv in (int, float):
        try:
            return conv(text)
        except ValueError:
            pass
    return text


@dataclass(frozen=True)
class SourceSpec:
    """A parsed source spec ``PREFIX[:REST][?key=value&...]``.

    prefix: ``images``, ``camera``, ``sim`` ...; rest: what follows the first ``:`` (a
    folder, a file, a camera index, a scene name; "" if none); options: the query's values
    as bool, int, float or str.
    """

    prefix: str
    rest: str = ""
    options: dict[str, Any] = field(default_factory=dict)


# What REST must look like for each built-in prefix, and the form to suggest.
_REST_RULES: dict[str, tuple[str, str]] = {
    "images": (r".+", "images:DIR"), "video": (r".+", "video:PATH"),
    "camera": (r"\d*", "camera:INDEX"), "replay": (r".+", "replay:FILE"),
    "picamera": (r"", "picamera?width=W&height=H&fps=F"), "sim": (r".*", "sim:SCENE"),
}


def parse_source_spec(spec: str, check: bool = False) -> SourceSpec:
    """The one parser of source specs (``SourceError`` naming the spec when malformed).

    check: also require a known prefix and a REST of the right form (``camera:INDEX``,
    ``images:DIR`` ...): what a configuration file is validated with.
    """
    spec = str(spec)
    base, _, query = spec.partition("?")
    prefix, _, rest = base.partition(":")
    opts: dict[str, Any] = {}
    for part in filter(None, query.split("&")):
        key, eq, value = part.partition("=")
        if not eq or not key:
            raise SourceError(f"{spec}: option {part!r} is not key=value")
        opts[key] = _parse_value(value)
    if check:
        if prefix not in source_prefixes():
            raise SourceError(f"{spec}: unknown source {prefix!r} (known: "
                              f"{', '.join(p + ':' for p in source_prefixes())})")
        rule = _REST_RULES.get(prefix)
        if rule is not None and not re.fullmatch(rule[0], rest):
            raise SourceError(f"{spec}: expected {rule[1]}")
    return SourceSpec(prefix, rest, opts)


def _images(rest: str, **opts: Any) -> FrameSource:
    return ImageFolderSource(rest, **opts)


def _video(rest: str, **opts: Any) -> FrameSource:
    return VideoSource(rest, **opts)


def _camera(rest: str, **opts: Any) -> FrameSource:
    try:
        index = int(rest or "0")
    except ValueError:
        raise SourceError(f"camera:{rest}: INDEX must be an integer (camera:0)") from None
    return CameraSource(index, **opts)


def _picamera(rest: str, **opts: Any) -> FrameSource:
    if rest:
        raise SourceError(f"picamera:{rest}: the Pi camera takes no argument; use options "
                          f"(picamera?width=1640&height=1232&fps=30)")
    return PiCameraSource(**opts)  # it imports picamera2 (the Pi only) when opened


def _sim(rest: str, **opts: Any) -> FrameSource:
    return open_sim(rest, **opts)


def _replay(rest: str, **opts: Any) -> FrameSource:
    return open_replay(rest, **opts)


_BUILTIN: dict[str, SourceFactory] = {"images": _images, "video": _video, "camera": _camera,
                                      "picamera": _picamera, "sim": _sim, "replay": _replay}


def open_source(spec: str, **options: Any) -> FrameSource:
    """Open a frame source from ``PREFIX:REST`` (see the module docstring).

    ``options`` are passed to the source (e.g. ``width``, ``height``, ``fps``, ``gray``) and
    override options given in the spec after ``?``. Raises ``SourceError`` for an unknown
    prefix, bad options, or a source that cannot be opened.
    """
    parsed = parse_source_spec(spec)
    prefix, rest, spec_opts = parsed.prefix, parsed.rest, {**parsed.options, **options}
    factory = _REGISTRY.get(prefix) or _BUILTIN.get(prefix)
    if factory is None:
        raise SourceError(f"{spec}: unknown source {prefix!r} (known: "
                          f"{', '.join(p + ':' for p in source_prefixes())})")
    try:
        return factory(rest, **spec_opts)
    except TypeError as e:
        # An option the source does not take: name it rather than show a traceback.
        m = re.search(r"unexpected keyword argument '(\w+)'", str(e))
        if m:
            raise SourceOptionError(f"{spec}: option {m.group(1)!r} is not supported by "
                                    f"{prefix}:") from None
        raise
