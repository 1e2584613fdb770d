"""What each mechanism of the tracking filter buys, on the held-out sets: each removed alone.

Every row is the shipped filter (``TUNED``) with one mechanism taken out, run on all
held-out motion sets together (5 % of the measurements replaced by jumps of 5-20 cm), beside
the filter with everything on and the paper's IIR filter. Columns: outlier-caused output
jumps above 3 sigma (of all outliers) and the largest in sigmas (against the same drive
without outliers), the position and heading RMSE, good measurements rejected, the slowest
re-acquisition after a kidnap, and the lag. The filter's requirement: at most 1 in 1,000
outliers moves the output by more than 3 sigma, none by more than 10 sigma, at a lag no
larger than the IIR filter's. Prints figures; no asserts.

    kmea bench tracking-ablation [--jobs 2] [--variants shipped,...]
"""

from __future__ import annotations

import argparse
import multiprocessing
import time

from kmea.benchmarks.tracking import HELD_OUT, TUNED, aggregate, drive_metrics

#: name -> the configuration changes that remove the mechanism (none for the shipped
#: filter). The re-acquisition rules (a chain broken by an outlier kept; a measurement
#: inside the gate that fits the chain better joins it) have no setting: their ablation,
#: and that of the mechanisms removed after it, is in docs/history/tracking-rounds.md.
VARIANTS: dict[str, dict] = {
    "shipped": {},
    "- step bound (step_k 1e9)": {"step_k": 1e9},
    "- IMM (one mode)": {"manoeuvre_scale": 1.0},
    "- outlier mixture (prior 1e-6)": {"outlier_probability": 1e-6},
    "- re-acquisition (reacquire_n 1e9)": {"reacquire_n": 10 ** 9},
}
IIR_ALPHA = 0.6


def _one(args: tuple[str, int]) -> tuple[str, list[dict]]:
    name, i = args
    mset = HELD_OUT[i]
    if name == "iir":
        return name, drive_metrics(mset, "iir", IIR_ALPHA)
    return name, drive_metrics(mset, "kalman", TUNED.with_(**VARIANTS[name]))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="kmea bench tracking-ablation",
                                description=(__doc__ or "").split("\n\n")[0])
    p.add_argument("--jobs", type=int, default=1)
    p.add_argument("--variants", default="all",
                   help="comma-separated names of VARIANTS (default: all of them)")
    args = p.parse_args(argv)
    names = list(VARIANTS) if args.variants == "all" else args.variants.split(",")
    names = [*names, "iir"]
    work = [(n, i) for n in names for i in range(len(HELD_OUT))]
    t0 = time.perf_counter()
    rows: dict[str, list[dict]] = {n: [] for n in names}
    with multiprocessing.Pool(args.jobs) as pool:
        for name, r in pool.imap_unordered(_one, work):
            rows[name] += r
    print(f"held-out sets: {', '.join(s.name.removeprefix('held-out ') for s in HELD_OUT)}"
          f" ({sum(len(s.seeds) for s in HELD_OUT)} drives); {time.perf_counter() - t0:.0f} s")
    print("| filter | caused jumps > 3 sigma | largest (sigma) | position RMSE mm "
          "| heading RMSE deg | good rejected | re-acquired (slowest s) | lag ms |")
    print("|---|---|---|---|---|---|---|---|")
    for n in names:
        a = aggregate(rows[n])
        label = f"IIR alpha {IIR_ALPHA}" if n == "iir" else n
        print(f"| {label} | {a['caused_big']}/{a['outliers']} | {a['caused_max_sig']:.1f} "
              f"| {a['pos'] * 1e3:.2f} | {a['head'] * 57.29578:.2f} | {a['false_rej']} "
              f"| {a['reacquired']}/{a['drives']} ({_slowest(rows[n])}) "
              f"| {abs(a['lag']) * 1e3:.0f} |")
    return 0


def _slowest(rows: list[dict]) -> str:
    """The slowest re-acquisition after the kidnap among the drives that re-acquired (a
    track that walked over without a restart has none)."""
    times = [r["reacquire_s"] for r in rows if r["reacquire_s"] == r["reacquire_s"]]
    return f"{max(times):.2f}" if times else "-"


if __name__ == "__main__":
    raise SystemExit(main())
