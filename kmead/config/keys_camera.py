"""The configuration keys of a camera's frames (kmead.config.schema gathers them):
where frames come from, the camera, the map, detection, estimation, the robots' filter
and the marker statistics."""

from __future__ import annotations

from kmea.estimators import DEFAULT_ALGORITHM
from kmea.robots.tracking import TrackerConfig
from kmead.config.checks import (
    Key,
    algorithm_name,
    choice,
    detector_parameters,
    dictionary_name,
    flag,
    integer,
    number,
    probability_value,
    source_spec,
    text_value,
)

# The tracking filter's [filter] keys take their defaults from the filter itself: one
# place to change them.
TRACKER = TrackerConfig()

CAMERA_KEYS: dict[str, dict[str, Key]] = {
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
}
