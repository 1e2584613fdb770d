"""A seeded fuzzer against a real daemon's control socket on loopback.

At least 2,000 requests across the kinds a hostile client would try. Every request gets a
reply; after each kind ``ping`` answers, frames still flow and nothing was written outside
the data directory. Run with ``-s`` to see the counts by kind.
"""

from __future__ import annotations

import json
import random
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from security_helpers import LiveDaemon

from kmea.wire.protocol import PROTOCOL_VERSION as V
from kmead.config.schema import SCHEMA

VB = str(V).encode()
SEED = 20261130
PER_KIND = 170

COMMANDS = ["ping", "get_state", "get_config", "set", "log_start", "log_stop", "record_start",
            "record_stop", "reload_map", "save_config", "reset_stats"]
KEYS = [f"{s}.{k}" for s, t in SCHEMA.items() for k in t] + [
    "robots", "detector", "detector.", "detector.a.b", "detector.parameters.minDistanceToBorder",
    "detector.foo", "", ".", "robots.0", "x" * 100]
ABSURD = [10**30, -10**30, 10**20, -1, 0, 2**63, 1e308, -1e308, 1e-320, True, False, None, "",
          "x" * 5000, [], {}, [[[[1]]]], {"a": {"b": {"c": 1}}}, "../../etc/passwd",
          "DICT_4X4_50", "udp:$(touch PWNED):9", [{"name": "x", "markers": [10**20]}],
          [{"name": "$(id)", "markers": [1]}], {"markerBorderBits": 0},
          {"perspectiveRemovePixelPerCell": 2000},
          {"adaptiveThreshWinSizeMax": 100000000000000000000},
          {"minMarkerPerimeterRate": 100000000000000000000}]


def _hostile_paths(root: Path) -> list[object]:
    return ["/etc/kmead-fuzz.csv", str(root / "outside.csv"), "../outside.csv",
            "../../made/by/remote/x.csv", "sub/x.csv", "~/.bashrc", ".bashrc", ".profile.csv",
            str(root / "site.toml"), "site.toml", "../site.toml", "link.csv", "existing.csv",
            "x\x00.csv", "con.csv/..", "a\\b.csv", "x" * 300 + ".csv", "", " ", 5, [], {},
            "site.local.toml", "/dev/null", "x.txt", "...csv", "%s%n.csv"]


def _json(obj: object) -> bytes:
    return json.dumps(obj).encode()


def kinds(root: Path) -> dict[str, Callable[[random.Random], bytes | list[bytes]]]:
    paths = _hostile_paths(root)

    def random_bytes(r: random.Random) -> bytes:
        return bytes(r.getrandbits(8) for _ in range(r.randint(0, 400)))

    def huge(r: random.Random) -> bytes:
        n = r.choice([70_000, 300_000, 1_100_000, 2_000_000])
        return b'{"v": ' + VB + b', "cmd": "ping", "pad": "' + b"x" * n + b'"}'

    def invalid_json(r: random.Random) -> bytes:
        good = _json({"v": V, "cmd": r.choice(COMMANDS), "key": "filter.alpha", "value": 0.5})
        return r.choice([good[: r.randint(0, len(good) - 1)], b"{'v': 1}", good + b"}",
                         good.replace(b":", b"", 1), b"[", b"", b"null", b"\xef\xbb\xbf" + good,
                         good.replace(b'"', b"'"), b"{" + bytes([r.randint(0, 31)]) + b"}"])

    def wrong_types(r: random.Random) -> bytes:
        odd = r.choice([1, 1.5, True, None, [], {}, "1", [1], {"a": 1}])
        return _json(r.choice([
            {"v": odd, "cmd": "ping"}, {"v": V, "cmd": odd},
            {"v": V, "cmd": "set", "key": odd, "value": 1},
            {"v": V, "cmd": "set", "key": "filter.alpha", "value": odd},
            {"v": V, "cmd": "log_start", "path": odd}, {"v": V, "cmd": "save_config",
                                                         "path": odd},
            {"v": V, "cmd": "set", "key": "filter.alpha"}, [1, 2, 3], "ping", 42]))

    def unknown_commands(r: random.Random) -> bytes:
        name = "".join(r.choice("abcdefghijklmnopqrstuvwxyz_.$/") for _ in range(r.randint(0, 30)))
        return _json({"v": V, "cmd": r.choice([name, "format_disk", "__init__", "_run",
                                               "cmd_ping", "PING", "stop", "close"])})

    def multipart(r: random.Random) -> list[bytes]:
        frames = [_json({"v": V, "cmd": "ping"})] * r.randint(2, 6)
        return [r.choice([f, b"", b"\xff" * r.randint(1, 50)]) for f in frames]

    def deep_nesting(r: random.Random) -> bytes:
        n = r.choice([33, 100, 995, 1000, 5000, 20000])
        if r.random() < 0.5:
            return b"[" * n + b"]" * n
        inner = b'{"a": ' * n + b"1" + b"}" * n
        return (b'{"v": ' + VB + b', "cmd": "set", "key": "detector.parameters", "value": '
                + inner + b"}")

    def nan(r: random.Random) -> bytes:
        bad = r.choice([b"NaN", b"Infinity", b"-Infinity"])
        return r.choice([b'{"v": ' + VB + b', "cmd": "set", "key": "filter.alpha", "value": '
                         + bad + b"}",
                         b'{"v": ' + bad + b', "cmd": "ping"}',
                         b'{"v": ' + VB + b', "cmd": "set", "key": "detector.parameters", "value": '
                         b'{"minMarkerPerimeterRate": ' + bad + b"}}"])

    def long_strings(r: random.Random) -> bytes:
        chunk = "".join(r.choices("a/.\\\u00e9\u2603\x00", k=97))
        s = chunk * r.randint(50, 600)
        return _json(r.choice([{"v": V, "cmd": s}, {"v": V, "cmd": "set", "key": s, "value": 1},
                               {"v": V, "cmd": "set", "key": "filter.alpha", "value": s},
                               {"v": V, "cmd": "log_start", "path": s},
                               {"v": V, "cmd": "record_start", "path": s}]))

    def absurd_values(r: random.Random) -> bytes:
        return _json({"v": V, "cmd": "set", "key": r.choice(KEYS), "value": r.choice(ABSURD)})

    def hostile_paths(r: random.Random) -> bytes:
        return _json({"v": V, "cmd": r.choice(["log_start", "record_start", "save_config"]),
                      "path": r.choice(paths)})

    def huge_numbers(r: random.Random) -> bytes:
        # Integers no float holds (valid JSON) and the largest floats, in every field.
        big = r.choice([10 ** 401, -10 ** 401, 10 ** 4000, 1e308, -1e308, 2 ** 64])
        body: dict = {"v": V, "cmd": r.choice([*COMMANDS, "camera_watch", "snapshot",
                                                "get_log"])}
        body[r.choice(["v", "key", "value", "path", "width", "height", "lease_s", "overlay",
                       "lines", "since"])] = big
        if body["cmd"] == "set" and "key" not in body:
            body["key"] = r.choice(KEYS)
        return _json(body)

    def valid_commands(r: random.Random) -> bytes:
        i = r.randint(0, 10**9)
        return _json(r.choice([
            {"v": V, "cmd": "ping"}, {"v": V, "cmd": "get_state"}, {"v": V, "cmd": "get_config"},
            {"v": V, "cmd": "set", "key": "filter.alpha", "value": r.uniform(0.2, 1.0)},
            {"v": V, "cmd": "set", "key": "stats.window", "value": r.randint(1, 1000)},
            {"v": V, "cmd": "reset_stats"}, {"v": V, "cmd": "reload_map"},
            {"v": V, "cmd": "log_start", "path": f"fuzz-{i}.csv"}, {"v": V, "cmd": "log_stop"},
            {"v": V, "cmd": "record_start", "path": f"fuzz-{i}.jsonl"},
            {"v": V, "cmd": "record_stop"}, {"v": V, "cmd": "save_config"}]))

    return {f.__name__: f for f in (random_bytes, huge, invalid_json, wrong_types,
                                    unknown_commands, multipart, deep_nesting, nan,
                                    long_strings, absurd_values, hostile_paths,
                                    huge_numbers, valid_commands)}


def _outside(root: Path) -> dict[str, bytes]:
    """Every file under ``root`` except the data directory and the daemon's own overlay."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file() and "data" not in p.relative_to(root).parts
            and p.name != "site.local.toml"}


@pytest.fixture
def live(tmp_path: Path) -> LiveDaemon:
    root = tmp_path / "site"
    root.mkdir()
    (root / "outside.csv").write_text("must survive\n")
    d = LiveDaemon(root)
    (d.data / "existing.csv").write_text("old rows\n")
    (d.data / "link.csv").symlink_to(root / "outside.csv")
    yield d
    d.close()


def test_seeded_fuzzer_every_request_answered_and_the_daemon_keeps_working(
        live: LiveDaemon) -> None:
    rng = random.Random(SEED)
    before = _outside(live.root)
    counts: dict[str, dict[str, int]] = {}
    slowest = 0.0
    t_all = time.perf_counter()
    for kind, make in kinds(live.root).items():
        c = counts.setdefault(kind, {"sent": 0, "ok": 0, "error": 0})
        t_kind = time.perf_counter()
        for i in range(PER_KIND):
            payload = make(rng)
            t0 = time.perf_counter()
            reply = live.request(payload, timeout=15.0)  # a hang, not a busy machine
            slowest = max(slowest, time.perf_counter() - t0)
            c["sent"] += 1
            assert reply is not None, f"{kind} #{i}: no reply to {bytes(payload)[:80]!r}"
            assert isinstance(reply.get("ok"), bool), reply
            if reply["ok"]:
                c["ok"] += 1
            else:
                c["error"] += 1
                assert reply["error"] and "\n" not in reply["error"], reply
                assert "internal error" not in reply["error"], (kind, bytes(payload)[:80])
                assert len(reply["error"]) <= 500
        c["ms"] = round((time.perf_counter() - t_kind) * 1e3)
        # After each kind: the control socket answers, frames flow, no file escaped.
        assert live.cmd("ping")["ok"], kind
        assert live.frames_flow(), f"frames stopped after {kind}"
        assert live.alive(), f"daemon died after {kind}: {live.error!r}"
        assert _outside(live.root) == before, f"a file outside the data directory changed: {kind}"
    total = sum(c["sent"] for c in counts.values())
    assert total >= 2000
    # Every refused kind was refused, every valid kind mostly served.
    for kind in ("random_bytes", "huge", "invalid_json", "multipart", "deep_nesting", "nan",
                 "unknown_commands", "long_strings", "hostile_paths"):
        assert counts[kind]["ok"] == 0, (kind, counts[kind])
    assert counts["valid_commands"]["ok"] > PER_KIND // 2
    assert not (live.data / "outside.csv").exists()
    assert (live.root / "outside.csv").read_text() == "must survive\n"
    assert (live.data / "existing.csv").read_text() == "old rows\n"
    print(f"\nfuzz: {total} requests in {time.perf_counter() - t_all:.1f} s, slowest reply "
          f"{slowest * 1e3:.0f} ms, seed {SEED}")
    print(f"{'kind':<18} {'sent':>5} {'ok':>5} {'error':>6} {'time ms':>8}")
    for kind, c in counts.items():
        print(f"{kind:<18} {c['sent']:>5} {c['ok']:>5} {c['error']:>6} {c['ms']:>8}")


def test_every_command_has_its_handler_in_the_table(live: LiveDaemon) -> None:
    from kmead.net.control import COMMANDS

    control = live.daemon.control
    assert control is not None
    assert set(control.handlers) == set(COMMANDS)
    assert len(set(COMMANDS)) == len(COMMANDS)  # a name listed twice would hide one
