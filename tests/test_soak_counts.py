"""The soak benchmark's datagram bookkeeping (benchmarks/soak.py): gaps, repeats, junk."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

SOAK = Path(__file__).resolve().parents[1] / "benchmarks" / "soak.py"


def _soak():
    spec = importlib.util.spec_from_file_location("soak_bench", SOAK)
    assert spec and spec.loader
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up there
    spec.loader.exec_module(mod)
    return mod


def test_counts_missing_and_repeated_seq_and_the_longest_valid_gap() -> None:
    soak = _soak()
    c = soak.RobotCount()
    for seq, t, valid in [(1, 0.0, 1), (2, 0.1, 1), (5, 0.2, 1), (5, 0.3, 1), (6, 0.9, 1),
                          (7, 5.0, 0)]:
        c.take(f"name=amr1;seq={seq};t=1.0;x=0;y=0;theta=0;valid={valid}".encode(), t)
    c.take(b"\xff\xfe", 6.0)
    c.take(b"no fields here", 6.0)
    assert (c.datagrams, c.valid, c.gaps, c.repeats, c.bad) == (6, 5, 2, 1, 2)
    # 0.3 -> 0.9 between valid datagrams; the stop message 4 s later is not a gap in service
    assert abs(c.longest_gap_s - 0.6) < 1e-9


def test_parses_the_relay_datagram_and_refuses_other_text() -> None:
    soak = _soak()
    assert soak.parse_datagram(b"name=amr2;seq=3;valid=1") == {
        "name": "amr2", "seq": "3", "valid": "1"}
    assert soak.parse_datagram(b"seq=3;;valid=1") is None
