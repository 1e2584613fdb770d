"""Full-resolution snapshots: the last frame as PNG, optionally with the overlay drawn.

The control command ``snapshot`` (``kmea snapshot``, the Camera tab's ``s`` key) takes
no path: a request from the network never chooses where the daemon writes. The file goes
to the data directory (kmead's working directory) under a new name
``snapshot-YYYYmmdd-HHMMSS-fFRAME[-overlay].png``, created exclusively (never overwriting).

Any client, a viewer too, may ask for one, so what they can pile up is bounded
(``log.snapshots_max`` files, ``log.snapshots_max_mb`` MB, and the data directory's
``log.min_free_mb`` floor): past a limit the request is refused with the limit's name.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from kmea.vision.overlay import OverlayMarker, draw_overlay
from kmead.outputs.datadir import free_bytes

PATTERN = "snapshot-*.png"


@dataclass(frozen=True)
class Limits:
    """What snapshots may take in their directory: files, MB (10^6 bytes), and the free
    space (MB) that must remain after one is written; 0 MB of floor = none."""

    max_count: int = 200
    max_mb: float = 500.0
    min_free_mb: float = 0.0


class SnapshotError(ValueError):
    """No snapshot could be saved; one line saying why."""


def check_room(directory: Path, limits: Limits, size: int = 0) -> None:
    """SnapshotError naming the limit when one more snapshot of ``size`` bytes would pass
    one of ``limits`` in ``directory``."""
    if limits.max_count <= 0:
        raise SnapshotError("snapshots are off (log.snapshots_max = 0)")
    count = total = 0
    for p in directory.glob(PATTERN):
        try:
            total += p.lstat().st_size
        except OSError:
            continue
        count += 1
    if count >= limits.max_count:
        raise SnapshotError(f"refused: {count} snapshots in {directory} already "
                            f"(log.snapshots_max = {limits.max_count}); delete some")
    if total + size > limits.max_mb * 1e6:
        raise SnapshotError(f"refused: snapshots in {directory} would take "
                            f"{(total + size) / 1e6:.1f} MB (log.snapshots_max_mb = "
                            f"{limits.max_mb:g} MB); delete some")
    free = free_bytes(directory)
    if limits.min_free_mb > 0 and free is not None and free - size < limits.min_free_mb * 1e6:
        raise SnapshotError(f"refused: {free / 1e6:.1f} MB free on the disk of {directory}, "
                            f"below log.min_free_mb = {limits.min_free_mb:g} MB after it")


def save_snapshot(image: np.ndarray | None, frame: int, directory: str | Path,
                  marks: list[OverlayMarker] | None = None, focus: float | None = None,
                  overlay: bool = False, limits: Limits | None = None) -> Path:
    """Write ``image`` ((H, W) grey or BGR uint8) as PNG in ``directory``; its path.
    ``limits``: see :class:`Limits` (None: no limit)."""
    if image is None:
        raise SnapshotError("no camera image to save (no frame yet, or a replay source)")
    d = Path(directory)
    if limits is not None:
        check_room(d, limits)  # before the encoding's tens of ms
    out = draw_overlay(image, marks or [], focus) if overlay else image
    ok, buf = cv2.imencode(".png", out)
    if not ok:
        raise SnapshotError("PNG encoding failed")
    if limits is not None:
        check_room(d, limits, buf.nbytes)
    stamp = time.strftime("%Y%m%d-%H%M%S")
    name = f"snapshot-{stamp}-f{frame}{'-overlay' if overlay else ''}.png"
    path = d / name
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0)
    for k in range(1, 100):
        try:
            fd = os.open(path, flags, 0o644)
            break
        except FileExistsError:
            path = d / name.replace(".png", f"-{k}.png")
        except OSError as e:
            raise SnapshotError(f"cannot write {path}: {e.strerror or e}") from None
    else:
        raise SnapshotError(f"{d}: too many snapshots this second")
    with os.fdopen(fd, "wb") as f:
        f.write(buf.tobytes())
    return path.resolve()
