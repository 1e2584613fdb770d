"""The paper's tables from a :class:`~kmea.experiments.run.RunResult`.

Every number comes from :mod:`kmea.stats.metrics` (no second implementation here): per marker
``marker_metrics(samples, truth, reference_length)``, per algorithm ``mean_metrics`` over the
evaluated markers, and ``percent_change`` of each averaged metric against the baseline.
Text and Markdown show millimetres and percent (for people); the CSV keeps metres.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from kmea.experiments.run import RunResult
from kmea.stats.metrics import MarkerMetrics, marker_metrics, mean_metrics, percent_change

__all__ = ["METRICS", "Scores", "modes_markdown", "score", "summary_markdown", "write_csv",
           "write_samples_csv"]

STD_NOTE = ("STD is the paper's figure (sample SD of the error magnitudes); it depends on a "
            "constant bias (for isotropic noise of sigma per axis: 0.66 sigma without bias, "
            "-> sigma with a large one). Scatter (2-D SD of the estimates about their mean) "
            "does not; Bias is |mean estimate - truth|.")

# (column title, MarkerMetrics field, scale to display units, unit)
METRICS: tuple[tuple[str, str, float, str], ...] = (
    ("RMSE", "rmse", 1e3, "mm"),
    ("STD", "std", 1e3, "mm"),
    ("MAE", "mae", 1e3, "mm"),
    ("MaxAE", "maxae", 1e3, "mm"),
    ("MRE", "mre", 1.0, "%"),
)


@dataclass
class Scores:
    """per_marker: (algorithm, id) -> metrics (absent when the marker has no sample);
    average: algorithm -> mean over the markers it estimated (None if none);
    change: algorithm -> metric field -> % change of the average against the baseline;
    complete: algorithm -> it estimated every evaluated marker at least once."""

    per_marker: dict[tuple[str, int], MarkerMetrics]
    average: dict[str, MarkerMetrics | None]
    change: dict[str, dict[str, float]]
    complete: dict[str, bool]


def score(result: RunResult) -> Scores:
    """Metrics of every (algorithm, marker) and their averages, from :mod:`kmea.stats.metrics`."""
    per: dict[tuple[str, int], MarkerMetrics] = {}
    for a in result.algorithms:
        for m in result.markers:
            s = result.samples.get((a, m))
            if s is not None and len(s):
                per[(a, m)] = marker_metrics(s, result.truth[m], result.reference_length)
    avg: dict[str, MarkerMetrics | None] = {}
    complete: dict[str, bool] = {}
    for a in result.algorithms:
        items = [per[(a, m)] for m in result.markers if (a, m) in per]
        avg[a] = mean_metrics(items) if items else None
        complete[a] = len(items) == len(result.markers)
    change: dict[str, dict[str, float]] = {}
    base = avg.get(result.baseline)
    for a in result.algorithms:
        if base is None or avg[a] is None:
            change[a] = {f: math.nan for _, f, _, _ in METRICS}
        else:
            change[a] = {f: percent_change(getattr(avg[a], f), getattr(base, f))
                         for _, f, _, _ in METRICS}
    return Scores(per, avg, change, complete)


def _f(x: float, digits: int = 2) -> str:
    return "n/a" if x is None or not math.isfinite(x) else f"{x:.{digits}f}"


def _pct(x: float) -> str:
    return "n/a" if not math.isfinite(x) else f"{x:+.1f} %"


def _md_table(header: list[str], rows: list[list[str]]) -> str:
    out = ["| " + " | ".join(header) + " |",
           "|" + "|".join("---:" if i else ":---" for i in range(len(header))) + "|"]
    out += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(out)


def mean_change(scores: Scores, algorithm: str) -> float:
    """Mean of the five metrics' % changes (the paper's "average" reduction, as we read it)."""
    v = [scores.change[algorithm][f] for _, f, _, _ in METRICS]
    return float(np.mean(v)) if all(math.isfinite(x) for x in v) else math.nan


def summary_rows(result: RunResult, scores: Scores) -> tuple[list[str], list[list[str]]]:
    """The paper's table: averaged metrics per algorithm and their % change vs the baseline."""
    header = ["Algorithm", *[f"{t} ({u})" for t, _, _, u in METRICS],
              *[f"Δ{t}" for t, _, _, _ in METRICS], "mean Δ", "Scatter (mm)", "Bias (mm)",
              "samples"]
    rows = []
    for a in result.algorithms:
        m = scores.average[a]
        vals = [_f(getattr(m, f) * k, 3 if f == "mre" else 2) if m else "n/a"
                for _, f, k, _ in METRICS]
        extra = [_f(m.scatter * 1e3) if m else "n/a", _f(m.bias * 1e3) if m else "n/a"]
        ch = ["—" if a == result.baseline else _pct(scores.change[a][f]) for _, f, _, _ in METRICS]
        ch.append("—" if a == result.baseline else _pct(mean_change(scores, a)))
        n = m.n if m else 0
        total = result.frames * len(result.markers)
        note = f"{n}/{total}" + ("" if scores.complete[a] else " (markers missing)")
        rows.append([a, *vals, *ch, *extra, note])
    return header, rows


def marker_rows(result: RunResult, scores: Scores) -> tuple[list[str], list[list[str]]]:
    """One row per evaluated marker and algorithm."""
    header = ["Marker", "Algorithm", "n", *[f"{t} ({u})" for t, _, _, u in METRICS]]
    rows = []
    for mk in result.markers:
        for a in result.algorithms:
            m = scores.per_marker.get((a, mk))
            vals = ([_f(getattr(m, f) * k, 3 if f == "mre" else 2) for _, f, k, _ in METRICS]
                    if m else ["n/a"] * len(METRICS))
            rows.append([str(mk), a, str(result.n(a, mk)), *vals])
    return header, rows


def rejected_summary(result: RunResult) -> dict[str, list[tuple[int, float, float]]]:
    """algorithm -> [(reference id, median disagreement m, fraction of frames rejected)]."""
    out = {}
    for a, rej in result.rejected.items():
        items = [(i, float(np.median(d)), len(d) / max(result.frames, 1))
                 for i, d in sorted(rej.items()) if d]
        if items:
            out[a] = items
    return out


def summary_markdown(result: RunResult, scores: Scores | None = None,
                     per_marker: bool = True) -> str:
    """The Part's report: settings, the paper's table, rejections and per-marker metrics."""
    scores = scores or score(result)
    lines = [f"## {result.title}", ""]
    sets = ", ".join(f"{k} {v}" for k, v in result.settings.items())
    lines += [f"N = {result.frames} frames; evaluated markers "
              f"{', '.join(map(str, result.markers))}; baseline {result.baseline}.", "",
              f"Settings: {sets}.", ""]
    h, r = summary_rows(result, scores)
    lines += ["Averages over the evaluated markers (Δ = % change against "
              f"{result.baseline}; negative = smaller error):", "", _md_table(h, r), "",
              STD_NOTE, ""]
    rej = rejected_summary(result)
    if rej:
        lines.append("References rejected by the robust estimators (median disagreement "
                     "with the map, share of frames):")
        lines.append("")
        for a, items in rej.items():
            desc = ", ".join(f"{i}: {d * 1e3:.1f} mm ({100 * f:.0f} %)" for i, d, f in items)
            lines.append(f"- {a}: {desc}")
        lines.append("")
    missing = []
    for (a, m), reasons in sorted(result.failures.items()):
        if reasons:
            desc = ", ".join(f"{k} x{v}" for k, v in sorted(reasons.items()))
            missing.append(f"- {a}, marker {m}: {desc}")
    if missing:
        lines += ["Frames without an estimate:", "", *missing, ""]
    if per_marker:
        h, r = marker_rows(result, scores)
        lines += ["Per marker:", "", _md_table(h, r), ""]
    return "\n".join(lines)


_MODE_TEXT = {
    "plane-known": "every estimator is told the evaluated marker's plane (its surveyed "
                   "height; Part II: its support's), the marker left out of the references",
    "off-map": "the evaluated marker is removed from the estimators' map (no reference, no "
               "plane): what a newly laid marker or an unconfigured robot is",
}


def modes_markdown(results: dict[str, RunResult], per_marker: bool = True) -> str:
    """One Part in every evaluation mode, then the paper's table beside the project's."""
    from kmea.experiments.paper import PAPER_SETTINGS, comparison_markdown

    lines = []
    averages = {}
    for mode, result in results.items():
        sc = score(result)
        averages[mode] = sc.average
        lines += [f"Mode **{mode}**: {_MODE_TEXT.get(mode, mode)}.", "",
                  summary_markdown(result, sc, per_marker=per_marker)]
    first = next(iter(results.values()))
    comp = comparison_markdown(first.part, averages)
    if comp:
        lines += [f"### Part {first.part}: the paper's table beside the project's", "",
                  f"Paper: {PAPER_SETTINGS.get(first.part, '')}; real rig, IIR filter, 256 "
                  "samples per marker. The paper gave its KMEA no plane for the evaluated "
                  "marker: the off-map columns are the like-for-like ones.", "", comp, ""]
    return "\n".join(lines)


CSV_FIELDS = ["part", "algorithm", "marker", "n", "frames", "truth_x_m", "truth_y_m",
              "mean_x_m", "mean_y_m", "mean_z_m", "rmse_m", "std_m", "mae_m", "maxae_m",
              "mre_pct", "rejected_refs"]


def write_csv(result: RunResult, path: str | Path, scores: Scores | None = None) -> Path:
    """Per-marker metrics, one row per (algorithm, marker), metres (MRE in percent).

    ``rejected_refs``: references the algorithm rejected during the run, as
    ``id:median_disagreement_m:fraction_of_frames`` joined by ``;`` (robust estimators).
    Rows of markers without any sample have empty metric cells.
    """
    scores = scores or score(result)
    path = Path(path)
    rej = rejected_summary(result)
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(CSV_FIELDS)
        for a in result.algorithms:
            rej_s = ";".join(f"{i}:{d:.6f}:{fr:.3f}" for i, d, fr in rej.get(a, []))
            for mk in result.markers:
                m = scores.per_marker.get((a, mk))
                s = result.samples.get((a, mk), np.zeros((0, 2)))
                z = result.heights.get((a, mk), np.zeros(0))
                t = result.truth[mk]
                row = [result.part, a, mk, len(s), result.frames, repr(float(t[0])),
                       repr(float(t[1]))]
                if m is None:
                    row += [""] * 8
                else:
                    row += [repr(float(s[:, 0].mean())), repr(float(s[:, 1].mean())),
                            repr(float(z.mean())) if len(z) else "",
                            *(repr(float(getattr(m, f))) for f in
                              ("rmse", "std", "mae", "maxae", "mre"))]
                w.writerow([*row, rej_s])
    return path


def write_samples_csv(result: RunResult, path: str | Path) -> Path:
    """Every sample: part, algorithm, marker, k (sample index), x_m, y_m, z_m."""
    path = Path(path)
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["part", "algorithm", "marker", "k", "x_m", "y_m", "z_m"])
        for a in result.algorithms:
            for mk in result.markers:
                s = result.samples.get((a, mk), np.zeros((0, 2)))
                z = result.heights.get((a, mk), np.full(len(s), math.nan))
                for k in range(len(s)):
                    w.writerow([result.part, a, mk, k, repr(float(s[k, 0])),
                                repr(float(s[k, 1])), repr(float(z[k]))])
    return path
