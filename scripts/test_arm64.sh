#!/usr/bin/env bash
# make test-arm64: the project on the Pi's CPU (arm64), emulated with qemu-user-static.
#
#   1. A Debian arm64 userland (debootstrap --arch=arm64 --variant=minbase, Debian's mirror)
#      with the apt packages deploy/install.sh relies on, cached as a tarball under
#      ${XDG_CACHE_HOME:-$HOME/.cache}/kmea/, keyed by the codename and the package list.
#   2. It is unpacked in a temporary directory under that cache (removed at the end), with
#      /proc, /dev, /sys mounted for pip and Python (unmounted by a trap) and pip's cache
#      kept beside the tarball, so a warm run downloads no wheel again.
#   3. In it, scripts/arm64_inside.sh: deploy/install.sh's route (apt numpy, a venv with
#      --system-site-packages, constraints/<codename>.txt, the zenoh extra; the user and
#      systemd steps skipped: KMEA_NO_SERVICE=1), a bounded kmead on the simulator,
#      `kmea doctor`, the Pi code paths' tests and the C decoder of the binary pose.
#   4. The same kmead run on this machine (x86) with .venv; scripts/compare_arm64.py matches
#      the two CSV logs row for row within stated tolerances.
#
# Environment: REQUIRE_ARM64=1 fails (exit 1) where arm64 cannot be emulated, else one loud
# "*** make: arm64 SKIPPED: <why> ***" line and exit 0. ARM64_CODENAME=trixie (default
# bookworm). ARM64_FRAMES (default 30). ARM64_KEEP_CACHE=0 rebuilds the userland (cold run).
# Needs root (debootstrap, chroot, mounts); when qemu-user-static or debootstrap is missing,
# root installs them with apt-get and registers qemu-aarch64 with binfmt_misc.
set -euo pipefail
cd "$(dirname "$0")/.."
REPO=$(pwd)
CODENAME=${ARM64_CODENAME:-bookworm}
FRAMES=${ARM64_FRAMES:-30}
REQUIRED=${REQUIRE_ARM64:-}
[ "$REQUIRED" = 0 ] && REQUIRED=
BIN=${BIN:-$REPO/.venv/bin}
CACHE=${XDG_CACHE_HOME:-$HOME/.cache}/kmea
MIRROR=${ARM64_MIRROR:-http://deb.debian.org/debian}
# What deploy/install.sh takes from apt on the Pi (but python3-picamera2: Raspberry Pi's
# archive only), the C compiler for the decoder, certificates for pip.
PACKAGES=python3,python3-venv,python3-numpy,ca-certificates,gcc,libc6-dev
SIM="sim:default?width=640&height=480"

skip() {  # cannot emulate: fail when required, else one loud line
    if [ -n "$REQUIRED" ]; then
        echo "make: arm64 cannot run here: $1 (REQUIRE_ARM64=1)" >&2
        exit 1
    fi
    echo "*** make: arm64 SKIPPED: $1 ***"
    exit 0
}
case "$CODENAME" in bookworm|trixie) ;; *) echo "make: ARM64_CODENAME=$CODENAME: bookworm or trixie" >&2; exit 2 ;; esac
[ "$(uname -s)" = Linux ] || skip "not Linux (needs chroot and binfmt_misc)"
[ "$(id -u)" = 0 ] || skip "needs root (debootstrap, chroot, mounts): sudo make test-arm64"
NATIVE=
[ "$(uname -m)" = aarch64 ] && NATIVE=1

# --------------------------------------------------------------------- tools and binfmt
if ! command -v debootstrap >/dev/null || { [ -z "$NATIVE" ] && [ ! -e /usr/libexec/qemu-binfmt/aarch64-binfmt-P ] && ! command -v qemu-aarch64-static >/dev/null; }; then
    command -v apt-get >/dev/null || skip "no debootstrap/qemu-user-static and no apt-get to install them"
    echo "arm64: apt-get install debootstrap qemu-user-static binfmt-support"
    { apt-get install -y -q debootstrap qemu-user-static binfmt-support >/dev/null 2>&1 \
      || { apt-get update -q >/dev/null 2>&1 && apt-get install -y -q debootstrap qemu-user-static binfmt-support >/dev/null 2>&1; }; } \
      || skip "apt-get could not install debootstrap qemu-user-static binfmt-support"
fi
if [ -z "$NATIVE" ]; then
    BM=/proc/sys/fs/binfmt_misc
    [ -e $BM/register ] || mount -t binfmt_misc binfmt_misc $BM 2>/dev/null \
        || skip "binfmt_misc cannot be mounted ($BM): a container without the privilege?"
    if ! grep -qs '^enabled' $BM/qemu-aarch64; then
        if command -v update-binfmts >/dev/null; then
            update-binfmts --enable qemu-aarch64 >/dev/null 2>&1 || true
        fi
        if ! grep -qs '^enabled' $BM/qemu-aarch64 && [ -r /usr/lib/binfmt.d/qemu-aarch64.conf ]; then
            # qemu-user-static's own registration line (flags F: the interpreter is opened
            # now, so the chroot needs no copy of it).
            cat /usr/lib/binfmt.d/qemu-aarch64.conf > $BM/register 2>/dev/null || true
        fi
        grep -qs '^enabled' $BM/qemu-aarch64 || skip "qemu-aarch64 cannot be registered with binfmt_misc"
    fi
fi

# --------------------------------------------------------------------- the userland
mkdir -p "$CACHE"
KEY=$(printf '%s %s %s' "$CODENAME" "$PACKAGES" "$MIRROR" | cksum | cut -d' ' -f1)
TARBALL=$CACHE/arm64-$CODENAME-$KEY.tar.zst
PIPCACHE=$CACHE/arm64-$CODENAME-pip
mkdir -p "$PIPCACHE"
[ "${ARM64_KEEP_CACHE:-1}" = 0 ] && rm -f "$TARBALL" && rm -rf "$PIPCACHE" && mkdir -p "$PIPCACHE"
ROOT=$(mktemp -d "$CACHE/arm64-root.XXXXXX")
T0=$(date +%s)
declare -a STEPS=()
step() { STEPS+=("$(printf '%-44s %5ds' "$1" $(( $(date +%s) - $2 )))"); }

cleanup() {
    local rc=$?
    # Unmount everything under the root first; never delete while anything is mounted there.
    for m in $(findmnt -rno TARGET | grep "^$ROOT/" | sort -r); do
        umount -l "$m" 2>/dev/null || true
    done
    if findmnt -rno TARGET | grep -q "^$ROOT/"; then
        echo "arm64: mounts remain under $ROOT: not removed" >&2
    else
        rm -rf --one-file-system "$ROOT"
    fi
    exit $rc
}
trap cleanup EXIT
trap 'exit 130' INT TERM

t=$(date +%s)
if [ -s "$TARBALL" ]; then
    tar --zstd -xpf "$TARBALL" -C "$ROOT"
    step "userland unpacked from the cache" "$t"
else
    echo "arm64: building the $CODENAME arm64 userland (debootstrap, minutes) -> $TARBALL"
    ARCHIVE=$CACHE/arm64-debootstrap-$KEY.log
    if ! debootstrap --arch=arm64 --variant=minbase --include="$PACKAGES" "$CODENAME" \
            "$ROOT" "$MIRROR" >"$ARCHIVE" 2>&1; then
        tail -20 "$ARCHIVE" >&2
        echo "make: debootstrap $CODENAME arm64 failed (log $ARCHIVE)" >&2
        exit 1
    fi
    rm -f "$ARCHIVE"
    chroot "$ROOT" apt-get clean
    tar --zstd -cpf "$TARBALL.tmp" -C "$ROOT" . && mv "$TARBALL.tmp" "$TARBALL"
    step "userland built (debootstrap) and cached" "$t"
fi
# mktemp's 0700 (kept by the tarball's ".") would lock the tests' unprivileged user out of /.
chmod 755 "$ROOT"

mount -t proc proc "$ROOT/proc"
mount --rbind /dev "$ROOT/dev" && mount --make-rslave "$ROOT/dev"
mount --rbind /sys "$ROOT/sys" && mount --make-rslave "$ROOT/sys"
mkdir -p "$ROOT/root/.cache/pip" && mount --bind "$PIPCACHE" "$ROOT/root/.cache/pip"
cp -L /etc/resolv.conf "$ROOT/etc/resolv.conf"
# The host's certificate authorities (a network whose egress re-signs TLS has its own CA in
# them, and the userland's ca-certificates package does not): pip inside trusts the same.
HOST_CA=${PIP_CERT:-${SSL_CERT_FILE:-/etc/ssl/certs/ca-certificates.crt}}
CA_ENV=()
if [ -r "$HOST_CA" ]; then
    cp -L "$HOST_CA" "$ROOT/etc/ssl/host-ca.crt"
    CA_ENV=(PIP_CERT=/etc/ssl/host-ca.crt SSL_CERT_FILE=/etc/ssl/host-ca.crt)
fi
# The project as committed plus the working tree's changes, without venvs and caches.
mkdir -p "$ROOT/src/kmea"
tar -C "$REPO" --exclude='./.venv*' --exclude='./.git' --exclude='./out' \
    --exclude='__pycache__' --exclude='./.pytest_cache' --exclude='./.ruff_cache' \
    --exclude='./runs' -cf - . | tar -C "$ROOT/src/kmea" -xf -

# --------------------------------------------------------------------- in the chroot
t=$(date +%s)
# The host's pip settings point at indexes on this machine's disk, which the chroot cannot
# see: pip inside uses PyPI alone.
env -i HOME=/root PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin \
    LANG=C.UTF-8 ARM64_FRAMES="$FRAMES" SIM="$SIM" "${CA_ENV[@]}" \
    chroot "$ROOT" /bin/sh /src/kmea/scripts/arm64_inside.sh
step "in the chroot (scripts/arm64_inside.sh)" "$t"
grep -h '' "$ROOT/src/steps.txt" | sed 's/^/  /' > "$CACHE/arm64-inside-steps.txt" || true

# --------------------------------------------------------------------- x86 and the comparison
t=$(date +%s)
X86=$ROOT/x86
mkdir -p "$X86"
[ -x "$BIN/kmead" ] || { echo "make: $BIN/kmead missing: make test-current first" >&2; exit 1; }
(cd "$X86" && "$BIN/kmead" --headless --free-ports --frames "$FRAMES" --source "$SIM" \
    --set source.fps=0 --status-every 0 --log x86.csv >kmead.out 2>&1) \
    || { cat "$X86/kmead.out" >&2; echo "make: the x86 kmead run failed" >&2; exit 1; }
step "x86 kmead, $FRAMES frames" "$t"
# Both logs kept beside the cache (the userland goes at the end) for a look after a failure.
mkdir -p "$CACHE/arm64-last" && cp "$X86/x86.csv" "$ROOT/src/arm.csv" "$CACHE/arm64-last/"
"$BIN/python" -c 'import sys, numpy, cv2; print("x86 run: Python %d.%d.%d, numpy %s, OpenCV %s" % (*sys.version_info[:3], numpy.__version__, cv2.__version__))'
"$BIN/python" scripts/compare_arm64.py "$X86/x86.csv" "$ROOT/src/arm.csv"

echo "arm64 ($CODENAME, $( [ -n "$NATIVE" ] && echo native || echo qemu-user-static)): steps"
for s in "${STEPS[@]}"; do echo "  $s"; done
cat "$CACHE/arm64-inside-steps.txt"
echo "  total                                        $(( $(date +%s) - T0 ))s"
