"""The paper's figures for one Part (needs the ``plots`` extra: matplotlib, imported lazily).

- ``part-X-bars-<metric>.png``: per-marker bars of one metric, one bar per algorithm;
- ``part-X-scatter.png``: every estimate of every evaluated marker against the truth;
- ``part-X-zoom-<id>.png``: one marker's estimates with 3-sigma confidence ellipses.

Plots show millimetres (for people); the world frame is x right, y up.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from kmea.experiments.run import RunResult
from kmea.experiments.tables import METRICS, Scores, score

__all__ = ["confidence_ellipse", "have_matplotlib", "write_plots"]


def have_matplotlib() -> bool:
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        return False
    return True


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")  # files only; never open a window
    import matplotlib.pyplot as plt

    return plt


def confidence_ellipse(points: np.ndarray, n_sigma: float = 3.0,
                       samples: int = 100) -> np.ndarray | None:
    """(samples, 2) outline of the ``n_sigma`` ellipse of the points' sample covariance
    (same units as the points), or None with fewer than 3 points or a singular covariance."""
    p = np.asarray(points, dtype=float).reshape(-1, 2)
    if len(p) < 3:
        return None
    c = np.cov(p.T)
    w, V = np.linalg.eigh(c)
    if not np.all(np.isfinite(w)) or w.max() <= 0:
        return None
    w = np.clip(w, 0.0, None)
    t = np.linspace(0.0, 2.0 * np.pi, samples)
    unit = np.stack([np.cos(t), np.sin(t)], axis=1)
    return p.mean(axis=0) + n_sigma * (unit * np.sqrt(w)) @ V.T


def _colors(n: int) -> list:
    plt = _pyplot()
    cmap = plt.get_cmap("tab10")
    return [cmap(i % 10) for i in range(n)]


def pick_zoom_marker(result: RunResult, scores: Scores) -> int:
    """The marker with the largest spread of the most scattered algorithm (the most telling
    zoom); the first marker if none has samples."""
    best, best_v = result.markers[0], -1.0
    for (_, m), mm in scores.per_marker.items():
        if mm.std == mm.std and mm.std > best_v:
            best, best_v = m, mm.std
    return best


def write_plots(result: RunResult, out_dir: str | Path, scores: Scores | None = None,
                zoom_marker: int | None = None) -> list[Path]:
    """Write the Part's PNGs into ``out_dir``; returns their paths."""
    plt = _pyplot()
    scores = scores or score(result)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    stem = f"part-{result.part}"
    algs = list(result.algorithms)
    colors = dict(zip(algs, _colors(len(algs)), strict=True))
    paths: list[Path] = []

    # Per-marker bars, one figure per metric.
    x = np.arange(len(result.markers))
    width = 0.8 / max(len(algs), 1)
    for title, fieldname, k, unit in METRICS:
        fig, ax = plt.subplots(figsize=(max(6.0, 0.7 * len(x) + 2), 4.0))
        for j, a in enumerate(algs):
            vals = [getattr(scores.per_marker[(a, m)], fieldname) * k
                    if (a, m) in scores.per_marker else np.nan for m in result.markers]
            ax.bar(x + (j - (len(algs) - 1) / 2) * width, vals, width, label=a, color=colors[a])
        ax.set_xticks(x, [str(m) for m in result.markers])
        ax.set_xlabel("marker id")
        ax.set_ylabel(f"{title} ({unit})")
        ax.set_title(f"Part {result.part}: {title} per marker")
        if any(v > 0 for a in algs for v in _finite(scores, a, result.markers, fieldname)):
            ax.set_yscale("log")
        ax.legend(fontsize="small", ncols=min(len(algs), 5), loc="upper center",
                  bbox_to_anchor=(0.5, -0.2), frameon=False)
        ax.grid(axis="y", alpha=0.3)
        paths.append(_save(plt, fig, out / f"{stem}-bars-{fieldname}.png"))

    # All estimates against the truth (metres on the floor).
    fig, ax = plt.subplots(figsize=(7.5, 5.6))
    for a in algs:
        pts = [result.samples[(a, m)] for m in result.markers if len(result.samples[(a, m)])]
        if pts:
            p_all = np.concatenate(pts)
            ax.scatter(p_all[:, 0], p_all[:, 1], s=4, alpha=0.5, color=colors[a], label=a)
    tr = np.array([result.truth[m] for m in result.markers])
    ax.scatter(tr[:, 0], tr[:, 1], marker="+", s=80, color="k", label="truth")
    for m in result.markers:
        tx, ty = result.truth[m][:2]
        ax.annotate(str(m), (tx, ty), textcoords="offset points", xytext=(5, 5), fontsize=8)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"Part {result.part}: estimates against the truth")
    ax.legend(fontsize="small", markerscale=3)
    ax.grid(alpha=0.3)
    paths.append(_save(plt, fig, out / f"{stem}-scatter.png"))

    # One marker, zoomed, with 3-sigma ellipses; millimetres relative to the truth.
    m = pick_zoom_marker(result, scores) if zoom_marker is None else zoom_marker
    fig, ax = plt.subplots(figsize=(6.0, 5.6))
    t = result.truth[m]
    for a in algs:
        s = result.samples.get((a, m), np.zeros((0, 2)))
        if not len(s):
            continue
        d = (s - t) * 1e3
        ax.scatter(d[:, 0], d[:, 1], s=6, alpha=0.6, color=colors[a], label=a)
        ell = confidence_ellipse(d, 3.0)
        if ell is not None:
            ax.plot(ell[:, 0], ell[:, 1], color=colors[a], lw=1.2)
    ax.scatter([0], [0], marker="+", s=120, color="k", label="truth")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x - x_true (mm)")
    ax.set_ylabel("y - y_true (mm)")
    ax.set_title(f"Part {result.part}: marker {m}, 3-sigma ellipses")
    ax.legend(fontsize="small", markerscale=2)
    ax.grid(alpha=0.3)
    paths.append(_save(plt, fig, out / f"{stem}-zoom-{m}.png"))
    return paths


def _save(plt, fig, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _finite(scores: Scores, a: str, markers, fieldname: str) -> list[float]:
    vals = [getattr(scores.per_marker[(a, m)], fieldname)
            for m in markers if (a, m) in scores.per_marker]
    return [v for v in vals if v == v]
