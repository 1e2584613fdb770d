"""kmead configuration: the packaged default, overlays, ``--set`` and validation.

The effective configuration is a plain nested dict ``{section: {key: value}}`` plus
``"robots"``: a list of robot tables. Every value is checked here, the same way for a file,
``--set`` and a live ``set`` request; a problem raises :class:`ConfigError` with one line
naming the file (or ``--set`` / ``control``), the key and the problem.
"""

from __future__ import annotations

import copy
import math
import os
import re
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

from kmea.robots import robot_from_table
from kmea.tomlvalue import parse_toml_value

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

__all__ = [
    "LIVE_KEYS",
    "Config",
    "ConfigError",
    "default_text",
    "is_live",
    "load_config",
    "parse_set",
    "validate_value",
]


class ConfigError(ValueError):
    """A bad configuration file or value; the message is one line naming file and key."""


Check = Callable[[Any, str], Any]


def _str(v: Any, where: str) -> str:
    if not isinstance(v, str):
        raise ConfigError(f"{where}: expected a string, got {v!r}")
    return v


def _bool(v: Any, where: str) -> bool:
    if not isinstance(v, bool):
        raise ConfigError(f"{where}: expected true or false, got {v!r}")
    return v


def _number(v: Any, where: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ConfigError(f"{where}: expected a number, got {v!r}")
    if not math.isfinite(v):
        raise ConfigError(f"{where}: expected a finite number, got {v!r}")
    return float(v)


def _positive(v: Any, where: str) -> float:
    x = _number(v, where)
    if x <= 0:
        raise ConfigError(f"{where}: must be > 0, got {v!r}")
    return x


def _nonneg(v: Any, where: str) -> float:
    x = _number(v, where)
    if x < 0:
        raise ConfigError(f"{where}: must be >= 0, got {v!r}")
    return x


def _int_ge(lo: int) -> Check:
    def check(v: Any, where: str) -> int:
        if isinstance(v, bool) or not isinstance(v, int):
            raise ConfigError(f"{where}: expected an integer, got {v!r}")
        if v < lo:
            raise ConfigError(f"{where}: must be >= {lo}, got {v}")
        return v
    return check


def _port(v: Any, where: str) -> int:
    p = _int_ge(0)(v, where)
    if p > 65535:
        raise ConfigError(f"{where}: a TCP port is 0 (any free port) to 65535, got {p}")
    return p


def _alpha(v: Any, where: str) -> float:
    x = _number(v, where)
    if not 0 < x <= 1:
        raise ConfigError(f"{where}: must be in (0, 1] (1 = no filtering), got {v!r}")
    return x


def _choice(*options: str) -> Check:
    def check(v: Any, where: str) -> str:
        if v not in options:
            raise ConfigError(f"{where}: must be one of {', '.join(options)}; got {v!r}")
        return v
    return check


def _source_spec(v: Any, where: str) -> str:
    from kmea.vision.sources import SourceError, parse_source_spec

    s = _str(v, where)
    try:
        parse_source_spec(s, check=True)
    except SourceError as e:
        raise ConfigError(f"{where}: {e}; use sim, sim:SCENE, picamera, camera:INDEX, "
                          "video:PATH, images:DIR or replay:FILE") from None
    return s


def _algorithm(v: Any, where: str) -> str:
    s = _str(v, where)
    from kmea import estimators

    if s not in estimators.available():
        raise ConfigError(f"{where}: unknown algorithm {s!r}; choose one of "
                          f"{', '.join(estimators.available())}")
    return s


def _dictionary(v: Any, where: str) -> str:
    s = _str(v, where)
    if s == "":
        return s
    try:
        from kmea.vision.dictionary import get_dictionary

        get_dictionary(s)
    except ImportError:  # pragma: no cover - vision module missing
        pass
    except ValueError as e:
        raise ConfigError(f"{where}: {e}") from None
    return s


def _probability(v: Any, where: str) -> float:
    x = _number(v, where)
    if not 0 < x < 1:
        raise ConfigError(f"{where}: must be in (0, 1), got {v!r}")
    return x


def _endpoints(v: Any, where: str) -> list[str]:
    if not isinstance(v, list):
        raise ConfigError(f"{where}: expected a list of ZeroMQ endpoints")
    return [_endpoint(e, f"{where}[{i}]") for i, e in enumerate(v)]


def _endpoint(v: Any, where: str) -> str:
    s = _str(v, where)
    if s and not re.match(r"^(tcp://[^:/]+:(\d+|\*)|ipc://.+|inproc://.+)$", s):
        raise ConfigError(f"{where}: expected a ZeroMQ endpoint like tcp://127.0.0.1:5555 "
                          f"(or \"\" for off), got {s!r}")
    return s


def _detector_parameters(v: Any, where: str) -> dict:
    if not isinstance(v, dict):
        raise ConfigError(f"{where}: expected a table of OpenCV DetectorParameters names")
    try:
        from kmea.vision.detection import DetectorConfig

        DetectorConfig(parameters=dict(v)).detector_parameters()
    except ImportError:  # pragma: no cover - vision module missing
        pass
    except ValueError as e:
        raise ConfigError(f"{where}: {e}") from None
    return dict(v)


SCHEMA: dict[str, dict[str, Check]] = {
    "source": {"spec": _source_spec, "fps": _nonneg, "width": _int_ge(0), "height": _int_ge(0)},
    "camera": {"file": _str},
    "map": {"file": _str},
    "detector": {"dictionary": _dictionary, "marker_length": _positive,
                 "corner_refinement": _choice("subpix", "none", "contour", "apriltag"),
                 "parameters": _detector_parameters, "workers": _int_ge(0),
                 "fast": _bool, "fast_window": _int_ge(0), "full_every": _int_ge(1)},
    "estimator": {"algorithm": _algorithm},
    "filter": {"alpha": _alpha, "reset_after_s": _positive, "kind": _choice("iir", "kalman"),
               "model": _choice("cv", "ctrv"), "accel_noise": _positive,
               "turn_noise": _positive, "gate_probability": _probability,
               "reacquire_n": _int_ge(1), "predict": _bool},
    "stats": {"loo": _bool, "window": _int_ge(1), "displaced_threshold": _positive,
              "displaced_frames": _int_ge(1)},
    "relay": {"stale_after_s": _positive, "stale_repeat_s": _nonneg, "extra_fields": _bool},
    "fusion": {"inputs": _endpoints, "max_age_s": _positive},
    "network": {"telemetry": _endpoint, "control": _endpoint, "status_period_s": _positive},
    "log": {"csv": _str, "record": _str,
            "level": _choice("debug", "info", "warning", "error")},
    "foxglove": {"enabled": _bool, "host": _str, "port": _port, "image_hz": _nonneg},
}

ROBOT_KEYS = ("name", "markers", "height", "length", "separation", "destinations")

# Keys a live ``set`` request may change (the rest need a restart).
LIVE_KEYS = {
    "estimator.algorithm", "filter.alpha", "filter.reset_after_s", "robots",
    "filter.kind", "filter.model", "filter.accel_noise", "filter.turn_noise",
    "filter.gate_probability", "filter.reacquire_n", "filter.predict",
    "relay.stale_after_s", "relay.stale_repeat_s", "relay.extra_fields", "stats.window",
    "stats.loo", "stats.displaced_threshold", "stats.displaced_frames", "log.level",
}
LIVE_SECTIONS = {"detector"}
# Keys of a live section that still need a restart (the detection threads start once).
RESTART_KEYS = {"detector.workers"}


def is_live(key: str) -> bool:
    """True when a live ``set`` request may change ``key``."""
    return key not in RESTART_KEYS and (key in LIVE_KEYS
                                        or key.partition(".")[0] in LIVE_SECTIONS)

_UDP_RE = re.compile(r"^udp:([^:]+):(\d{1,5})$")


def parse_destination(d: str, where: str) -> tuple[str, int]:
    """``"udp:HOST:PORT"`` -> (host, port)."""
    m = _UDP_RE.match(d) if isinstance(d, str) else None
    if not m or not 0 < int(m.group(2)) < 65536:
        raise ConfigError(f"{where}: destination must be \"udp:HOST:PORT\", got {d!r}")
    return m.group(1), int(m.group(2))


def _robot(row: Any, where: str) -> dict:
    if not isinstance(row, dict):
        raise ConfigError(f"{where}: expected a table with {', '.join(ROBOT_KEYS)}")
    bad = sorted(set(row) - set(ROBOT_KEYS))
    if bad:
        raise ConfigError(f"{where}: unknown key {bad[0]!r} (robot keys: {', '.join(ROBOT_KEYS)})")
    try:
        spec = robot_from_table(row, where)  # kmea.robots: the one robot validation
    except ValueError as e:
        raise ConfigError(str(e)) from None
    dests = row.get("destinations", [])
    if not isinstance(dests, list):
        raise ConfigError(f"{where}.destinations: expected a list like [\"udp:127.0.0.1:9001\"]")
    for i, d in enumerate(dests):
        parse_destination(d, f"{where}.destinations[{i}]")
    return {"name": spec.name, "markers": list(spec.markers), "height": spec.height,
            "length": spec.length, "separation": spec.separation, "destinations": list(dests)}


def _robots(rows: Any, where: str) -> list[dict]:
    if not isinstance(rows, list):
        raise ConfigError(f"{where}: expected an array of tables [[robots]]")
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


def validate_value(key: str, value: Any, where: str) -> Any:
    """Check one ``section.key`` (or ``robots``); returns the normalised value."""
    if key == "robots":
        return _robots(value, f"{where}: robots")
    section, _, name = key.partition(".")
    if section not in SCHEMA:
        raise ConfigError(f"{where}: unknown section {section!r} in key {key!r} "
                          f"(sections: {', '.join([*SCHEMA, 'robots'])})")
    if not name or "." in name:
        raise ConfigError(f"{where}: key {key!r} must be SECTION.KEY")
    if name not in SCHEMA[section]:
        raise ConfigError(f"{where}: unknown key {key!r} (known in [{section}]: "
                          f"{', '.join(SCHEMA[section])})")
    return SCHEMA[section][name](value, f"{where}: key {key!r}")


def _merge(base: dict, doc: dict, where: str) -> None:
    """Overlay a parsed TOML document on ``base`` in place, validating every key."""
    for section, table in doc.items():
        if section == "robots":
            base["robots"] = validate_value("robots", table, where)
            continue
        if section not in SCHEMA:
            raise ConfigError(f"{where}: unknown section [{section}] "
                              f"(sections: {', '.join([*SCHEMA, 'robots'])})")
        if not isinstance(table, dict):
            raise ConfigError(f"{where}: {section} must be a table [{section}]")
        for key, value in table.items():
            base.setdefault(section, {})[key] = validate_value(f"{section}.{key}", value, where)


def default_text() -> str:
    """The packaged default configuration (identical to the repository's config.toml)."""
    return (resources.files("kmead") / "default_config.toml").read_text()


def _read_toml(path: Path) -> dict:
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such file") from None
    except OSError as e:
        raise ConfigError(f"{path}: cannot read: {e.strerror or e}") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not a text file") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{path}: invalid TOML: {e}") from None


def parse_set(item: str) -> tuple[str, Any]:
    """``"SECTION.KEY=VALUE"`` -> (key, value); VALUE as :func:`kmea.tomlvalue.parse_toml_value`
    reads it (TOML, or a bare string), but a value that starts like a TOML array, table or
    string and is not valid TOML is an error rather than a string.
    """
    key, sep, raw = item.partition("=")
    key = key.strip()
    if not sep or not key:
        raise ConfigError(f"--set {item!r}: expected SECTION.KEY=VALUE")
    raw = raw.strip()
    value = parse_toml_value(raw)
    if value == raw and isinstance(value, str) and raw.startswith(("[", "{", '"', "'")):
        raise ConfigError(f"--set {key}: value {raw!r} is not valid TOML")
    return key, value


@dataclass
class Config:
    """The effective configuration and where it came from.

    data: {section: {key: value}, "robots": [robot tables]}.
    files: configuration files read, in order (the packaged default first).
    base: the configuration from the files alone (no overlay, no command line): what
        ``save_config`` diffs against.
    """

    data: dict
    files: list[str] = field(default_factory=list)
    user_file: str | None = None
    base: dict = field(default_factory=dict)

    def __getitem__(self, section: str) -> Any:
        return self.data[section]

    def get(self, key: str) -> Any:
        if key == "robots":
            return self.data["robots"]
        section, _, name = key.partition(".")
        return self.data[section][name]

    def set(self, key: str, value: Any, where: str = "control") -> Any:
        """Validate and apply one key; returns the stored value."""
        v = validate_value(key, value, where)
        if key == "robots":
            self.data["robots"] = v
        else:
            section, _, name = key.partition(".")
            self.data[section][name] = v
        return v

    def to_dict(self) -> dict:
        return copy.deepcopy(self.data)

    @property
    def overlay_path(self) -> Path:
        """Where ``save_config`` writes by default (see docs/daemon.md)."""
        if self.user_file:
            p = Path(self.user_file)
            return p.with_name(p.name.removesuffix(".toml") + ".local.toml")
        return default_overlay_path()


def default_overlay_path() -> Path:
    """The overlay of a plain start (no --config): ``$XDG_CONFIG_HOME/kmead/kmead.local.toml``
    (``~/.config/kmead/...``), the working directory's ``kmead.local.toml`` without a home."""
    base = os.environ.get("XDG_CONFIG_HOME", "")
    if not base:
        try:
            base = str(Path.home() / ".config")
        except RuntimeError:  # no home directory (a bare service account)
            return Path("kmead.local.toml").resolve()
    return Path(base) / "kmead" / "kmead.local.toml"


# The kmead option that sets a key (errors name what the user typed).
OPTION_OF = {"source.spec": "--source", "camera.file": "--camera", "map.file": "--map",
             "estimator.algorithm": "--algorithm", "log.csv": "--log", "log.record": "--record"}


def load_config(path: str | None = None, sets: list[str] | None = None,
                overrides: dict[str, Any] | None = None, use_local: bool = True) -> Config:
    """Default config, overlaid by ``path``, ``path.local.toml``, ``overrides`` then ``sets``.

    overrides: key -> value from the dedicated command-line options (``--source`` ...).
    Raises :class:`ConfigError` with one line naming the file or option, the key and problem.
    """
    data: dict = {}
    _merge(data, tomllib.loads(default_text()), "<default config>")
    files = ["<default config>"]
    if path is not None:
        p = Path(path)
        _merge(data, _read_toml(p), str(p))
        files.append(str(p))
    cfg = Config(data=data, files=files, user_file=str(Path(path).resolve()) if path else None)
    cfg.base = copy.deepcopy(data)
    # FILE.local.toml next to --config FILE; without --config, the per-user overlay (what
    # the UI's Save wrote during an earlier plain start).
    if use_local and cfg.overlay_path.exists():
        _merge(data, _read_toml(cfg.overlay_path), str(cfg.overlay_path))
        files.append(str(cfg.overlay_path))
    for key, value in (overrides or {}).items():
        cfg.set(key, value, where=OPTION_OF.get(key, f"--{key.split('.')[-1]}"))
    for item in sets or []:
        key, value = parse_set(item)
        cfg.set(key, value, where="--set")
    return cfg


def overlay_doc(cfg: Config) -> dict:
    """The keys of ``cfg`` that differ from its files: what ``save_config`` writes."""
    doc: dict = {}
    for section, table in cfg.data.items():
        if section == "robots":
            if table != cfg.base.get("robots"):
                doc["robots"] = table
            continue
        for key, value in table.items():
            if cfg.base.get(section, {}).get(key) != value:
                doc.setdefault(section, {})[key] = value
    return doc


def save_overlay(cfg: Config, path: str | Path | None = None) -> tuple[Path, dict]:
    """Write the changed keys to an overlay TOML file (never touches the user's file)."""
    import time

    import tomli_w

    p = Path(path) if path else cfg.overlay_path
    doc = overlay_doc(cfg)
    head = (f"# Written by kmead save_config at {time.strftime('%Y-%m-%d %H:%M:%S')}.\n"
            f"# Settings changed at run time; they overlay {cfg.user_file or 'the default config'}"
            ".\n# Delete this file to go back to that configuration.\n")
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(p.name + ".tmp")
    tmp.write_text(head + tomli_w.dumps(doc))
    tmp.replace(p)
    return p, doc
