#!/usr/bin/env bash
# scripts/results_fingerprint.sh OUT: the results issue 11 promised not to change, written to OUT:
# the fixed-seed experiment tables (kmea experiment all, 24 samples, seed 0) and the daemon's CSV
# (kmea, kmea-robust, corner-pnp) on a fixed images: input (40 rendered default-floor frames in
# OUT/frames, or FRAMES=DIR to reuse a folder, so two checkouts see the same pixels).
# Compare two outputs with: python3 scripts/compare_results.py OUT_A OUT_B
set -euo pipefail
out=$1; mkdir -p "$out"
B=${BIN:-.venv/bin}
frames=${FRAMES:-$out/frames}
[ -d "$frames" ] || "$B/python" -m kmea.sim "sim:default" --frames 40 --out "$frames"
"$B/kmea" experiment all --samples 24 --seed 0 --jobs 2 --no-plots --quiet --out "$out/exp"
for a in kmea kmea-robust corner-pnp; do
  name=run-$a.csv; [ "$a" = kmea ] && name=run.csv
  "$B/kmead" --source "images:$frames" --algorithm "$a" --set 'network.telemetry=""' \
    --set 'network.control=""' --headless --log "$out/$name" > /dev/null 2>&1
done
