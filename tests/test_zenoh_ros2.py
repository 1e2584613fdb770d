"""ROS 2 poses on Zenoh, tested without ROS 2: golden vectors, and a real kmead on loopback.

- Golden vectors: the REP-2011 type hashes rosbags computes against the values ROS 2
  publishes (rmw_zenoh's design.md for std_msgs/String, `ros2 topic info -v` and rosidl's
  generated hashes for the other two), a message's CDR bytes written out from the CDR rules,
  rmw_zenoh's own examples of keys and liveliness tokens, and the attachment against Zenoh's
  own serializer.
- A real kmead (subprocess, the simulated floor) connects to a Zenoh session this test
  opens on loopback; the test's subscriber does what an rmw_zenoh subscription does with a
  sample (drops it without a valid attachment, checks the key and the CDR encapsulation,
  decodes with rosbags) and checks every field, the liveliness tokens, and the binary pose,
  which a C decoder compiled here also reads.
"""

from __future__ import annotations

import math
import os
import shutil
import socket
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from deadlines import DEADLINE, JOIN

zenoh = pytest.importorskip("zenoh", reason="the zenoh extra is not installed "
                                            "(pip install 'kmea[zenoh]')")
pytest.importorskip("rosbags", reason="the zenoh extra is not installed")

from rosbags.typesys import Stores, get_typestore  # noqa: E402

from kmead.outputs import ros2_messages as msgs  # noqa: E402
from kmead.outputs import ros2_wire as wire  # noqa: E402
from kmead.outputs.robot_pose_wire import STOPPING, TRACKED, unpack_pose  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent

STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
POSE_HASH = "RIHS01_26432f9803e43727d3c8f668d1fdb3c630f548af631e2f4e31382371bfea3b6e"
TF_HASH = "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"


# ------------------------------------------------------------------------- golden vectors

@pytest.mark.parametrize("store", [Stores.ROS2_JAZZY, Stores.ROS2_KILTED])
def test_type_hashes_are_the_ones_ros_publishes(store) -> None:
    ts = get_typestore(store)
    assert ts.hash_rihs01("std_msgs/msg/String") == STRING_HASH
    assert ts.hash_rihs01(msgs.POSE_TYPE) == POSE_HASH
    assert ts.hash_rihs01(msgs.TF_TYPE) == TF_HASH
    assert msgs.type_hash(msgs.POSE_TYPE) == POSE_HASH


def test_keys_and_tokens_are_rmw_zenohs_examples() -> None:
    # Verbatim from rmw_zenoh's docs/design.md (a talker and a listener on /chatter).
    assert (wire.topic_keyexpr(0, "/chatter", "std_msgs/msg/String", STRING_HASH)
            == f"0/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}")
    assert (wire.node_token(0, "aac3178e146ba6f1fc6e6a4085e77f21", 0, "/", "listener")
            == "@ros2_lv/0/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener")
    assert (wire.publisher_token(0, "8b20917502ee955ac4476e0266340d5c", 0, 10, "/", "talker",
                                 "/chatter", "std_msgs/msg/String", STRING_HASH,
                                 wire.Qos(depth=7))
            == "@ros2_lv/0/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/"
               f"std_msgs::msg::dds_::String_/{STRING_HASH}/::,7:,:,:,,")
    assert wire.qos_keyexpr(wire.Qos(depth=5, reliability=wire.BEST_EFFORT)) == "2::,5:,:,:,,"
    assert wire.bridge_keyexpr("/kmea/amr1/pose") == "kmea/amr1/pose"


def test_attachment_is_zenohs_serialization_of_seq_time_gid() -> None:
    from zenoh.ext import Int64, z_deserialize, z_serialize

    gid = bytes(range(16))
    att = wire.attachment(7, 1_764_000_000_123_456_789, gid)
    assert len(att) == 33
    assert att == z_serialize((Int64(7), Int64(1_764_000_000_123_456_789), gid)).to_bytes()
    assert z_deserialize(tuple[Int64, Int64, bytes], zenoh.ZBytes(att)) == (
        7, 1_764_000_000_123_456_789, gid)
    assert wire.parse_attachment(att) == (7, 1_764_000_000_123_456_789, gid)
    for bad in (att[:-1], att + b"\0", att[:16] + b"\x0f" + att[17:], b""):
        with pytest.raises(ValueError):
            wire.parse_attachment(bad)


def test_pose_cdr_is_the_bytes_the_cdr_rules_give() -> None:
    cov = msgs.covariance6(msgs.covariance3(0.004, None))
    data = msgs.pose_cdr(1764000000.25, "map", 0.5, -0.25, math.pi / 2, cov)
    s, c = math.sin(math.pi / 4), math.cos(math.pi / 4)
    expected = (b"\x00\x01\x00\x00"  # encapsulation: CDR little-endian, options 0
                + struct.pack("<iII4s", 1764000000, 250_000_000, 4, b"map\0")  # header
                + struct.pack("<7d", 0.5, -0.25, 0.0, 0.0, 0.0, s, c)  # 8-aligned already
                + struct.pack("<36d", *cov))
    assert data == expected
    tf = msgs.tf_cdr(1764000000.25, "map", "amr1/kmea", 0.5, -0.25, math.pi / 2)
    expected_tf = (b"\x00\x01\x00\x00" + struct.pack("<I", 1)
                   + struct.pack("<iII4s", 1764000000, 250_000_000, 4, b"map\0")
                   + struct.pack("<I10s", 10, b"amr1/kmea\0") + b"\0" * 6  # align to 8
                   + struct.pack("<7d", 0.5, -0.25, 0.0, 0.0, 0.0, s, c))
    assert tf == expected_tf


def test_covariance_is_the_filters_and_never_zero() -> None:
    cov3 = np.array([[4e-6, 1e-6, 2e-7], [1e-6, 9e-6, -3e-7], [2e-7, -3e-7, 4e-4]])
    c = msgs.covariance6(msgs.covariance3(0.003, cov3)).reshape(6, 6)
    assert np.allclose(c[np.ix_([0, 1, 5], [0, 1, 5])], cov3)
    assert c[2, 2] == c[3, 3] == c[4, 4] == msgs.UNESTIMATED_VARIANCE
    assert np.allclose(c, c.T)
    # The IIR filter: the pose's sigma; none at all: the tracking filter's default sigma.
    c = msgs.covariance6(msgs.covariance3(0.01, None)).reshape(6, 6)
    assert math.isclose(c[0, 0], 1e-4) and math.isclose(c[1, 1], 1e-4)
    assert math.isclose(c[5, 5], (0.01 / 0.05) ** 2)
    for sigma, cov in ((None, None), (0.0, None), (0.0, np.zeros((3, 3))),
                       (math.nan, np.full((3, 3), math.nan))):
        d = np.diag(msgs.covariance6(msgs.covariance3(sigma, cov)).reshape(6, 6))
        assert np.all(d > 0), (sigma, cov)


# ------------------------------------------------------------------------- a real kmead

def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def rmw_zenoh_take(sample, ros_type: str) -> tuple[tuple[int, int, bytes], object]:
    """What rmw_zenoh's subscription does with a sample: no attachment or a bad one, and it
    is dropped (ValueError here); a key that is not the topic's with the type's hash, or a
    payload that is not little-endian CDR, cannot be taken."""
    if sample.attachment is None:
        raise ValueError("no attachment: rmw_zenoh drops the sample")
    att = wire.parse_attachment(sample.attachment.to_bytes())
    key = str(sample.key_expr)
    assert key.endswith(f"/{wire.dds_type_name(ros_type)}/{msgs.type_hash(ros_type)}"), key
    payload = sample.payload.to_bytes()
    assert payload[:4] == b"\x00\x01\x00\x00", payload[:4]
    return att, msgs.decode(payload, ros_type)


class Capture:
    """Everything the test's Zenoh session receives, with the tokens alive."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.samples: list = []
        self.tokens: list[tuple[str, str]] = []  # (kind, key)
        self.done = threading.Event()

    def on_sample(self, s) -> None:
        with self.lock:
            self.samples.append(s)
            stops = {str(x.key_expr) for x in self.samples
                     if str(x.key_expr).startswith("kmea/robots/")
                     and unpack_pose(x.payload.to_bytes()).flags & STOPPING}
        if len(stops) == 2:
            self.done.set()

    def on_token(self, s) -> None:
        with self.lock:
            self.tokens.append((str(s.kind).rsplit(".", 1)[-1], str(s.key_expr)))


@pytest.fixture(scope="module")
def daemon_run(tmp_path_factory):
    port = _free_port()
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("listen/endpoints", f'["tcp/127.0.0.1:{port}"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    cap = Capture()
    session = zenoh.open(conf)
    subs = [session.declare_subscriber("0/**", cap.on_sample),
            session.declare_subscriber("kmea/**", cap.on_sample),
            session.liveliness().declare_subscriber("@ros2_lv/0/**", cap.on_token,
                                                    history=True)]
    env = dict(os.environ, PYTHONPATH=f"{ROOT}{os.pathsep}" + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.run(
        [sys.executable, "-m", "kmead.cli", "--headless", "--frames", "30", "--free-ports",
         "--status-every", "0", "--set", "source.fps=0", "--set", "source.width=820",
         "--set", "source.height=616", "--set", "zenoh.enabled=true",
         "--set", f'zenoh.connect=["tcp/127.0.0.1:{port}"]', "--set", "zenoh.dds_bridge=true"],
        capture_output=True, text=True, env=env, timeout=DEADLINE, cwd=tmp_path_factory.mktemp("z"))
    assert proc.returncode == 0, proc.stderr
    # The valid = 0 "stopping" pose of both robots is the last thing kmead sends.
    assert cap.done.wait(DEADLINE), f"no stopping poses; got {len(cap.samples)} samples"
    for s in subs:
        s.undeclare()
    session.close()
    return cap, proc.stderr


def _by_key(cap: Capture, prefix: str) -> list:
    return [s for s in cap.samples if str(s.key_expr).startswith(prefix)]


def test_pose_topic_samples_are_taken_as_rmw_zenoh_takes_them(daemon_run) -> None:
    cap, _ = daemon_run
    key = f"0/kmea/amr1/pose/geometry_msgs::msg::dds_::PoseWithCovarianceStamped_/{POSE_HASH}"
    samples = [s for s in cap.samples if str(s.key_expr) == key]
    assert len(samples) >= 10  # 30 frames; the first may go before the route is set up
    binary = [unpack_pose(s.payload.to_bytes()) for s in _by_key(cap, "kmea/robots/amr1/")]
    fixes = {round(b.t, 6): b for b in binary if b.valid}
    seqs, gids = [], set()
    for s in samples:
        (seq, ts, gid), m = rmw_zenoh_take(s, msgs.POSE_TYPE)
        seqs.append(seq)
        gids.add(gid)
        assert abs(ts - time.time_ns()) < 600e9  # ns since the epoch, at the send
        assert m.header.frame_id == "map"
        t = m.header.stamp.sec + m.header.stamp.nanosec * 1e-9
        b = fixes[round(t, 6)]  # the capture instant is the binary pose's t
        p = m.pose.pose
        assert math.isclose(p.position.x, b.x, abs_tol=1e-6)
        assert math.isclose(p.position.y, b.y, abs_tol=1e-6)
        assert p.position.z == 0.0
        q = p.orientation
        assert math.isclose(math.atan2(2 * q.w * q.z, 1 - 2 * q.z * q.z), b.theta, abs_tol=1e-6)
        c = np.asarray(m.pose.covariance).reshape(6, 6)
        xy_yaw = c[np.ix_([0, 1, 5], [0, 1, 5])]
        assert np.all(np.linalg.eigvalsh(xy_yaw) > 0)  # the filter's, positive definite
        assert math.isclose(math.sqrt(c[0, 0]), b.sigma_x, rel_tol=1e-5)
        assert c[2, 2] == msgs.UNESTIMATED_VARIANCE
    # One publisher, in order (congestion control DROP may lose one under load, never
    # reorder: Zenoh's reliable channel).
    assert seqs == sorted(set(seqs)) and seqs[0] >= 1
    assert len(gids) == 1


def test_tf_goes_from_map_to_robot_kmea(daemon_run) -> None:
    cap, _ = daemon_run
    samples = _by_key(cap, "0/tf/tf2_msgs::msg::dds_::TFMessage_/" + TF_HASH)
    children = set()
    for s in samples:
        _, m = rmw_zenoh_take(s, msgs.TF_TYPE)
        (tr,) = m.transforms
        assert tr.header.frame_id == "map"
        children.add(tr.child_frame_id)
    assert children == {"amr1/kmea", "amr2/kmea"}


def test_samples_without_attachment_would_be_dropped_and_the_bridge_key_has_none(
        daemon_run) -> None:
    cap, _ = daemon_run
    bridge = _by_key(cap, "kmea/amr1/pose")
    assert bridge and all(s.attachment is None for s in bridge)
    with pytest.raises(ValueError, match="drops"):
        rmw_zenoh_take(bridge[0], msgs.POSE_TYPE)
    m = msgs.decode(bridge[0].payload.to_bytes(), msgs.POSE_TYPE)  # the same CDR
    assert m.header.frame_id == "map"


def test_liveliness_tokens_of_the_node_and_publishers(daemon_run) -> None:
    cap, _ = daemon_run
    puts = {k for kind, k in cap.tokens if kind == "PUT"}
    deletes = {k for kind, k in cap.tokens if kind == "DELETE"}
    node = [k for k in puts if "/NN/" in k]
    assert len(node) == 1
    zid = node[0].split("/")[2]
    assert node[0] == wire.node_token(0, zid, 0, "/kmea", "kmead")
    for topic, ros_type, h, depth in (("/kmea/amr1/pose", msgs.POSE_TYPE, POSE_HASH, 10),
                                      ("/kmea/amr2/pose", msgs.POSE_TYPE, POSE_HASH, 10),
                                      ("/tf", msgs.TF_TYPE, TF_HASH, 100)):
        (tok,) = [k for k in puts if f"/MP/%/%kmea/kmead/{wire.mangle(topic)}/" in k]
        parts = tok.split("/")
        assert parts[:4] == ["@ros2_lv", "0", zid, "0"] and parts[5] == "MP"
        assert parts[9:] == [wire.mangle(topic), wire.dds_type_name(ros_type), h,
                             f"::,{depth}:,:,:,,"]
    assert deletes == puts  # kmead stopped: every token went with it


def test_binary_pose_every_message_and_the_stopping_one(daemon_run) -> None:
    cap, _ = daemon_run
    poses = [unpack_pose(s.payload.to_bytes()) for s in _by_key(cap, "kmea/robots/amr2/pose")]
    assert sum(p.valid for p in poses) >= 10
    assert all(p.flags & TRACKED and p.sigma_x > 0 and p.sigma_theta > 0 for p in poses)
    assert [p.seq for p in poses] == sorted(p.seq for p in poses)
    last = poses[-1]
    assert not last.valid and last.flags & STOPPING


@pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler (cc) on this machine")
def test_the_c_decoder_reads_the_bytes_kmead_sent(daemon_run, tmp_path) -> None:
    cap, _ = daemon_run
    exe = tmp_path / "kmea_pose_decode"
    subprocess.run(["cc", "-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-o",
                    str(exe), str(ROOT / "examples" / "kmea_pose_decode.c")], check=True,
                   timeout=JOIN)
    payloads = [s.payload.to_bytes() for s in _by_key(cap, "kmea/robots/")]
    out = subprocess.run([str(exe)], input=b"".join(payloads), capture_output=True,
                         check=True, timeout=JOIN).stdout.decode().splitlines()
    assert len(out) == len(payloads)
    for line, data in zip(out, payloads, strict=True):
        p = unpack_pose(data)
        f = dict(kv.split("=") for kv in line.split())
        assert int(f["seq"]) == p.seq and int(f["valid"]) == p.valid
        assert int(f["flags"]) == p.flags
        for k in ("t", "x", "y", "theta", "sigma_x", "sigma_y", "sigma_theta", "vx", "vy",
                  "omega", "age"):
            assert math.isclose(float(f[k]), getattr(p, k), abs_tol=1e-6), k
    # A message of another size or version is refused.
    bad = subprocess.run([str(exe)], input=b"\x02" + payloads[0][1:], capture_output=True,
                         timeout=JOIN)
    assert bad.returncode == 1 and b"refused" in bad.stderr
