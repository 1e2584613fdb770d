"""Every settable key has a type and a range (kmead.config.schema); nothing else escapes."""

from __future__ import annotations

import contextlib
import math

import cv2
import pytest

from kmea.vision.detection import DETECTOR_PARAMETERS
from kmead.config.checks import (
    ConfigError,
    check_intrinsics,
    parse_destination,
)
from kmead.config.schema import SCHEMA, validate_setting

HUGE = 10**30


@pytest.mark.parametrize("key, value, why", [
    ("stats.window", HUGE, r"\[1, 100000\]"),
    ("stats.displaced_frames", HUGE, r"\[1, 1000\]"),
    ("detector.fixed_full_every", 0, "integer in"),
    ("detector.workers", 1000, r"\[0, 16\]"),
    ("source.width", -1, "integer in"),
    ("source.fps", 1e9, "must be in"),
    ("filter.alpha", 0, "must be in"),
    ("filter.alpha", math.nan, "finite"),
    ("stats.window", 3.0, "expected an integer"),
    ("stats.window", True, "expected an integer"),
    ("stats.loo", 1, "true or false"),
    ("relay.stale_after_s", HUGE, "must be in"),
    ("network.status_period_s", 0, "must be in"),
    ("network.control", "tcp://0.0.0.0:99999", "ZeroMQ endpoint"),
    ("log.level", "trace", "one of"),
    ("detector", 1, "must be SECTION.KEY"),
    ("detector.", 1, "must be SECTION.KEY"),
    ("detector.a.b", 1, "must be SECTION.KEY"),
    ("detector.foo", 1, "unknown key"),
    ("detector.parameters.minDistanceToBorder", 1, "must be SECTION.KEY"),
    ("nosuch.key", 1, "unknown section"),
    ("detector.parameters", {"adaptiveThreshWinSizeMax": 10**20}, r"\[3, 255\]"),
    ("detector.parameters", {"minMarkerPerimeterRate": 10**400}, "out of range"),
    ("detector.parameters", {"markerBorderBits": 0}, r"\[1, 4\]"),
    ("detector.parameters", {"perspectiveRemovePixelPerCell": 2000}, r"\[1, 32\]"),
    ("detector.parameters", {"cornerRefinementMethod": 1}, "corner_refinement"),
    ("detector.parameters", {"adaptiveThreshWinSizeMin": 30,
                             "adaptiveThreshWinSizeMax": 10}, "below"),
    ("detector.parameters", {"nope": 1}, "unknown detector parameter"),
    ("detector.parameters", {"adaptiveThreshWinSizeMax": 255,
                             "adaptiveThreshWinSizeStep": 1}, "253 thresholding passes"),
    ("detector.parameters", [1], "expected a table"),
    ("detector.dictionary", "NOT_A_DICT", "not a predefined"),
])
def test_bad_values_are_one_line_config_errors(key: str, value: object, why: str) -> None:
    with pytest.raises(ConfigError, match=why) as e:
        validate_setting(key, value, "control")
    assert "\n" not in str(e.value) and len(str(e.value)) < 400


def test_same_check_from_file_set_and_control_except_file_names() -> None:
    for where in ("config.toml", "--set", "control"):
        assert validate_setting("stats.window", 300, where) == 300
        with pytest.raises(ConfigError, match=where.replace("-", r"\-")):
            validate_setting("stats.window", HUGE, where)
    # A dictionary file is the operator's own choice in a file; over the network it would
    # read files and tell whether they exist.
    with pytest.raises(ConfigError, match="predefined name"):
        validate_setting("detector.dictionary", "/etc/passwd", "control", remote=True)
    with pytest.raises(ConfigError, match="predefined name"):
        validate_setting("detector.dictionary", "secret.yml", "control", remote=True)
    assert validate_setting("detector.dictionary", "DICT_4X4_50", "control", remote=True)


def test_every_detector_parameter_exists_in_opencv_and_its_range_is_accepted() -> None:
    names = {a for a in dir(cv2.aruco.DetectorParameters()) if not a.startswith("_")}
    p = cv2.aruco.DetectorParameters()
    for name, spec in DETECTOR_PARAMETERS.items():
        if name not in names:
            continue  # another OpenCV version: refused as unknown there
        for v in ((True, False) if spec.kind == "bool" else
                  (spec.hi,) if spec.lo_open else (spec.lo, spec.hi)):
            if spec.kind == "int":
                v = int(v)
            value = {name: v}
            if name == "adaptiveThreshWinSizeMax":
                value.update(adaptiveThreshWinSizeMin=3, adaptiveThreshWinSizeStep=255)
            if name == "adaptiveThreshWinSizeMin":
                value.update(adaptiveThreshWinSizeMax=255, adaptiveThreshWinSizeStep=255)
            if name == "adaptiveThreshWinSizeStep" and v < 10:
                value["adaptiveThreshWinSizeMax"] = 13
            if name == "minMarkerPerimeterRate":
                value["maxMarkerPerimeterRate"] = 4.0
                if v >= 4.0:
                    continue
            if name == "maxMarkerPerimeterRate" and v <= 0.04:
                continue
            validate_setting("detector.parameters", value, "control")
            setattr(p, name, v)  # OpenCV takes it too


def test_robot_names_and_destinations() -> None:
    ok = {"name": "amr-1_b", "markers": [40, 41], "destinations": [
        "udp:127.0.0.1:9001", "udp:robot-3.local:65535", "udp:localhost:1"]}
    assert validate_setting("robots", [ok], "control")[0]["name"] == "amr-1_b"
    for name in ("$(touch x)", "a;b", "a b", "", "x" * 33, "r\n1"):
        with pytest.raises(ConfigError, match="name"):
            validate_setting("robots", [{**ok, "name": name}], "control")
    for dest in ("udp:$(touch /tmp/PWNED):9", "udp:127.0.0.1:0", "udp:127.0.0.1:65536",
                 "udp:256.1.1.1:9", "udp:1.2.3:9", "udp:-bad.host:9", "tcp:1.2.3.4:9",
                 "udp:a..b:9", "udp:host:9:9", "udp:ho st:9", 5):
        with pytest.raises(ConfigError, match="destination"):
            validate_setting("robots", [{**ok, "destinations": [dest]}], "control")
    with pytest.raises(ConfigError, match="at most 8"):
        validate_setting("robots", [{**ok, "destinations": ["udp:1.2.3.4:9"] * 9}], "control")
    with pytest.raises(ConfigError, match="ids 0-4095"):
        validate_setting("robots", [{**ok, "markers": [99999999999999]}], "control")
    with pytest.raises(ConfigError, match="at most 64"):
        validate_setting("robots", [{"name": f"r{i}", "markers": [i]} for i in range(65)],
                         "control")
    assert parse_destination("udp:10.0.0.7:9001", "x") == ("10.0.0.7", 9001)


def test_camera_intrinsics_must_fit_the_image() -> None:
    check_intrinsics(1200, 1200, 820, 616, 1640, 1232, "cam.yml")
    for fx, fy, cx, cy in ((1200, 1200, 1e9, 616), (0, 1200, 820, 616),
                           (1200, 1200, -1, 616), (1200, 1200, 820, 5000),
                           (1e12, 1e12, 820, 616), (math.nan, 1200, 820, 616)):
        with pytest.raises(ConfigError, match=r"cam\.yml"):
            check_intrinsics(fx, fy, cx, cy, 1640, 1232, "cam.yml")


def test_every_schema_key_survives_hostile_values() -> None:
    hostile = [None, True, -1, 0, HUGE, -HUGE, 1e308, math.inf, math.nan, "", "x" * 10000,
               "\x00", [], [[[]]], {}, {"a": {"b": 1}}, "../../etc/passwd", 10**400]
    for section, table in SCHEMA.items():
        for name in table:
            for v in hostile:
                # Accepted or a ConfigError: any other exception fails the test.
                with contextlib.suppress(ConfigError):
                    validate_setting(f"{section}.{name}", v, "control", remote=True)
    for v in hostile:
        if v != []:  # no robots is a valid list
            with pytest.raises(ConfigError):
                validate_setting("robots", v, "control")
        if v != 0:  # a single marker id 0 is valid
            with pytest.raises(ConfigError):
                validate_setting("robots", [{"name": "r", "markers": v}], "control")
