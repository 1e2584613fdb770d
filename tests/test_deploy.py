"""deploy/: the systemd unit, the Pi configuration and the install script agree and parse."""

from __future__ import annotations

import configparser
import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from kmead.config.layers import load_config

ROOT = Path(__file__).resolve().parents[1]
DEPLOY = ROOT / "deploy"


def _unit() -> configparser.SectionProxy:
    cp = configparser.ConfigParser(strict=True, interpolation=None)
    cp.optionxform = str  # systemd keys are case-sensitive
    cp.read(DEPLOY / "kmead.service")
    return cp["Service"]


def _exec_argv() -> list[str]:
    """ExecStart as the shell receives it (systemd: $$ -> $, %% -> %)."""
    argv = shlex.split(_unit()["ExecStart"])
    return [a.replace("$$", "$").replace("%%", "%") for a in argv]


def test_unit_is_notify_with_watchdog_and_restarts() -> None:
    s = _unit()
    assert s["Type"] == "notify" and s["NotifyAccess"] == "main"
    assert s["WatchdogSec"] == "30s"
    assert s["Restart"] == "on-failure" and s["RestartPreventExitStatus"] == "2"
    assert s["User"] == "kmead" and "video" in s["SupplementaryGroups"].split()
    assert s["StateDirectory"] == "kmea" and s["WorkingDirectory"] == "/var/lib/kmea"


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="no systemd-analyze here")
def test_systemd_analyze_verify_has_nothing_to_say(tmp_path: Path) -> None:
    """systemd's own parser; it exits 0 even for ignored lines, so its output must be empty."""
    r = subprocess.run(["systemd-analyze", "verify", "--man=no", str(DEPLOY / "kmead.service")],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0
    assert "kmead.service" not in r.stdout + r.stderr, r.stdout + r.stderr


def test_exec_start_runs_kmead_on_the_camera_with_a_new_log(tmp_path: Path) -> None:
    """ExecStart's shell line, run with a stand-in kmead: exec (kmead stays the main process
    for NotifyAccess=main), --source picamera, the Pi config and a timestamped log."""
    argv = _exec_argv()
    assert argv[:2] == ["/bin/sh", "-c"] and argv[2].startswith("exec /opt/kmea/bin/kmead ")
    stub = tmp_path / "kmead"
    stub.write_text('#!/bin/sh\necho "pid $$"\nfor a in "$@"; do echo "$a"; done\n')
    stub.chmod(0o755)
    line = argv[2].replace("/opt/kmea/bin/kmead", str(stub))
    r = subprocess.run(["/bin/sh", "-c", f"echo sh $$; {line}"], capture_output=True, text=True,
                       env={**os.environ, "STATE_DIRECTORY": str(tmp_path)}, timeout=30)
    out = r.stdout.splitlines()
    assert out[0].split()[1] == out[1].split()[1]  # exec: the stub has the shell's pid
    args = out[2:]
    assert args[:5] == ["--headless", "--source", "picamera", "--config",
                        "/etc/kmead/kmead.toml"]
    assert args[5] == "--log"
    assert re.fullmatch(re.escape(str(tmp_path)) + r"/logs/kmea-\d{8}-\d{6}\.csv", args[6])


def test_pi_config_is_the_camera_with_a_camera_file() -> None:
    cfg = load_config(str(DEPLOY / "pi.toml"), use_local=False)
    assert cfg["source"]["spec"] == "picamera"
    assert (cfg["source"]["width"], cfg["source"]["height"]) == (1640, 1232)
    assert cfg["camera"]["file"] == "/etc/kmead/camera.yml"


def test_install_script_puts_what_the_unit_names_in_place() -> None:
    sh = re.sub(r"[ \t]+", " ", (DEPLOY / "install.sh").read_text().replace("\\\n", " "))
    assert subprocess.run(["sh", "-n", str(DEPLOY / "install.sh")]).returncode == 0
    assert os.access(DEPLOY / "install.sh", os.X_OK)
    unit = _unit()
    # the user and group the unit runs as
    assert re.search(r"useradd --system --user-group --groups video .* kmead\b", sh)
    # the venv and the config the unit's ExecStart names, the camera file pi.toml names
    assert 'VENV=${KMEA_VENV:-/opt/kmea}' in sh and "/opt/kmea/bin/kmead" in unit["ExecStart"]
    assert '"$REPO/deploy/pi.toml" "$ETC/kmead.toml"' in sh and "ETC=/etc/kmead" in sh
    assert '"$ETC/camera.yml"' in sh
    assert "--system-site-packages" in sh and 'CONSTRAINTS="$REPO/constraints/$CODENAME.txt"' in sh
    assert '"$REPO/deploy/kmead.service" "$UNIT"' in sh
    assert "UNIT=/etc/systemd/system/kmead.service" in sh
    for codename in ("bookworm", "trixie"):
        assert (ROOT / "constraints" / f"{codename}.txt").is_file()


def test_install_script_refuses_without_root(tmp_path: Path) -> None:
    # The script on stdin: a normal user may not be able to read the checkout's folder.
    cmd = ["sh", "-s"]
    if os.geteuid() == 0:  # as root (CI): run it as nobody
        if shutil.which("runuser") is None:
            pytest.skip("root without runuser: cannot run the script as a normal user")
        cmd = ["runuser", "-u", "nobody", "--", *cmd]
    r = subprocess.run(cmd, input=(DEPLOY / "install.sh").read_text(), capture_output=True,
                       text=True, timeout=30, cwd="/")
    assert r.returncode == 1 and "run as root: sudo make install-service" in r.stderr


def test_constraints_files_pin_the_apt_numpy() -> None:
    def pins(name: str) -> dict[str, str]:
        out = {}
        for line in (ROOT / "constraints" / name).read_text().splitlines():
            line = line.split("#")[0].strip()
            if line:
                pkg = re.match(r"[A-Za-z0-9_.-]+", line).group(0)
                out[pkg] = line[len(pkg):]
        return out

    bw, tx = pins("bookworm.txt"), pins("trixie.txt")
    assert bw["numpy"] == ">=1.24,<1.25" and bw["opencv-python-headless"] == ">=4.11,<4.12"
    assert tx["numpy"] == ">=2.2,<2.3" and tx["opencv-python-headless"] == ">=5.0,<5.1"


def test_no_pi_extra() -> None:
    """picamera2 comes from apt only (README, On the Raspberry Pi)."""
    if sys.version_info >= (3, 11):
        import tomllib
    else:  # pragma: no cover
        import tomli as tomllib

    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"][
        "optional-dependencies"]
    assert "pi" not in extras
    assert not any("picamera2" in dep for deps in extras.values() for dep in deps)
