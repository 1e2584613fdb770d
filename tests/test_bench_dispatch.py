"""``kmea bench``'s dispatcher: names and the options it passes to each benchmark."""

from __future__ import annotations

import argparse

from kmea.benchmarks import cli as bench


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

    benches = {"counted": counted, "plain": plain}
    assert bench.run(_args("counted", "plain", "--frames", "300", benches=benches)) == 0
    assert calls == [("counted", {"quick": False, "frames": 300}),
                     ("plain", {"quick": False})]
    calls.clear()
    assert bench.run(_args("counted", "--quick", benches=benches)) == 0
    assert calls == [("counted", {"quick": True, "frames": None})]


def test_an_unknown_benchmark_is_named_and_nothing_runs(capsys):
    ran: list[str] = []
    benches = {"plain": lambda quick=False: ran.append("plain")}
    assert bench.run(_args("plain", "nope", benches=benches)) == 2
    assert ran == [] and "'nope'" in capsys.readouterr().out


def test_help_lists_every_command_and_every_benchmark(capsys):
    import pytest

    from kmead.tools import kmea_cli

    with pytest.raises(SystemExit):
        kmea_cli.main(["--help"])
    text = capsys.readouterr().out
    for name in {**kmea_cli.cli.COMMANDS, **kmea_cli.DAEMON_COMMANDS}:
        assert f"    {name}" in text, name
    description = text.split("\n\n")[1]
    assert description.rstrip().endswith(")."), description  # a whole sentence, not cut
    with pytest.raises(SystemExit):
        kmea_cli.main(["bench", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    for name in {**bench.BENCHES, **kmea_cli.DAEMON_BENCHES}:
        assert f" {name}," in text or f" {name} " in text, name


def test_daemon_benchmarks_are_importable_targets():
    from importlib import import_module

    from kmead.tools import kmea_cli

    for target in kmea_cli.DAEMON_BENCHES.values():
        module, func = target.split(":")
        assert callable(getattr(import_module(module), func)), target
