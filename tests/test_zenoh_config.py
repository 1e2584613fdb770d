"""The [zenoh] section: its defaults, one clear line per bad value, the exposure rule that
start-up and --check share, and the one line that says what to install without the extra."""

from __future__ import annotations

import sys

import pytest

from kmead import cli
from kmead.config.layers import ConfigError, load_config
from kmead.config.plan import plan_startup, zenoh_plan
from kmead.config.site_tls import make_site
from kmead.config.startup import StartupError
from kmead.config.zenoh import ros_token_problem, zenoh_exposure

NET = ["--set", 'network.telemetry="tcp://127.0.0.1:*"',
       "--set", 'network.control="tcp://127.0.0.1:*"']


def _cfg(*sets: str):
    return load_config(None, ["zenoh.enabled=true", *sets], use_local=False)


def test_defaults_are_off_and_loopback_only() -> None:
    z = load_config(None, [], use_local=False)["zenoh"]
    assert z["enabled"] is False
    assert (z["mode"], z["connect"], z["listen"], z["multicast"]) == ("peer", [], [], False)
    assert (z["site"], z["lease_s"], z["ros2"], z["ros_domain"]) == ("kmea", 3.0, True, 0)
    assert (z["ros_namespace"], z["frame_id"], z["insecure"]) == ("/kmea", "map", False)
    assert zenoh_exposure(_cfg()["zenoh"]) == (None, None)


@pytest.mark.parametrize(("setting", "words"), [
    ('zenoh.listen=["tcp/0.0.0.0:7447#iface=eth0"]', "Zenoh endpoint"),
    ('zenoh.connect=["tcp://127.0.0.1:7447"]', "Zenoh endpoint"),
    ('zenoh.connect=["tcp/127.0.0.1:99999"]', "Zenoh endpoint"),
    ("zenoh.connect=" + str(["tcp/127.0.0.1:7447"] * 17).replace("'", '"'), "at most 16"),
    ('zenoh.site="a/b"', "first part of every Zenoh key"),
    ('zenoh.site="*"', "first part of every Zenoh key"),
    ('zenoh.ros_namespace="kmea"', "ROS 2 namespace"),
    ('zenoh.ros_namespace="/1kmea"', "ROS 2 namespace"),
    ('zenoh.frame_id="/map"', "tf2 frame id"),
    ("zenoh.ros_domain=300", "[0, 232]"),
    ("zenoh.lease_s=0.01", "[0.5, 3600] s"),
    ('zenoh.mode="router"', "peer, client"),
])
def test_a_bad_value_is_one_line_naming_the_key(setting: str, words: str) -> None:
    with pytest.raises(ConfigError) as e:
        load_config(None, [setting], use_local=False)
    msg = str(e.value)
    assert f"'{setting.split('=')[0]}'" in msg and words in msg and "\n" not in msg


def test_listening_on_loopback_needs_no_tls_and_insecure_is_warned() -> None:
    assert zenoh_plan(_cfg('zenoh.listen=["tcp/127.0.0.1:7447", "tcp/localhost:7448"]')) == []
    warnings = zenoh_plan(_cfg('zenoh.listen=["tcp/10.0.0.5:7447"]', "zenoh.insecure=true"))
    assert len(warnings) == 1 and "tcp/10.0.0.5:7447" in warnings[0]
    assert "unauthenticated" in warnings[0]


def test_tls_with_certificate_files_may_listen_beyond_loopback(tmp_path) -> None:
    pytest.importorskip("cryptography", reason="the zenoh extra is not installed")
    make_site(tmp_path, "kmea", cameras=["cam0"])
    cfg = _cfg('zenoh.listen=["tls/0.0.0.0:7447"]', f'zenoh.tls_ca="{tmp_path}/ca.pem"',
               f'zenoh.tls_cert="{tmp_path}/cam0.pem"', f'zenoh.tls_key="{tmp_path}/cam0.key"')
    assert zenoh_plan(cfg) == []
    # A file that is no certificate: one line at --check, not a failure at opening.
    (tmp_path / "cert.pem").write_text("-----BEGIN CERTIFICATE-----\n")
    with pytest.raises(StartupError, match=r"zenoh\.tls_cert.*cert\.pem: not a PEM"):
        zenoh_plan(_cfg('zenoh.listen=["tls/0.0.0.0:7447"]', f'zenoh.tls_ca="{tmp_path}/ca.pem"',
                        f'zenoh.tls_cert="{tmp_path}/cert.pem"',
                        f'zenoh.tls_key="{tmp_path}/cam0.key"'))


def test_the_refusal_is_the_same_line_from_check_and_start(capsys) -> None:
    args = [*NET, "--set", "source.fps=0", "--set", "zenoh.enabled=true",
            "--set", 'zenoh.listen=["tcp/192.168.1.10:7447"]']
    assert cli.main([*args, "--check"]) == 2
    check_err = capsys.readouterr().err.strip().splitlines()[-1]
    assert cli.main([*args, "--headless", "--frames", "1"]) == 2
    run_err = capsys.readouterr().err.strip().splitlines()[-1]
    assert check_err == run_err
    assert "zenoh.listen" in run_err and "tls/" in run_err and "insecure" in run_err


def test_without_the_extra_one_line_says_what_to_install(monkeypatch) -> None:
    monkeypatch.setitem(sys.modules, "zenoh", None)  # import zenoh raises ImportError
    with pytest.raises(StartupError) as e:
        plan_startup(_cfg())
    assert str(e.value) == ("key 'zenoh.enabled': the zenoh extra is not installed "
                            "(pip install 'kmea[zenoh]')")
    assert e.value.code == 2
    # Disabled, nothing is imported and nothing is said.
    assert zenoh_plan(load_config(None, [], use_local=False)) == []


def test_robot_names_and_ros_tokens() -> None:
    assert ros_token_problem("amr1") is None and ros_token_problem("_r") is None
    assert "zenoh.ros2 = false" in ros_token_problem("amr-1")
    assert ros_token_problem("1amr") is not None
    robots = 'robots=[{name="amr-1", markers=[40, 41]}]'
    with pytest.raises(StartupError, match="amr-1"):
        zenoh_plan(_cfg(robots))
    assert zenoh_plan(_cfg(robots, "zenoh.ros2=false")) == []


def test_this_machine_meets_on_a_loopback_rendezvous_without_endpoints() -> None:
    """No connect, no listen, no multicast (the defaults): the processes of one machine
    find each other on loopback (docs/fusion.md); endpoints given are used as they are."""
    pytest.importorskip("zenoh", reason="the zenoh extra is not installed")
    import json

    from kmead.outputs.zenoh_session import RENDEZVOUS, session_config

    conf = session_config(_cfg()["zenoh"])
    assert json.loads(conf.get_json("connect/endpoints")) == [RENDEZVOUS]
    listen = json.loads(conf.get_json("listen/endpoints"))
    assert listen == [RENDEZVOUS, "tcp/127.0.0.1:0"]
    assert RENDEZVOUS.startswith("tcp/127.0.0.1:")
    conf = session_config(_cfg('zenoh.connect=["tcp/127.0.0.1:7000"]')["zenoh"])
    assert json.loads(conf.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7000"]
    assert json.loads(conf.get_json("listen/endpoints")) == []
    # Zenoh's lease: 3/4 of lease_s (a silent peer is found gone within lease_s).
    assert json.loads(conf.get_json("transport/link/tx/lease")) == 2250


def test_camera_ids_and_map_digests() -> None:
    from kmea.maps.files import map_digest
    from kmea.sim.scenes import get_scene, wide_map
    from kmead.outputs.zenoh_camera import camera_id

    z = _cfg()["zenoh"]
    assert camera_id(z, "sim:wide?camera=1&speed=0.1") == "cam1"
    assert camera_id(z, "sim:wide") == "cam0" and camera_id(z, "sim:wide-cam1") == "cam1"
    assert camera_id({**z, "camera": "north"}, "sim:wide?camera=1") == "north"
    assert camera_id(z, "picamera").replace("-", "").replace("_", "").isalnum()
    with pytest.raises(ConfigError, match=r"zenoh\.camera"):
        load_config(None, ['zenoh.camera="a/b"'], use_local=False)
    wide = get_scene("wide").effective_map()
    assert map_digest(wide) == map_digest(wide_map())
    assert map_digest(wide) != map_digest(get_scene("default").effective_map())


def test_a_paced_wide_scene_runs_on_the_wall_clock() -> None:
    """Cameras started separately show the robots at the same place (docs/fusion.md)."""
    from kmead.config.startup import source_options

    paced = load_config(None, ['source.spec="sim:wide?camera=1"'], use_local=False)
    assert source_options(paced, "sim")["clock"] == "wall"
    given = load_config(None, ['source.spec="sim:wide?clock=frame"'], use_local=False)
    assert "clock" not in source_options(given, "sim")
    flat = load_config(None, ['source.spec="sim:wide"', "source.fps=0"], use_local=False)
    assert "clock" not in source_options(flat, "sim")
