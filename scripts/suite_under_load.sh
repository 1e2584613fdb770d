#!/usr/bin/env bash
# The suite, again and again, beside CPU hogs, until it passes N times in a row (a suite that
# fails by chance shows up here, not in CI). One line per run; the last line is the figure.
#
#   scripts/suite_under_load.sh [PYTHON] [N] [MAX_RUNS] [HOGS]
#     PYTHON    the stack's interpreter (default .venv/bin/python; .venv-bookworm/bin/python)
#     N         passes in a row wanted (default 5); MAX_RUNS: give up after (default 10)
#     HOGS      busy-looping processes beside the suite (default 2)
set -uo pipefail
cd "$(dirname "$0")/.."
PYTHON=${1:-.venv/bin/python}
WANT=${2:-5}
MAX=${3:-10}
HOGS=${4:-2}
hogs=()
for _ in $(seq "$HOGS"); do
    "$PYTHON" -c 'while True: pass' &
    hogs+=($!)
done
trap 'kill "${hogs[@]}" 2>/dev/null' EXIT
stack=$("$PYTHON" -c 'import sys, numpy, cv2; print("Python %d.%d.%d, numpy %s, OpenCV %s" % (*sys.version_info[:3], numpy.__version__, cv2.__version__))')
streak=0
for run in $(seq "$MAX"); do
    start=$(date +%s)
    log=$(mktemp)
    "$PYTHON" -m pytest -q -n 2 -p no:cacheprovider >"$log" 2>&1
    rc=$?
    summary=$(grep -E '^[0-9]+ (passed|failed)|^=+ .*(passed|failed)' "$log" | tail -1)
    echo "run $run: exit $rc in $(( $(date +%s) - start )) s: $summary"
    if [ $rc -eq 0 ]; then
        streak=$((streak + 1))
    else
        streak=0
        grep -E '^(FAILED|ERROR) ' "$log" | sed 's/^/    /'
        kept="${KEEP_DIR:-/tmp}/suite-under-load-run$run.log"
        cp "$log" "$kept" && echo "    log: $kept"
    fi
    rm -f "$log"
    if [ $streak -ge "$WANT" ]; then
        echo "$stack: $WANT passes in a row beside $HOGS CPU hogs after $run runs"
        exit 0
    fi
done
echo "$stack: no $WANT passes in a row within $MAX runs beside $HOGS CPU hogs"
exit 1
