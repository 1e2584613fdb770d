"""``kmead``: the localization daemon (see docs/daemon.md for the command-line contract).

Exit codes: 0 done (end of a file source, --frames, SIGINT/SIGTERM); 1 runtime failure (a
camera that cannot be opened or stops, a port in use); 2 bad configuration, map, camera
file or option.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
from typing import Any

from kmead.config import ConfigError, load_config
from kmead.startup import EXIT_CONFIG


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="kmead",
        description="Marker-based localization daemon: camera -> ArUco -> KMEA -> robots.",
        epilog="Configuration: the packaged default (config.toml), overlaid by --config FILE, "
               "FILE.local.toml, then these options. See docs/daemon.md.")
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


def _setup_logging(level: str) -> None:
    root = logging.getLogger("kmead")
    root.setLevel(level.upper())
    mine = [h for h in root.handlers if getattr(h, "_kmead", False)]
    for h in mine:  # main() run again in one process: today's stderr, not a closed one
        if isinstance(h, logging.StreamHandler) and h.stream is not sys.stderr:
            with h.lock:  # not setStream(): it flushes the old stream, which may be closed
                h.stream = sys.stderr
    if not mine:
        h = logging.StreamHandler(sys.stderr)
        h.setFormatter(logging.Formatter("kmead: %(levelname)s: %(message)s"))
        h._kmead = True  # type: ignore[attr-defined]
        root.addHandler(h)
    root.propagate = False


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.frames is not None and args.frames < 1:
        print("kmead: --frames: must be >= 1", file=sys.stderr)
        return EXIT_CONFIG
    try:
        cfg = load_config(args.config, args.set, _overrides(args))
    except ConfigError as e:
        print(f"kmead: configuration error: {e}", file=sys.stderr)
        return EXIT_CONFIG
    _setup_logging(cfg["log"]["level"])
    ui = not args.headless and sys.stdout.isatty() and sys.stdin.isatty()

    from kmead.daemon import Daemon, StartupError

    try:
        daemon = Daemon(cfg, max_frames=args.frames)
    except StartupError as e:
        print(f"kmead: {e}", file=sys.stderr)
        return e.code
    except ConfigError as e:
        print(f"kmead: configuration error: {e}", file=sys.stderr)
        return EXIT_CONFIG
    except KeyboardInterrupt:  # Ctrl-C while starting (the simulator builds its floor)
        return 130

    endpoints = [f"telemetry {daemon.telemetry.bound or 'off'}",
                 f"control {daemon.control.bound if daemon.control else 'off'}"]
    print(f"kmead: {', '.join(endpoints)}", file=sys.stderr, flush=True)
    code = 0
    try:
        if ui:
            code = _run_with_ui(daemon)
        else:
            previous = {s: signal.signal(s, lambda *_: daemon.stop())
                        for s in (signal.SIGINT, signal.SIGTERM)}
            try:
                code = daemon.run()
            finally:
                for s, h in previous.items():
                    signal.signal(s, h)
    except KeyboardInterrupt:
        daemon.stop()
    finally:
        daemon.close()
    print(daemon.summary(), flush=True)
    return code


def _run_with_ui(daemon) -> int:
    """Daemon in a background thread, the Textual UI in the foreground on its sockets."""
    try:
        from kmea_tui.app import KmeaTui
        from kmea_tui.client import DaemonClient
    except ImportError as e:
        logging.getLogger("kmead").warning("terminal UI unavailable (%s); running headless", e)
        signal.signal(signal.SIGTERM, lambda *_: daemon.stop())
        return daemon.run()
    # A keyed daemon's own UI connects as the operator of its key directory.
    from kmea.curve_client import CurveKeyError

    try:
        client = DaemonClient(_connectable(daemon.telemetry.bound),
                              _connectable(daemon.control.bound if daemon.control else ""),
                              keys=daemon.cfg["network"]["keys"] or None)
    except CurveKeyError as e:
        logging.getLogger("kmead").warning("terminal UI unavailable (%s); running headless", e)
        signal.signal(signal.SIGTERM, lambda *_: daemon.stop())
        return daemon.run()
    result: dict[str, int] = {}
    # The UI owns the terminal: log lines go to its Log tab (telemetry "log"), not stderr.
    root = logging.getLogger("kmead")
    quiet = [h for h in root.handlers if getattr(h, "_kmead", False)]
    for h in quiet:
        root.removeHandler(h)
    app = KmeaTui(client)
    t = threading.Thread(target=lambda: result.setdefault("code", daemon.run()),
                         name="kmead-main", daemon=True)
    t.start()

    def terminate(*_: object) -> None:
        daemon.stop()
        app.exit()

    previous = signal.signal(signal.SIGTERM, terminate)
    try:
        app.run()  # until the user quits (q) or SIGTERM
    finally:
        signal.signal(signal.SIGTERM, previous)
        daemon.stop()
        t.join(timeout=5.0)
        for h in quiet:
            root.addHandler(h)
    return result.get("code", 0)


def _connectable(endpoint: str) -> str:
    # A daemon bound to every interface is reached on loopback.
    return endpoint.replace("tcp://0.0.0.0:", "tcp://127.0.0.1:").replace(
        "tcp://*:", "tcp://127.0.0.1:")


if __name__ == "__main__":
    sys.exit(main())
