"""kmead configuration: the shipped default, overlays, --set, clear errors, exit code 2."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from kmead import cli
from kmead.config.layers import ConfigError, load_config, overlay_doc, parse_set, save_overlay

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

ROOT = Path(__file__).resolve().parent.parent


def test_default_has_the_documented_keys() -> None:
    cfg = load_config(None)
    for key in ("source.spec", "camera.file", "map.file", "detector.dictionary",
                "detector.marker_length", "estimator.algorithm", "filter.alpha",
                "network.telemetry", "network.control", "log.csv", "log.record"):
        cfg.get(key)  # KeyError if missing
    assert cfg.get("source.spec") == "sim"
    assert cfg.get("estimator.algorithm") == "corner-pnp"
    assert cfg.get("filter.alpha") == 1.0
    robots = {r["name"]: r for r in cfg["robots"]}
    assert robots["amr1"]["markers"] == [40, 41] and robots["amr2"]["markers"] == [42]
    assert all(r["height"] == 0.2 and r["length"] == 0.06 for r in robots.values())
    assert cfg.get("network.control").startswith("tcp://127.0.0.1:")


def test_overlay_file_and_set(tmp_path: Path) -> None:
    f = tmp_path / "site.toml"
    f.write_text('[filter]\nalpha = 0.5\n[[robots]]\nname = "solo"\nmarkers = 7\n')
    cfg = load_config(str(f), ["estimator.algorithm=umeyama", "detector.dictionary=DICT_6X6_250",
                               'source.spec="images:/tmp"'])
    assert cfg.get("filter.alpha") == 0.5
    assert cfg.get("filter.reset_after_s") == 1.0  # untouched keys keep the default
    assert [r["name"] for r in cfg["robots"]] == ["solo"]
    assert cfg["robots"][0]["markers"] == [7]
    assert cfg.get("estimator.algorithm") == "umeyama"
    assert cfg.get("detector.dictionary") == "DICT_6X6_250"  # unquoted value taken as string
    assert cfg.get("source.spec") == "images:/tmp"


def test_parse_set_values() -> None:
    assert parse_set("filter.alpha=0.25") == ("filter.alpha", 0.25)
    assert parse_set("stats.loo=false") == ("stats.loo", False)
    robots = parse_set('robots=[{name="a", markers=[1, 2]}]')[1]
    assert robots == [{"name": "a", "markers": [1, 2]}]
    with pytest.raises(ConfigError, match=r"SECTION\.KEY=VALUE"):
        parse_set("filter.alpha")
    with pytest.raises(ConfigError, match="not valid TOML"):
        parse_set("robots=[{name=}]")


@pytest.mark.parametrize(("content", "expect"), [
    ("[filter]\nalpha = 2.0\n", "key 'filter.alpha': must be in [0.001, 1]"),
    ("[filter]\nalfa = 0.5\n", "unknown key 'filter.alfa'"),
    ("[nonsense]\nx = 1\n", "unknown section [nonsense]"),
    ("[filter\nalpha = 1\n", "invalid TOML"),
    ("[estimator]\nalgorithm = \"magic\"\n", "unknown algorithm 'magic'"),
    ("[source]\nspec = \"webcam\"\n", "unknown source 'webcam'"),
    ("[network]\ncontrol = \"localhost\"\n", "expected a ZeroMQ endpoint"),
    ("[detector]\ndictionary = \"DICT_9X9_1\"\n", "key 'detector.dictionary'"),
    ("[detector]\nparameters = { adaptiveThreshWinSizeMax = \"big\" }\n",
     "adaptiveThreshWinSizeMax"),
    ("[[robots]]\nname = \"a\"\nmarkers = [1, 2, 3]\n", "robots[0].markers"),
    ("[[robots]]\nname = \"a\"\nmarkers = [1]\nwheels = 4\n", "unknown key 'wheels'"),
    ("[[robots]]\nname = \"a\"\nmarkers = [1]\ndestinations = [\"tcp:x:1\"]\n",
     "destinations[0]: destination must be \"udp:HOST:PORT\""),
    ("[[robots]]\nname = \"a\"\nmarkers = [1]\n[[robots]]\nname = \"b\"\nmarkers = [1]\n",
     "marker 1 already belongs to robot 'a'"),
])
def test_bad_config_file_refuses_to_start(tmp_path: Path, capsys: pytest.CaptureFixture,
                                          content: str, expect: str) -> None:
    f = tmp_path / "bad.toml"
    f.write_text(content)
    assert cli.main(["--config", str(f), "--headless", "--frames", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0, err  # one line
    assert str(f) in err and expect in err, err


@pytest.mark.parametrize(("args", "expect"), [
    (["--set", "filter.beta=1"], "--set: unknown key 'filter.beta'"),
    (["--set", "filter.alpha=fast"],
     "--set: key 'filter.alpha': expected a number, got the string 'fast'"),
    (["--set", 'filter.alpha="0.5"'], "--set: key 'filter.alpha': expected a number, got the "
     "string '0.5' (a number is written without quotes: 0.5)"),
    (["--set", "stats.window=0"], "--set: key 'stats.window': must be an integer in [1, 100000]"),
    (["--set", "noequals"], "expected SECTION.KEY=VALUE"),
    (["--algorithm", "nope"], "--algorithm: key 'estimator.algorithm': unknown algorithm"),
    (["--config", "/nonexistent/kmead.toml"], "/nonexistent/kmead.toml: no such file"),
    (["--frames", "0"], "--frames: must be >= 1"),
])
def test_bad_options_refuse_to_start(capsys: pytest.CaptureFixture, args: list[str],
                                     expect: str) -> None:
    assert cli.main([*args, "--headless"]) == 2
    err = capsys.readouterr().err
    assert expect in err, err


def test_bad_map_and_camera_files(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    bad_map = tmp_path / "floor.csv"
    bad_map.write_text("id,x,y,z\n1,0,0,0\n1,0.1,0,0\n")
    net = ["--set", 'network.telemetry=""', "--set", 'network.control=""']
    assert cli.main(["--map", str(bad_map), "--headless", "--frames", "1", *net]) == 2
    err = capsys.readouterr().err
    assert str(bad_map) in err and "duplicate marker id 1" in err
    bad_cam = tmp_path / "cam.yml"
    bad_cam.write_text("%YAML:1.0\n---\ndistortion_coefficients: !!opencv-matrix\n"
                       "   rows: 1\n   cols: 5\n   dt: d\n   data: [0, 0, 0, 0, 0]\n")
    assert cli.main(["--camera", str(bad_cam), "--headless", "--frames", "1", *net]) == 2
    err = capsys.readouterr().err
    assert str(bad_cam) in err and "camera_matrix" in err


def test_missing_camera_is_a_clear_runtime_error(capsys: pytest.CaptureFixture) -> None:
    code = cli.main(["--source", "camera:99", "--headless", "--frames", "1",
                     "--set", 'network.telemetry=""', "--set", 'network.control=""'])
    assert code == 1
    assert "camera:99" in capsys.readouterr().err


def test_save_overlay_keeps_the_users_file(tmp_path: Path) -> None:
    f = tmp_path / "site.toml"
    original = "# my precious comments\n[filter]\nalpha = 0.5  # smooth\n"
    f.write_text(original)
    cfg = load_config(str(f))
    cfg.set("estimator.algorithm", "lmea")
    cfg.set("robots", [{"name": "x", "markers": [5], "destinations": ["udp:10.0.0.2:7000"]}])
    assert set(overlay_doc(cfg)) == {"estimator", "robots"}
    path, _ = save_overlay(cfg)
    assert path == tmp_path / "site.local.toml"
    assert f.read_text() == original
    doc = tomllib.loads(path.read_text())
    assert doc["estimator"] == {"algorithm": "lmea"} and "filter" not in doc
    again = load_config(str(f))  # the overlay is picked up at the next start
    assert again.get("estimator.algorithm") == "lmea"
    assert again.get("filter.alpha") == 0.5
    assert again["robots"][0]["destinations"] == ["udp:10.0.0.2:7000"]
    assert str(path) in again.files
