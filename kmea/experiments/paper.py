"""The KMEA paper's own results (Tables 1-4), to show beside the project's.

Braun, Lima, Pereira, Costa, "Kabsch Marker Estimation Algorithm" (IEEE Access, 2024): real
rig (RobotAtFactory 4.0 floor printed on canvas, Raspberry Pi 4B, Pi Camera Module 2), both
algorithms with a first-order IIR filter, each evaluated marker left out of its own
estimate, 256 samples per marker and algorithm. ``kmea/data/paper_tables.csv`` is a copy of
``shared/paper/tables.csv``: part, metric, unit (m or %), kmea, lmea, pct_change.

The paper's KMEA places an evaluated marker from its own PnP pose, given no plane: the
project's *off-map* mode is the like-for-like comparison for KMEA and LMEA (``plane-known``
gives them the marker's plane as well).
"""

from __future__ import annotations

import csv
import math
from functools import lru_cache
from importlib import resources

from kmea.stats.metrics import percent_change

__all__ = ["PAPER_SETTINGS", "comparison_markdown", "paper_table"]

PAPER_SETTINGS = {
    "I": "scenario one: camera on the central part of the structure, pointing down at about "
         "the floor's centre",
    "II": "as I, each evaluated marker on a 20 cm high support",
    "III": "as I, anchors 4, 13 and 16 moved and rotated a little",
    "IV": "scenario two: camera at the top-left, pointing at the origin; 4, 13, 16 "
          "displaced more",
}

# Paper metric name -> (MarkerMetrics field, scale from metres to the paper's unit).
_FIELDS = {"RMSE": ("rmse", 1.0), "STD": ("std", 1.0), "MAE": ("mae", 1.0),
           "MaxAE": ("maxae", 1.0), "MRE": ("mre", 1.0)}


@lru_cache(maxsize=1)
def _rows() -> tuple[dict[str, str], ...]:
    text = (resources.files("kmea") / "data" / "paper_tables.csv").read_text(encoding="utf-8")
    return tuple(csv.DictReader(text.splitlines()))


def paper_table(part: str) -> dict[str, tuple[float, float, float, str]]:
    """Metric -> (KMEA, LMEA, % change, unit) of the paper's table for ``part`` ("I".."IV");
    empty for anything else (a replay)."""
    return {r["metric"]: (float(r["kmea"]), float(r["lmea"]), float(r["pct_change"]),
                          r["unit"]) for r in _rows() if r["part"] == part}


def _mm(v: float, unit: str) -> str:
    if not math.isfinite(v):
        return "n/a"
    return f"{v * 1e3:.2f}" if unit == "m" else f"{v:.3f}"


def comparison_markdown(part: str, averages: dict[str, dict[str, object]]) -> str:
    """The paper's KMEA and LMEA beside the project's, one row per metric.

    averages: mode -> algorithm -> MarkerMetrics (averaged over the evaluated markers), for
    the modes to show; "kmea" and "lmea" (and "lmea-printed" when present) are used.
    Returns "" when the paper has no table for ``part``.
    """
    table = paper_table(part)
    if not table:
        return ""
    modes = list(averages)
    header = ["metric", "paper KMEA", "paper LMEA", "paper Δ"]
    for mode in modes:
        algs = [a for a in ("kmea", "lmea", "lmea-printed") if a in averages[mode]]
        header += [f"{a.upper() if a != 'lmea-printed' else 'LMEA as printed'} ({mode})"
                   for a in algs]
        header += [f"Δ KMEA vs LMEA ({mode})"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for metric, (pk, pl, pc, unit) in table.items():
        field, _ = _FIELDS[metric]
        row = [f"{metric} ({'mm' if unit == 'm' else '%'})", _mm(pk, unit), _mm(pl, unit),
               f"{pc:+.1f} %"]
        for mode in modes:
            av = averages[mode]
            for a in ("kmea", "lmea", "lmea-printed"):
                if a in av:
                    m = av[a]
                    row.append(_mm(getattr(m, field), unit) if m is not None else "n/a")
            k, lm = av.get("kmea"), av.get("lmea")
            pct = (percent_change(getattr(k, field), getattr(lm, field))
                   if k is not None and lm is not None else math.nan)
            row.append(f"{pct:+.1f} %" if math.isfinite(pct) else "n/a")
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines)
