"""``kmea bench``'s dispatcher: names, the options it passes to each benchmark, the
benchmarks with their own options, and the one table of every benchmark (the library's in
``kmea/benchmarks/``, the daemon's in ``kmead/benchmarks/``)."""

from __future__ import annotations

import argparse
import inspect
from importlib import import_module
from pathlib import Path

import pytest

from kmea.cli import bench

ROOT = Path(__file__).resolve().parent.parent


def _args(*argv: str, benches: dict) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    bench.add_arguments(p)
    args = p.parse_args(list(argv))
    args.daemon_benches = benches
    return args


def test_frames_reaches_the_benchmarks_that_take_a_count_only():
    calls: list[tuple[str, dict]] = []

    def counted(quick: bool = False, frames: int | None = None) -> None:
        calls.append(("counted", {"quick": quick, "frames": frames}))

    def plain(quick: bool = False) -> None:
        calls.append(("plain", {"quick": quick}))

    benches = {"counted": (counted, "c"), "plain": (plain, "p")}
    assert bench.run(_args("counted", "plain", "--frames", "300", benches=benches)) == 0
    assert calls == [("counted", {"quick": False, "frames": 300}),
                     ("plain", {"quick": False})]
    calls.clear()
    assert bench.run(_args("counted", "--quick", benches=benches)) == 0
    assert calls == [("counted", {"quick": True, "frames": None})]
    calls.clear()
    assert bench.run(_args("--frames", "7", "counted", benches=benches)) == 0
    assert calls == [("counted", {"quick": False, "frames": 7})]


def test_a_benchmark_with_its_own_options_gets_its_command_line_and_runs_alone(
        capsys, monkeypatch):
    got: list[list[str]] = []

    def main(argv: list[str] | None = None) -> int:
        got.append(list(argv or []))
        return 3

    ran: list[str] = []
    benches = {"own": (main, "o"), "plain": (lambda quick=False: ran.append("plain"), "p")}
    assert bench.run(_args("own", "--frames", "60", "--x", "y", benches=benches)) == 3
    assert got == [["--frames", "60", "--x", "y"]]
    # Not with others, not by default, and its options after its name.
    assert bench.run(_args("plain", "own", benches=benches)) == 2
    assert bench.run(_args("--quick", "own", benches=benches)) == 2
    assert "kmea bench own --help" in capsys.readouterr().out
    monkeypatch.setattr(bench, "BENCHES", {})  # no name: every run(quick) one, here "plain"
    assert bench.run(_args(benches=benches)) == 0
    assert ran == ["plain"] and len(got) == 1


def test_an_unknown_benchmark_is_named_and_nothing_runs(capsys):
    ran: list[str] = []
    benches = {"plain": (lambda quick=False: ran.append("plain"), "p")}
    assert bench.run(_args("plain", "nope", benches=benches)) == 2
    assert ran == [] and "'nope'" in capsys.readouterr().out


def test_help_and_list_name_every_benchmark_with_a_line_each(capsys):
    from kmead.tools import kmea_cli

    with pytest.raises(SystemExit):
        kmea_cli.main(["--help"])
    text = capsys.readouterr().out
    for name in {**kmea_cli.cli.COMMANDS, **kmea_cli.DAEMON_COMMANDS}:
        assert f"    {name}" in text, name
    description = text.split("\n\n")[1]
    assert description.rstrip().endswith(")."), description  # a whole sentence, not cut
    every = {**bench.BENCHES, **kmea_cli.DAEMON_BENCHES}
    with pytest.raises(SystemExit):
        kmea_cli.main(["bench", "--help"])
    text = capsys.readouterr().out
    assert kmea_cli.main(["bench", "--list"]) == 0
    listed = capsys.readouterr().out.splitlines()
    assert len(listed) == len(every)
    for name, (_, help_) in every.items():
        assert help_ and "\n" not in help_, name
        assert any(line.split()[0] == name and line.endswith(help_) for line in listed), name
        assert f"  {name} " in text, name


def test_every_benchmark_is_an_importable_function_of_its_kind():
    from kmead.tools import kmea_cli

    assert not set(bench.BENCHES) & set(kmea_cli.DAEMON_BENCHES)
    for table, package in ((bench.BENCHES, "kmea.benchmarks."),
                           (kmea_cli.DAEMON_BENCHES, "kmead.benchmarks.")):
        for name, (target, _) in table.items():
            assert isinstance(target, str) and target.startswith(package), name
            module, func = target.split(":")
            params = inspect.signature(getattr(import_module(module), func)).parameters
            assert ("argv" in params) == bench.takes_argv(target), name
            assert "argv" in params or "quick" in params, name


def test_benchmarks_live_in_the_two_packages_only():
    assert not list((ROOT / "benchmarks").glob("*.py"))  # the old top-level scripts
    modules = {p.stem for pkg in ("kmea", "kmead") for p in (ROOT / pkg / "benchmarks").glob(
        "*.py")} - {"__init__", "cli"}
    registered = {t.partition(":")[0].rpartition(".")[2]
                  for t, _ in [*bench.BENCHES.values(), *_daemon().values()]}
    # Helpers of the benchmarks are modules too; every registered one is a file here.
    assert registered <= modules


def _daemon() -> dict:
    from kmead.benchmarks import BENCHES

    return BENCHES
