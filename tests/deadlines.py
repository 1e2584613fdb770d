"""How long a test waits for an event before it fails: generous, because a test waits for
the event and a passing test never pays it. A CI runner shared with other jobs, or the
suite beside CPU hogs (scripts/suite_under_load.sh), can run a daemon at under one frame a
second; only a hang may fail a test."""

DEADLINE = 120.0  # s: an event a test waits for (frames, replies, a process's exit)
JOIN = 60.0  # s: a thread or process asked to stop, at the end of a test
