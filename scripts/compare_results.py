#!/usr/bin/env python3
"""compare_results.py A B: compare two ``results_fingerprint.sh`` outputs file by file.

Prints, per file of A: ``identical``; for CSVs, how many cells differ and the largest absolute
difference (with its column and row) plus how many differing cells are not numbers; for other
text files, the lines that differ. Exit status 0 when every file is identical, else 1.
"""

from __future__ import annotations

import csv
import difflib
import sys
from pathlib import Path


def compare_csv(pa: Path, pb: Path) -> str:
    ra = list(csv.reader(pa.open()))
    rb = list(csv.reader(pb.open()))
    if len(ra) != len(rb):
        return f"row count differs: {len(ra)} vs {len(rb)}"
    head = ra[0]
    worst, where, nonnum, ncell = 0.0, None, 0, 0
    for x, y in zip(ra[1:], rb[1:], strict=True):
        for k, (u, v) in enumerate(zip(x, y, strict=False)):
            if u == v:
                continue
            ncell += 1
            try:
                d = abs(float(u) - float(v))
            except ValueError:
                nonnum += 1
                continue
            if d > worst:
                worst, where = d, (head[k] if k < len(head) else k, x[:4])
    return f"{ncell} cells differ, max |diff| {worst:.3g} at {where}, non-numeric {nonnum}"


def main(a: Path, b: Path) -> int:
    same = True
    for pa in sorted(p for p in a.rglob("*") if p.is_file() and "frames" not in p.parts):
        rel = pa.relative_to(a)
        pb = b / rel
        if not pb.exists():
            print(f"{rel}: missing in {b}")
            same = False
        elif pa.read_bytes() == pb.read_bytes():
            print(f"{rel}: identical")
        else:
            same = False
            if pa.suffix == ".csv":
                print(f"{rel}: {compare_csv(pa, pb)}")
            else:
                print(f"{rel}: differs")
                diff = difflib.unified_diff(pa.read_text().splitlines(),
                                            pb.read_text().splitlines(), lineterm="", n=0)
                for line in list(diff)[2:]:
                    if not line.startswith("@@"):
                        print(f"    {line}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main(Path(sys.argv[1]), Path(sys.argv[2])))
