#!/usr/bin/env python3
"""compare_arm64.py X86.csv ARM.csv: two kmead CSV logs of the same frames, row for row.

Rows are matched on (frame, kind, id). Both logs must have the same keys, every robot of the
run tracked (a ``robot`` row with a position) in both, and every number within these
tolerances (the two runs differ in CPU, and possibly in numpy and OpenCV builds: the
simulator's rendering and the estimators' floating point are then not bit-identical):

- positions ``x, y, z`` of markers and robots: :data:`POS_TOL_M`
- ``yaw``: :data:`YAW_TOL_RAD`
- ``error`` (a fit's residual or a rejected reference's distance, m): :data:`ERR_TOL_M`
- ``refs`` (references used) and ``algorithm``: equal
- ``timestamp`` (the simulator's clock): :data:`TIME_TOL_S`

Those are the floating point's scale, and all but a few values meet them. A corner found a
hundredth of a pixel apart (the CPUs' vector code rounds differently) can move one small
marker's pose, and through its robot's filter the next few poses, by far more: at most
:data:`OUTLIER_SHARE` of each column's values may exceed its tolerance, and none the
system's own noise (:data:`NOISE`: a robot marker's position noise is about 0.5 mm, its
heading's 10 mrad).

Prints one line per column with the largest difference found, then OK or what failed;
exit 0 when every check holds, 1 otherwise, 2 on unreadable input (one line naming the file).
"""

from __future__ import annotations

import csv
import math
import sys
from pathlib import Path

POS_TOL_M = 1e-6
YAW_TOL_RAD = 1e-5
ERR_TOL_M = 1e-6
TIME_TOL_S = 1e-6
TOLERANCES = {"timestamp": TIME_TOL_S, "x": POS_TOL_M, "y": POS_TOL_M, "z": POS_TOL_M,
              "yaw": YAW_TOL_RAD, "error": ERR_TOL_M}
HEADER = ["frame", "timestamp", "algorithm", "kind", "id", "x", "y", "z", "yaw", "error", "refs"]
OUTLIER_SHARE = 0.02
NOISE = {"timestamp": TIME_TOL_S, "x": 5e-4, "y": 5e-4, "z": 5e-4, "yaw": 1e-2, "error": 5e-4}
Key = tuple[int, str, str]


def load(path: Path) -> dict[Key, dict[str, str]]:
    try:
        with path.open(newline="") as f:
            rows = list(csv.reader(f))
    except OSError as e:
        raise SystemExit(f"compare_arm64: {path}: {e.strerror or e}") from None
    if not rows or rows[0] != HEADER:
        raise SystemExit(f"compare_arm64: {path}: not a kmead CSV log (header "
                         f"{','.join(HEADER)})")
    out: dict[Key, dict[str, str]] = {}
    for n, r in enumerate(rows[1:], start=2):
        if len(r) != len(HEADER):
            raise SystemExit(f"compare_arm64: {path}: line {n} has {len(r)} fields, not "
                             f"{len(HEADER)}")
        d = dict(zip(HEADER, r, strict=True))
        out[(int(d["frame"]), d["kind"], d["id"])] = d
    return out


def _num(s: str) -> float | None:
    return float(s) if s != "" else None


def tracked(rows: dict[Key, dict[str, str]]) -> dict[str, int]:
    """Robot name -> frames with a position."""
    out: dict[str, int] = {}
    for (_, kind, ident), d in rows.items():
        if kind == "robot" and d["x"] != "":
            out[ident] = out.get(ident, 0) + 1
    return out


def compare(a: dict[Key, dict[str, str]], b: dict[Key, dict[str, str]]) -> list[str]:
    """The failures (empty: the logs agree); prints the largest difference per column."""
    bad: list[str] = []
    only_a, only_b = sorted(a.keys() - b.keys()), sorted(b.keys() - a.keys())
    if only_a or only_b:
        bad.append(f"rows only in x86: {len(only_a)} {only_a[:3]}; only in arm64: "
                   f"{len(only_b)} {only_b[:3]}")
    worst = dict.fromkeys(TOLERANCES, (0.0, None))
    beyond = dict.fromkeys(TOLERANCES, 0)
    counted = dict.fromkeys(TOLERANCES, 0)
    for key in sorted(a.keys() & b.keys()):
        ra, rb = a[key], b[key]
        for col in ("algorithm", "refs"):
            if ra[col] != rb[col]:
                bad.append(f"{key}: {col} {ra[col]!r} vs {rb[col]!r}")
        for col, tol in TOLERANCES.items():
            u, v = _num(ra[col]), _num(rb[col])
            if (u is None) != (v is None):
                bad.append(f"{key}: {col} {ra[col]!r} vs {rb[col]!r}")
                continue
            if u is None or v is None:
                continue
            d = abs(u - v)
            if col == "yaw":
                d = abs(math.remainder(u - v, math.tau))
            if d > worst[col][0]:
                worst[col] = (d, key)
            counted[col] += 1
            beyond[col] += d > tol
            if d > NOISE[col]:
                bad.append(f"{key}: {col} differs by {d:.3g} (beyond the noise {NOISE[col]:g})")
    for col, (d, key) in worst.items():
        share = beyond[col] / max(counted[col], 1)
        print(f"  {col:9s} {beyond[col]} of {counted[col]} beyond {TOLERANCES[col]:g} "
              f"({share:.2%}); largest {d:.3g} (noise {NOISE[col]:g})"
              + (f" at frame {key[0]} {key[1]} {key[2]}" if key else ""))
        if share > OUTLIER_SHARE:
            bad.append(f"{col}: {share:.2%} of the values beyond {TOLERANCES[col]:g} "
                       f"(at most {OUTLIER_SHARE:.0%})")
    ta, tb = tracked(a), tracked(b)
    if len(ta) < 2 or ta != tb:
        bad.append(f"robots tracked (frames with a pose): x86 {ta}, arm64 {tb}; both robots "
                   "in both runs expected")
    return bad


def main(argv: list[str]) -> int:
    if len(argv) != 2:
        print("usage: compare_arm64.py X86.csv ARM.csv", file=sys.stderr)
        return 2
    a, b = load(Path(argv[0])), load(Path(argv[1]))
    frames = len({k[0] for k in a})
    print(f"compare x86 {argv[0]} with arm64 {argv[1]}: {len(a)} and {len(b)} rows, "
          f"{frames} frames; robots tracked {tracked(a)}")
    bad = compare(a, b)
    for line in bad[:20]:
        print(f"  DIFFERS {line}")
    if len(bad) > 20:
        print(f"  ... {len(bad) - 20} more")
    print("compare: OK, the same rows within the tolerances" if not bad else
          f"compare: {len(bad)} differences beyond the tolerances")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
