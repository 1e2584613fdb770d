#!/bin/sh
# Run by scripts/test_arm64.sh inside the arm64 chroot (the project in /src/kmea). Each step's
# time goes to /src/steps.txt; any failure stops the run with that step's name.
set -eu
REPO=/src/kmea
VENV=/opt/kmea
FRAMES=${ARM64_FRAMES:-30}
SIM=${SIM:-sim:default?width=640&height=480}
CODENAME=$(. /etc/os-release && echo "$VERSION_CODENAME")
: >/src/steps.txt
step() {  # step NAME COMMAND...: run it, record its time
    name=$1; shift
    echo "== arm64: $name"
    s=$(date +%s)
    if ! "$@"; then
        echo "make: arm64 step failed: $name" >&2
        exit 1
    fi
    printf '%-44s %5ds\n' "$name" $(( $(date +%s) - s )) >>/src/steps.txt
}

run_kmead() {
    cd /src && "$VENV/bin/kmead" --headless --free-ports --frames "$FRAMES" --source "$SIM" \
        --set source.fps=0 --status-every 0 --log /src/arm.csv
}

run_doctor() {
    cd /src && "$VENV/bin/kmea" doctor | tee /src/doctor.txt
}

# The tests of the code that runs only on a Pi: picamera2 (its fakes), camera timing and the
# sensor tables, the install script and unit, the doctor; the C decoder of the binary pose,
# compiled here by this userland's cc and fed the bytes a kmead running here sent.
run_tests() {
    cd "$REPO" && "$VENV/bin/python" -m pytest -q -p no:cacheprovider \
        tests/test_picamera_source.py tests/test_timing.py tests/test_deploy.py \
        tests/test_doctor.py \
        "tests/test_zenoh_ros2.py::test_the_c_decoder_reads_the_bytes_kmead_sent"
}

echo "== arm64: $(uname -m), Debian $CODENAME, $(python3 --version)"
# deploy/install.sh's own route: apt (python3-picamera2 is in Raspberry Pi's archive only:
# here its apt numpy and venv), the venv with --system-site-packages, pip with
# constraints/<codename>.txt, the zenoh extra; no user, /etc/kmead or systemd in a chroot.
step "install (deploy/install.sh, zenoh extra)" \
    env KMEA_NO_SERVICE=1 KMEA_APT="python3-numpy python3-venv" KMEA_EXTRAS=zenoh \
    KMEA_VENV="$VENV" "$REPO/deploy/install.sh"
step "pytest and its plugins" "$VENV/bin/python" -m pip install -q \
    -c "$REPO/constraints/$CODENAME.txt" "pytest>=8,<9" pytest-asyncio pytest-benchmark
"$VENV/bin/python" -c 'import sys, numpy, cv2, zmq, zenoh
from importlib.metadata import version
print("== arm64 stack: Python %d.%d.%d, numpy %s (%s), OpenCV %s, pyzmq %s, zenoh %s" % (
    *sys.version_info[:3], numpy.__version__, numpy.__file__.split("/")[1],
    cv2.__version__, zmq.__version__, version("eclipse-zenoh")))'
step "kmead, $FRAMES frames of the simulator" run_kmead
step "kmea doctor" run_doctor
step "tests of the Pi code paths, the C decoder" run_tests
