"""Every key is declared once (kmead.config.schema.KEYS); config.toml, the key table of
docs/daemon.md, the live keys and the tracking filter's defaults follow from it."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import fields
from pathlib import Path

import pytest
import tomllib

from kmea.robots.tracking import TrackerConfig
from kmead.config.layers import load_config
from kmead.config.schema import (
    ADVANCED,
    KEYS,
    LIVE_KEYS,
    default_config,
    default_config_text,
    keys_table,
    validate_setting,
)

ROOT = Path(__file__).resolve().parent.parent
FIX = "run `make config` (it writes config.toml and docs/daemon.md from the declarations)"


def test_config_toml_is_the_declarations() -> None:
    assert (ROOT / "config.toml").read_text() == default_config_text(), FIX


def test_the_docs_key_table_is_the_declarations() -> None:
    assert keys_table() in (ROOT / "docs" / "daemon.md").read_text(), FIX


def test_the_documented_text_parses_back_to_the_defaults() -> None:
    """config.toml holds a technician's keys (at most 40) with their defaults; the advanced
    ones are named in it and set only where they differ."""
    shown = tomllib.loads(default_config_text())
    full = default_config()
    expected = {s: ({n: v for n, v in vals.items() if f"{s}.{n}" not in ADVANCED}
                    if isinstance(vals, dict) else vals) for s, vals in full.items()}
    assert shown == expected
    assert sum(len(v) for v in shown.values() if isinstance(v, dict)) <= 40
    text = default_config_text()
    assert all(key.split(".")[1] in text for key in ADVANCED)  # named, out of the tables
    loaded = load_config(None, use_local=False).to_dict()
    assert loaded == {**default_config(), "robots": validate_setting(
        "robots", default_config()["robots"], "test")}


@pytest.mark.parametrize("key", [f"{s}.{n}" for s, keys in KEYS.items() for n in keys])
def test_every_default_passes_its_own_check(key: str) -> None:
    section, _, name = key.partition(".")
    default = KEYS[section][name].default
    assert validate_setting(key, default, "test") == default


def test_every_section_opens_with_a_meaning() -> None:
    # A key without a summary joins the table row above it; without a doc it shares the
    # comment above it: neither can open a section.
    for section, keys in KEYS.items():
        first = next(iter(keys.values()))
        assert first.summary and first.doc, section


def test_the_tracking_filter_defaults_are_the_declared_ones() -> None:
    # The library's TrackerConfig() is what a script gets; the daemon gets the declared
    # defaults. Fields without a key (e.g. min_sigma) are the filter's own constants.
    cfg = TrackerConfig()
    shared = [f.name for f in fields(TrackerConfig) if f.name in KEYS["filter"]]
    assert len(shared) >= 12, shared
    for name in shared:
        assert getattr(cfg, name) == KEYS["filter"][name].default, name


def test_live_keys_are_the_declared_ones() -> None:
    assert "robots" in LIVE_KEYS and "filter.accel_noise" in LIVE_KEYS
    assert "detector.workers" not in LIVE_KEYS and "network.control" not in LIVE_KEYS


def test_kmead_prints_the_documented_default() -> None:
    code = "from kmead.cli import main; raise SystemExit(main(['--default-config']))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, check=True).stdout
    assert out == default_config_text()


@pytest.mark.parametrize("old", ["detector.tracking", "detector.track_full_every"])
def test_a_renamed_key_is_one_line_naming_the_new_one(old: str) -> None:
    from kmead.config.layers import ConfigError
    from kmead.config.schema import RENAMED

    with pytest.raises(ConfigError) as e:
        load_config(None, sets=[f"{old}=true"], use_local=False)
    assert RENAMED[old] in str(e.value) and "\n" not in str(e.value)


def test_a_removed_key_is_one_line_saying_why(tmp_path) -> None:
    from kmead.config.layers import ConfigError

    path = tmp_path / "old.toml"
    path.write_text("[detector]\nfast = true\n")
    with pytest.raises(ConfigError) as e:
        load_config(str(path), use_local=False)
    msg = str(e.value)
    assert "'detector.fast' was removed" in msg and "detector.fixed_camera" in msg
    assert str(path) in msg and "\n" not in msg
