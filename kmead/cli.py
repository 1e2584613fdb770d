"""kmead: the localization daemon (see docs/daemon.md for the command-line contract).

Exit codes: 0 done (end of a file source, --frames, SIGINT/SIGTERM); 1 runtime failure (a
camera that cannot be opened or stops, a port in use); 2 bad configuration, map, camera
file or option.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import sys
from typing import Any

from kmead.config.layers import ConfigError, load_config, parse_set
from kmead.config.startup import EXIT_CONFIG

STATUS_PERIOD_S = 5.0
FREE_PORTS = ['network.telemetry="tcp://127.0.0.1:*"', 'network.control="tcp://127.0.0.1:*"']


def version() -> str:
    from kmea import __version__

    return __version__


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="kmead",
        description="Marker-based localization daemon: camera -> ArUco -> KMEA -> robots.",
        epilog="Configuration: the packaged default (config.toml), overlaid by --config FILE "
               "and FILE.local.toml (without --config: ~/.config/kmead/kmead.local.toml, "
               "what the UI's Save wrote), then these options. kmead --check shows the "
               "result. See docs/daemon.md.")
    p.add_argument("--config", metavar="FILE", help="configuration file overlaid on the default")
    p.add_argument("--source", metavar="SPEC",
                   help="sim, sim:SCENE, picamera, camera:INDEX, video:PATH, images:DIR, "
                        "replay:FILE")
    p.add_argument("--camera", metavar="FILE", help="camera model file (camera.file)")
    p.add_argument("--map", metavar="FILE", help="marker map .toml or .csv (map.file)")
    p.add_argument("--algorithm", metavar="NAME", help="estimator (estimator.algorithm)")
    p.add_argument("--set", metavar="SECTION.KEY=VALUE", action="append", default=[],
                   help="override any configuration key; VALUE is TOML (repeatable)")
    p.add_argument("--headless", action="store_true", help="no terminal UI")
    p.add_argument("--log", metavar="FILE.csv", help="CSV log of every estimate (log.csv)")
    p.add_argument("--record", metavar="FILE", help="record detections for replay (log.record)")
    p.add_argument("--frames", metavar="N", type=int,
                   help="stop after N processed frames")
    p.add_argument("--check", action="store_true",
                   help="validate the configuration, map and camera files, print the "
                        "effective configuration and the warnings, then exit (0 OK, 2 not); "
                        "opens no camera and binds no port")
    p.add_argument("--default-config", action="store_true",
                   help="print the documented default configuration (config.toml: every key "
                        "with its default, meaning, range and unit) and exit")
    p.add_argument("--free-ports", action="store_true",
                   help="bind telemetry and control to free ports on 127.0.0.1 (printed at "
                        "start), e.g. next to another running kmead")
    p.add_argument("--status-every", metavar="SECONDS", type=float, default=STATUS_PERIOD_S,
                   help="headless: a one-line status on stderr this often "
                        "(default %(default)g s; 0 = none)")
    p.add_argument("--version", action="version", version=f"kmead {version()}")
    return p


def _overrides(args: argparse.Namespace) -> dict[str, Any]:
    o: dict[str, Any] = {}
    for opt, key in (("source", "source.spec"), ("camera", "camera.file"), ("map", "map.file"),
                     ("algorithm", "estimator.algorithm"), ("log", "log.csv"),
                     ("record", "log.record")):
        v = getattr(args, opt)
        if v is not None:
            o[key] = v
    return o


def _setup_logging(level: str, timestamps: bool | None = None) -> None:
    """kmead's stderr log handler; ``timestamps`` None: unless stderr is the journal."""
    if timestamps is None:
        from kmead.run.status_line import stderr_is_journal

        timestamps = not stderr_is_journal()
    root = logging.getLogger("kmead")
    root.setLevel(level.upper())
    # One stderr handler, on the stderr of this call (main() may run more than once in a
    # process: tests, the UI's embedded daemon), with the time unless journald stamps it.
    for h in [h for h in root.handlers if getattr(h, "_kmead", False)]:
        root.removeHandler(h)
    h = _StderrHandler()
    fmt = "kmead: %(levelname)s: %(message)s"
    h.setFormatter(logging.Formatter(f"%(asctime)s {fmt}" if timestamps else fmt,
                                     "%Y-%m-%d %H:%M:%S"))
    h._kmead = True  # type: ignore[attr-defined]
    root.addHandler(h)
    root.propagate = False


@contextlib.contextmanager
def stderr_logging(level: str, timestamps: bool | None = None):
    """:func:`_setup_logging` for the length of one command, then the ``kmead`` logger as
    it was: main() also runs inside other processes (tests, the benchmarks), where a
    handler left behind would print every later in-process daemon's INFO lines on the
    terminal."""
    root = logging.getLogger("kmead")
    level_before, propagate_before = root.level, root.propagate
    before = [h for h in root.handlers if getattr(h, "_kmead", False)]
    _setup_logging(level, timestamps)
    try:
        yield
    finally:
        for h in [h for h in root.handlers if getattr(h, "_kmead", False)]:
            root.removeHandler(h)
        for h in before:
            root.addHandler(h)
        root.setLevel(level_before)
        root.propagate = propagate_before


class _StderrHandler(logging.StreamHandler):
    """A stream handler on whatever ``sys.stderr`` is when a record is written: a handler
    holding the stderr of an earlier call (a test's captured stream, closed since) would
    fail on every later record of a daemon in the same process."""

    @property  # type: ignore[override]
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:
        pass


def _port_hint(text: str) -> str:
    if "Address already in use" not in text and "address in use" not in text.lower():
        return text
    return (f"{text}; another kmead is probably running (stop it: systemctl stop kmead, or "
            "Ctrl+C in its terminal), or start this one with --free-ports")


def starting_what(spec: str) -> str:
    """What a start with source ``spec`` spends its first seconds on, in a few words."""
    kind = str(spec).partition(":")[0]
    what = {"sim": "building the simulated floor, ~15 s",
            "picamera": "opening the camera", "camera": "opening the camera",
            "video": "opening the video", "images": "reading the images",
            "replay": "opening the recording"}.get(kind, f"opening {spec}")
    return f"loading the map, {what}"


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.default_config:
        from kmead.config.schema import default_config_text

        sys.stdout.write(default_config_text())
        return 0
    if args.frames is not None and args.frames < 1:
        print("kmead: --frames: must be >= 1", file=sys.stderr)
        return EXIT_CONFIG
    if not args.status_every >= 0:
        print("kmead: --status-every: give seconds >= 0", file=sys.stderr)
        return EXIT_CONFIG
    try:
        cfg = load_config(args.config, args.set, _overrides(args))
        if args.free_ports:
            # For this run only: a save_config writes the configured endpoints, never
            # tcp://127.0.0.1:* (every later start would bind random ports). An explicit
            # --set of the same key wins, as before.
            given = {parse_set(item)[0] for item in args.set}
            for item in FREE_PORTS:
                key, value = parse_set(item)
                if key not in given:
                    cfg.set_for_run(key, value, "--free-ports")
    except ConfigError as e:
        print(f"kmead: configuration error: {e}", file=sys.stderr)
        return EXIT_CONFIG
    if args.check:
        from kmead.config.check import run_check

        return run_check(cfg)
    from kmead.run.status_line import stderr_is_journal

    journal = stderr_is_journal()
    with stderr_logging(cfg["log"]["level"], timestamps=not journal):
        return _serve(args, cfg, journal)


def _serve(args: argparse.Namespace, cfg: Any, journal: bool) -> int:
    """The daemon's run, its UI or headless status line, and its summary."""
    from kmead.run.status_line import StatusReporter
    from kmead.tools.host import serve

    ui = not args.headless and sys.stdout.isatty() and sys.stdin.isatty()

    from kmead.run.daemon import Daemon, StartupError
    from kmead.run.notify import Notifier

    if ui:
        # The daemon is built before the UI can show anything (the simulator's floor takes
        # 15-20 s on a Pi): say what is happening rather than leave the terminal blank.
        print(f"kmead: starting ({starting_what(cfg['source']['spec'])})...",
              file=sys.stderr, flush=True)
    try:
        daemon = Daemon(cfg, max_frames=args.frames)
    except StartupError as e:
        print(f"kmead: {_port_hint(str(e))}", file=sys.stderr)
        return e.code
    except ConfigError as e:
        print(f"kmead: configuration error: {e}", file=sys.stderr)
        return EXIT_CONFIG
    except KeyboardInterrupt:  # Ctrl-C while starting (the simulator builds its floor)
        return 130

    endpoints = [f"telemetry {(daemon.telemetry.bound if daemon.telemetry else '') or 'off'}",
                 f"control {daemon.control.bound if daemon.control else 'off'}"]
    print(f"kmead: {', '.join(endpoints)}", file=sys.stderr, flush=True)
    if len(cfg.files) > 1:  # say which files, so a saved overlay never surprises anyone
        print(f"kmead: configuration: {', '.join(cfg.files)}", file=sys.stderr, flush=True)
    holder: list[StatusReporter] = []

    def status_line(notifier: Notifier) -> StatusReporter:
        # The headless status line doubles as systemd's STATUS=.
        r = StatusReporter(daemon.progress, args.status_every or STATUS_PERIOD_S,
                           stream=None if ui else sys.stderr, timestamps=not journal,
                           on_line=notifier.status if notifier.enabled else None)
        if (not ui and args.status_every > 0) or notifier.enabled:
            r.start()
        holder.append(r)
        return r

    code = serve(daemon, ui, f"running: {cfg['source']['spec']}", status_line)
    print(daemon.summary(), flush=True)
    why = "stop requested" if daemon.stop_event.is_set() else (
        f"--frames {args.frames} reached" if args.frames is not None
        and daemon.frames_read >= args.frames else "the source ended")
    final = (f"stopped ({why}): {daemon.totals.frames} frames, exit code {code}"
             if code == 0 else f"stopped with an error: exit code {code}")
    print(holder[0].stamp(final) if holder else final, file=sys.stderr, flush=True)
    return code


if __name__ == "__main__":
    sys.exit(main())
