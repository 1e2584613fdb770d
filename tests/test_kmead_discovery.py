"""The daemon's discovery thread (kmead.run.discovery): one job at a time, the newest wins,
after the frame's robots were sent, at a lower priority; the daemon wires it to the
pipeline. No sleeps: a fake executor runs the queue's task in the test's thread, the real
one is waited for with its own event."""

from __future__ import annotations

import os
import threading

from deadlines import wait_until

from kmead.run.discovery import NICE, Discovery, DiscoveryQueue


class Later:
    """An executor that keeps the tasks it is given until the test runs them."""

    def __init__(self) -> None:
        self.tasks: list = []

    def submit(self, fn):
        self.tasks.append(fn)

    def run(self) -> None:
        tasks, self.tasks = self.tasks, []
        for fn in tasks:
            fn()


class Gate:
    """A gate that records what the queue asks of it."""

    def __init__(self, log: list) -> None:
        self.log = log

    def wait(self, timeout: float) -> bool:
        self.log.append("gate")
        return True

    def clear(self) -> None:
        self.log.append("clear")

    def set(self) -> None:
        self.log.append("set")


def test_one_task_runs_the_newest_job_after_the_gate_and_gives_its_result_once() -> None:
    log: list = []
    ex = Later()
    q = DiscoveryQueue(ex, Gate(log))  # type: ignore[arg-type]
    q.frame_started()
    q.submit(lambda: log.append("old") or "old")  # type: ignore[arg-type]
    q.submit(lambda: log.append("new") or "new")  # type: ignore[arg-type]
    assert len(ex.tasks) == 1 and q.busy  # the running task takes the newer job
    assert q.take() is None
    ex.run()
    assert log == ["clear", "gate", "new"]  # the replaced job never ran
    assert not q.busy and q.done.is_set()
    assert q.take() == "new" and q.take() is None and not q.done.is_set()


def test_a_failing_job_gives_no_result_and_a_closed_queue_takes_no_job() -> None:
    ex = Later()
    q = DiscoveryQueue(ex, Gate([]))  # type: ignore[arg-type]

    def boom():
        raise ValueError("a frame the detector cannot digest")

    q.submit(boom)  # type: ignore[arg-type]
    ex.run()
    assert q.take() is None and not q.busy
    q.submit(lambda: "queued")  # type: ignore[arg-type]
    q.close()  # the queued job is dropped
    ex.run()
    assert q.take() is None
    q.submit(lambda: "after")  # type: ignore[arg-type]
    assert ex.tasks == [] and not q.busy


def test_the_worker_waits_for_the_robots_then_runs_below_the_frame_path() -> None:
    """On the daemon's thread: a job queued after a frame started waits for
    ``robots_sent`` (the gate: a generous timeout, so only the gate lets it go), then runs
    at nice NICE on a thread of its own."""
    d = Discovery(gate_wait_s=600.0)
    q = d.jobs()
    started = threading.Event()
    seen: dict = {}

    def job():
        started.set()
        seen["thread"] = threading.current_thread().name
        seen["nice"] = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
        return "found"

    try:
        q.frame_started()
        q.submit(job)  # type: ignore[arg-type]
        assert q.busy and not started.is_set() and not d.gate.is_set()
        d.robots_sent()
        wait_until(q.done.is_set, "the discovery's result")
        assert started.is_set() and q.take() == "found"
        assert seen["thread"].startswith("kmead-discover")
        assert seen["nice"] >= NICE  # (at least: the test may itself run niced)
    finally:
        d.shutdown(wait=True)


def test_a_shut_down_worker_takes_no_job() -> None:
    d = Discovery()
    d.shutdown(wait=True)
    q = d.jobs()
    q.submit(lambda: "never")  # type: ignore[arg-type]
    assert not q.busy and q.take() is None


def test_the_daemon_gives_its_pipeline_the_discovery_thread() -> None:
    from kmead.config.layers import load_config
    from kmead.run.daemon import Daemon

    d = Daemon(load_config(None, ["source.spec=sim:default", 'network.telemetry=""',
                                  'network.control=""'], use_local=False))
    try:
        assert isinstance(d.discovery, Discovery)
        assert d.pipeline.background is d.discovery
    finally:
        d.close()
