"""rmw_zenoh's wire format: key expressions, liveliness tokens, the sample attachment.

What a ROS 2 node on ``rmw_zenoh_cpp`` (Humble 0.1, Jazzy 0.2, Kilted 0.6) expects from a
publisher, read from each distro's release of ``ros2/rmw_zenoh`` (``liveliness_utils.cpp``,
``attachment_helpers.cpp``, ``rmw_publisher_data.cpp``; versions in docs/ros2.md) and held
by tests/test_ros2_distros.py against bytes that source produced. Pure functions on strings
and bytes, no Zenoh import; the CDR payload is :mod:`kmead.outputs.ros2_messages` (rosbags).

The three distros differ in one place: Humble has no REP-2011 type hashes, and its
rmw_zenoh puts ``TypeHashNotSupported`` where Jazzy and Kilted put the ``RIHS01_...``
hash, in the data key and in the publisher's token. Everything else (token layout, QoS
text, GID, attachment) is the same bytes in all three.

- Data key: ``<domain>/<topic without its leading and trailing slash>/<dds type>/<RIHS01
  hash>``, e.g. ``0/kmea/amr1/pose/geometry_msgs::msg::dds_::PoseWithCovarianceStamped_/
  RIHS01_2643...``.
- Liveliness tokens (``ros2 topic list`` and ``ros2 node list`` are built from them):
  ``@ros2_lv/<domain>/<zid>/<nid>/<id>/<NN|MP|...>/<enclave>/<namespace>/<node>`` and for a
  publisher ``.../<topic>/<dds type>/<hash>/<qos>``; every '/' inside a name becomes '%',
  an empty enclave or the root namespace is ``%``.
- Attachment (without it an rmw_zenoh subscriber drops the sample): Zenoh's own
  serialization of (int64 sequence number, int64 source timestamp in ns since the epoch,
  the 16-byte publisher GID as a sequence): 8 + 8 + 1 (LEB128 length, 16) + 16 = 33 bytes,
  little-endian.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import xxhash

ADMIN_SPACE = "@ros2_lv"
DISTROS = ("humble", "jazzy", "kilted")
HUMBLE_TYPE_HASH = "TypeHashNotSupported"  # rmw_zenoh 0.1 (Humble), rmw_publisher_data.cpp
GID_SIZE = 16  # RMW_GID_STORAGE_SIZE
ATTACHMENT = struct.Struct("<qqB16s")  # seq, source timestamp ns, len(gid) = 16, gid

# rmw/types.h enum values, and rmw_zenoh's defaults: a QoS component equal to its default
# is left empty in the token ("::,7:,:,:,," is a talker with depth 7, the rest default).
RELIABLE, BEST_EFFORT = 1, 2
TRANSIENT_LOCAL, VOLATILE = 1, 2
KEEP_LAST, KEEP_ALL = 1, 2
_QOS_DEFAULTS = {"reliability": RELIABLE, "durability": VOLATILE, "history": KEEP_LAST,
                 "depth": 42}


@dataclass(frozen=True)
class Qos:
    """A publisher's QoS as the token states it (deadline, lifespan, liveliness: rmw's
    defaults, infinite and automatic)."""

    depth: int
    reliability: int = RELIABLE
    durability: int = VOLATILE
    history: int = KEEP_LAST


def mangle(name: str) -> str:
    """A ROS name as one key chunk: every '/' becomes '%'; the empty name is '%'."""
    return name.replace("/", "%") if name else "%"


def dds_type_name(ros_type: str) -> str:
    """``geometry_msgs/msg/Pose`` -> ``geometry_msgs::msg::dds_::Pose_`` (rmw's type name)."""
    package, kind, name = ros_type.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def strip_slashes(topic: str) -> str:
    """One leading and one trailing '/' removed, as rmw_zenoh's ``strip_slashes``."""
    start = 1 if topic.startswith("/") else 0
    end = len(topic) - 1 if topic.endswith("/") and len(topic) > start else len(topic)
    return topic[start:end]


def topic_keyexpr(domain: int, topic: str, ros_type: str, type_hash: str) -> str:
    return f"{domain}/{strip_slashes(topic)}/{dds_type_name(ros_type)}/{type_hash}"


def bridge_keyexpr(topic: str) -> str:
    """zenoh-bridge-ros2dds's key for a topic: its name without the leading slash."""
    return topic[1:] if topic.startswith("/") else topic


def qos_keyexpr(q: Qos) -> str:
    """``<reliability>:<durability>:<history>,<depth>:<deadline>:<lifespan>:<liveliness>``,
    defaults empty (``rmw_zenoh_cpp`` ``qos_to_keyexpr``)."""
    def part(key: str, value: int) -> str:
        return "" if value == _QOS_DEFAULTS[key] else str(value)
    return (f"{part('reliability', q.reliability)}:{part('durability', q.durability)}:"
            f"{part('history', q.history)},{part('depth', q.depth)}:,:,:,,")


def node_token(domain: int, zid: str, node_id: int, namespace: str, node: str,
               enclave: str = "") -> str:
    """The node's liveliness token (``NN``); a node's token repeats its id."""
    return (f"{ADMIN_SPACE}/{domain}/{zid}/{node_id}/{node_id}/NN/{mangle(enclave)}/"
            f"{mangle(namespace.rstrip('/'))}/{mangle(node)}")


def publisher_token(domain: int, zid: str, node_id: int, entity_id: int, namespace: str,
                    node: str, topic: str, ros_type: str, type_hash: str, qos: Qos,
                    enclave: str = "") -> str:
    """A publisher's liveliness token (``MP``)."""
    return (f"{ADMIN_SPACE}/{domain}/{zid}/{node_id}/{entity_id}/MP/{mangle(enclave)}/"
            f"{mangle(namespace.rstrip('/'))}/{mangle(node)}/{mangle(topic)}/"
            f"{dds_type_name(ros_type)}/{type_hash}/{qos_keyexpr(qos)}")


def distro_type_hash(distro: str, rihs01: str) -> str:
    """The type hash a ``distro``'s rmw_zenoh puts in keys and tokens: the REP-2011
    ``rihs01`` hash, or Humble's placeholder."""
    if distro not in DISTROS:
        raise ValueError(f"ROS 2 distro {distro!r}: one of {', '.join(DISTROS)}")
    return HUMBLE_TYPE_HASH if distro == "humble" else rihs01


def gid_for(token: str) -> bytes:
    """A publisher's 16-byte GID as rmw_zenoh computes it (``Entity::Entity``): XXH3-128 of
    its liveliness token, the low 64 bits then the high 64 bits, each little-endian. A
    subscriber reports this GID per message and the graph reports it per publisher: equal
    only if both are computed so."""
    return xxhash.xxh3_128_intdigest(token.encode()).to_bytes(GID_SIZE, "little")


def attachment(seq: int, source_timestamp_ns: int, gid: bytes) -> bytes:
    """The 33-byte attachment of one sample (module docstring)."""
    return ATTACHMENT.pack(seq, source_timestamp_ns, GID_SIZE, gid)


def parse_attachment(data: bytes) -> tuple[int, int, bytes]:
    """(sequence number, source timestamp ns, gid), as an rmw_zenoh subscriber reads it;
    ValueError for anything else (it drops such a sample)."""
    if len(data) != ATTACHMENT.size:
        raise ValueError(f"attachment of {len(data)} bytes, expected {ATTACHMENT.size}")
    seq, ts, n, gid = ATTACHMENT.unpack(data)
    if n != GID_SIZE:
        raise ValueError(f"attachment gid length {n}, expected {GID_SIZE}")
    return seq, ts, gid
