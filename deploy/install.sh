#!/bin/sh
# Install kmead as a systemd service on Raspberry Pi OS Bookworm or Trixie (64-bit).
# Run from the repository as root:  sudo make install-service   (or: sudo deploy/install.sh)
#
# What it does (each step is safe to run again):
#   1. apt: python3-picamera2 (brings libcamera and the apt numpy), python3-venv
#   2. the system user kmead, in the group video (camera devices)
#   3. the venv /opt/kmea with --system-site-packages and constraints/<codename>.txt, so the
#      apt numpy that picamera2 was built for is the one used (README, On the Raspberry Pi)
#   4. /etc/kmead: kmead.toml (deploy/pi.toml) and camera.yml, kept if they exist
#   5. /etc/systemd/system/kmead.service, enabled; `kmea doctor`; the service (re)started
# Environment: KMEA_VENV (default /opt/kmea), KMEA_NO_START=1 (install, do not start),
# KMEA_EXTRAS (extras to install, e.g. zenoh), KMEA_APT (the apt packages of step 1),
# KMEA_NO_SERVICE=1 (steps 1 and 3 only: the venv in a chroot or a container, where there is
# no systemd; make test-arm64).
set -eu

REPO=$(cd "$(dirname "$0")/.." && pwd)
VENV=${KMEA_VENV:-/opt/kmea}
ETC=/etc/kmead
UNIT=/etc/systemd/system/kmead.service

say() { printf 'install: %s\n' "$*"; }
die() { printf 'install: %s\n' "$*" >&2; exit 1; }

[ "$(id -u)" = 0 ] || die "run as root: sudo make install-service"
[ -r /etc/os-release ] || die "/etc/os-release missing: not Raspberry Pi OS?"
CODENAME=$(. /etc/os-release && echo "${VERSION_CODENAME:-}")
case "$CODENAME" in
    bookworm|trixie) ;;
    *) die "Raspberry Pi OS Bookworm or Trixie expected, this is '${CODENAME}' (docs/pi.md)" ;;
esac
CONSTRAINTS="$REPO/constraints/$CODENAME.txt"
[ -r "$CONSTRAINTS" ] || die "$CONSTRAINTS missing"

APT=${KMEA_APT:-python3-picamera2 python3-venv}
EXTRAS=${KMEA_EXTRAS:+[$KMEA_EXTRAS]}
NO_SERVICE=${KMEA_NO_SERVICE:-0}

say "apt: $APT"
# shellcheck disable=SC2086 # a list of package names
apt-get install -y --no-install-recommends $APT

if [ "$NO_SERVICE" = 1 ]; then
    :
elif ! id -u kmead >/dev/null 2>&1; then
    say "user kmead (system, group video)"
    useradd --system --user-group --groups video --home-dir /var/lib/kmea --no-create-home \
        --shell /usr/sbin/nologin kmead
else
    usermod -a -G video kmead
fi

if [ ! -x "$VENV/bin/python" ]; then
    say "venv $VENV (--system-site-packages)"
    python3 -m venv --system-site-packages "$VENV"
fi
say "pip install -c constraints/$CODENAME.txt $REPO$EXTRAS"
"$VENV/bin/python" -m pip install -q -c "$CONSTRAINTS" "$REPO$EXTRAS"
if [ "$NO_SERVICE" = 1 ]; then
    say "KMEA_NO_SERVICE=1: venv $VENV only (no user, $ETC, unit or start)"
    exit 0
fi

install -d -o root -g kmead -m 2775 "$ETC"
if [ ! -e "$ETC/kmead.toml" ]; then
    install -o root -g kmead -m 0664 "$REPO/deploy/pi.toml" "$ETC/kmead.toml"
    say "$ETC/kmead.toml from deploy/pi.toml"
fi
if [ ! -e "$ETC/camera.yml" ]; then
    "$VENV/bin/python" -c 'import sys
from kmea.vision.camera import pi_camera_v2, save_camera
save_camera(pi_camera_v2(), sys.argv[1])' "$ETC/camera.yml"
    chgrp kmead "$ETC/camera.yml"
    say "$ETC/camera.yml: a NOMINAL Pi Camera v2 model; calibrate this camera (docs/pi.md)"
fi

install -m 0644 "$REPO/deploy/kmead.service" "$UNIT"
systemctl daemon-reload
systemctl enable kmead
if "$VENV/bin/kmead" --help | grep -q -- '--check'; then
    "$VENV/bin/kmead" --check --config "$ETC/kmead.toml" --source picamera >/dev/null \
        || die "kmead --check failed on $ETC/kmead.toml: fix it, then run this again"
fi
# The doctor runs as the service's user (group video) before the service holds the camera.
runuser -u kmead -- "$VENV/bin/kmea" doctor --config "$ETC/kmead.toml" || true
if [ "${KMEA_NO_START:-0}" != 1 ]; then
    systemctl restart kmead
    say "started: systemctl status kmead; journalctl -u kmead -f"
fi
