"""``benchmarks/camera_rate.py`` (the tracking filter against the camera's frame rate) runs
end to end on a small sample and prints one row of figures per rate."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "camera_rate.py"


def test_prints_a_row_per_rate_with_the_outliers_counted() -> None:
    out = subprocess.run([sys.executable, str(SCRIPT), "--jobs", "1", "--fps", "20,40",
                          "--sets", "1", "--duration", "8"],
                         capture_output=True, text=True, timeout=300, check=True).stdout
    rows = {}
    for line in out.splitlines():
        f = line.split()
        if f and f[0] in ("20", "40"):
            rows[f[0]] = f
    assert set(rows) == {"20", "40"}, out
    for fps, f in rows.items():
        outliers, caused, caught = int(f[1]), int(f[2]), int(f[8])
        # 6 drives of 8 s from 1 s on, 5 % of the frames are outliers.
        assert 0.02 * 6 * 7 * float(fps) < outliers < 0.08 * 6 * 8 * float(fps), f
        assert 0 <= caused <= outliers and 0 < caught <= outliers
        kalman_mm, iir_mm = float(f[10]), float(f[14])
        assert 0.0 < kalman_mm < iir_mm  # the IIR filter follows every outlier
    assert int(rows["40"][1]) > int(rows["20"][1])  # more frames, more outliers
