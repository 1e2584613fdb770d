"""Every configuration key, declared once: its default, its check (type, range, unit),
whether a running daemon may change it, and what it means. The declarations are the
tables of :mod:`kmead.config.keys_camera` and :mod:`kmead.config.keys_service`; this module
gathers them (:data:`KEYS`) and is what the rest of kmead imports.

Everything else is derived from :data:`KEYS`: the checks of configuration files, ``--set``
and live ``set`` requests (:func:`validate_setting`), the live keys (:data:`LIVE_KEYS`),
the documented default configuration (:func:`default_config_text`: the repository's
``config.toml`` and ``kmead --default-config``) and the key table of docs/daemon.md
(:func:`keys_table`). tests/test_settings_schema.py fails when either file disagrees; after
changing a key, ``make config`` writes both.
"""

from __future__ import annotations

import copy
import json
import math
from typing import Any

from kmead.config.checks import Check, ConfigError, Key, shown, validate_robots
from kmead.config.keys_camera import CAMERA_KEYS
from kmead.config.keys_service import (
    DEFAULT_ROBOTS,
    ROBOTS_DOC,
    ROBOTS_SUMMARY,
    SERVICE_KEYS,
)

__all__ = [
    "ADVANCED",
    "KEYS",
    "LIVE_KEYS",
    "SCHEMA",
    "Key",
    "default_config",
    "default_config_text",
    "is_live",
    "keys_table",
    "validate_setting",
]

HEADER = """\
kmead configuration: the documented default. Every key is here with its default value;
a trailing comment gives its range and unit, and "live" when the terminal UI (or any
control client) can change it while kmead runs (the others need a restart).
This file is generated from kmead/config/schema.py (`kmead --default-config` prints it).

kmead always starts from these defaults, then overlays, in order:
  --config FILE           only the keys FILE sets ([[robots]] in FILE replaces the whole list)
  FILE.local.toml         if it exists: what `save_config` (terminal UI, Configuration tab) wrote
  --source/--camera/--map/--algorithm/--log/--record and --set SECTION.KEY=VALUE
Unknown keys and bad values are errors: kmead names the file, the key and the problem
and does not start (exit code 2).
Units: metres, seconds, radians (degrees never appear in this file)."""

# The key table, section by section in config.toml's order: a camera's frames
# (kmead.config.keys_camera), then what every service has (kmead.config.keys_service).
KEYS: dict[str, dict[str, Key]] = {**CAMERA_KEYS, **SERVICE_KEYS}

ADVANCED: frozenset[str] = frozenset({
    "detector.corner_refinement", "detector.parameters", "detector.workers",
    "detector.fixed_camera",
    "detector.fixed_full_every", "detector.fixed_refit_every",
    "estimator.unknown_plane",
    "filter.reset_after_s", "filter.model", "filter.accel_noise", "filter.turn_noise",
    "filter.gate_probability", "filter.reacquire_n", "filter.manoeuvre_scale",
    "filter.manoeuvre_time_s", "filter.cruise_time_s", "filter.step_k",
    "filter.outlier_probability", "filter.outlier_radius",
    "stats.loo", "stats.window", "stats.displaced_frames",
    "relay.stale_repeat_s", "relay.max_sigma_m", "relay.max_time_step_s",
    "fusion.max_age_s", "fusion.max_future_s", "fusion.clock_warn_s", "fusion.max_clock_offset_s",
    "fusion.max_sigma_m", "fusion.margin_m",
    "network.status_period_s",
    "log.part_mb", "log.part_min", "log.min_free_mb", "log.snapshots_max",
    "log.snapshots_max_mb",
    "foxglove.host", "foxglove.image_hz",
    "zenoh.mode", "zenoh.multicast", "zenoh.camera", "zenoh.lease_s", "zenoh.ros_namespace",
    "zenoh.frame_id", "zenoh.dds_bridge", "zenoh.robot_pose", "zenoh.insecure",
})

# Keys that changed their name: a file or request that uses the old one is told the new.
# ("track" names the robots' tracking filter only; the fixed camera's keys say so.)
RENAMED = {"log.record_part_mb": "log.part_mb", "log.record_part_min": "log.part_min",
           "detector.tracking": "detector.fixed_camera",
           "detector.track_full_every": "detector.fixed_full_every",
           "detector.track_refit_every": "detector.fixed_refit_every"}
# Keys that are gone: a file or request that uses one is told why, in one line.
_FIXED = "the fixed camera's tracking (detector.fixed_camera) does its work, faster"
REMOVED = {"detector.fast": _FIXED, "detector.fast_window": _FIXED,
           "detector.full_every": _FIXED}

# ---------------------------------------------------------------------------- derived

SCHEMA: dict[str, dict[str, Check]] = {
    section: {name: key.check for name, key in keys.items()} for section, keys in KEYS.items()}
LIVE_KEYS: frozenset[str] = frozenset(
    {"robots"} | {f"{s}.{n}" for s, keys in KEYS.items() for n, k in keys.items() if k.live})


def is_live(key: object) -> bool:
    """True when a live ``set`` request may change ``key``."""
    return isinstance(key, str) and key in LIVE_KEYS


def validate_setting(key: Any, value: Any, where: str, remote: bool = False) -> Any:
    """Check one ``section.key`` (or ``robots``); returns the normalised value.

    ``remote``: the value came over the network (stricter where a value names a file).
    Raises :class:`ConfigError` only.
    """
    if not isinstance(key, str) or len(key) > 64:
        raise ConfigError(f"{where}: key must be a short string SECTION.KEY, got {shown(key)}")
    if key == "robots":
        return validate_robots(value, f"{where}: robots", remote)
    section, _, name = key.partition(".")
    if section not in SCHEMA:
        raise ConfigError(f"{where}: unknown section {shown(section)} in key {shown(key)} "
                          f"(sections: {', '.join([*SCHEMA, 'robots'])})")
    if not name or "." in name:
        raise ConfigError(f"{where}: key {shown(key)} must be SECTION.KEY")
    if name not in SCHEMA[section]:
        if key in RENAMED:
            raise ConfigError(f"{where}: key {key!r} is now {RENAMED[key]!r} (same meaning)")
        if key in REMOVED:
            raise ConfigError(f"{where}: key {key!r} was removed ({REMOVED[key]}): delete it")
        raise ConfigError(f"{where}: unknown key {shown(key)} (known in [{section}]: "
                          f"{', '.join(SCHEMA[section])})")
    try:
        return SCHEMA[section][name](value, f"{where}: key {key!r}", remote)
    except ConfigError:
        raise
    except (ValueError, TypeError, OverflowError, RecursionError) as e:
        # A check is written not to raise anything else; if one does, it is still one line.
        raise ConfigError(f"{where}: key {key!r}: {type(e).__name__}: {e}") from None


def default_config() -> dict[str, Any]:
    """``{section: {key: default}, "robots": [robot tables]}``, fresh copies."""
    out: dict[str, Any] = {s: {n: copy.deepcopy(k.default) for n, k in keys.items()}
                           for s, keys in KEYS.items()}
    out["robots"] = copy.deepcopy(DEFAULT_ROBOTS)
    return out


def toml_value(v: Any) -> str:
    """``v`` (a default: bool, int, float, str, list, empty table) as TOML text."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) and ("." in repr(v) or "e" in repr(v)) else f"{v}.0"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, str):
        return json.dumps(v)  # a JSON string of printable text is a TOML basic string
    if isinstance(v, list):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} = {toml_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(f"no TOML text for {type(v).__name__}")


def _comment(text: str) -> list[str]:
    return [f"# {line}".rstrip() for line in text.splitlines()]


def _trailer(key: Key) -> str:
    parts = [t for t in (getattr(key.check, "text", ""), "live" if key.live else "") if t]
    return f"  # {', '.join(parts)}" if parts else ""


def default_config_text() -> str:
    """The documented default configuration (config.toml): every key a technician sets
    (not :data:`ADVANCED`) with its default, the comment that explains it, and its range,
    unit and whether it is live; each section names its advanced keys in one line."""
    out = _comment(HEADER)
    for section, keys in KEYS.items():
        out += ["", f"[{section}]"]
        for name, key in keys.items():
            if f"{section}.{name}" in ADVANCED:
                continue
            doc = key.doc
            if not doc:  # the comment above an earlier key covers it: unless that one is out
                above = [(n, k) for n, k in list(keys.items())[:list(keys).index(name)] if k.doc]
                if above and f"{section}.{above[-1][0]}" in ADVANCED:
                    doc = above[-1][1].doc
            out += _comment(doc)
            out.append(f"{name} = {toml_value(key.default)}{_trailer(key)}")
        advanced = [n for n in keys if f"{section}.{n}" in ADVANCED]
        if advanced:
            out += _comment(f"Advanced (docs/daemon.md, Advanced keys; --set or this file): "
                            f"{', '.join(advanced)}")
    out += ["", *_comment(ROBOTS_DOC)]
    for robot in DEFAULT_ROBOTS:
        out += ["[[robots]]"] + [f"{k} = {toml_value(v)}" for k, v in robot.items()] + [""]
    return "\n".join(out[:-1]) + "\n"


def keys_table() -> str:
    """The key tables of docs/daemon.md (markdown): key, default, meaning, a technician's
    keys first, then :data:`ADVANCED`; a key without a summary joins the row above it."""
    return (_table(advanced=False) + "\n#### Advanced keys\n\nTuning internals and "
            "plumbing, out of the generated `config.toml` and the terminal UI's form; set "
            "them with `--set`, a configuration file or a control `set` (the live ones).\n\n"
            + _table(advanced=True))


def _table(advanced: bool) -> str:
    rows: list[tuple[list[str], list[str], str]] = []
    for section, keys in KEYS.items():
        for name, key in keys.items():
            if (f"{section}.{name}" in ADVANCED) != advanced:
                continue
            cell = f"`{toml_value(key.default)}`"
            if not key.summary and rows:
                rows[-1][0].append(f"`{section}.{name}`")
                rows[-1][1].append(cell)
            else:
                rows.append(([f"`{section}.{name}`"], [cell], key.summary))
    lines = ["| key | default | meaning |", "|-----|---------|---------|"]
    for names, defaults, summary in rows:
        # one default for a row whose keys share it
        shown_default = defaults[0] if len(set(defaults)) == 1 else ", ".join(defaults)
        lines.append(f"| {', '.join(names)} | {shown_default} | {summary} |")
    if not advanced:
        names = ", ".join(DEFAULT_ROBOTS[i]["name"] for i in range(len(DEFAULT_ROBOTS)))
        lines.append(f"| `[[robots]]` | {names} | {ROBOTS_SUMMARY} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    """Write config.toml and the key table of docs/daemon.md from :data:`KEYS` (``make
    config``, from the repository's root)."""
    from pathlib import Path

    Path("config.toml").write_text(default_config_text())
    doc = Path("docs/daemon.md")
    text = doc.read_text()
    start = text.index("| key | default | meaning |")
    last = start  # the tables end with the advanced keys' (keys_table writes both)
    while (nxt := text.find("| key | default | meaning |", last + 1)) != -1:
        last = nxt
    end = text.index("\n\n", last) + 1
    doc.write_text(text[:start] + keys_table() + text[end:])


if __name__ == "__main__":
    main()
