"""``kmea bench soak`` (kmead/benchmarks/soak.py): its datagram bookkeeping and its /proc
parsing (not its timing)."""

from __future__ import annotations

import os
import socket
import threading
from pathlib import Path

import pytest

from kmead.benchmarks import soak
from kmead.outputs.relay import datagram


def test_seq_gaps_missing_reordering_and_the_longest_silence() -> None:
    r = soak.RobotStats()
    # (seq, valid, arrival s): 4 is lost, 7 and 8 are lost, 9 arrives before 10's late twin.
    for seq, valid, t in [(1, True, 0.0), (2, True, 0.033), (3, True, 0.066), (5, True, 0.133),
                          (6, False, 0.166), (9, True, 0.5), (8, True, 0.51), (10, True, 0.54)]:
        r.add(seq, valid, t)
    assert (r.count, r.valid) == (8, 7)
    assert (r.gaps, r.missing) == (2, 3)  # 4; 7 and 8 (8 came later, out of order)
    assert r.out_of_order == 1
    assert r.longest_s == pytest.approx(0.334) and r.longest_at == 0.5


def test_the_exit_summary_gives_frames_dropped_and_bad() -> None:
    text = ("kmead summary: 1678 frames in 116.1 s (14.4 frames/s), source sim, algorithm x\n"
            "  dropped frames: 11, bad frames: 0, not estimated: 0\n")
    assert soak.summary_counts(text) == {"frames": 1678, "dropped": 11, "bad": 0}
    assert soak.summary_counts("kmead: key 'x': bad\n") == {}


def test_rss_from_proc_status_text_and_from_this_process() -> None:
    text = "Name:\tkmead\nVmPeak:\t  500000 kB\nVmRSS:\t  123456 kB\nThreads:\t9\n"
    assert soak.rss_kb(text) == 123456
    assert soak.rss_kb("Name:\tzombie\n") is None
    if Path("/proc/self/status").exists():
        assert soak._rss(os.getpid()) > 1000  # kB: this Python process


def test_per_hour() -> None:
    assert soak.per_hour(1_000_000, 60.0) == pytest.approx(60_000_000)
    assert soak.per_hour(5, 0.0) == 0.0


def test_the_listener_counts_real_datagrams_from_the_relays_format() -> None:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    listener = soak.Listener(s)
    stop = threading.Event()
    t = threading.Thread(target=listener.run, args=(stop,))
    t.start()
    try:
        out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        for seq in (1, 2, 4):
            out.sendto(datagram("amr1", seq, 1764060000.0 + seq, 0.1, 0.2, 0.3, True),
                       s.getsockname())
        out.sendto(b"not a datagram", s.getsockname())
        out.close()
        deadline = threading.Event()
        for _ in range(300):  # up to 30 s
            if listener.robots.get("amr1") and listener.robots["amr1"].count == 3 \
                    and listener.bad == 1:
                break
            deadline.wait(0.1)
    finally:
        stop.set()
        t.join()
        s.close()
    r = listener.robots["amr1"]
    assert (r.count, r.gaps, r.missing, listener.bad) == (3, 1, 1, 1)
