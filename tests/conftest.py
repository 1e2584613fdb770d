"""Shared fixtures. ``../shared`` holds real data; tests that need it skip when it is absent."""

from __future__ import annotations

import logging
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


@pytest.fixture(scope="session")
def default_frames():
    """24 rendered frames of ``sim:default`` at 820x616 and their source (the fixed-camera
    tests: tests/fixed_camera_helpers.py)."""
    from fixed_camera_helpers import frames_of

    return frames_of("sim:default", 24)


@pytest.fixture(scope="session")
def pi_frames():
    """14 rendered frames of ``sim:default`` at the Pi's 1640x1232 and their source."""
    from fixed_camera_helpers import frames_of

    return frames_of("sim:default", 14, width=1640)


@pytest.fixture(autouse=True)
def _own_config_home(tmp_path_factory, monkeypatch) -> None:
    """A plain kmead start reads the per-user overlay ($XDG_CONFIG_HOME/kmead/...): every
    test gets an empty config home, so a developer's saved settings never leak in."""
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path_factory.mktemp("config-home")))


@pytest.fixture(autouse=True)
def _own_runtime_dir(tmp_path_factory, monkeypatch) -> None:
    """Daemons announce their endpoints in $XDG_RUNTIME_DIR/kmea: every test gets its own,
    so a UI started by one test never finds a daemon another test (or worker) started."""
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path_factory.mktemp("runtime")))


@pytest.fixture(autouse=True)
def _no_kmead_logging_leak():
    """Every test leaves the ``kmead`` logger's handlers as it found them. One left behind
    (kmead's stderr log after an in-process ``main()``, a daemon never closed) keeps
    writing: its lines then appear in pytest's progress output, from whichever test runs
    next. The level a daemon sets (``log.level``) prints nothing by itself: it is only
    put back."""
    log = logging.getLogger("kmead")
    before = (list(log.handlers), log.propagate)
    level = log.level
    yield
    after = (list(log.handlers), log.propagate)
    log.handlers[:] = before[0]
    log.propagate = before[1]
    log.setLevel(level)
    assert after == before, f"the test left the 'kmead' logger changed: {before} -> {after}"
