"""The run's files: the CSV log and the recording, started and stopped safely.

One object for the daemon and the fusion node. What it guarantees (docs/daemon.md, "A full
disk"):

- over control (``remote``), a new plain file in the data directory
  (:mod:`kmead.outputs.datadir`); an operator's own path is theirs;
- a restart never truncates: an existing CSV log of this format is continued, anything else
  goes to a new name (``keep``);
- neither starts below ``log.min_free_mb`` (:class:`LowSpace`), and a running one stops
  cleanly, between two frames, when its disk falls below it;
- a write error (ENOSPC, EIO) stops that output only: whole rows stay (the writers cut a
  failed write back), an event and the status say why; robots and telemetry go on;
- the CSV log and the recording go on in a new part at ``log.part_mb`` / ``log.part_min``,
  and kmead's older files beyond ``log.keep_days`` / ``log.keep_mb`` are removed
  (:mod:`kmead.outputs.retention`) when an output or a part starts, and hourly.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

from kmea.recordings.format import Recorder
from kmead.outputs.csvlog import CsvLog, ends_whole, has_header
from kmead.outputs.datadir import DataDir, low_space, next_part, same_file, split_suffix
from kmead.outputs.retention import prune

__all__ = ["OUTPUT_NAMES", "FileOutputs", "LowSpace", "Totals"]

log = logging.getLogger("kmead")

OUTPUT_NAMES = {"log": "CSV log", "record": "recording"}
# How often (s) the free space under a running output is checked: statvfs is a few
# microseconds, but every frame would be needless.
SPACE_CHECK_S = 1.0
# How often (s) retention runs besides the start of each output and part.
PRUNE_EVERY_S = 3600.0


class LowSpace(ValueError):
    """An output refused because its disk is below ``log.min_free_mb`` (one line)."""


class Totals(Protocol):
    """Where the run's summary finds the files it wrote (kmead.outputs.totals.RunTotals)."""

    csv_rows: int
    csv_paths: list[str]
    record_paths: list[str]


# (path, part, previous part's name) -> a Recorder with the run's header
RecorderFactory = Callable[[str | Path, int, str | None], Recorder]


class FileOutputs:
    """The CSV log (:attr:`csv`) and the recording (:attr:`recorder`) of one run.

    ``log_cfg``: the ``[log]`` table (read at each use: live keys); ``event(level, text)``
    reports a stop; ``new_recorder`` makes a recording (None: this process records nothing,
    as the fusion node).
    """

    def __init__(self, log_cfg: dict[str, Any], data_dir: DataDir, totals: Totals,
                 event: Callable[[str, str], None],
                 new_recorder: RecorderFactory | None = None) -> None:
        self.log_cfg = log_cfg
        self.data_dir = data_dir
        self.totals = totals
        self.event = event
        self.new_recorder = new_recorder
        self.csv: CsvLog | None = None
        self.recorder: Recorder | None = None
        # Why each output last stopped on its own (a write error, the free-space floor);
        # None while it runs or after a stop that was asked for. In the status body.
        self.errors: dict[str, str | None] = {"log": None, "record": None}
        self._space_t = 0.0
        self._prune_t = -PRUNE_EVERY_S
        self.csv_started = 0.0  # time.monotonic() when this CSV part started

    # ------------------------------------------------------------------ start and stop
    def start_csv(self, path: str, remote: bool = False, keep: bool = False) -> CsvLog:
        """Start the CSV log. keep: an existing file is never truncated (a restart over
        control: see :meth:`_keep_existing`); else an operator's path is written afresh."""
        if self.csv is not None:
            raise ValueError(f"already logging to {self.csv.path}; stop it first")
        self._check_space(path, "log", remote)
        mode = "create"
        if keep and not remote:
            path, mode = self._keep_existing(path, "log", self.event)
        path = self._output_path(path, "log", self.recorder, remote)
        try:
            self.csv = CsvLog(path, append=mode == "append")
        except OSError as e:
            self._forget_created(path, remote)
            raise ValueError(f"log: cannot write {path}: {e.strerror or e}") from None
        self.csv.mode = mode
        self._started_csv()
        log.info("CSV log started: %s%s", self.csv.path,
                 " (appending: the earlier rows are kept)" if mode == "append" else "")
        self.prune()
        return self.csv

    def _started_csv(self) -> None:
        assert self.csv is not None
        self.csv_started = time.monotonic()
        self.errors["log"] = None
        self.totals.csv_paths.append(str(self.csv.path))

    def stop_csv(self) -> dict:
        if self.csv is None:
            raise ValueError("not logging")
        c, self.csv = self.csv, None
        c.close()
        self.totals.csv_rows += c.rows
        log.info("CSV log stopped: %s (%d rows)", c.path, c.rows)
        return {"path": str(c.path), "rows": c.rows, "bytes": c.bytes}

    def start_recording(self, path: str, remote: bool = False, keep: bool = False
                        ) -> Recorder:
        """Start recording; keep: as for :meth:`start_csv` (a recording is never appended
        to: a new name)."""
        if self.new_recorder is None:
            raise ValueError("record: a fusion node has no frames to record")
        if self.recorder is not None:
            raise ValueError(f"already recording to {self.recorder.path}; stop it first")
        self._check_space(path, "record", remote)
        mode = "create"
        if keep and not remote:
            path, mode = self._keep_existing(path, "record", self.event)
        path = self._output_path(path, "record", self.csv, remote)
        try:
            self.recorder = self._recorder(path)
        except OSError as e:
            self._forget_created(path, remote)
            raise ValueError(f"record: cannot write {path}: {e.strerror or e}") from None
        self.recorder.mode = mode
        self.errors["record"] = None
        log.info("recording started: %s%s", self.recorder.path, "" if self.recorder.compressed
                 else " (plain JSON lines: 3 to 25 times the size of a name ending .zst)")
        self.prune()
        return self.recorder

    def stop_recording(self) -> dict:
        if self.recorder is None:
            raise ValueError("not recording")
        r, self.recorder = self.recorder, None
        r.close()
        log.info("recording stopped: %s (%d frames)", r.path, r.frames)
        return {"path": str(r.path), "frames": r.frames, "bytes": r.bytes, "part": r.part}

    def refused(self, kind: str, text: str) -> None:
        """An output that could not start or run: the status says why, and an event."""
        self.errors[kind] = text
        self.event("error", text)

    def close(self) -> None:
        if self.csv is not None:
            self.stop_csv()
        if self.recorder is not None:
            self.stop_recording()

    # ------------------------------------------------------------------ each frame
    def write_csv(self, lines: list[str]) -> None:
        """Whole rows, or the log stops (a write error) with the rest of the run going on."""
        if self.csv is None:
            return
        try:
            self.csv.write_rows(lines)
        except OSError as e:
            self._failed("log", e)
            return
        why = self._csv_part_due()
        if why:
            self._next_csv_part(why)

    def write_frame(self, write: Callable[[Recorder], None]) -> None:
        """``write(recorder)`` one frame; then a new part when one is due."""
        if self.recorder is None:
            return
        try:
            write(self.recorder)
        except OSError as e:
            self._failed("record", e)
            return
        why = self._part_due()
        if why:
            self._next_part(why)

    def prune(self) -> None:
        """Retention (:mod:`kmead.outputs.retention`) in the data directory and the
        directories of the running outputs; one event when something was removed."""
        self._prune_t = time.monotonic()
        lg = self.log_cfg
        if not (lg["keep_days"] or lg["keep_mb"]):
            return
        active = [o.path for o in (self.csv, self.recorder) if o is not None]
        dirs = {self.data_dir.root, *(Path(p).resolve().parent for p in active)}
        removed = prune(dirs, lg["keep_days"], lg["keep_mb"], active)
        if removed:
            where = ", ".join(sorted({str(f.path.parent) for f in removed}))
            self.event("info", f"retention: removed {len(removed)} of kmead's files "
                               f"({sum(f.bytes for f in removed) / 1e6:.1f} MB, the oldest "
                               f"{removed[0].path.name}) from {where}: older than "
                               f"log.keep_days = {lg['keep_days']:g} or beyond log.keep_mb = "
                               f"{lg['keep_mb']:g}")

    def watch_space(self) -> None:
        """Stop an output cleanly (between two frames: whole rows) when its disk falls
        below the floor, long before a write fails; retention hourly."""
        now = time.monotonic()
        if now - self._prune_t >= PRUNE_EVERY_S and (self.csv or self.recorder):
            self.prune()
        if now - self._space_t < SPACE_CHECK_S or (self.csv is None and self.recorder is None):
            return
        self._space_t = now
        for kind, out in (("log", self.csv), ("record", self.recorder)):
            if out is None:
                continue
            reason = low_space(out.path, self.log_cfg["min_free_mb"])
            if reason:
                self._stop(kind, f"{OUTPUT_NAMES[kind]} {out.path}: stopped after "
                                 f"{self._count(kind)}: {reason}; robots and telemetry go on")

    # ------------------------------------------------------------------ inside
    def _count(self, kind: str) -> str:
        if kind == "log":
            return f"{self.csv.rows if self.csv else 0} rows"
        return f"{self.recorder.frames if self.recorder else 0} frames"

    def _recorder(self, path: str | Path, part: int = 1, previous: str | None = None
                  ) -> Recorder:
        assert self.new_recorder is not None
        r = self.new_recorder(path, part, previous)
        self.totals.record_paths.append(str(r.path))
        return r

    def _output_path(self, name: str, kind: str, other: Any, remote: bool) -> str:
        """Where an output goes: over control a new plain file in the data directory;
        never the file the other output writes."""
        busy = [other.path] if other is not None else []
        if remote:
            return str(self.data_dir.create(name, kind, busy))
        for b in busy:
            if same_file(name, b):
                raise ValueError(f"{kind}: {name} is the file the other output writes")
        return name

    def _check_space(self, path: str, kind: str, remote: bool) -> None:
        reason = low_space(self.data_dir.root if remote else path, self.log_cfg["min_free_mb"])
        if reason:
            raise LowSpace(f"{kind}: not started: {reason}")

    def _failed(self, kind: str, e: OSError) -> None:
        """A write error stops that output only: the file keeps its whole rows."""
        out = self.csv if kind == "log" else self.recorder
        cut = ("" if getattr(e, "cut_back", True)
               else "; its last row may be cut (the file could not be truncated)")
        self._stop(kind, f"{OUTPUT_NAMES[kind]} {out.path if out else ''}: write failed: "
                         f"{e.strerror or e}; stopped after {self._count(kind)}{cut}; robots "
                         "and telemetry go on")

    def _stop(self, kind: str, text: str) -> None:
        try:
            self.stop_csv() if kind == "log" else self.stop_recording()
        except OSError as e:  # closing a file on a failing disk: it is stopped all the same
            log.debug("closing the %s: %s", OUTPUT_NAMES[kind], e)
            if kind == "log":
                self.csv = None
            else:
                self.recorder = None
        self.refused(kind, text)

    @staticmethod
    def _forget_created(path: str, remote: bool) -> None:
        # The empty file a refused control request created (a full disk): its name stays
        # free for the next try.
        if remote:
            with contextlib.suppress(OSError):
                if os.path.getsize(path) == 0:
                    os.unlink(path)

    @staticmethod
    def _keep_existing(path: str, kind: str, event: Callable[[str, str], None]
                       ) -> tuple[str, str]:
        """Where a restarted output goes without truncating anything: (path, mode).

        mode "create": no file (or an empty one) there; "append": a CSV log of this format
        ending with a whole row, continued without a second header; "new name": the file
        is kept as it is and the output goes to ``NAME-2.csv`` (``-3`` ...), the first free
        name. A recording always gets a new name: its header holds the camera, the map and
        the configuration of the run that started it, which may have changed since.
        """
        p = Path(path)
        try:
            if not p.exists() or (p.is_file() and p.stat().st_size == 0):
                return path, "create"
            if kind == "log" and p.is_file() and has_header(p) and ends_whole(p):
                return path, "append"
        except OSError:
            pass  # unreadable: never written over, a new name instead
        base, suffix = split_suffix(p)
        for n in range(2, 10000):
            other = f"{base}-{n}{suffix}"
            if not os.path.lexists(other):
                event("warning", f"{kind}: {path} exists and is kept: writing {other}")
                return other, "new name"
        raise ValueError(f"{kind}: {base}-2{suffix} to -9999 all exist; give a path")

    def _due(self, size: int, started: float) -> str | None:
        """Why an output of ``size`` bytes started at ``started`` (monotonic s) must go on
        in a new part (log.part_mb / log.part_min), or None."""
        lg = self.log_cfg
        if lg["part_mb"] and size >= lg["part_mb"] * 1e6:
            return f"log.part_mb = {lg['part_mb']:g} MB reached"
        if lg["part_min"] and time.monotonic() - started >= lg["part_min"] * 60:
            return f"log.part_min = {lg['part_min']:g} min reached"
        return None

    def _part_due(self) -> str | None:
        r = self.recorder
        return None if r is None else self._due(r.bytes, r.started)

    def _csv_part_due(self) -> str | None:
        c = self.csv
        return None if c is None else self._due(c.size, self.csv_started)

    def _next_csv_part(self, why: str) -> None:
        """Close this CSV part and go on in a new file with its own header."""
        old = self.csv
        assert old is not None
        try:
            path, part = next_part(old.path, old.part + 1)
            new = CsvLog(path)
        except OSError as e:
            self._failed("log", e)
            return
        new.part, new.mode = part, old.mode
        old.close()
        self.totals.csv_rows += old.rows
        self.csv = new
        self._started_csv()
        log.info("CSV log goes on in %s (%s)", path, why)
        self.prune()

    def _next_part(self, why: str) -> None:
        """Close this part and go on in a new file (a new name: nothing is written over);
        each part has its own header and replays alone."""
        old = self.recorder
        assert old is not None
        try:
            path, part = next_part(old.path, old.part + 1)
            new = self._recorder(path, part, previous=old.path.name)
        except OSError as e:
            self._failed("record", e)
            return
        new.mode = old.mode
        old.close()
        self.recorder = new
        log.info("recording: part %d in %s (%s; %s kept, %d frames)", part, path, why,
                 old.path.name, old.frames)
