"""Every configuration key, declared once: its default, its check (type, range, unit),
whether a running daemon may change it, and what it means.

Everything else is derived from :data:`KEYS`: the checks of configuration files, ``--set``
and live ``set`` requests (:func:`validate_setting`), the live keys (:data:`LIVE_KEYS`),
the documented default configuration (:func:`default_config_text`: the repository's
``config.toml`` and ``kmead --default-config``) and the key table of docs/daemon.md
(:func:`keys_table`). tests/test_settings_schema.py fails when either file disagrees; after
changing a key, ``make config`` writes both.
"""

from __future__ import annotations

import copy
import json
import math
from dataclasses import dataclass
from typing import Any

from kmea.estimators import DEFAULT_ALGORITHM
from kmea.robots.tracking import TrackerConfig
from kmead.config.checks import (
    Check,
    ConfigError,
    algorithm_name,
    camera_id,
    choice,
    detector_parameters,
    dictionary_name,
    flag,
    frame_id,
    integer,
    number,
    off_or_number,
    probability_value,
    ros_namespace,
    shown,
    site_name,
    source_spec,
    text_value,
    validate_robots,
    zenoh_endpoints,
    zmq_endpoint,
)

# The tracking filter's [filter] keys take their defaults from the filter itself: one
# place to change them.
TRACKER = TrackerConfig()

__all__ = [
    "ADVANCED",
    "KEYS",
    "LIVE_KEYS",
    "SCHEMA",
    "Key",
    "default_config",
    "default_config_text",
    "is_live",
    "keys_table",
    "validate_setting",
]


@dataclass(frozen=True)
class Key:
    """One ``section.key``: ``default`` (what config.toml holds), ``check(value, where,
    remote) -> normalised value``, ``summary`` (one line, the docs' table), ``doc`` (the
    comment above it in config.toml; "" = the comment above an earlier key covers it) and
    ``live`` (a running daemon may change it; the others need a restart)."""

    default: Any
    check: Check
    summary: str
    doc: str = ""
    live: bool = False


HEADER = """\
kmead configuration: the documented default. Every key is here with its default value;
a trailing comment gives its range and unit, and "live" when the terminal UI (or any
control client) can change it while kmead runs (the others need a restart).
This file is generated from kmead/config/schema.py (`kmead --default-config` prints it).

kmead always starts from these defaults, then overlays, in order:
  --config FILE           only the keys FILE sets ([[robots]] in FILE replaces the whole list)
  FILE.local.toml         if it exists: what `save_config` (terminal UI, Configuration tab) wrote
  --source/--camera/--map/--algorithm/--log/--record and --set SECTION.KEY=VALUE
Unknown keys and bad values are errors: kmead names the file, the key and the problem
and does not start (exit code 2).
Units: metres, seconds, radians (degrees never appear in this file)."""

KEYS: dict[str, dict[str, Key]] = {
    "source": {
        "spec": Key('sim', source_spec,
                  'frame source (see above)',
                  doc="""\
Where frames come from:
  "sim" or "sim:SCENE"   the simulated RobotAtFactory floor (see `kmea` docs for scenes)
  "picamera"             Raspberry Pi camera through picamera2 (greyscale stream)
  "camera:INDEX"         an OpenCV / V4L2 camera
  "video:PATH"           a video file (every frame, then exit)
  "images:DIR"           an image folder, sorted by name (every image, then exit)
  "replay:FILE"          a kmead recording (--record): re-runs estimation on its detections"""),
        "fps": Key(30.0, number(0, 240, unit=" frames/s"),
                  'rate asked of live cameras; pace of the simulator (0 = unpaced, every frame)',
                  doc="""\
Frame rate asked of live sources (picamera, camera:) and the pace of the simulator.
0 = as fast as possible; for "sim" that also means every rendered frame is processed
(nothing dropped), which is what tests and benchmarks want."""),
        "width": Key(0, integer(0, 16384),
                  "capture size; 0 = the source's default (sim, picamera: 1640x1232)",
                  doc="""\
Capture resolution in pixels; 0 = the source's default (sim and picamera: 1640x1232,
the Pi camera v2 binned mode). The camera model is scaled to it (same aspect ratio only)."""),
        "height": Key(0, integer(0, 16384),
                  ''),
    },
    "camera": {
        "file": Key('', text_value,
                  ('camera model; `""` = the simulator\'s camera (sim), the recording\'s (replay),'
                   ' else a nominal Pi Camera v2'),
                  doc="""\
Camera model file (OpenCV FileStorage YAML/XML/JSON or TOML from `kmea calibrate`).
"" = the simulator's camera for sim sources, the recording's camera for replay,
otherwise a nominal Raspberry Pi Camera v2."""),
        "max_exposure_ms": Key(2.0, number(0, 1000, unit=" ms"),
                  ('exposure asked of the Pi camera (`picamera`), ms; the analogue gain makes up'
                   ' the light (more noise). Blur = speed x exposure (1.5 m/s x 2 ms = 3 mm); 0 '
                   "= the camera's auto exposure. kmead warns once when a robot at "
                   '`filter.max_speed` would smear by more than 4.5 mm ([motion.md](motion.md))'),
                  doc="""\
Exposure (ms) asked of the Pi camera (picamera source), the analogue gain making up the
light: a robot smears by its speed times the exposure (1.5 m/s x 2 ms = 3 mm), and a
shorter exposure means more gain, more noise (docs/motion.md: the trade, measured).
The frame rate (source.fps) bounds it too. 0 = the camera's auto exposure (indoors
10-30 ms: 15-45 mm of smear at 1.5 m/s, markers of moving robots often not found)."""),
    },
    "map": {
        "file": Key('', text_value,
                  ('marker map; `""` = built-in RobotAtFactory 4.0 map (replay: the recording\'s '
                   'map)'),
                  doc="""\
Marker map (.toml or .csv, see docs/maps.md). "" = the built-in RobotAtFactory 4.0 map
(for replay: the map stored in the recording)."""),
    },
    "detector": {
        "dictionary": Key('', dictionary_name,
                  ('ArUco dictionary name or file; `""` = the map\'s (DICT_5X5_100 for the '
                   'built-in map). Also the dictionary of a CSV map'),
                  doc="""\
ArUco dictionary name. "" = the map's dictionary (DICT_5X5_100 for the built-in map:
the RobotAtFactory DICT_5X5_50 codes plus the wall markers 50-65).""",
                  live=True),
        "marker_length": Key(0.06, number(1e-4, 10, unit=" m"),
                  ('side (m) of detected markers neither in the map nor on a robot; default '
                   'length of a CSV map'),
                  doc="""\
Side (m) of detected markers that are neither in the map nor on a robot.""",
                  live=True),
        "corner_refinement": Key('subpix', choice("subpix", "none", "contour", "apriltag"),
                  '`subpix`, `none`, `contour`, `apriltag`',
                  doc="""\
Corner refinement: "subpix" (recommended: corners feed every estimator), "none",
"contour" or "apriltag".""",
                  live=True),
        "parameters": Key({}, detector_parameters,
                  '`cv2.aruco.DetectorParameters` overrides by name',
                  doc="""\
cv2.aruco.DetectorParameters overrides by attribute name, over kmea's defaults for 60 mm
markers seen from 1.2-1.5 m (docs/vision.md), e.g. { adaptiveThreshWinSizeMax = 31 }.""",
                  live=True),
        "workers": Key(2, integer(0, 16),
                  ('detection threads working ahead of the rest of the pipeline (live sources: '
                   'one); 0 = main thread only (see Performance)'),
                  doc="""\
Detection threads working ahead of the rest of the pipeline (both cores busy). 0 = detect
in the main thread. Live sources use one detection thread (newest frame wins) whatever the
number; file sources and the unpaced simulator use this many, in frame order, with results
identical to 0. Replay has nothing to detect. Needs a restart."""),
        "fixed_camera": Key(True, flag,
                  ('a fixed camera, live sources only: markers followed where they were, a full'
                   ' detection in the background (see Performance)'),
                  doc="""\
A fixed camera, live sources only (camera, Pi camera, paced simulator): floor markers are
checked where they were, robot markers detected near where their motion predicts them, a
full detection runs in the background every fixed_full_every frames (markers new in the
view) and at once when the camera is bumped; marker poses and leave-one-out statistics
are recomputed only when something changed (docs/speed.md).
false = full detection of every frame. File sources (images:, video:, replay:, the
unpaced simulator) always use full detection: their results stay frame-exact.""",
                  live=True),
        "fixed_full_every": Key(6, integer(1, 100000),
                  'fixed camera: a full detection every N frames',
                  live=True),
        "fixed_refit_every": Key(30, integer(1, 100000),
                  ("fixed camera: the floor's camera fit updated at most every N frames"
                   " (1 = at every change)"),
                  doc="""\
With a fixed camera, the floor's camera fit is updated at most every fixed_refit_every frames:
in between, a floor marker whose corners were averaged with one more look keeps those of
the last fit, and a floor marker new in the view is placed with the last fit without
being a reference yet (a refit costs 10-40 ms of CPU and moves the fit by micrometres).
1 = refit at every change.""",
                  live=True),
    },
    "estimator": {
        "algorithm": Key(DEFAULT_ALGORITHM, algorithm_name,
                  ('estimator name (why this default: '
                   '[accuracy.md](accuracy.md#the-default-estimator)); `kmea-robust` is slow: '
                   'about 0.3 s of CPU a frame'),
                  doc="""\
corner-pnp (default: the camera from every reference's corners, markers from their corner
rays; the most accurate within the frame budget, see docs/accuracy.md), kmea (the
paper's Algorithm 2), lmea (Algorithm 1), umeyama, kmea-robust (slow: about 0.3 s of CPU a
frame, 2-3 frames/s where kmea runs 70;
an unknown name makes kmead list the available ones).""",
                  live=True),
        "unknown_plane": Key('auto', choice("auto", "floor", "free"),
                  ('markers neither in the map nor on a configured robot: `auto` (on a plane of '
                   'the map when consistent with it, else free with reference-corrected depth), '
                   "`floor`, `free` (the paper's KMEA)"),
                  doc="""\
Markers neither in the map nor on a configured robot: "auto" puts each on a plane of the
map (the floor, a wall) when its corners are consistent with it (a likelihood-ratio test
at the measured corner noise), else estimates it free with its depth corrected by the
references; "floor" always on the floor; "free" never on a plane (the paper's KMEA). The
choice is published per marker (telemetry "plane", CSV rows of kind "plane").""",
                  live=True),
    },
    "filter": {
        "kind": Key('kalman', choice("iir", "kalman"),
                  ('robots: `kalman` = the tracking filter ([tracking.md](tracking.md)), `iir` ='
                   " the paper's filter with `filter.alpha`; markers always use the IIR filter"),
                  doc="""\
Robots: "kalman" = the tracking filter (docs/tracking.md: a Kalman filter per robot driven
by each measurement's sigma, with gating of wrong detections and velocity / turn rate),
"iir" = the paper's first-order filter below. Markers always use the IIR filter.""",
                  live=True),
        "alpha": Key(1.0, number(1e-3, 1),
                  'IIR weight of the new sample, [0.001, 1]; 1 = no filtering',
                  doc="""\
First-order IIR filter on every marker (and, with kind = "iir", robot) pose:
y = alpha*x + (1 - alpha)*y_prev. 1.0 = no filtering.""",
                  live=True),
        "reset_after_s": Key(TRACKER.reset_after_s, number(0.01, 3600, unit=" s"),
                  'a track unseen this long restarts unfiltered',
                  doc="""\
A track not seen for this long (s) restarts from its next measurement.""",
                  live=True),
        "model": Key(TRACKER.model, choice("cv", "ctrv"),
                  ('tracking filter motion model: `ctrv` (drives along its heading), `cv` '
                   '(holonomic)'),
                  doc="""\
Tracking filter: motion model "ctrv" (drives along its heading: differential drive) or
"cv" (position and heading move independently: holonomic robots); process noise as white
acceleration, m^2/s^3 (while cruising, see manoeuvre_scale), and white angular
acceleration, rad^2/s^3 (tuned by `kmea bench tracking`); chi-square gate probability
(3 dof); consistent rejected measurements that re-acquire a robot moved by hand.""",
                  live=True),
        "accel_noise": Key(TRACKER.accel_noise, number(1e-6, 1000, unit=" m^2/s^3"),
                  ('tracking filter process noise while cruising, m^2/s^3 (tuned by `kmea bench '
                   'tracking`)'),
                  live=True),
        "turn_noise": Key(TRACKER.turn_noise, number(1e-6, 1000, unit=" rad^2/s^3"),
                  'tracking filter angular process noise, rad^2/s^3',
                  live=True),
        "gate_probability": Key(TRACKER.gate_probability, probability_value,
                  ('chi-square gate (3 dof); a measurement outside is rejected and reported '
                   '(`event`)'),
                  live=True),
        "reacquire_n": Key(TRACKER.reacquire_n, integer(1, 1000),
                  'consistent rejected measurements that re-acquire a robot moved by hand',
                  live=True),
        "manoeuvre_scale": Key(TRACKER.manoeuvre_scale, number(1, 1e6),
                  ('> 1: a second motion model with this many times the process noise '
                   '(manoeuvres), run with the first as an IMM; 1 = one model '
                   '([tracking.md](tracking.md))'),
                  doc="""\
Manoeuvres (docs/tracking.md): with manoeuvre_scale > 1 a second motion model whose process
noise is that many times the above runs alongside (two models, IMM); the mean time (s) of
a manoeuvre and between manoeuvres set how fast the filter switches. 1 = one model.""",
                  live=True),
        "manoeuvre_time_s": Key(TRACKER.manoeuvre_time_s, number(0.01, 3600, unit=" s"),
                  ("mean time in a manoeuvre and between manoeuvres, s (the models' switching "
                   'rates)'),
                  live=True),
        "cruise_time_s": Key(TRACKER.cruise_time_s, number(0.01, 3600, unit=" s"),
                  '',
                  live=True),
        "step_k": Key(TRACKER.step_k, number(0.01, 1e9),
                  ("no measurement moves the position by more than step_k of the filter's own "
                   'sigma after it; 1e9 = no bound ([tracking.md](tracking.md))'),
                  doc="""\
Step bound: no accepted measurement moves the position by more than step_k of the
filter's own sigma after it (an outlier inside the gate moves the output that far at
most; 1e9 = no bound).""",
                  live=True),
        "outlier_probability": Key(TRACKER.outlier_probability, probability_value,
                  ("the outlier mixture's prior: the fraction of measurements that are outliers "
                   '(the reported covariance after an accepted measurement includes the chance '
                   'that it was one)'),
                  doc="""\
Outlier mixture: the covariance after an accepted measurement includes the chance that it
was an outlier (probabilistic data association): prior outlier_probability, an outlier's
position uniform within outlier_radius (m) of the robot. The reported sigma then says how
doubtful the measurement was (docs/tracking.md).""",
                  live=True),
        "outlier_radius": Key(TRACKER.outlier_radius, number(1e-4, 10, unit=" m"),
                  'm (0.0001-10); an outlier falls anywhere within this distance of the robot',
                  live=True),
        "max_speed": Key(TRACKER.max_speed, number(1e-3, 100, unit=" m/s"),
                  ('m/s: re-acquisition candidates further apart than this speed allows are not '
                   'one robot (also the 1-sigma speed of a new track)'),
                  doc="""\
Re-acquisition: the fastest a robot drives (m/s; also the 1-sigma of a new track's
speed): candidates further apart than that allows are not one robot.""",
                  live=True),
        "predict": Key(False, flag,
                  ("live sources: send each pose predicted to the send time (the datagram's `t` "
                   'is then the send time)'),
                  doc="""\
Latency compensation: send each robot's pose predicted to the send time (the datagram's
t is then the send time) instead of the pose at the capture time.""",
                  live=True),
    },
    "stats": {
        "loo": Key(True, flag,
                  'leave-one-out error of every detected map marker every frame',
                  doc="""\
Leave-one-out error of every detected map marker every frame (feeds the statistics).""",
                  live=True),
        "window": Key(300, integer(1, 100000),
                  'statistics window (samples per marker)',
                  doc="""\
Statistics window, in frames.""",
                  live=True),
        "displaced_threshold": Key(0.01, number(1e-4, 10, unit=" m"),
                  ('smallest median offset (m) called a moved marker at 1 mm per pixel (it scales '
                   'with the metres per pixel at the marker and the error level, '
                   '`kmea/stats/moved.py`)'),
                  doc="""\
A map marker has moved (event, and "moved" in the markers telemetry) when the median of
its leave-one-out error over the last N frames it was measured in exceeds this (m, at 1 mm
per pixel at the marker: twice it at 820x616) and 3x the error level of the other markers
and of its own jitter (kmea/stats/moved.py).""",
                  live=True),
        "displaced_frames": Key(5, integer(1, 1000),
                  ('... over the last N frames it was measured in (median of N, at least 3 '
                   'figures)'),
                  live=True),
    },
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
# documented in docs/daemon.md's "Advanced keys". The rest are what a technician sets.
ADVANCED: frozenset[str] = frozenset({
    "detector.corner_refinement", "detector.parameters", "detector.workers",
    "detector.fixed_camera",
    "detector.fixed_full_every", "detector.fixed_refit_every",
    "estimator.unknown_plane",
    "filter.reset_after_s", "filter.model", "filter.accel_noise", "filter.turn_noise",
    "filter.gate_probability", "filter.reacquire_n", "filter.manoeuvre_scale",
    "filter.manoeuvre_time_s", "filter.cruise_time_s", "filter.step_k",
    "filter.outlier_probability", "filter.outlier_radius",
    "stats.loo", "stats.window", "stats.displaced_frames",
    "relay.stale_repeat_s", "relay.max_sigma_m", "relay.max_time_step_s",
    "fusion.max_age_s", "fusion.max_future_s", "fusion.clock_warn_s", "fusion.max_clock_offset_s",
    "fusion.max_sigma_m", "fusion.margin_m",
    "network.status_period_s",
    "log.part_mb", "log.part_min", "log.min_free_mb", "log.snapshots_max",
    "log.snapshots_max_mb",
    "foxglove.host", "foxglove.image_hz",
    "zenoh.mode", "zenoh.multicast", "zenoh.camera", "zenoh.lease_s", "zenoh.ros_namespace",
    "zenoh.frame_id", "zenoh.dds_bridge", "zenoh.robot_pose", "zenoh.insecure",
})

# Keys that changed their name: a file or request that uses the old one is told the new.
# ("track" names the robots' tracking filter only; the fixed camera's keys say so.)
RENAMED = {"log.record_part_mb": "log.part_mb", "log.record_part_min": "log.part_min",
           "detector.tracking": "detector.fixed_camera",
           "detector.track_full_every": "detector.fixed_full_every",
           "detector.track_refit_every": "detector.fixed_refit_every"}

# ---------------------------------------------------------------------------- derived

SCHEMA: dict[str, dict[str, Check]] = {
    section: {name: key.check for name, key in keys.items()} for section, keys in KEYS.items()}
LIVE_KEYS: frozenset[str] = frozenset(
    {"robots"} | {f"{s}.{n}" for s, keys in KEYS.items() for n, k in keys.items() if k.live})


def is_live(key: object) -> bool:
    """True when a live ``set`` request may change ``key``."""
    return isinstance(key, str) and key in LIVE_KEYS


def validate_setting(key: Any, value: Any, where: str, remote: bool = False) -> Any:
    """Check one ``section.key`` (or ``robots``); returns the normalised value.

    ``remote``: the value came over the network (stricter where a value names a file).
    Raises :class:`ConfigError` only.
    """
    if not isinstance(key, str) or len(key) > 64:
        raise ConfigError(f"{where}: key must be a short string SECTION.KEY, got {shown(key)}")
    if key == "robots":
        return validate_robots(value, f"{where}: robots", remote)
    section, _, name = key.partition(".")
    if section not in SCHEMA:
        raise ConfigError(f"{where}: unknown section {shown(section)} in key {shown(key)} "
                          f"(sections: {', '.join([*SCHEMA, 'robots'])})")
    if not name or "." in name:
        raise ConfigError(f"{where}: key {shown(key)} must be SECTION.KEY")
    if name not in SCHEMA[section]:
        if key in RENAMED:
            raise ConfigError(f"{where}: key {key!r} is now {RENAMED[key]!r} (same meaning)")
        raise ConfigError(f"{where}: unknown key {shown(key)} (known in [{section}]: "
                          f"{', '.join(SCHEMA[section])})")
    try:
        return SCHEMA[section][name](value, f"{where}: key {key!r}", remote)
    except ConfigError:
        raise
    except (ValueError, TypeError, OverflowError, RecursionError) as e:
        # A check is written not to raise anything else; if one does, it is still one line.
        raise ConfigError(f"{where}: key {key!r}: {type(e).__name__}: {e}") from None


def default_config() -> dict[str, Any]:
    """``{section: {key: default}, "robots": [robot tables]}``, fresh copies."""
    out: dict[str, Any] = {s: {n: copy.deepcopy(k.default) for n, k in keys.items()}
                           for s, keys in KEYS.items()}
    out["robots"] = copy.deepcopy(DEFAULT_ROBOTS)
    return out


def toml_value(v: Any) -> str:
    """``v`` (a default: bool, int, float, str, list, empty table) as TOML text."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) and ("." in repr(v) or "e" in repr(v)) else f"{v}.0"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, str):
        return json.dumps(v)  # a JSON string of printable text is a TOML basic string
    if isinstance(v, list):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} = {toml_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(f"no TOML text for {type(v).__name__}")


def _comment(text: str) -> list[str]:
    return [f"# {line}".rstrip() for line in text.splitlines()]


def _trailer(key: Key) -> str:
    parts = [t for t in (getattr(key.check, "text", ""), "live" if key.live else "") if t]
    return f"  # {', '.join(parts)}" if parts else ""


def default_config_text() -> str:
    """The documented default configuration (config.toml): every key a technician sets
    (not :data:`ADVANCED`) with its default, the comment that explains it, and its range,
    unit and whether it is live; each section names its advanced keys in one line."""
    out = _comment(HEADER)
    for section, keys in KEYS.items():
        out += ["", f"[{section}]"]
        for name, key in keys.items():
            if f"{section}.{name}" in ADVANCED:
                continue
            doc = key.doc
            if not doc:  # the comment above an earlier key covers it: unless that one is out
                above = [(n, k) for n, k in list(keys.items())[:list(keys).index(name)] if k.doc]
                if above and f"{section}.{above[-1][0]}" in ADVANCED:
                    doc = above[-1][1].doc
            out += _comment(doc)
            out.append(f"{name} = {toml_value(key.default)}{_trailer(key)}")
        advanced = [n for n in keys if f"{section}.{n}" in ADVANCED]
        if advanced:
            out += _comment(f"Advanced (docs/daemon.md, Advanced keys; --set or this file): "
                            f"{', '.join(advanced)}")
    out += ["", *_comment(ROBOTS_DOC)]
    for robot in DEFAULT_ROBOTS:
        out += ["[[robots]]"] + [f"{k} = {toml_value(v)}" for k, v in robot.items()] + [""]
    return "\n".join(out[:-1]) + "\n"


def keys_table() -> str:
    """The key tables of docs/daemon.md (markdown): key, default, meaning, a technician's
    keys first, then :data:`ADVANCED`; a key without a summary joins the row above it."""
    return (_table(advanced=False) + "\n#### Advanced keys\n\nTuning internals and "
            "plumbing, out of the generated `config.toml` and the terminal UI's form; set "
            "them with `--set`, a configuration file or a control `set` (the live ones).\n\n"
            + _table(advanced=True))


def _table(advanced: bool) -> str:
    rows: list[tuple[list[str], list[str], str]] = []
    for section, keys in KEYS.items():
        for name, key in keys.items():
            if (f"{section}.{name}" in ADVANCED) != advanced:
                continue
            cell = f"`{toml_value(key.default)}`"
            if not key.summary and rows:
                rows[-1][0].append(f"`{section}.{name}`")
                rows[-1][1].append(cell)
            else:
                rows.append(([f"`{section}.{name}`"], [cell], key.summary))
    lines = ["| key | default | meaning |", "|-----|---------|---------|"]
    for names, defaults, summary in rows:
        # one default for a row whose keys share it
        shown_default = defaults[0] if len(set(defaults)) == 1 else ", ".join(defaults)
        lines.append(f"| {', '.join(names)} | {shown_default} | {summary} |")
    if not advanced:
        names = ", ".join(DEFAULT_ROBOTS[i]["name"] for i in range(len(DEFAULT_ROBOTS)))
        lines.append(f"| `[[robots]]` | {names} | {ROBOTS_SUMMARY} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    """Write config.toml and the key table of docs/daemon.md from :data:`KEYS` (``make
    config``, from the repository's root)."""
    from pathlib import Path

    Path("config.toml").write_text(default_config_text())
    doc = Path("docs/daemon.md")
    text = doc.read_text()
    start = text.index("| key | default | meaning |")
    last = start  # the tables end with the advanced keys' (keys_table writes both)
    while (nxt := text.find("| key | default | meaning |", last + 1)) != -1:
        last = nxt
    end = text.index("\n\n", last) + 1
    doc.write_text(text[:start] + keys_table() + text[end:])


if __name__ == "__main__":
    main()
