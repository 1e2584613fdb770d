"""The configuration keys of every service (kmead.config.schema gathers them): the
robots' outputs, fusion, the sockets, the files, Foxglove and Zenoh; and the robots'
table."""

from __future__ import annotations

from typing import Any

from kmead.config.checks import (
    Key,
    camera_id,
    choice,
    flag,
    frame_id,
    integer,
    number,
    off_or_number,
    ros_namespace,
    site_name,
    text_value,
    zenoh_endpoints,
    zmq_endpoint,
)

SERVICE_KEYS: dict[str, dict[str, Key]] = {
    "relay": {
        "stale_after_s": Key(0.5, number(0.01, 3600, unit=" s"),
                  'a robot unseen this long gets `valid=0`',
                  doc="""\
A robot not seen for this long (s) gets one message with valid=0 (and is shown stale).""",
                  live=True),
        "stale_repeat_s": Key(1.0, number(0, 3600, unit=" s"),
                  'repeat `valid=0` this often while unseen; 0 = once',
                  doc="""\
While a robot stays unseen, repeat the valid=0 message this often (s); 0 = only once.""",
                  live=True),
        "extra_fields": Key(False, flag,
                  ('append `vx`, `vy`, `omega`, `sigma`, `age` to each datagram, after the '
                   'existing fields ([protocol.md](protocol.md))'),
                  doc="""\
Append ;vx=..;vy=..;omega=..;sigma=.. (m/s, rad/s, m) to each datagram, after the
existing fields (parsers that read the first seven fields are unaffected).""",
                  live=True),
        "max_sigma_m": Key(0.1, number(1e-4, 100, unit=" m"),
                  'a pose less certain than this (1-sigma) is sent as `valid=0`',
                  doc="""\
A pose whose 1-sigma position uncertainty (m) is beyond what a robot can use is sent with
valid=0 (and shown as no fix), as is a pose that is not finite.""",
                  live=True),
        "max_time_step_s": Key(5.0, number(0.1, 3600, unit=" s"),
                  ('a source whose time steps back, or forward by more than this, sends '
                   'every robot `valid=0` at once'),
                  doc="""\
A source whose frame time steps back, or jumps forward by more than this (s), sends every
robot valid=0 at once and restarts the robots' filters (an event says so)."""),
    },
    "fusion": {
        "max_age_s": Key(0.5, number(1e-3, 3600, unit=" s"),
                  '`kmea fuse` only ([fusion.md](fusion.md))',
                  doc="""\
`kmea fuse` only (docs/fusion.md; it finds the cameras on Zenoh, [zenoh] below): the age
(s) behind the newest measurement beyond which a measurement is dropped."""),
        "max_future_s": Key(0.1, number(0, 60, unit=" s"),
                  'a measurement stamped later than the node\'s clock plus this is refused',
                  doc="""\
A measurement or heartbeat stamped later than the node's own (Unix) clock plus this (s)
is refused and counted: a camera's clock ahead can never move the fusion clock."""),
        "clock_warn_s": Key(0.05, number(1e-3, 3600, unit=" s"),
                  'a camera whose clock is off by more than this gets an event',
                  doc="""\
Each camera's clock offset against the node's is estimated from its messages (status
inputs); beyond this (s) an event names the camera and the offset."""),
        "max_clock_offset_s": Key(5.0, number(1e-3, 3600, unit=" s"),
                  'a camera whose clock is off by more than this is refused until it is back',
                  doc="""\
A camera whose estimated clock offset is beyond this (s) is refused (its state and
reason say so) until its offset is back within it. Behind includes the camera's
processing and network delay and the node's own backlog (a loaded node saw 1.1 s): keep
it well above those."""),
        "max_sigma_m": Key(0.1, number(1e-4, 100, unit=" m"),
                  'a measurement whose sigma is beyond this is refused',
                  doc="""\
A camera's measurement with a 1-sigma position uncertainty beyond this (m) is refused and
counted (below 0.1 mm it is taken as 0.1 mm)."""),
        "margin_m": Key(1.0, number(0, 1000, unit=" m"),
                  'a measurement this far outside the map\'s markers is refused',
                  doc="""\
A measurement further than this (m) outside the extent of the map's markers is refused
and counted."""),
    },
    "network": {
        "telemetry": Key('tcp://127.0.0.1:5555', zmq_endpoint,
                  'PUB endpoint, `""` = off',
                  doc="""\
ZeroMQ PUB socket for telemetry (docs/protocol.md); "" = off."""),
        "control": Key('tcp://127.0.0.1:5556', zmq_endpoint,
                  'REP endpoint, `""` = off',
                  doc="""\
ZeroMQ REP socket for control; localhost only unless you change it. "" = off."""),
        "status_period_s": Key(1.0, number(0.05, 3600, unit=" s"),
                  'period of the `status` message',
                  doc="""\
Period (s) of the "status" telemetry message."""),
        "keys": Key('', text_value,
                  ('CURVE key directory (`kmea keys init DIR`); `""` = no keys: loopback only '
                   '([security.md](security.md))'),
                  doc="""\
CURVE key directory (made by `kmea keys init DIR`, clients added with `kmea keys add DIR
NAME [--viewer]`). "" = no authentication and no encryption: then both sockets may only
bind to loopback (127.x.x.x, localhost, [::1]) or ipc://. With keys, only the public keys
in DIR/operators/ (control and watch) and DIR/viewers/ (watch only) can connect; the
folders are re-read when they change. See docs/security.md."""),
        "insecure": Key(False, flag,
                  '`true` allows binding beyond loopback without keys (warned at every start)',
                  doc="""\
true = allow binding beyond loopback WITHOUT keys (anyone on the network can then move
the robots); kmead warns at every start. Use keys instead."""),
    },
    "log": {
        "dir": Key('', text_value,
                  ('data directory: the only place control requests write (`""` = working '
                   'directory)'),
                  doc="""\
The data directory: the only place a control request (terminal UI, any client) can make
kmead write. log_start / record_start over control take a plain new file name (x.csv,
x.jsonl) created there; never a path, never an existing file. "" = the working directory
(/var/lib/kmead under the systemd unit). Paths in this file and on the command line are
yours and are not confined."""),
        "csv": Key('', text_value,
                  'CSV log from the start',
                  doc="""\
CSV log of every estimate (docs/daemon.md); "" = not at start (it can be started live)."""),
        "record": Key('', text_value,
                  ('recording from the start; a name ending `.zst` is compressed ([Recording and'
                   ' replay](#recording-and-replay))'),
                  doc="""\
Recording of every frame's detections, for --source replay:FILE; "" = off. A name ending
in .zst (run.jsonl.zst) is zstd-compressed: about 1/40 of the plain size on a fixed camera
(0.1 GB an hour at 30 frames/s), 1/3 when every number changes; any other name is plain
JSON lines (about 4 GB an hour at 30 frames/s). docs/daemon.md, Recording and replay."""),
        "part_mb": Key(500.0, off_or_number(1, 1e6, unit=" MB"),
                  ('the CSV log and the recording go on in a new part when its file reaches '
                   'this size (MB on disk); `0` = no limit, else at least 1'),
                  doc="""\
The CSV log and the recording are cut into parts (run-part2.csv, run-part2.jsonl.zst, ...:
new names, each with its header; each recording part replays alone) when the file reaches
this size (MB, 10^6 bytes on disk) or this age (minutes); 0 = no limit of that kind."""),
        "part_min": Key(60.0, off_or_number(1, 7 * 24 * 60, unit=" min"),
                  '... or this age (minutes); `0` = no limit, else at least 1'),
        "keep_days": Key(14.0, off_or_number(0.01, 3650, unit=" days"),
                  ("kmead's files (CSV logs, recordings, snapshots) older than this many days "
                   'are removed from the directories it writes to; `0` = kept forever'),
                  doc="""\
Retention: kmead's own files (CSV logs, recordings, snapshots, recognised by their
content: a user's other files are never touched) in the data directory and the
directories of the running log and recording are removed when older than keep_days days,
oldest first until they take at most keep_mb MB; never a file being written. At the start
of each output, of each part, and hourly. 0 = no limit of that kind."""),
        "keep_mb": Key(4000.0, off_or_number(10, 1e7, unit=" MB"),
                  "... and beyond this many MB of them, the oldest first; `0` = no limit"),
        "min_free_mb": Key(50.0, number(0, 1e7, unit=" MB"),
                  ('free-space floor (MB, 10^6 bytes) for the CSV log and the recording; `0` = '
                   'none ([A full disk](#a-full-disk))'),
                  doc="""\
Free-space floor (MB, 10^6 bytes) for the CSV log and the recording: neither starts when
the disk it goes to has less free, and a running one stops cleanly (whole rows, an event,
"error" in the status) when the disk falls below it, long before it is full. Robots and
telemetry go on. 0 = no floor (a full disk still only stops that output)."""),
        "snapshots_max": Key(200, integer(0, 100000),
                  ('snapshots (`snapshot-*.png`) the data directory may hold: a `snapshot` '
                   'request past it is refused; `0` = none'),
                  doc="""\
Snapshots (control's `snapshot`, `kmea snapshot`, the Camera tab's `s`) in the data
directory: a request is refused when this many snapshot-*.png files are there already, or
when they take this many MB, or below min_free_mb. 0 snapshots = none may be taken."""),
        "snapshots_max_mb": Key(500.0, number(1, 1e6, unit=" MB"),
                  '... and the MB they may take (also refused below `log.min_free_mb`)'),
        "level": Key('info', choice("debug", "info", "warning", "error"),
                  '`debug`, `info`, `warning`, `error`',
                  doc="""\
Level of the daemon's own log lines (stderr and the "log" telemetry topic).""",
                  live=True),
    },
    "foxglove": {
        "enabled": Key(False, flag,
                  ("serve the Foxglove WebSocket protocol; extra `pip install 'kmea[foxglove]'`"
                   " ([Foxglove](#foxglove))"),
                  doc="""\
Serve the Foxglove WebSocket protocol (the optional extra: pip install 'kmea[foxglove]'):
the camera image with marker outlines, the floor, the map markers, the robots and their
poses, for the Foxglove app (Open connection > Foxglove WebSocket > ws://HOST:PORT)."""),
        "host": Key('127.0.0.1', text_value,
                  'interface it listens on (`"127.0.0.1"` = this machine only)',
                  doc="""\
Interface and port; "127.0.0.1" = this machine only. Port 0 = any free port (logged)."""),
        "port": Key(8765, integer(0, 65535),
                  'its port; 0 = any free port (logged)'),
        "image_hz": Key(5.0, number(0, 60, unit=" images/s"),
                  'camera images sent per second at most (JPEG, only while shown; 0 = every frame)',
                  doc="""\
Camera images sent per second at most (JPEG, only while a client shows them; 0 = every frame)."""),
    },
    "zenoh": {
        "enabled": Key(False, flag,
                  ('robot poses on Zenoh: ROS 2 topics (rmw_zenoh) and the binary pose; extra '
                   "`pip install 'kmea[zenoh]'` ([ros2.md](ros2.md))"),
                  doc="""\
Robot poses on Eclipse Zenoh (the optional extra: pip install 'kmea[zenoh]'), natively as
ROS 2 topics (rmw_zenoh's wire format) and as a compact binary pose for robots without
ROS (zenoh-pico). docs/ros2.md."""),
        "mode": Key('peer', choice("peer", "client"),
                  ('`peer` or `client` (a client listens nowhere and needs `connect` or '
                   '`multicast`)'),
                  doc="""\
"peer" (talks to peers and routers directly) or "client" (through one router or peer)."""),
        "connect": Key([], zenoh_endpoints,
                  ('Zenoh endpoints (`tcp/HOST:PORT`, `tls/...`, `udp/...`, `quic/...`, at most '
                   '16 each); listening beyond loopback needs `tls/` and the three certificate '
                   'files, or `zenoh.insecure`; none of them and no multicast (peer mode): the '
                   'processes of this machine meet on loopback ([fusion.md](fusion.md))'),
                  doc="""\
Endpoints to connect to, e.g. ["tcp/127.0.0.1:7447"] for the ROS 2 router (rmw_zenohd);
static endpoints work without multicast. With no connect, no listen and no multicast
(peer mode), the processes of this machine find each other on loopback (docs/fusion.md)."""),
        "listen": Key([], zenoh_endpoints,
                  '',
                  doc="""\
Endpoints this kmead listens on (peer mode only); [] = none. Beyond loopback only tls/
endpoints (mutual TLS, the three files below), unless insecure = true."""),
        "multicast": Key(False, flag,
                  'multicast scouting (static endpoints work without it)',
                  doc="""\
Multicast scouting (finds peers on the LAN without endpoints; unreliable on Wi-Fi)."""),
        "site": Key('kmea', site_name,
                  'first part of every kmea key (`<site>/robots/<robot>/pose`)',
                  doc="""\
The site: the first part of every Zenoh key (<site>/robots/<robot>/pose)."""),
        "camera": Key('', camera_id,
                  ("this camera's id in `<site>/cam/<id>/...` (its measurements for a fusion"
                   " node, [fusion.md](fusion.md)); `\"\"`: `camN` for `sim:wide?camera=N`,"
                   " else the host name"),
                  doc="""\
This camera's id: its measurements go on <site>/cam/<camera>/robots/<robot> for a fusion
node (docs/fusion.md); "" = camN for the simulator's sim:wide?camera=N, else the host name."""),
        "lease_s": Key(3.0, number(0.5, 3600, unit=" s"),
                  ("s (0.5-3600): a silent peer counts as gone within this (Zenoh's own lease is"
                   " 3/4 of it); a fusion node drops a camera silent this long, and a standby"
                   " takes over within it"),
                  doc="""\
s: a peer silent this long counts as gone (Zenoh's transport lease); a camera that sends
nothing for this long is dropped by the fusion node, and a standby node takes over
within it."""),
        "ros2": Key(True, flag,
                  ('the ROS 2 output: `PoseWithCovarianceStamped` on '
                   '`<ros_namespace>/<robot>/pose` and `/tf` `frame_id` -> `<robot>/kmea`, every'
                   ' frame'),
                  doc="""\
ROS 2 output (rmw_zenoh): geometry_msgs/msg/PoseWithCovarianceStamped on
<ros_namespace>/<robot>/pose and /tf from frame_id to <robot>/kmea, every frame."""),
        "ros_distro": Key('jazzy', choice("humble", "jazzy", "kilted"),
                  ("the robots' ROS 2 distro: `humble`, `jazzy` or `kilted` (Humble's "
                   'rmw_zenoh has no type hashes in its keys: the others do)'),
                  doc="""\
The ROS 2 distro of the robots' rmw_zenoh: humble, jazzy or kilted. Humble's keys and
publisher tokens carry TypeHashNotSupported where Jazzy's and Kilted's carry the message
type's RIHS01 hash, so a Humble node hears only a Humble-form publisher (docs/ros2.md)."""),
        "ros_domain": Key(0, integer(0, 232),
                  'ROS domain id (0-232), topic namespace, world frame id'),
        "ros_namespace": Key('/kmea', ros_namespace,
                  ''),
        "frame_id": Key('map', frame_id,
                  ''),
        "dds_bridge": Key(False, flag,
                  "also the CDR on zenoh-bridge-ros2dds's keys (DDS teams)",
                  doc="""\
Also the same CDR on zenoh-bridge-ros2dds's key (the topic name without its leading
slash, no attachment) for teams on a DDS middleware."""),
        "robot_pose": Key(True, flag,
                  'the 56-byte binary pose on `<site>/robots/<robot>/pose`',
                  doc="""\
The compact binary pose (docs/ros2.md, "Robots without ROS") on <site>/robots/<robot>/pose."""),
        "tls_ca": Key('', text_value,
                  "mutual TLS: CA certificate, this kmead's certificate and key (PEM)",
                  doc="""\
Mutual TLS: the CA certificate, this kmead's certificate and private key (PEM files)."""),
        "tls_cert": Key('', text_value,
                  ''),
        "tls_key": Key('', text_value,
                  ''),
        "acl": Key('', text_value,
                  ("the site's access control (`acl.json5` of `kmea keys site`): each peer may "
                   'publish only its own keys ([security.md](security.md)); needs the TLS files'),
                  doc="""\
The site's Zenoh access control file (acl.json5, made by kmea keys site with the site's
certificates): a camera may publish only under <site>/cam/<its id>/, a fusion node only
under <site>/fusion/<its id>/, each besides the robots' outputs; keyed by the
certificate's common name, so it needs tls_ca, tls_cert and tls_key (docs/security.md)."""),
        "insecure": Key(False, flag,
                  '`true` allows listening beyond loopback without TLS (warned at every start)',
                  doc="""\
true: listen beyond loopback without TLS (warned at every start)."""),
    },
}

ROBOTS_DOC = """\
Robots. markers = [id] (single marker: its centre and yaw) or [left, right] (a pair as seen
by the robot looking forward: the midpoint, heading = (right - left) turned +90 degrees).
height: marker plane above the floor (m); length: marker side (m); separation: distance
between the two centres of a pair (m, default 0.10).
destinations: where poses go besides the "robot.NAME" telemetry topic:
  "udp:HOST:PORT"  one ASCII datagram per message, e.g.
                   name=amr1;seq=17;t=1700000000.123456;x=0.512300;y=0.200100;theta=1.570800;valid=1"""
ROBOTS_SUMMARY = ('`name`, `markers` (`[id]` or `[left, right]`), `height` (m, marker plane '
                  'above the floor), `length` (m), `separation` (m, pair centre distance, '
                  'default 0.10), `destinations` (`["udp:HOST:PORT", ...]`)')
DEFAULT_ROBOTS: list[dict[str, Any]] = [
    {"name": "amr1", "markers": [40, 41], "height": 0.2, "length": 0.06, "separation": 0.1,
     "destinations": ["udp:127.0.0.1:9001"]},
    {"name": "amr2", "markers": [42], "height": 0.2, "length": 0.06,
     "destinations": ["udp:127.0.0.1:9002"]},
]

# Tuning internals and plumbing a technician does not choose: out of the generated
# config.toml and the terminal UI's form, still settable (--set, a file, control) and
