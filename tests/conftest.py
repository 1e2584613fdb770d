"""Shared fixtures. ``../shared`` holds real data; tests that need it skip when it is absent."""

from __future__ import annotations

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SHARED = ROOT.parent / "shared"


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    """``../shared/data``; skips the test with a reason when it is absent."""
    d = SHARED / "data"
    if not d.is_dir():
        pytest.skip(f"shared data not found at {d} (clone next to ../shared to run this test)")
    return d


@pytest.fixture(autouse=True)
def _own_config_home(tmp_path_factory, monkeypatch) -> None:
    """A plain kmead start reads the per-user overlay ($XDG_CONFIG_HOME/kmead/...): every
    test gets an empty config home, so a developer's saved settings never leak in."""
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path_factory.mktemp("config-home")))
