"""The tracking filter's settings under ``[filter]`` (the schema reads their defaults from
TrackerConfig): a bad value is a one-line error naming the key (kmead, the fusion node, a
config file), and every value reaches the filter of the daemon's pipeline and of the fusion
node."""

from __future__ import annotations

from pathlib import Path

import pytest

from kmea.pipeline import PipelineSettings
from kmea.robots.tracking import TrackerConfig
from kmead import cli
from kmead.config.layers import load_config
from kmead.fusion.node import tracker_config as fusion_tracker_config
from kmead.tools.kmea_cli import main as kmea_main

OFF = ["--set", 'network.telemetry=""', "--set", 'network.control=""']

BAD = [("step_k", "0", "must be in [0.01, 1e+09]"),
       ("step_k", "-1.5", "must be in [0.01, 1e+09]"),
       ("gate_probability", "1.0", "must be a probability in [1e-06, 1 - 1e-09]"),
       ("manoeuvre_scale", "0.5", "must be in [1, 1e+06]"),
       ("manoeuvre_time_s", "0", "must be in [0.01, 3600] s"),
       ("cruise_time_s", '"long"', "expected a number"),
       ("reacquire_n", "1.5", "expected an integer"),
       ("max_speed", "-1", "must be in [0.001, 100] m/s"),
       # A length or a noise density of 1e-300 is no setting anyone means (issue 30).
       ("step_k", "1e-300", "must be in [0.01, 1e+09]"),
       ("outlier_probability", "1.5", "must be a probability in [1e-06, 1 - 1e-09]"),
       # A radius of 1e-300 m is no radius: it once made every frame fail (issue 30).
       ("outlier_radius", "1e-300", "must be in [0.0001, 10] m"),
       ("accel_noise", "1e-300", "must be in [1e-06, 1000] m^2/s^3")]


@pytest.mark.parametrize(("key", "value", "expect"), BAD)
def test_bad_value_on_the_command_line_names_the_key(capsys: pytest.CaptureFixture, key: str,
                                                     value: str, expect: str) -> None:
    assert cli.main(["--set", f"filter.{key}={value}", "--headless", "--frames", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0, err
    assert f"filter.{key}" in err and expect in err, err


@pytest.mark.parametrize(("key", "value", "expect"), BAD)
def test_bad_value_in_a_config_file_names_file_and_key(tmp_path: Path,
                                                       capsys: pytest.CaptureFixture, key: str,
                                                       value: str, expect: str) -> None:
    f = tmp_path / "bad.toml"
    f.write_text(f"[filter]\n{key} = {value}\n")
    assert cli.main(["--config", str(f), "--headless", "--frames", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0, err
    assert str(f) in err and key in err and expect in err, err


def test_bad_value_for_the_fusion_node_names_the_key(capsys: pytest.CaptureFixture) -> None:
    assert kmea_main(["fuse", "--set", "filter.step_k=0", "--headless", *OFF]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "filter.step_k" in err, err


def test_values_reach_the_daemon_and_fusion_filters() -> None:
    sets = ["filter.step_k=1.25", "filter.manoeuvre_scale=1", "filter.manoeuvre_time_s=0.5",
            "filter.cruise_time_s=4.0", "filter.max_speed=2.5", "filter.gate_probability=0.99",
            "filter.model=\"cv\""]
    cfg = load_config(None, sets=sets, use_local=False)
    want = TrackerConfig().with_(step_k=1.25, manoeuvre_scale=1.0, manoeuvre_time_s=0.5,
                                 cruise_time_s=4.0, max_speed=2.5, gate_probability=0.99,
                                 model="cv")
    assert fusion_tracker_config(cfg) == want
    assert PipelineSettings.from_config(cfg.data).tracker == want


@pytest.mark.parametrize("key, value", [("step_k", 1e9), ("step_k", 0.01),
                                        ("gate_probability", 1e-6),
                                        ("manoeuvre_scale", 1.0), ("manoeuvre_scale", 1e6),
                                        ("manoeuvre_time_s", 3600.0), ("cruise_time_s", 0.01),
                                        ("max_speed", 1e-3), ("max_speed", 100.0),
                                        ("outlier_probability", 1e-6),
                                        ("outlier_radius", 1e-4), ("outlier_radius", 10.0)])
def test_every_value_the_schema_accepts_builds_a_filter(key: str, value: float) -> None:
    # The schema's ranges lie inside the filter's own checks: a setting that passes the
    # configuration check never fails later, when the daemon builds the filter.
    cfg = load_config(None, sets=[f"filter.{key}={value!r}"], use_local=False)
    assert getattr(TrackerConfig.from_table(cfg["filter"]), key) == value
