"""The README's commands on a machine without Python 3.11 or without the venv module (issue 31).

These run the real Makefile recipes. The suite's own venv stands in for .venv (``STAMP=``
skips the install step), so each case takes a few seconds and changes nothing in the tree.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
NO_PY = "no-such-python3.11"
SKIP_LINE = f"*** make: Bookworm stack SKIPPED: {NO_PY} not found"

pytestmark = pytest.mark.skipif(shutil.which("make") is None, reason="needs GNU make")


def _make(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    # Under `make test` the outer make's command-line variables and REQUIRE_BOOKWORM reach
    # this process through the environment; the inner make must not inherit them.
    inherited = {"MAKEFLAGS", "MFLAGS", "MAKELEVEL", "MAKEOVERRIDES", "REQUIRE_BOOKWORM", "ARGS",
                 "REQUIRE_ARM64", "SKIP_ARM64"}
    clean = {k: v for k, v in os.environ.items() if k not in inherited}
    clean.update(env or {})
    return subprocess.run(
        ["make", "--no-print-directory", "-C", str(ROOT), *args],
        env=clean, capture_output=True, text=True, timeout=300,
    )


def _here() -> list[str]:
    """Run lint and the suite with the interpreter running these tests, without installing
    (and without pyright: `make test` itself runs it, a minute of CPU; nor the arm64 run,
    minutes of emulation: its own tests are below)."""
    return ["STAMP=", f"BIN={Path(sys.executable).parent}", f"PY_BOOKWORM={NO_PY}", "PYRIGHT=",
            "SKIP_ARM64=1"]


def test_make_test_without_python311_runs_current_stack_and_says_bookworm_was_skipped() -> None:
    r = _make("test", *_here(), "ARGS=-n 0 -p no:cacheprovider tests/test_jsonsafe.py")
    out = r.stdout + r.stderr
    assert r.returncode == 0, out
    assert "All checks passed" in out  # ruff ran
    assert "== suite on Python" in out and " passed" in out  # the suite ran on today's stack
    lines = [ln for ln in r.stdout.splitlines() if ln.strip()]
    # the skip lines come last, after the suite: the Bookworm stack's, then arm64's
    assert lines[-2].startswith(SKIP_LINE), out
    assert "PY_BOOKWORM=" in lines[-2] and "Python 3.11" in lines[-2]
    assert lines[-1].startswith("*** make: arm64 SKIPPED: SKIP_ARM64 is set"), out


def test_make_test_fails_and_prints_no_skip_line_when_the_suite_fails() -> None:
    r = _make("test", *_here(), "ARGS=-n 0 -p no:cacheprovider tests/no_such_test_file.py")
    out = r.stdout + r.stderr
    assert r.returncode != 0, out
    assert "SKIPPED" not in out


def test_required_bookworm_fails_when_python311_is_missing() -> None:
    r = _make("test-bookworm", f"PY_BOOKWORM={NO_PY}", env={"REQUIRE_BOOKWORM": "1"})
    out = r.stdout + r.stderr
    assert r.returncode != 0, out
    assert f"make: {NO_PY} not found: the Bookworm stack needs Python 3.11" in out
    assert "SKIPPED" not in out


def test_optional_bookworm_is_skipped_with_exit_0() -> None:
    r = _make("test-bookworm", f"PY_BOOKWORM={NO_PY}")
    assert r.returncode == 0, r.stdout + r.stderr
    assert r.stdout.strip().startswith(SKIP_LINE)


def test_ci_runs_exactly_the_readme_test_command() -> None:
    ci = (ROOT / ".ci" / "run").read_text()
    command = [ln for ln in ci.splitlines() if ln.strip() and not ln.startswith("#")][-1]
    assert command == "REQUIRE_BOOKWORM=1 REQUIRE_ARM64=1 make test"
    assert f"`{command}`" in (ROOT / "README.md").read_text()


def test_on_a_pi_make_test_uses_the_pis_own_stack(tmp_path: Path) -> None:
    # No Pi here: a dry run with the Pi detection forced shows the plan make would carry out.
    r = _make("-n", "test", "ON_PI=yes", "CODENAME=trixie", f"VENV={tmp_path / 'v'}",
              f"PY_BOOKWORM={NO_PY}")
    out = r.stdout + r.stderr
    assert r.returncode == 0, out
    assert "--system-site-packages" in out and "-c constraints/trixie.txt" in out
    assert "bookworm" not in out.lower(), out  # neither run nor reported as skipped
    assert f"{tmp_path / 'v'}/bin/python -m pytest" in out


def test_missing_venv_module_gets_one_line_naming_the_package(tmp_path: Path) -> None:
    # A Python like Debian's without python3-venv: `import ensurepip` fails.
    shadow = tmp_path / "shadow" / "ensurepip"
    shadow.mkdir(parents=True)
    (shadow / "__init__.py").write_text("raise ImportError('No module named ensurepip')\n")
    fake = tmp_path / "python3"
    fake.write_text(f'#!/bin/sh\nPYTHONPATH={shadow.parent} exec {sys.executable} "$@"\n')
    fake.chmod(0o755)
    venv = tmp_path / "venv"
    r = _make("lint", f"PY={fake}", f"VENV={venv}")
    out = r.stdout + r.stderr
    assert r.returncode != 0
    assert "Traceback" not in out and "ensurepip is not available" not in out
    ours = [ln for ln in out.splitlines() if not ln.startswith("make: ***")]
    v = sys.version_info
    assert ours == [
        f"make: {fake} cannot create a venv (no venv/ensurepip module): "
        f"sudo apt install python{v[0]}.{v[1]}-venv (python3-venv for the system python3)"
    ], out
    assert not venv.exists()  # nothing half-made for the next run to trip over


def test_make_run_beside_a_kmead_on_the_default_ports(tmp_path: Path) -> None:
    """The main job binds free ports: a daemon already on 5555/5556 does not stop it, and
    ARGS reaches kmead (here: where the log goes and a small frame size)."""
    import socket

    held = []
    try:
        for port in (5555, 5556):
            s = socket.socket()
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                s.bind(("127.0.0.1", port))
            except OSError:  # someone else holds it: the case this test makes
                s.close()
                continue
            s.listen(1)
            held.append(s)
        log = tmp_path / "run.csv"
        r = _make("run", "STAMP=", f"BIN={Path(sys.executable).parent}", "FRAMES=3",
                  f"ARGS=--log {log} --set source.width=640 --set source.height=480")
        assert r.returncode == 0, r.stdout + r.stderr
        assert "telemetry tcp://127.0.0.1:" in r.stderr and ":5555" not in r.stderr
        assert log.read_text().startswith("frame,timestamp,")
    finally:
        for s in held:
            s.close()


def test_required_arm64_fails_when_skipped_and_optional_says_so_loudly() -> None:
    r = _make("test-arm64", "STAMP=", "SKIP_ARM64=1", env={"REQUIRE_ARM64": "1"})
    assert r.returncode != 0 and "SKIPPED" not in r.stdout
    assert "make: arm64 required (REQUIRE_ARM64=1) but SKIP_ARM64 is set" in r.stdout
    r = _make("test-arm64", "STAMP=", "SKIP_ARM64=1")
    assert r.returncode == 0 and r.stdout.strip().startswith("*** make: arm64 SKIPPED")


def test_arm64_without_root_is_one_loud_line_or_a_failure_when_required(
        request: pytest.FixtureRequest) -> None:
    """The script needs root (debootstrap, chroot, mounts): without it, one line."""
    script = ROOT / "scripts" / "test_arm64.sh"
    cmd = [str(script)]
    if os.geteuid() == 0:  # as root (CI): run it as nobody, from a copy nobody can read
        if shutil.which("runuser") is None:
            pytest.skip("root without runuser: cannot run the script as a normal user")
        top = Path(tempfile.mkdtemp(prefix="kmea-arm64-", dir="/tmp"))
        request.addfinalizer(lambda: shutil.rmtree(top, ignore_errors=True))
        copy = top / "scripts"
        copy.mkdir()
        shutil.copy(script, copy / "test_arm64.sh")
        for p in (top, copy, copy / "test_arm64.sh"):
            p.chmod(0o755)
        cmd = ["runuser", "-u", "nobody", "--", str(copy / "test_arm64.sh")]
    env = {k: v for k, v in os.environ.items() if k not in ("REQUIRE_ARM64", "SKIP_ARM64")}
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stdout + r.stderr
    assert r.stdout.strip().splitlines() == [
        "*** make: arm64 SKIPPED: needs root (debootstrap, chroot, mounts): sudo make "
        "test-arm64 ***"]
    r = subprocess.run(cmd, env={**env, "REQUIRE_ARM64": "1"}, capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 1 and r.stdout == ""
    assert "make: arm64 cannot run here: needs root" in r.stderr
