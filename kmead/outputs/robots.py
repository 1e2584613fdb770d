"""What the robots get of each frame, sent from inside the pipeline as soon as their poses
are known (before statistics, files or telemetry: docs/architecture.md, "One frame").

Per robot: the pose at its own instant (its markers' mid-exposure, kmea.timing), or with
latency compensation predicted to the send time; the filter's velocity, turn rate and
covariance; the measurement itself (``raw``) for a fusion node. Every datagram goes first
(a telemetry body wakes the telemetry thread, which would take the GIL from the next
robot's datagram), then the telemetry, then the measurements for the fusion nodes on Zenoh.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from kmead.outputs.relay import Relay
from kmead.outputs.totals import RunTotals

__all__ = ["RobotSender"]

# Latencies kept for the summary: beyond, the oldest half goes.
MAX_LATENCIES = 100000


class RobotSender:
    """The robots' outputs of one daemon: its :class:`Relay` (UDP, ``robot.NAME``
    telemetry, Zenoh's sink), and ``camera`` (kmead.outputs.zenoh_camera.ZenohCamera, set
    when Zenoh is on). ``event(level, text)`` reports a robot gone stale."""

    def __init__(self, relay: Relay, totals: RunTotals,
                 event: Callable[[str, str], None]) -> None:
        self.relay = relay
        self.totals = totals
        self.event = event
        self.camera: Any = None
        self.last_t: float | None = None  # the source's last frame time

    def time_step(self, t: float, max_step_s: float, pipeline: Any) -> bool:
        """Before the frame at ``t`` (s): a source whose time steps back, or forward by more
        than ``max_step_s``, would have the robots follow poses of another time (and the
        filters refuse every measurement as too old, or predict across the gap). Every
        robot with a pose gets ``valid=0`` at once, the robots' filters (``pipeline``'s)
        restart, one event. True when it stepped."""
        last, self.last_t = self.last_t, t
        if last is None or last <= t <= last + max_step_s:
            return False
        names = self.relay.invalidate(t)
        pipeline.filter.reset()
        if pipeline.tracker is not None:
            pipeline.tracker.reset()
        step = f"back {last - t:.3f} s" if t < last else f"forward {t - last:.3f} s"
        self.event("warning", f"source time steps {step}: valid=0 sent to "
                              f"{', '.join(names) or 'no robot'}, filters restarted "
                              f"(relay.max_time_step_s {max_step_s:g} s)")
        return True

    def send(self, t: float, fixes: dict, tracker: Any, predict: bool,
             t_capture: float, measured: dict | None = None) -> None:
        """``fixes`` (name -> kmea.pipeline.RobotFix) of the frame at ``t`` (s); ``tracker``
        the pipeline's tracking filter (None: the IIR filter); ``predict``: send each pose
        predicted to now; ``t_capture``: the frame's capture (``perf_counter``), for the
        capture-to-relay latency (0: unknown); ``measured``: the frame's measurements
        before the filter, accepted or not (``Pipeline.measured``: name -> (t, x, y, theta,
        sigma)), for the fusion nodes (default: the fixes' own)."""
        tot = self.totals
        cam = self.camera
        for fix in fixes.values():
            if cam is not None:  # how well this camera sees the robot: who speaks to it
                cam.voice.want(fix.name, fix.raw[3] if fix.raw is not None else fix.sigma)
            extra = None
            t_pose = t if fix.t is None else fix.t
            t_fix, x, y, th, sigma, cov = t_pose, fix.x, fix.y, fix.theta, fix.sigma, fix.cov
            if fix.vx is not None:
                extra = {"vx": fix.vx, "vy": fix.vy, "omega": fix.omega, "age": 0.0}
                if fix.raw is not None:  # the measurement itself, for a fusion node
                    raw: dict[str, float] = dict(zip(("x", "y", "theta", "sigma"), fix.raw,
                                                     strict=True))
                    raw["t"] = t_pose  # its own instant, also when t is predicted
                    extra["raw"] = raw
                if predict and tracker is not None:
                    now = time.time()
                    st = tracker.predict(fix.name, now)
                    if st is not None and now >= t_pose:
                        t_fix, x, y, th, sigma = now, st.x, st.y, st.theta, st.sigma
                        cov = st.cov
                        extra.update(vx=st.vx, vy=st.vy, omega=st.omega, age=now - t_pose)
            self.relay.update(fix.name, t_fix, x, y, th, sigma, extra, publish=False,
                              cov=cov)
            tot.robots_seen.add(fix.name)
        self.relay.publish_fixes(list(fixes))
        if cam is not None:  # the measurements, for the fusion nodes (after the datagrams)
            if measured is None:
                measured = {f.name: (t if f.t is None else f.t, *(f.raw if f.raw is not None
                                     else (f.x, f.y, f.theta, f.sigma)))
                            for f in fixes.values()}
            # Every measurement, also those this camera's own filter rejected: the node
            # gates them itself, and re-acquires a robot as this camera does (given only
            # the accepted ones it missed a re-acquisition's evidence and lagged behind).
            for name, (tm, mx, my, mth, ms) in measured.items():
                cam.measurement(name, tm, mx, my, mth, ms)
            cam.frame(t, set(fixes))
        for name in self.relay.tick(t):
            self.event("warning", f"robot {name} not seen for "
                                  f"{self.relay.stale_after_s:g} s: stale (valid=0 sent)")
        if t_capture:
            tot.latency_ms.append((time.perf_counter() - t_capture) * 1e3)
            if len(tot.latency_ms) > MAX_LATENCIES:
                del tot.latency_ms[:MAX_LATENCIES // 2]
