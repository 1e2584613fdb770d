"""The daemon's benchmarks behind ``kmea bench`` (they print figures): everything that needs
the daemon, sockets, Zenoh or processes of kmead. The library's (numpy and OpenCV only) are
in :mod:`kmea.benchmarks`; the ``kmea`` front door (``kmead/tools/kmea_cli.py``) adds
:data:`BENCHES` to them, and :mod:`kmea.cli.bench` runs both (``run(quick)`` and
``main(argv)`` functions: see there).
"""

from __future__ import annotations

# name -> ("module:function", one-line description), imported only when run.
BENCHES: dict[str, tuple[str, str]] = {
    "daemon": ("kmead.benchmarks.daemon:run_daemon",
               "frames/s of the whole daemon beside bare detectMarkers"),
    "latency": ("kmead.benchmarks.daemon:run_latency",
                "frame to UDP datagram latency, 1640x1232 at 30 frames/s"),
    "fusion-node": ("kmead.benchmarks.fusion_node:run",
                    "what one fusion node carries, and the latency it adds"),
    "tui": ("kmead.benchmarks.daemon:run_tui",
            "kmea-tui's CPU per tab; the daemon's fps with it, without"),
    "curve": ("kmead.benchmarks.curve:main",
              "telemetry msgs/s and latency, plain and with CURVE"),
    "recording-size": ("kmead.benchmarks.recording_size:main",
                       "what a recording costs: bytes and CPU a frame, GB/hour"),
    "zenoh-latency": ("kmead.benchmarks.zenoh_latency:main",
                      "frame to Zenoh vs frame to UDP; the ROS 2 output's CPU"),
    "fusion-zenoh": ("kmead.benchmarks.fusion_zenoh:main",
                     "fusion on Zenoh: a camera dropped, a node's failover"),
    "fused-accuracy": ("kmead.benchmarks.fused_accuracy:main",
                       "the fused stream's RMSE against truth beside each camera's"),
    "voice-seams": ("kmead.benchmarks.voice_seams:main",
                    "what a robot hears at each seam: silences, seq, jumps, voices"),
    "fused-turns": ("kmead.benchmarks.fused_turns:main",
                    "the fused stream at the wide scene's tight turns: jumps per 1,000"),
    "soak": ("kmead.benchmarks.soak:main",
             "a real kmead for an hour with a venue day's load"),
}
