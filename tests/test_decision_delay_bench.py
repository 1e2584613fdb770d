"""``benchmarks/decision_delay.py`` (each output sent L frames late, from the track after
frame k + L): with no delay it is exactly the benchmark's filter run, and it runs end to
end."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import numpy as np

from kmea.benchmarks.tracking import TUNED, make_measurements, run_kalman, trajectory

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "decision_delay.py"


def _module():
    spec = importlib.util.spec_from_file_location("decision_delay", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_no_delay_is_the_filter_and_a_delay_uses_the_later_frames() -> None:
    dd = _module()
    tr = trajectory(31, duration=8.0)
    ms = make_measurements(tr, 31, outliers=0.05)
    ref, ref_info = run_kalman(ms, TUNED)
    out0, info0 = dd.run_delayed(ms, 0)
    assert np.array_equal(out0, ref) and np.array_equal(info0["sigma"], ref_info["sigma"])
    assert np.array_equal(info0["rejected"], ref_info["rejected"])
    out1, _ = dd.run_delayed(ms, 1)
    # The output for each frame now knows the next measurement: it differs, and the last
    # frame (no later one) is the filter's own.
    assert not np.array_equal(out1[:-1], ref[:-1])
    assert np.array_equal(out1[-1], ref[-1])
    gx, gy, _ = tr.at(ms.t)
    keep = ms.t >= 1.0

    def err(o: np.ndarray) -> float:
        return float(np.sqrt(np.mean(((o[:, 0] - gx) ** 2 + (o[:, 1] - gy) ** 2)[keep])))

    assert err(out1) < err(ref)  # one more measurement: closer to the truth


def test_prints_the_held_out_rows_per_delay() -> None:
    out = subprocess.run([sys.executable, str(SCRIPT), "--frames", "0,1", "--jobs", "2",
                          "--sets", "B"], capture_output=True, text=True, timeout=300,
                         check=True).stdout
    rows = [line.split() for line in out.splitlines() if line.split()[1:2] == ["held-out"]]
    assert [(r[0], r[2]) for r in rows] == [("0", "B"), ("1", "B")], out
    for r in rows:
        caused, outliers = (int(v) for v in r[3].split("/"))
        assert outliers == 338 and 0 <= caused <= outliers
        assert 0.0 < float(r[5]) < 5.0  # position RMSE, mm (B: 1.5 mm measurements)
