"""The garbage collector runs between frames of a live source, never inside one."""

from __future__ import annotations

import gc
import threading
import time
import weakref

from deadlines import DEADLINE

from kmead.run.gc_pacing import GcPacing


class _Node:
    def __init__(self) -> None:
        self.me = self  # a reference cycle: only the cyclic collector frees it


def test_pacing_collects_cycles_when_due_and_restores_the_collector():
    assert gc.isenabled()
    p = GcPacing()
    try:
        assert not gc.isenabled()
        cyc = weakref.ref(_Node())
        assert cyc() is not None  # not collected: the automatic collector is off
        # Container allocations (the count is allocations minus frees: kept alive).
        junk = [[] for _ in range(3 * p.thresholds[0])]
        assert p.idle() >= 0
        del junk
        assert cyc() is None  # collected by idle(), with the thresholds of the default
        assert p.idle() == -1  # nothing due right after a collection
    finally:
        p.close()
    assert gc.isenabled()


def test_two_daemons_share_one_pacing():
    a, b = GcPacing(), GcPacing()
    a.close()
    assert not gc.isenabled()  # b still runs
    a.close()  # idempotent: does not release b's share
    assert not gc.isenabled()
    b.close()
    assert gc.isenabled()


def test_a_live_daemon_collects_only_between_frames():
    from kmea.sim.scenes import scene_from_spec
    from kmea.sources.registry import register_source
    from kmea.sources.sim import SimSource
    from kmead.config.layers import load_config
    from kmead.run.daemon import Daemon

    scene = scene_from_spec("sim:default", width=820)
    src = SimSource(scene, frames=20)
    frames = [src.read() for _ in range(20)]
    # The 20 frames served again and again, in real time, until the run has what it checks
    # (a loaded machine drops frames of a live source: wait for events, not a count).
    register_source("gctest", lambda rest, **o: SimSource(scene, realtime=True,
                                                          rendered=frames * 300, fps=20))
    d = Daemon(load_config(None, ["source.spec=gctest", 'network.telemetry=""',
                                  'network.control=""']))
    assert d.live
    where: list[bool] = []
    idle = threading.local()
    orig = GcPacing.idle

    def paced(self):
        idle.inside = True
        try:
            return orig(self)
        finally:
            idle.inside = False

    def seen(phase, info):
        if phase == "start" and not gc.isenabled():  # while the daemon paces (run())
            where.append(getattr(idle, "inside", False))

    stop = threading.Event()

    def litter() -> None:  # another thread making cyclic garbage (as a service thread may)
        while not stop.wait(0.002):
            for _ in range(200):
                _Node()

    def enough() -> None:  # stop once 10 frames and a paced collection happened (60 s at most)
        end = time.monotonic() + DEADLINE
        while time.monotonic() < end and not stop.is_set():
            pacing = d.gc_pacing
            if d.totals.frames >= 10 and pacing is not None and pacing.collections >= 1:
                break
            stop.wait(0.05)
        d.stop()

    GcPacing.idle = paced
    gc.callbacks.append(seen)
    t = threading.Thread(target=litter)
    w = threading.Thread(target=enough)
    t.start()
    w.start()
    try:
        d.run()
    finally:
        stop.set()
        t.join()
        w.join()
        gc.callbacks.remove(seen)
        GcPacing.idle = orig
        d.close()
    assert d.totals.frames >= 10
    assert d.gc_pacing is not None and d.gc_pacing.collections >= 1
    assert where and all(where), where  # every collection of the run came from idle()
    assert gc.isenabled()
