"""Full-resolution snapshots: the last frame as PNG, optionally with the overlay drawn.

The control command ``snapshot`` (``kmea snapshot``, the Camera tab's ``s`` key) takes
no path: a request from the network never chooses where the daemon writes. The file goes
to the data directory (kmead's working directory) under a new name
``snapshot-YYYYmmdd-HHMMSS-fFRAME[-overlay].png``, created exclusively (never overwriting).
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import cv2
import numpy as np

from kmea.vision.overlay import OverlayMarker, draw_overlay


class SnapshotError(ValueError):
    """No snapshot could be saved; one line saying why."""


def save_snapshot(image: np.ndarray | None, frame: int, directory: str | Path,
                  marks: list[OverlayMarker] | None = None, focus: float | None = None,
                  overlay: bool = False) -> Path:
    """Write ``image`` ((H, W) grey or BGR uint8) as PNG in ``directory``; its path."""
    if image is None:
        raise SnapshotError("no camera image to save (no frame yet, or a replay source)")
    out = draw_overlay(image, marks or [], focus) if overlay else image
    ok, buf = cv2.imencode(".png", out)
    if not ok:
        raise SnapshotError("PNG encoding failed")
    d = Path(directory)
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
