"""The confined data directory (kmead.outputs.datadir) and JSON with limits
(kmea.wire.jsonlimits)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from kmea.wire.jsonlimits import JsonLimitError, json_depth, safe_loads
from kmead.outputs.datadir import DataDir, FileRefused


def _listing(root: Path) -> set[str]:
    return {str(p.relative_to(root)) for p in root.rglob("*")}


def test_plain_new_names_are_created_in_the_data_directory(tmp_path: Path) -> None:
    d = DataDir(tmp_path / "data")
    p = d.create("run-1.csv", "log")
    assert p == (tmp_path / "data" / "run-1.csv").resolve() and p.read_bytes() == b""
    assert d.create("rec_2.jsonl", "record").exists()


@pytest.mark.parametrize("name, why", [
    ("/etc/passwd.csv", "plain file name"),
    ("../out.csv", "plain file name"),
    ("..csv", "'..'"),
    ("sub/x.csv", "plain file name"),
    ("a\\b.csv", "plain file name"),
    (".bashrc.csv", "not starting with '.'"),
    ("x.txt", "must end with .csv"),
    (".csv", "not starting with '.'"),
    ("x" * 200 + ".csv", "at most 128"),
    ("nul\x00.csv", "plain file name"),
    ("spa ce.csv", "letters, digits"),
])
def test_hostile_names_are_refused_and_nothing_is_written(tmp_path: Path, name: str,
                                                          why: str) -> None:
    root = tmp_path / "data"
    d = DataDir(root)
    before = _listing(tmp_path)
    with pytest.raises(FileRefused, match=why.replace("(", r"\(").replace(".", r"\.")):
        d.create(name, "log")
    assert _listing(tmp_path) == before


def test_existing_files_and_symlinks_are_never_opened(tmp_path: Path) -> None:
    root = tmp_path / "data"
    d = DataDir(root)
    outside = tmp_path / "victim.csv"
    outside.write_text("keep me\n")
    (root / "old.csv").write_text("old rows\n")
    os.symlink(outside, root / "link.csv")
    os.symlink(tmp_path / "missing.csv", root / "dangling.csv")
    for name in ("old.csv", "link.csv", "dangling.csv"):
        with pytest.raises(FileRefused, match="already exists"):
            d.create(name, "log")
    assert outside.read_text() == "keep me\n"
    assert (root / "old.csv").read_text() == "old rows\n"
    assert not (tmp_path / "missing.csv").exists()


def test_the_other_output_file_is_refused(tmp_path: Path) -> None:
    d = DataDir(tmp_path)
    busy = d.create("same.jsonl", "record")
    with pytest.raises(FileRefused):
        d.create("same.jsonl", "record", busy=[busy])


def test_json_depth_and_limits() -> None:
    assert json_depth(b'{"a": "[[[[", "b": [1, [2]]}', limit=2) == 3
    assert json_depth(b'"[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[["') == 0
    assert json_depth(b"[" * 1000 + b"]" * 1000) == 1000
    assert safe_loads(b'{"v": 1, "x": [[1]]}', 100) == {"v": 1, "x": [[1]]}
    nested = json.dumps(json.loads("[" * 32 + "]" * 32)).encode()
    assert safe_loads(nested, 1 << 10) == json.loads(nested)
    for data, why in ((b"[" * 33 + b"]" * 33, "nested too deeply"),
                      (b"[" * 100000 + b"]" * 100000, "too large"),
                      (b"[1, NaN]", "NaN"), (b'{"x": -Infinity}', "Infinity"),
                      (b"9" * 5000, "not UTF-8 JSON"), (b"\xff\xfe", "not UTF-8 JSON"),
                      (b'{"a": 1', "not UTF-8 JSON")):
        with pytest.raises(JsonLimitError, match=why):
            safe_loads(data, 1 << 16)


def test_log_and_record_at_start_never_write_over_an_existing_file(
        tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """``--log`` and ``--record`` follow control's rule: a CSV log of this format is
    continued, anything else is kept and the output goes to ``NAME-2``; an event says so."""
    from kmead import cli

    csv = tmp_path / "run.csv"
    rec = tmp_path / "run.jsonl"
    csv.write_text("not a log of kmead\n" * 50)
    rec.write_text('{"an earlier": "recording"}\n' * 60)
    before = csv.read_bytes(), rec.read_bytes()
    code = cli.main(["--source", "sim:default", "--headless", "--frames", "3",
                     "--set", "source.width=640", "--set", "source.height=480",
                     "--set", "source.fps=0", "--set", 'network.telemetry="tcp://127.0.0.1:*"',
                     "--set", 'network.control=""', "--log", str(csv), "--record", str(rec)])
    err = capsys.readouterr().err
    assert code == 0, err
    assert (csv.read_bytes(), rec.read_bytes()) == before
    assert (tmp_path / "run-2.csv").read_text().count("\n") > 3
    assert (tmp_path / "run-2.jsonl").read_text().count("\n") >= 4
    assert f"{csv} exists and is kept: writing {tmp_path / 'run-2.csv'}" in err
    # A CSV log of kmead's own format is continued: the rows before it stay.
    rows = (tmp_path / "run-2.csv").read_text().splitlines()
    assert cli.main(["--source", "sim:default", "--headless", "--frames", "2",
                     "--set", "source.width=640", "--set", "source.height=480",
                     "--set", "source.fps=0", "--set", 'network.telemetry="tcp://127.0.0.1:*"',
                     "--set", 'network.control=""', "--log", str(tmp_path / "run-2.csv")]) == 0
    after = (tmp_path / "run-2.csv").read_text().splitlines()
    assert after[:len(rows)] == rows and len(after) > len(rows)
