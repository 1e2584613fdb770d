"""Start-up and ``kmead --check`` are one judgement (kmead.config.plan): every configuration that
start-up refuses, --check refuses with the same line and the same exit code, and the
reverse. Each case runs both, in-process, through the real command line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from kmead import cli

NET = ["--set", 'network.telemetry="tcp://127.0.0.1:*"',
       "--set", 'network.control="tcp://127.0.0.1:*"']
SMALL = ["--set", "source.width=640", "--set", "source.height=480", "--set", "source.fps=0"]


def _robots_config(tmp: Path) -> list[str]:
    p = tmp / "robots.toml"
    p.write_text('[detector]\ndictionary = "DICT_4X4_50"\n\n'
                 '[[robots]]\nname = "r1"\nmarkers = [60, 61]\n')
    return ["--config", str(p)]


def _robot_on(markers: str):
    """A robot carrying markers the map places (the built-in floor's 13, 16, 4)."""
    def args(tmp: Path) -> list[str]:
        p = tmp / "robots.toml"
        p.write_text(f'[[robots]]\nname = "r1"\nmarkers = {markers}\n')
        return ["--config", str(p)]
    return args


def _undecodable_images(tmp: Path) -> list[str]:
    d = tmp / "frames"
    d.mkdir()
    for i in range(3):
        (d / f"f{i}.png").write_bytes(b"not a png at all")
    return ["--source", f"images:{d}"]


def _same_outputs(tmp: Path) -> list[str]:
    return ["--log", str(tmp / "run.out"), "--record", str(tmp / "run.out")]


def _missing_keys(tmp: Path) -> list[str]:
    return ["--set", f'network.keys="{tmp / "no-keys"}"']


def _bad_map(tmp: Path) -> list[str]:
    p = tmp / "m.csv"
    p.write_text("id,x,y,z,rx_deg,ry_deg,rz_deg\n13,0,0,0,0,0,zero\n")
    return ["--map", str(p)]


def _map_row(row: str, name: str = "m.csv"):
    """A CSV map of the three anchors and one more marker ``row``."""
    def args(tmp: Path) -> list[str]:
        p = tmp / name
        p.write_text("id,x,y,z,rx_deg,ry_deg,rz_deg,length\n13,0,0,0,,,,\n16,0.695,0,0,,,,\n"
                     f"4,0,0.355,0,,,,\n{row}\n")
        return ["--map", str(p)]
    return args


def _toml_map(text: str):
    def args(tmp: Path) -> list[str]:
        p = tmp / "m.toml"
        p.write_text(text)
        return ["--map", str(p)]
    return args


def _camera(name: str, text: str):
    def args(tmp: Path) -> list[str]:
        p = tmp / name
        p.write_text(text)
        return ["--camera", str(p)]
    return args


def _deep(path: Path, option: str) -> list[str]:
    path.write_text("a = " + "[" * 700 + "]" * 700 + "\n")
    return [option, str(path)]


_K = "[[1357.0, 0.0, 819.5], [0.0, 1357.0, 615.5], [0.0, 0.0, 1.0]]"
_SIZE = "width = 1640\nheight = 1232\n"

# name -> arguments (a function of a temporary folder); each is a configuration problem.
REFUSALS = {
    "reachable telemetry without keys": lambda t: [
        "--set", 'network.telemetry="tcp://0.0.0.0:5555"'],
    "robot markers outside the dictionary": _robots_config,
    "robot on a floor marker": _robot_on("[13]"),
    "robot on a pair of floor markers": _robot_on("[16, 4]"),
    "telemetry and control on one endpoint": lambda t: [
        "--set", 'network.telemetry="tcp://127.0.0.1:5599"',
        "--set", 'network.control="tcp://127.0.0.1:5599"'],
    "telemetry and control on one port, one of them on every address": lambda t: [
        "--set", 'network.telemetry="tcp://127.0.0.1:5599"',
        "--set", 'network.control="tcp://*:5599"', "--set", "network.insecure=true"],
    "unknown sim scene": lambda t: ["--source", "sim:nosuchscene"],
    "missing image folder": lambda t: ["--source", f"images:{t / 'nodir'}"],
    "image folder without a decodable image": _undecodable_images,
    "missing video": lambda t: ["--source", f"video:{t / 'none.mp4'}"],
    "missing recording": lambda t: ["--source", f"replay:{t / 'none.jsonl'}"],
    "missing map file": lambda t: ["--map", str(t / "none.csv")],
    "malformed map": _bad_map,
    "missing camera file": lambda t: ["--camera", str(t / "none.yml")],
    "unwritable log": lambda t: ["--log", "/proc/kmead-test.csv"],
    "log and recording the same file": _same_outputs,
    "missing key directory": _missing_keys,
    "Pi camera exposure longer than a frame": lambda t: [
        "--source", "picamera", "--set", "camera.max_exposure_ms=40"],
    # Issue 30: files accepted although broken (numpy warnings on every frame, or every
    # frame "not estimated" with exit 0), and tracebacks.
    "marker at 1e308 m": _map_row("5,1e308,0,0,,,,"),
    "map scaled by 1e200": _toml_map("[[markers]]\nid = 13\nx = 0.0\ny = 0.0\nz = 0.0\n"
                                     "[[markers]]\nid = 16\nx = 0.695e200\ny = 0.0\nz = 0.0\n"
                                     "[[markers]]\nid = 4\nx = 0.0\ny = 0.355e200\nz = 0.0\n"),
    "marker angle 1e300 degrees": _map_row("5,0.3,0.3,0,1e300,,,"),
    "marker id 1e20": _map_row("100000000000000000000,0.3,0.3,0,,,,"),
    "marker length 1e300 m": _map_row("5,0.3,0.3,0,,,,1e300"),
    "map id of 400 digits": _toml_map("[[markers]]\nid = 1" + "0" * 400
                                      + "\nx = 0.0\ny = 0.0\nz = 0.0\n"),
    "distortion 1e300": _camera("cam.toml", f"{_SIZE}camera_matrix = {_K}\n"
                                            "dist_coeffs = [1e300, -0.25, 0, 0, 0.1]\n"),
    "distortion k1 = 9000": _camera("cam.toml", f"{_SIZE}camera_matrix = {_K}\n"
                                                "dist_coeffs = [9000, 0, 0, 0, 0]\n"),
    "focal length 0.001 px": _camera(
        "cam.toml", f"{_SIZE}camera_matrix = [[1357.0, 0, 819.5], [0, 0.001, 615.5], [0, 0, 1]]"
                    "\ndist_coeffs = [0, 0, 0, 0]\n"),
    "camera value not finite": _camera(
        "cam.yml", "%YAML:1.0\n---\ncamera_matrix: [1357.0, 0, 819.5, 0, 1357.0, 615.5, 0, 0, 1]"
                   "\ndistortion_coefficients: [0.1, .nan, 0, 0]\n"),
    "camera values not numbers": _camera(
        "cam.json", '{"camera_matrix": [1357, 0, 819.5, 0, 1357, 615.5, 0, 0, "x"], '
                    '"dist_coeffs": [0, 0, 0, 0]}'),
    "camera file a list": _camera("cam.yml", "%YAML:1.0\n---\n- 1\n- 2\n"),
    "camera skew 1e300": _camera("cam.toml", f"{_SIZE}fx = 1357.0\nfy = 1357.0\ncx = 819.5\n"
                                             "cy = 615.5\nskew = 1e300\n"
                                             "dist_coeffs = [0, 0, 0, 0]\n"),
    # TOML nested 600 deep was a 3,002-line RecursionError; --set echoed 1,400 characters.
    "--set nested 700 deep": lambda t: ["--set", "filter.alpha=" + "[" * 700 + "]" * 700],
    "configuration nested 700 deep": lambda t: _deep(t / "c.toml", "--config"),
    "map nested 700 deep": lambda t: _deep(t / "m.toml", "--map"),
    "camera nested 700 deep": lambda t: _deep(t / "cam.toml", "--camera"),
}


def _zenoh(*sets: str, robots: str = ""):
    """[zenoh] enabled with ``sets`` (and a robot list): judged before any session opens."""
    def args(tmp: Path) -> list[str]:
        out = ["--set", "zenoh.enabled=true"]
        for s in sets:
            out += ["--set", s.replace("TMP", str(tmp))]
        if robots:
            p = tmp / "robots.toml"
            p.write_text(robots)
            out = ["--config", str(p), *out]
        return out
    return args


REFUSALS.update({
    "zenoh listens on the LAN without TLS": _zenoh('zenoh.listen=["tcp/192.168.1.10:7447"]'),
    "zenoh listens on every interface without TLS": _zenoh('zenoh.listen=["tcp/[::]:7447"]'),
    "zenoh tls endpoint without certificates": _zenoh('zenoh.listen=["tls/0.0.0.0:7447"]'),
    "zenoh client that listens": _zenoh('zenoh.mode="client"',
                                        'zenoh.connect=["tcp/127.0.0.1:7447"]',
                                        'zenoh.listen=["tcp/127.0.0.1:7448"]'),
    "zenoh client with nowhere to connect": _zenoh('zenoh.mode="client"'),
    "zenoh certificate file missing": _zenoh('zenoh.tls_ca="TMP/none.pem"',
                                             'zenoh.tls_cert="TMP/none.pem"',
                                             'zenoh.tls_key="TMP/none.pem"'),
    "zenoh robot name that is no ROS 2 token": _zenoh(
        robots='[[robots]]\nname = "amr-1"\nmarkers = [40, 41]\n'),
})


def _run(argv: list[str], capsys) -> tuple[int, str]:
    code = cli.main(argv)
    return code, capsys.readouterr().err.strip()


@pytest.mark.parametrize("case", sorted(REFUSALS))
def test_every_refusal_is_the_same_through_check_and_start(case, tmp_path, capsys):
    args = REFUSALS[case](tmp_path)
    net = [] if any("network.telemetry" in a for a in args) else NET
    check_code, check_err = _run([*args, *SMALL, *net, "--check"], capsys)
    run_code, run_err = _run([*args, *SMALL, *net, "--headless", "--frames", "1"], capsys)
    assert run_code == 2, f"start-up: {run_err}"
    assert check_code == run_code, f"--check: {check_err}\nstart-up: {run_err}"
    # Start-up may log warnings before the refusal; the refusal is its last line, and
    # --check prints the same line.
    last = run_err.splitlines()[-1]
    assert last in check_err.splitlines(), f"--check: {check_err}\nstart-up: {last}"
    assert len(last) < 400 and "Traceback" not in run_err + check_err


def test_a_configuration_check_accepts_starts(tmp_path, capsys):
    log = tmp_path / "run.csv"
    args = [*SMALL, *NET, "--source", "sim", "--log", str(log)]
    assert _run([*args, "--check"], capsys)[0] == 0
    assert not log.exists()  # --check writes nothing
    code, err = _run([*args, "--headless", "--frames", "2"], capsys)
    assert code == 0, err
    assert len(log.read_text().splitlines()) > 1


def test_image_folder_with_one_decodable_image_passes(tmp_path, capsys):
    import cv2

    d = tmp_path / "frames"
    d.mkdir()
    (d / "a.png").write_bytes(b"broken")
    cv2.imwrite(str(d / "b.png"), np.full((48, 64), 128, np.uint8))
    code, err = _run(["--source", f"images:{d}", *SMALL, *NET, "--check"], capsys)
    assert code == 0, err


def test_a_camera_file_of_plain_lists_starts(tmp_path, capsys):
    """docs/camera.md accepts plain lists in a JSON or YAML camera file; under OpenCV 5 this
    was a cv2.error traceback at --check and at start."""
    cam = tmp_path / "cam.json"
    cam.write_text('{"camera_matrix": [1357.0, 0, 819.5, 0, 1357.0, 615.5, 0, 0, 1], '
                   '"dist_coeffs": [0.12, -0.25, 0, 0, 0.1], "width": 1640, "height": 1232}')
    args = ["--camera", str(cam), "--source", "sim", *NET]
    code, err = _run([*args, "--check"], capsys)
    assert code == 0, err
    code, err = _run([*args, "--headless", "--frames", "1"], capsys)
    assert code == 0 and "Traceback" not in err, err


def test_markers_all_at_one_point_refused_at_check_and_start(tmp_path, capsys):
    p = tmp_path / "zero.csv"
    p.write_text("id,x,y,z\n" + "".join(f"{i},0,0,0\n" for i in range(20)))
    check = _run(["--map", str(p), *SMALL, *NET, "--check"], capsys)
    run = _run(["--map", str(p), *SMALL, *NET, "--headless", "--frames", "1"], capsys)
    assert check[0] == run[0] == 2
    assert run[1].splitlines()[-1] in check[1].splitlines()
    assert "span 0 m" in run[1] and "Traceback" not in run[1]
    # One summary line, not the 190 pairs.
    assert len(check[1].splitlines()) <= 2


def test_a_map_in_millimetres_is_warned_at_check_and_start(tmp_path, capsys):
    p = tmp_path / "mm.csv"
    p.write_text("id,x,y,z\n13,0,0,0\n16,1700,0,0\n4,0,1200,0\n5,850,600,0\n")
    check = _run(["--map", str(p), *SMALL, *NET, "--check"], capsys)
    run = _run(["--map", str(p), *SMALL, *NET, "--headless", "--frames", "1"], capsys)
    assert check[0] == run[0] == 0
    assert "millimetres" in check[1] and "millimetres" in run[1]


def test_a_saved_overlay_is_named_in_the_summary(tmp_path, capsys):
    """The per-user overlay (what the UI's Save writes) is loaded by every later plain
    start; the run's summary and the UI's status line say it is in effect."""
    import os

    from kmea_tui.widgets.status_bar import status_text

    overlay = Path(os.environ["XDG_CONFIG_HOME"]) / "kmead" / "kmead.local.toml"
    overlay.parent.mkdir(parents=True, exist_ok=True)
    overlay.write_text("[filter]\nalpha = 0.5\n")
    try:
        assert cli.main([*SMALL, *NET, "--headless", "--frames", "1"]) == 0
        out = capsys.readouterr().out
    finally:
        overlay.unlink()
    assert f"configuration overlay in effect: {overlay}" in out
    assert "overlay" in status_text("connected", None, overlay=True).plain
    assert "overlay" not in status_text("connected", None).plain


def test_a_camera_whose_robots_go_to_this_machine_only_is_warned(capsys):
    """The installed service's configuration without [[robots]]: its poses reach no robot.
    The simulator (make run) sends to loopback on purpose and is not warned."""
    assert cli.main(["--check", "--source", "picamera", "--free-ports"]) == 0
    err = capsys.readouterr().err
    assert ("warning: robots: robots' UDP poses go to this machine only (udp:127.0.0.1:9001, "
            "udp:127.0.0.1:9002): set each [[robots]] destinations") in err
    assert cli.main(["--check", "--free-ports"]) == 0
    assert "this machine only" not in capsys.readouterr().err
    robots = ('robots=[{name="amr1", markers=[40, 41], height=0.2, '
              'destinations=["udp:192.168.1.21:9001"]}]')
    assert cli.main(["--check", "--source", "picamera", "--free-ports", "--set", robots]) == 0
    assert "this machine only" not in capsys.readouterr().err


def test_a_dictionary_of_another_family_than_the_maps_is_warned(capsys):
    assert cli.main(["--check", "--free-ports", "--set", 'detector.dictionary="DICT_6X6_250"']) == 0
    err = capsys.readouterr().err
    assert ("warning: key 'detector.dictionary': DICT_6X6_250 is not the family of the map's "
            "DICT_5X5_100") in err
    assert "configuration OK (1 warning)" in err
    assert cli.main(["--check", "--free-ports", "--set", 'detector.dictionary="DICT_5X5_100"']) == 0
    assert "family" not in capsys.readouterr().err
