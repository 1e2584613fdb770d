"""kmead configuration: the declared defaults (kmead.config.schema), overlays, ``--set``
and validation.

The effective configuration is a plain nested dict ``{section: {key: value}}`` plus
``"robots"``: a list of robot tables. Every value is checked here, the same way for a file,
``--set`` and a live ``set`` request; a problem raises :class:`ConfigError` with one line
naming the file (or ``--set`` / ``control``), the key and the problem.
"""

from __future__ import annotations

import contextlib
import copy
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from kmea.wire import tomlvalue as toml
from kmea.wire.tomlvalue import parse_toml_value
from kmead.config.checks import ConfigError, parse_destination
from kmead.config.schema import LIVE_KEYS, SCHEMA, default_config, is_live, validate_setting

__all__ = [
    "LIVE_KEYS",
    "Config",
    "ConfigError",
    "is_live",
    "load_config",
    "parse_destination",
    "parse_set",
    "validate_setting",
]


def _merge(base: dict, doc: dict, where: str) -> None:
    """Overlay a parsed TOML document on ``base`` in place, validating every key."""
    for section, table in doc.items():
        if section == "robots":
            base["robots"] = validate_setting("robots", table, where)
            continue
        if section not in SCHEMA:
            raise ConfigError(f"{where}: unknown section [{section}] "
                              f"(sections: {', '.join([*SCHEMA, 'robots'])})")
        if not isinstance(table, dict):
            raise ConfigError(f"{where}: {section} must be a table [{section}]")
        for key, value in table.items():
            base.setdefault(section, {})[key] = validate_setting(f"{section}.{key}", value, where)


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
        return toml.loads(text)
    except (toml.TOMLDecodeError, toml.TooDeep) as e:
        raise ConfigError(f"{path}: invalid TOML: {e}") from None


def parse_set(item: str) -> tuple[str, Any]:
    """``"SECTION.KEY=VALUE"`` -> (key, value); VALUE as
    :func:`kmea.wire.tomlvalue.parse_toml_value`
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
        # Cut: the value can be kilobytes (a 700-deep array), the line is one line to read.
        shown = repr(raw) if len(raw) <= 80 else repr(raw[:60]) + f" ... ({len(raw)} characters)"
        raise ConfigError(f"--set {key}: value {shown} is not valid TOML")
    return key, value


@dataclass
class Config:
    """The effective configuration and where it came from.

    data: {section: {key: value}, "robots": [robot tables]}.
    files: configuration files read, in order (the packaged default first).
    base: the configuration from the files alone (no overlay, no command line): what
        ``save_config`` diffs against.
    run_only: ``section.key`` -> the configured value, for keys this run uses another value
        of (``--free-ports``): ``save_config`` writes the configured one, never the run's.
    """

    data: dict
    files: list[str] = field(default_factory=list)
    user_file: str | None = None
    base: dict = field(default_factory=dict)
    run_only: dict[str, Any] = field(default_factory=dict)

    def __getitem__(self, section: str) -> Any:
        return self.data[section]

    def get(self, key: str) -> Any:
        """The value of ``section.key`` or ``robots``; ConfigError for an unknown key."""
        if key == "robots":
            return self.data["robots"]
        section, _, name = key.partition(".") if isinstance(key, str) else ("", "", "")
        try:
            return self.data[section][name]
        except (KeyError, TypeError):
            validate_setting(key, None, "control")  # raises the one-line unknown-key error
            raise ConfigError(f"control: key {key!r} is not set") from None

    def set(self, key: str, value: Any, where: str = "control", remote: bool = False) -> Any:
        """Validate and apply one key; returns the stored value. ``remote``: the value came
        over the network (see kmead.config.schema)."""
        v = validate_setting(key, value, where, remote)
        if key == "robots":
            self.data["robots"] = v
        else:
            section, _, name = key.partition(".")
            self.data[section][name] = v
        return v

    def set_for_run(self, key: str, value: Any, where: str) -> Any:
        """Like :meth:`set`, for this run only: a save keeps the value configured before."""
        configured = self.get(key)
        v = self.set(key, value, where)
        self.run_only.setdefault(key, configured)
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
    _merge(data, default_config(), "<default config>")
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
    log_ = cfg["log"]
    if log_["csv"] and log_["record"]:
        from kmead.config.checks import same_file

        if same_file(log_["csv"], log_["record"]):
            raise ConfigError(f"log.csv and log.record: both are {log_['csv']!r}; a log and a "
                              "recording in one file would corrupt both")
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
            value = cfg.run_only.get(f"{section}.{key}", value)
            if cfg.base.get(section, {}).get(key) != value:
                doc.setdefault(section, {})[key] = value
    return doc


def save_overlay(cfg: Config, path: str | Path | None = None,
                 doc: dict | None = None) -> tuple[Path, dict]:
    """Write the changed keys (``doc``, default :func:`overlay_doc`) to an overlay TOML file
    (never touches the user's file). Written to ``PATH.tmp`` then renamed: a failure leaves
    the old overlay and no temporary file."""
    import os
    import time

    import tomli_w

    p = Path(path) if path else cfg.overlay_path
    doc = overlay_doc(cfg) if doc is None else doc
    head = (f"# Written by kmead save_config at {time.strftime('%Y-%m-%d %H:%M:%S')}.\n"
            f"# Settings changed at run time; they overlay {cfg.user_file or 'the default config'}"
            ".\n# Delete this file to go back to that configuration.\n")
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(p.name + ".tmp")
    try:
        tmp.write_text(head + tomli_w.dumps(doc))
        os.replace(tmp, p)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    return p, doc
