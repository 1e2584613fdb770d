"""Recordings (kmea/recordings/format.py, kmea/recordings/recfile.py): the compressed
format, a file cut at any byte, the first format's files, and a recording cut into parts by
the daemon.

Real files throughout; frames from the real pipeline on the simulated floor."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import zstandard

from kmea.pipeline import FrameInput, Pipeline, PipelineSettings
from kmea.recordings.format import Recorder, read_header
from kmea.sources.base import SourceError
from kmea.sources.registry import open_source
from kmea.sources.replay import ReplaySource

DATA = Path(__file__).parent / "data"
NET = ["--set", 'network.telemetry="tcp://127.0.0.1:*"',
       "--set", 'network.control="tcp://127.0.0.1:*"']
SMALL = ["--set", "source.width=640", "--set", "source.height=480", "--set", "source.fps=0"]


@pytest.fixture(scope="module")
def frames():
    """Six processed frames of the simulated floor (the pipeline's results)."""
    with open_source("sim:default?width=640&height=480", frames=6) as src:
        p = Pipeline(src.camera, src.world_map,
                     PipelineSettings(robots=tuple(src.scene.robot_specs())))
        results = [p.process(FrameInput(f.index, f.timestamp, f.image)) for f in src]
        return results, src.camera, src.world_map


def _record(path: Path, frames) -> list[int]:
    """Write the frames; the file's size after each one (where each frame's flush ends)."""
    results, camera, world_map = frames
    rec = Recorder(path, camera, world_map, "sim:default", {"robots": []})
    ends = [rec.bytes]
    for r in results:
        rec.write_frame(r.index, r.timestamp, r.ids, r.corners, r.observations, r.diagnostics)
        ends.append(rec.bytes)
    rec.close()
    return ends


def _replayed(path: Path) -> tuple[list, bool]:
    src = ReplaySource(path)
    try:
        got = list(src)
    finally:
        src.close()
    return got, src.truncated


def _same_observations(a, b) -> None:
    assert [o.id for o in a] == [o.id for o in b]
    for x, y in zip(a, b, strict=True):
        for f in ("marker2cam_R", "marker2cam_t", "corners"):
            assert np.array_equal(getattr(x, f), getattr(y, f)), f
        assert (x.reproj_error, x.alt_reproj_error, x.ambiguous, x.flipped, x.suspect) == \
            (y.reproj_error, y.alt_reproj_error, y.ambiguous, y.flipped, y.suspect)


@pytest.mark.parametrize("name", ["run.jsonl", "run.jsonl.zst"])
def test_frames_read_back_bit_identical(tmp_path: Path, frames, name: str) -> None:
    path = tmp_path / name
    _record(path, frames)
    raw = path.read_bytes()
    # The compressed file is a plain zstd stream of the same JSON lines (zstdcat reads it).
    text = (zstandard.ZstdDecompressor().decompressobj().decompress(raw)
            if name.endswith(".zst") else raw)
    assert raw.startswith(b"\x28\xb5\x2f\xfd") == name.endswith(".zst")
    lines = text.decode().splitlines()
    assert json.loads(lines[0])["version"] == 2 and len(lines) == 7
    # Version 2 does not repeat a marker's corners (they are its detection's), nor keep the
    # other IPPE pose (nothing reads it).
    markers = [m for line in lines[1:] for m in json.loads(line)["markers"]]
    assert not any({"corners", "alt_R", "alt_t"} & set(m) for m in markers)
    got, cut = _replayed(path)
    assert not cut and len(got) == 6
    for r, f in zip(frames[0], got, strict=True):
        ids, corners, obs, _diag = f.meta["replay"]
        assert f.index == r.index and f.timestamp == r.timestamp
        assert np.array_equal(ids, r.ids) and np.array_equal(corners, r.corners)
        _same_observations(obs, r.observations)


def test_a_compressed_recording_cut_at_any_byte_replays_its_whole_frames(
        tmp_path: Path, frames) -> None:
    """What a kill leaves: any prefix of the file. Every frame flushed before the cut reads
    back whole and identical; nothing after it, no error, never a broken frame."""
    whole = tmp_path / "run.jsonl.zst"
    ends = _record(whole, frames)
    data = whole.read_bytes()
    full, _ = _replayed(whole)
    cut = tmp_path / "cut.jsonl.zst"
    # Every flush boundary and its neighbours, and a stride through everything between.
    points = sorted({e + d for e in ends for d in (-1, 0, 1)} | set(range(ends[0], len(data), 97)))
    for n in points:
        if not ends[0] <= n <= len(data):
            continue
        cut.write_bytes(data[:n])
        got, truncated = _replayed(cut)
        assert truncated == (n < len(data)), n  # a cut is said, even between two frames
        flushed = sum(1 for e in ends[1:] if e <= n)
        assert len(got) >= flushed, f"cut at {n}: {len(got)} frames, {flushed} flushed"
        for a, b in zip(got, full, strict=False):
            assert "error" not in a.meta, (n, a.meta)
            assert a.index == b.index
            _same_observations(a.meta["replay"][2], b.meta["replay"][2])
    # Cut inside the header: not a recording, one line naming the file.
    cut.write_bytes(data[:ends[0] // 2])
    with pytest.raises(SourceError, match=r"cut\.jsonl\.zst: line 1"):
        ReplaySource(cut)


def test_a_killed_daemon_leaves_a_compressed_recording_that_replays(tmp_path: Path) -> None:
    rec = tmp_path / "run.jsonl.zst"
    p = subprocess.Popen([sys.executable, "-m", "kmead.cli", "--headless", "--record", str(rec),
                          *SMALL[:4], "--set", "source.fps=15", *NET], cwd=tmp_path,
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        end = time.monotonic() + 60
        while time.monotonic() < end:
            if rec.exists() and rec.stat().st_size > 4000:
                lines = zstandard.ZstdDecompressor().decompressobj().decompress(
                    rec.read_bytes()).count(b"\n")
                if lines > 20:
                    break
            assert p.poll() is None, p.communicate()
            time.sleep(0.1)
        p.kill()
        p.communicate(timeout=20)
    finally:
        if p.poll() is None:
            p.kill()
            p.communicate()
    got, _ = _replayed(rec)
    assert len(got) >= 20 and all("replay" in f.meta for f in got)
    index = [f.index for f in got]  # a live source may skip frames when the CPU is busy
    assert index == sorted(set(index))


def test_a_version_1_recording_still_replays_to_its_rows(tmp_path: Path) -> None:
    """tests/data/recording_v1.jsonl: two frames written by the first format's writer
    (every marker's corners, every flag), with the CSV log of that run.

    Marker rows and the first frame's robot rows come from the recording alone and
    must match exactly. A later robot row is the tracking filter's output, and the
    filter has changed since that run (a new track now takes its velocity from its
    first two measurements), so it is held to the recorded pose within 1 mm and 2 deg."""
    from kmead import cli

    assert read_header(DATA / "recording_v1.jsonl")["version"] == 1
    shutil.copy(DATA / "recording_v1.jsonl", tmp_path)
    out = tmp_path / "again.csv"
    assert cli.main(["--source", f"replay:{tmp_path / 'recording_v1.jsonl'}", "--headless",
                     "--log", str(out), *NET]) == 0
    got = out.read_text().splitlines()
    want = (DATA / "recording_v1.csv").read_text().splitlines()
    assert got[0] == want[0] and len(got) == len(want)
    filtered = 0
    for g, w in zip(got[1:], want[1:], strict=True):
        gf, wf = g.split(","), w.split(",")
        if wf[3] == "marker" or wf[0] == "0":
            assert g == w
            continue
        filtered += 1
        assert gf[:5] == wf[:5] and gf[9:] == wf[9:]
        xyz = np.array(gf[5:8], float) - np.array(wf[5:8], float)
        assert np.linalg.norm(xyz) < 1e-3, (g, w)
        dyaw = (float(gf[8]) - float(wf[8]) + np.pi) % (2 * np.pi) - np.pi
        assert abs(dyaw) < np.radians(2.0), (g, w)
    assert filtered == 2


def test_corrupt_compressed_bytes_are_one_line_naming_the_file(tmp_path: Path, frames) -> None:
    path = tmp_path / "run.jsonl.zst"
    ends = _record(path, frames)
    data = bytearray(path.read_bytes())
    for i in range(ends[2], ends[3]):
        data[i] ^= 0x5A
    path.write_bytes(bytes(data))
    src = ReplaySource(path)
    try:
        with pytest.raises(SourceError, match=r"run.jsonl.zst: after line \d+: corrupt") as e:
            list(src)
        assert "\n" not in str(e.value)
    finally:
        src.close()


def test_the_daemon_cuts_a_recording_into_parts_that_each_replay(tmp_path: Path) -> None:
    """log.part_mb: new files with new names (an existing name is skipped, never
    written over), each with its own header; together every frame, in order."""
    from kmead import cli

    rec = tmp_path / "run.jsonl"  # plain: 1 MB (the smallest part) is ~30 frames
    (tmp_path / "run-part2.jsonl").write_text("someone else's file\n")
    assert cli.main(["--headless", "--frames", "90", "--record", str(rec), *SMALL,
                     "--set", "detector.fixed_camera=false", "--set", "log.part_mb=1",
                     *NET]) == 0
    assert (tmp_path / "run-part2.jsonl").read_text() == "someone else's file\n"
    parts = [rec, *sorted(tmp_path.glob("run-part[3-9].jsonl"))]
    assert len(parts) >= 2
    indices = []
    for k, part in enumerate(parts):
        head = read_header(part)
        if k:
            assert head["part"] == k + 2 and head["previous"] == parts[k - 1].name
        assert part.stat().st_size < 1e6 + 60_000  # one frame past the limit at most
        got, cut = _replayed(part)
        assert not cut and got
        indices += [f.index for f in got]
    assert indices == list(range(90))


def test_part_limits_are_off_or_physical(tmp_path: Path) -> None:
    from kmead.config.layers import ConfigError, load_config

    cfg = load_config(None, ["log.part_mb=0", "log.part_min=0"])
    assert cfg["log"]["part_mb"] == 0 and cfg["log"]["part_min"] == 0
    for bad in ("log.part_mb=0.001", "log.part_min=0.01",
                "log.part_mb=-1", "log.snapshots_max=-1"):
        with pytest.raises(ConfigError) as e:
            load_config(None, [bad])
        assert bad.split("=")[0] in str(e.value) and "\n" not in str(e.value)


def test_a_part_is_due_by_size_or_by_age(tmp_path: Path, frames) -> None:
    """log.part_mb / _min against a real recorder (its bytes on disk, its start)."""
    from kmead.outputs.datadir import DataDir
    from kmead.outputs.files import FileOutputs
    from kmead.outputs.totals import RunTotals

    _, camera, world_map = frames
    rec = Recorder(tmp_path / "run.jsonl.zst", camera, world_map, "sim", {})
    try:
        log_cfg = {"part_mb": 1.0, "part_min": 1.0, "min_free_mb": 0.0}
        files = FileOutputs(log_cfg, DataDir(str(tmp_path)), RunTotals(), lambda *a: None)
        files.recorder = rec
        assert files._part_due() is None
        rec.started -= 61.0  # as if started a minute and a second ago
        assert files._part_due() == "log.part_min = 1 min reached"
        log_cfg["part_min"] = 0.0  # off
        assert files._part_due() is None
        log_cfg["part_mb"] = rec.bytes / 1e6  # its size now
        assert files._part_due() == f"log.part_mb = {rec.bytes / 1e6:g} MB reached"
    finally:
        rec.close()


def test_a_full_disk_leaves_a_compressed_recording_of_whole_frames(
        tmp_path: Path, frames, monkeypatch: pytest.MonkeyPatch) -> None:
    """The write that fills the disk is cut back to the last whole frame; the recording
    then stops, closed without its end mark, and replays every frame it counted."""
    from test_kmead_faults import Disk, FullingFile

    from kmea.recordings import wholewrite

    disk = Disk(0)
    real_open = wholewrite.open_output
    monkeypatch.setattr(wholewrite, "open_output",
                        lambda path, append=False: FullingFile(real_open(path, append), disk))
    results, camera, world_map = frames
    path = tmp_path / "run.jsonl.zst"
    disk.free = 10**9
    rec = Recorder(path, camera, world_map, "sim", {})
    disk.free = 2 * (rec.bytes + 1000)  # room for a frame or so more, never all six
    with pytest.raises(OSError):
        for r in results:
            rec.write_frame(r.index, r.timestamp, r.ids, r.corners, r.observations,
                            r.diagnostics)
    rec.close()
    assert disk.partial_writes == 1 and path.stat().st_size == rec.bytes
    got, truncated = _replayed(path)
    assert truncated and len(got) == rec.frames < len(results)
    assert [f.index for f in got] == [r.index for r in results[:rec.frames]]


def test_the_readmes_record_then_replay_example_gives_the_same_rows(tmp_path: Path) -> None:
    """README, "Examples": a live run recorded with every frame detected in full replays to
    the same CSV rows, row for row (markers, robots, their times)."""
    from kmead import cli

    assert cli.main(["--headless", "--frames", "40", "--set", "detector.fixed_camera=false",
                     "--record", str(tmp_path / "run.jsonl.zst"), "--log",
                     str(tmp_path / "run.csv"), *SMALL[:4], *NET]) == 0
    assert cli.main(["--source", f"replay:{tmp_path / 'run.jsonl.zst'}", "--headless",
                     "--log", str(tmp_path / "again.csv"), *NET]) == 0
    run = (tmp_path / "run.csv").read_text().splitlines()
    again = (tmp_path / "again.csv").read_text().splitlines()
    assert len(run) > 40 and any(",robot," in r for r in run)
    assert again == run
