"""The SD card survives the week: the CSV log goes on in parts, and kmead's own files beyond
log.keep_days / log.keep_mb are removed oldest first, never a user's file or one being
written (real files, real recordings, the real daemon)."""

from __future__ import annotations

import os
import time
from pathlib import Path

from kmead.config.layers import load_config
from kmead.outputs.csvlog import HEADER
from kmead.outputs.datadir import DataDir
from kmead.outputs.files import FileOutputs
from kmead.outputs.retention import kmea_files, prune, usage
from kmead.outputs.totals import RunTotals

DAY = 86400.0
NET = ["--set", 'network.telemetry="tcp://127.0.0.1:*"',
       "--set", 'network.control="tcp://127.0.0.1:*"']


def _csv(path: Path, kb: int, age_days: float, now: float) -> Path:
    path.write_text(HEADER + "\n" + ("1,0.0,kmea,marker,5,0,0,0,0,,4\n" * (kb * 1000 // 32)))
    os.utime(path, (now - age_days * DAY, now - age_days * DAY))
    return path


def test_only_kmeads_own_files_go_the_oldest_first(tmp_path: Path) -> None:
    now = time.time()
    old = _csv(tmp_path / "kmea-20261101.csv", 10, 30, now)
    mid = _csv(tmp_path / "kmea-20261201.csv", 400, 5, now)
    new = _csv(tmp_path / "kmea-20261206.csv", 400, 1, now)
    active = _csv(tmp_path / "kmea-now.csv", 400, 0, now)
    users = tmp_path / "results.csv"  # the user's own CSV, old and large
    users.write_text("a,b\n" + "1,2\n" * 300_000)
    os.utime(users, (now - 90 * DAY, now - 90 * DAY))
    shot = tmp_path / "snapshot-1.png"
    shot.write_bytes(b"\x89PNG" + b"0" * 1000)
    os.utime(shot, (now - 20 * DAY, now - 20 * DAY))
    other = tmp_path / "notes.txt"
    other.write_text("keep me")
    assert {f.path.name for f in kmea_files([tmp_path])} == {
        old.name, mid.name, new.name, active.name, shot.name}
    # By age: the 30- and 20-day-old files; by size: then the oldest until <= 1 MB.
    removed = prune([tmp_path], keep_days=14, keep_mb=1.0, active=[active], now=now)
    assert [f.path.name for f in removed] == [old.name, shot.name, mid.name]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        [new.name, active.name, users.name, other.name])
    # The one being written is never removed, even alone beyond the limit.
    assert prune([tmp_path], keep_days=0.01, keep_mb=0.1, active=[active, new],
                 now=now + 10 * DAY) == []
    u = usage([tmp_path], now=now)
    assert u.files == 2 and 0.7e6 < u.bytes < 0.9e6 and 0.9 < (u.oldest_days or 0) < 1.1


def test_the_csv_log_goes_on_in_parts_each_with_its_header(tmp_path: Path) -> None:
    cfg = load_config(None, ["log.part_mb=1", "log.keep_days=0", "log.keep_mb=0"],
                      use_local=False)
    events: list[tuple[str, str]] = []
    files = FileOutputs(cfg["log"], DataDir(str(tmp_path)), RunTotals(),
                        lambda level, text: events.append((level, text)))
    files.start_csv(str(tmp_path / "run.csv"))
    row = "7,1764000000.000000,kmea,marker,5,0.1,0.2,0.0,0.0,0.0001,4\n"
    for _ in range(30):
        files.write_csv([row] * 1000)  # 30 frames of ~58 kB: about 1.7 MB
    files.close()
    parts = [tmp_path / "run.csv", tmp_path / "run-part2.csv"]
    assert set(tmp_path.glob("run*.csv")) == set(parts)
    for p in parts:
        lines = p.read_text().splitlines()
        assert lines[0] == HEADER and lines[1:] and all(r == row.strip() for r in lines[1:])
    assert parts[0].stat().st_size < 1e6 + 60_000  # cut at the first frame past 1 MB
    assert sum(len(p.read_text().splitlines()) - 1 for p in parts) == 30_000


def test_the_daemon_removes_old_logs_where_it_writes_at_start(tmp_path: Path) -> None:
    from kmead import cli

    now = time.time()
    logs = tmp_path / "logs"
    logs.mkdir()
    stale = _csv(logs / "kmea-20261001-101010.csv", 5, 40, now)
    recent = _csv(logs / "kmea-20261205-101010.csv", 5, 2, now)
    users = logs / "mine.csv"
    users.write_text("x,y\n1,2\n")
    os.utime(users, (now - 100 * DAY, now - 100 * DAY))
    assert cli.main(["--headless", "--frames", "3", "--log", str(logs / "run.csv"),
                     "--set", "source.width=320", "--set", "source.height=240",
                     "--set", "source.fps=0", "--set", f'log.dir="{tmp_path}"', *NET]) == 0
    assert not stale.exists() and recent.exists() and users.exists()
    assert (logs / "run.csv").read_text().startswith(HEADER)
