"""How long a test waits for an event before it fails: generous, because a test waits for
the event and a passing test never pays it. A CI runner shared with other jobs, or the
suite beside CPU hogs (scripts/suite_under_load.sh), can run a daemon at under one frame a
second; only a hang may fail a test."""

DEADLINE = 120.0  # s: an event a test waits for (frames, replies, a process's exit)
JOIN = 60.0  # s: a thread or process asked to stop, at the end of a test


def wait_until(cond, what: str, timeout: float = DEADLINE, interval: float = 0.05,
               check=None, detail=None) -> None:
    """Return as soon as ``cond()`` is true; fail after ``timeout`` s naming ``what``.
    ``check()``: called while waiting, raises when waiting is pointless (a process died);
    ``detail()``: text added to the timeout's message (the processes' last lines)."""
    import time

    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return
        if check is not None:
            check()
        time.sleep(interval)
    raise AssertionError(f"timed out after {timeout:g} s waiting for {what}"
                         + (f": {detail()}" if detail is not None else ""))


async def pilot_until(pilot, cond, what: str, timeout: float = DEADLINE) -> None:
    """:func:`wait_until` for a Textual app driven by its Pilot: the app runs while waiting."""
    import time

    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return
        await pilot.pause(0.05)
    raise AssertionError(f"timed out after {timeout:g} s waiting for {what}")
