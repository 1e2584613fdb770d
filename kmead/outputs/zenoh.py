"""Robot poses on Zenoh: ROS 2 topics in rmw_zenoh's wire format, and the binary pose.

Fed by the relay (:class:`kmead.outputs.relay.Relay` calls :meth:`ZenohOutput.send` for every
message a robot gets, after the frame's UDP datagrams went out), per robot:

- ``<site>/robots/<robot>/pose``: the 56-byte binary pose (:mod:`kmead.outputs.robot_pose_wire`),
  every message, valid = 0 ones too;
- ROS 2 (``zenoh.ros2``), fixes only (a ROS consumer judges staleness by ``header.stamp``):
  ``PoseWithCovarianceStamped`` on ``<ros_namespace>/<robot>/pose`` and a ``TFMessage`` on
  ``/tf`` from ``frame_id`` to ``<robot>/kmea``, each with rmw_zenoh's attachment, and the
  liveliness tokens of the node ``kmead`` and of each publisher (``ros2 node list``,
  ``ros2 topic list``). QoS: reliable, volatile, keep last 10 (pose) / 100 (/tf, as tf2's
  broadcaster); Zenoh's congestion control DROP: a slow subscriber loses samples, never
  blocks the frame loop.
- ``zenoh.dds_bridge``: the same CDR on zenoh-bridge-ros2dds's key (the topic name without
  its leading slash), no attachment.

A failed put is counted in :attr:`errors` and logged once; the frame loop never sees it.

Threads: the publisher table (:attr:`ZenohOutput.robots`) is filled lazily by :meth:`send`,
which the relay calls from the frame loop and from the stall watcher (the control thread's
:meth:`kmead.run.daemon.Daemon.tick`, robots gone stale while no frame comes), and emptied by
:meth:`retain` (a live ``robots`` change) and :meth:`close`. Every one of these calls is
made under the owner's lock (the daemon's, or the fusion node's), so the table has one
owner at a time and needs no lock of its own; nothing here starts a thread.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any

from kmead.config.zenoh import ros_token_problem
from kmead.outputs import ros2_messages as msgs
from kmead.outputs import ros2_wire as wire
from kmead.outputs.robot_pose_wire import PREDICTED, STOPPING, TRACKED, BinaryPose, pack_pose
from kmead.outputs.zenoh_session import import_zenoh, open_session

log = logging.getLogger("kmead.zenoh")

NODE_NAME = "kmead"
FUSION_NODE_NAME = "kmea_fuse"
POSE_QOS, TF_QOS = wire.Qos(depth=10), wire.Qos(depth=100)


@dataclass
class RosPublisher:
    """One ROS 2 publisher: its Zenoh publisher, liveliness token, GID and sequence."""

    publisher: Any
    token: Any
    gid: bytes
    bridge: Any = None  # the zenoh-bridge-ros2dds key's publisher
    seq: int = 0  # rmw_zenoh's sequence numbers start at 1

    def put(self, payload: bytes, seq: int | None = None) -> None:
        """``seq``: the robot's own sequence number (one sequence per robot across
        speakers, kmead.outputs.voice), when above this publisher's last."""
        self.seq = seq if seq is not None and seq > self.seq else self.seq + 1
        att = wire.attachment(self.seq, time.time_ns(), self.gid)
        self.publisher.put(payload, attachment=att)
        if self.bridge is not None:
            self.bridge.put(payload)

    def undeclare(self) -> None:
        for entity in (self.publisher, self.token, self.bridge):
            if entity is not None:
                entity.undeclare()


@dataclass
class RobotPublishers:
    binary: Any = None
    pose: RosPublisher | None = None
    skipped_ros: bool = False  # a name that cannot be a ROS topic token (warned once)


@dataclass
class ZenohOutput:
    z: dict
    session: Any = None
    zid: str = ""
    robots: dict[str, RobotPublishers] = field(default_factory=dict)
    tf: RosPublisher | None = None
    node_token: Any = None
    node_name: str = NODE_NAME
    owns_session: bool = True  # close() closes the session (else its owner does)
    sent: int = 0
    errors: int = 0
    _next_entity: int = 1  # 0 is the node's id
    _warned: bool = False

    @classmethod
    def open(cls, z: dict, session: Any = None, node_name: str = NODE_NAME) -> ZenohOutput:
        """On a new session, or on ``session`` (its owner closes it)."""
        out = cls(z, session if session is not None else open_session(z),
                  node_name=node_name, owns_session=session is None)
        out.zid = str(out.session.info.zid())
        if z["ros2"]:
            out.node_token = out.session.liveliness().declare_token(
                wire.node_token(z["ros_domain"], out.zid, 0, out._namespace, node_name))
        log.info("zenoh: session %s (%s), site %r%s", out.zid, z["mode"], z["site"],
                 f", ROS 2 domain {z['ros_domain']}" if z["ros2"] else "")
        return out

    @property
    def _namespace(self) -> str:
        return self.z["ros_namespace"] or "/"

    def pose_topic(self, robot: str) -> str:
        return f"{self.z['ros_namespace']}/{robot}/pose"

    def _declare(self, key: str):
        zenoh = import_zenoh()
        return self.session.declare_publisher(
            key, reliability=zenoh.Reliability.RELIABLE,
            congestion_control=zenoh.CongestionControl.DROP)  # not express: it lost samples

    def _ros_publisher(self, topic: str, ros_type: str, qos: wire.Qos) -> RosPublisher:
        z = self.z
        h = wire.distro_type_hash(z["ros_distro"], msgs.type_hash(ros_type))
        token_key = wire.publisher_token(z["ros_domain"], self.zid, 0, self._next_entity,
                                         self._namespace, self.node_name, topic, ros_type, h,
                                         qos)
        self._next_entity += 1
        pub = self._declare(wire.topic_keyexpr(z["ros_domain"], topic, ros_type, h))
        token = self.session.liveliness().declare_token(token_key)
        bridge = self._declare(wire.bridge_keyexpr(topic)) if z["dds_bridge"] else None
        return RosPublisher(pub, token, wire.gid_for(token_key), bridge)

    def _publishers(self, name: str) -> RobotPublishers:
        rp = self.robots.get(name)
        if rp is None:
            rp = self.robots[name] = RobotPublishers()
            if self.z["robot_pose"]:
                rp.binary = self._declare(f"{self.z['site']}/robots/{name}/pose")
            if self.z["ros2"]:
                problem = ros_token_problem(name)
                if problem is None:
                    rp.pose = self._ros_publisher(self.pose_topic(name), msgs.POSE_TYPE,
                                                  POSE_QOS)
                else:
                    rp.skipped_ros = True
                    log.warning("zenoh: no ROS 2 topic for robot %s: %s", name, problem)
        return rp

    def send(self, tr: Any, t: float, valid: bool, stopping: bool = False) -> None:
        """One relay message of robot track ``tr`` (a :class:`kmead.outputs.relay.RobotChannel`) at
        time ``t`` (s). Never raises: a failure is counted and logged once."""
        try:
            self._send(tr, t, valid, stopping)
            self.sent += 1
        except Exception as e:  # Zenoh errors, a closed session at shutdown
            self.errors += 1
            if not self._warned:
                self._warned = True
                log.warning("zenoh: publishing robot %s failed: %s (counted; further "
                            "failures are not logged)", tr.name, e)

    def _send(self, tr: Any, t: float, valid: bool, stopping: bool) -> None:
        rp = self._publishers(tr.name)
        extra = tr.extra if valid else {}
        c3 = msgs.covariance3(tr.sigma, tr.cov)
        if rp.binary is not None:
            flags = ((PREDICTED if extra.get("age", 0.0) > 0 else 0)
                     | (TRACKED if tr.cov is not None else 0) | (STOPPING if stopping else 0))
            rp.binary.put(pack_pose(BinaryPose(
                valid, flags, tr.seq, t, tr.x, tr.y, tr.theta, math.sqrt(c3[0][0]),
                math.sqrt(c3[1][1]), math.sqrt(c3[2][2]), extra.get("vx", 0.0),
                extra.get("vy", 0.0), extra.get("omega", 0.0), extra.get("age", 0.0))))
        if not valid or rp.pose is None:
            return
        rp.pose.put(msgs.pose_cdr(t, self.z["frame_id"], tr.x, tr.y, tr.theta,
                                  msgs.covariance6(c3)), seq=tr.seq)
        if self.tf is None:  # declared with the first pose: a silent speaker lists none
            self.tf = self._ros_publisher("/tf", msgs.TF_TYPE, TF_QOS)
        self.tf.put(msgs.tf_cdr(t, self.z["frame_id"], f"{tr.name}/kmea", tr.x, tr.y,
                                tr.theta))

    def retain(self, names: set[str]) -> None:
        """Undeclare the publishers (and their tokens) of robots no longer configured."""
        for name in [n for n in self.robots if n not in names]:
            self.quiet(name)

    def quiet(self, name: str) -> None:
        """This process no longer speaks for robot ``name`` (another speaker does,
        kmead.outputs.voice): its publishers and their ROS 2 tokens go, so that the ROS
        graph lists the speaking publisher only (``/tf``'s too once no robot is left)."""
        rp = self.robots.pop(name, None)
        if rp is not None:
            for entity in (rp.binary, rp.pose):
                if entity is not None:
                    entity.undeclare()
        if self.tf is not None and not any(r.pose is not None for r in self.robots.values()):
            self.tf.undeclare()
            self.tf = None

    def close(self) -> None:
        if self.session is None:
            return
        self.retain(set())
        for entity in (self.tf, self.node_token):
            if entity is not None:
                entity.undeclare()
        self.tf = self.node_token = None
        if self.owns_session:
            try:
                self.session.close()
            except Exception as e:  # zenoh.ZError: "close operation timed out"
                log.warning("zenoh: closing the session: %s", str(e).splitlines()[0])
        self.session = None
