"""Put the fake Pi camera stack (tests/fake_picamera2) first on sys.path for one test.

Use as::

    @pytest.fixture
    def rig(monkeypatch):
        yield fakepi.install(monkeypatch)
        fakepi.forget()
"""

from __future__ import annotations

import sys
from pathlib import Path
from types import ModuleType

import pytest

FAKE_DIR = Path(__file__).parent / "fake_picamera2"
FAKE_MODULES = ("picamera2", "libcamera", "simplejpeg", "fakecam_rig")


def forget() -> None:
    """Drop the fake modules from sys.modules (the next import runs their code again)."""
    for name in list(sys.modules):
        if name.split(".")[0] in FAKE_MODULES:
            del sys.modules[name]


def install(monkeypatch: pytest.MonkeyPatch) -> ModuleType:
    """The rig module (``fakecam_rig``), reset; ``import picamera2`` now runs the fakes.

    Modules are forgotten first, so an import failure set on the rig happens at import, as
    on a Pi. The sys.path entry goes with ``monkeypatch``; call :func:`forget` after."""
    forget()
    monkeypatch.syspath_prepend(str(FAKE_DIR))
    import fakecam_rig

    fakecam_rig.reset()
    return fakecam_rig
