"""The three ROS 2 distros teams run (``zenoh.ros_distro``), held against rmw_zenoh's own bytes.

The golden values below were produced from each distro's release of ``ros2/rmw_zenoh``
(the ros2-gbp release repository: humble 0.1.9, jazzy 0.2.10, kilted 0.6.7):

- the GIDs by compiling that release's ``src/detail/simplified_xxhash3.cpp`` and hashing the
  token with it as ``Entity::Entity`` does (low 64 bits, then high 64 bits, host order on
  x86-64 and arm64: little-endian); the three releases carry the same file and give the
  same bytes;
- ``TypeHashNotSupported``: the literal Humble's ``rmw_publisher_data.cpp`` puts where Jazzy
  and Kilted ask ``rosidl_stringify_type_hash`` for the ``RIHS01_...`` text; token layout,
  QoS text and attachment are the same code in the three (``liveliness_utils.cpp``,
  ``attachment_helpers.cpp``: only ``RMW_GID_STORAGE_SIZE`` replaces a literal 16).

A real kmead then publishes in the Humble form, and every sample's GID is the one its
publisher's token gives, as an rmw_zenoh graph computes it.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from deadlines import DEADLINE

zenoh = pytest.importorskip("zenoh", reason="the zenoh extra is not installed "
                                            "(pip install 'kmea[zenoh]')")
pytest.importorskip("rosbags", reason="the zenoh extra is not installed")

from kmead.config.checks import ConfigError  # noqa: E402
from kmead.config.schema import validate_setting  # noqa: E402
from kmead.outputs import ros2_messages as msgs  # noqa: E402
from kmead.outputs import ros2_wire as wire  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
ZID = "aac3178e146ba6f1fc6e6a4085e77f21"
POSE_HASH = "RIHS01_26432f9803e43727d3c8f668d1fdb3c630f548af631e2f4e31382371bfea3b6e"
TF_HASH = "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"
STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"

# token -> the GID rmw_zenoh's simplified_xxhash3.cpp gives it (module docstring).
RMW_ZENOH_GIDS = {
    f"@ros2_lv/0/{ZID}/0/1/MP/%/%kmea/kmead/%tf/tf2_msgs::msg::dds_::TFMessage_/{TF_HASH}/"
    "::,100:,:,:,,": "1c50159df8610e8e2fc6111ac5f6cb17",
    f"@ros2_lv/0/{ZID}/0/1/MP/%/%kmea/kmead/%tf/tf2_msgs::msg::dds_::TFMessage_/"
    "TypeHashNotSupported/::,100:,:,:,,": "2931aac193aa1eb57f46d57e858c0aa0",
    f"@ros2_lv/0/{ZID}/0/2/MP/%/%kmea/kmead/%kmea%amr1%pose/geometry_msgs::msg::dds_::"
    f"PoseWithCovarianceStamped_/{POSE_HASH}/::,10:,:,:,,": "26cda97e74f5feb68e4db3608657d088",
    f"@ros2_lv/0/{ZID}/0/2/MP/%/%kmea/kmead/%kmea%amr1%pose/geometry_msgs::msg::dds_::"
    "PoseWithCovarianceStamped_/TypeHashNotSupported/::,10:,:,:,,":
        "22f0ebac49127917cd16b56f4ff97861",
    # rmw_zenoh's design.md talker.
    "@ros2_lv/0/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/"
    f"std_msgs::msg::dds_::String_/{STRING_HASH}/::,7:,:,:,,":
        "eb85fa883b7846dc448a4501890ad062",
}


@pytest.mark.parametrize("token", sorted(RMW_ZENOH_GIDS))
def test_the_gid_is_rmw_zenohs_hash_of_the_token(token: str) -> None:
    assert wire.gid_for(token).hex() == RMW_ZENOH_GIDS[token]


@pytest.mark.parametrize("distro", wire.DISTROS)
def test_each_distro_builds_its_own_keys_and_tokens(distro: str) -> None:
    h = wire.distro_type_hash(distro, msgs.type_hash(msgs.POSE_TYPE))
    assert h == ("TypeHashNotSupported" if distro == "humble" else POSE_HASH)
    key = wire.topic_keyexpr(0, "/kmea/amr1/pose", msgs.POSE_TYPE, h)
    assert key == f"0/kmea/amr1/pose/geometry_msgs::msg::dds_::PoseWithCovarianceStamped_/{h}"
    token = wire.publisher_token(0, ZID, 0, 2, "/kmea", "kmead", "/kmea/amr1/pose",
                                 msgs.POSE_TYPE, h, wire.Qos(depth=10))
    assert token in RMW_ZENOH_GIDS  # the exact token whose rmw_zenoh GID is golden
    assert wire.gid_for(token).hex() == RMW_ZENOH_GIDS[token]
    tf_h = wire.distro_type_hash(distro, msgs.type_hash(msgs.TF_TYPE))
    tf_token = wire.publisher_token(0, ZID, 0, 1, "/kmea", "kmead", "/tf", msgs.TF_TYPE, tf_h,
                                    wire.Qos(depth=100))
    assert tf_token in RMW_ZENOH_GIDS


def test_an_unknown_distro_is_one_line_naming_the_key() -> None:
    with pytest.raises(ValueError, match="iron"):
        wire.distro_type_hash("iron", POSE_HASH)
    with pytest.raises(ConfigError, match=r"zenoh\.ros_distro"):
        validate_setting("zenoh.ros_distro", "rolling", "--set")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def humble_run(tmp_path_factory):
    """A kmead with ``zenoh.ros_distro = "humble"``: every ROS 2 sample and token it sent."""
    port = _free_port()
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("listen/endpoints", f'["tcp/127.0.0.1:{port}"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    lock, samples, tokens = threading.Lock(), [], []
    gone = threading.Event()

    def on_sample(s) -> None:
        with lock:
            samples.append((str(s.key_expr), s.attachment.to_bytes() if s.attachment else None))

    def on_token(s) -> None:
        with lock:
            kind = str(s.kind).rsplit(".", 1)[-1]
            tokens.append((kind, str(s.key_expr)))
            if kind == "DELETE" and "/NN/" in str(s.key_expr):
                gone.set()

    session = zenoh.open(conf)
    subs = [session.declare_subscriber("0/**", on_sample),
            session.liveliness().declare_subscriber("@ros2_lv/0/**", on_token, history=True)]
    env = dict(os.environ, PYTHONPATH=f"{ROOT}{os.pathsep}" + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.run(
        [sys.executable, "-m", "kmead.cli", "--headless", "--frames", "20", "--free-ports",
         "--status-every", "0", "--set", "source.fps=0", "--set", "source.width=820",
         "--set", "source.height=616", "--set", "zenoh.enabled=true",
         "--set", 'zenoh.ros_distro="humble"',
         "--set", f'zenoh.connect=["tcp/127.0.0.1:{port}"]'],
        capture_output=True, text=True, env=env, timeout=DEADLINE,
        cwd=tmp_path_factory.mktemp("humble"))
    assert proc.returncode == 0, proc.stderr
    assert gone.wait(DEADLINE), "kmead's node token never went"
    for s in subs:
        s.undeclare()
    session.close()
    with lock:
        return list(samples), list(tokens)


def test_a_humble_kmead_publishes_humbles_keys_and_tokens(humble_run) -> None:
    samples, tokens = humble_run
    keys = {k for k, _ in samples}
    assert ("0/kmea/amr1/pose/geometry_msgs::msg::dds_::PoseWithCovarianceStamped_/"
            "TypeHashNotSupported") in keys
    assert "0/tf/tf2_msgs::msg::dds_::TFMessage_/TypeHashNotSupported" in keys
    assert not any("RIHS01" in k for k in keys)
    publishers = {k for kind, k in tokens if kind == "PUT" and "/MP/" in k}
    assert publishers and all(k.split("/")[-2] == "TypeHashNotSupported" for k in publishers)


def test_every_samples_gid_is_the_graphs_gid_of_its_publisher(humble_run) -> None:
    samples, tokens = humble_run
    graph = {}  # topic chunk -> the GID a graph computes from the publisher's token
    for kind, k in tokens:
        if kind == "PUT" and "/MP/" in k:
            graph[k.split("/")[9]] = wire.gid_for(k)
    seen = 0
    for key, att in samples:
        assert att is not None, key
        _, _, gid = wire.parse_attachment(att)
        topic = "%" + key.split("/", 1)[1].rsplit("/", 2)[0].replace("/", "%")
        assert gid == graph[topic], key
        seen += 1
    assert seen >= 10
