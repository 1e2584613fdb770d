"""Has a map marker moved? The one rule, with its evidence (stdlib only).

The daemon feeds, every frame, one *displacement figure* (metres) per map marker that was a
usable measurement: its leave-one-out error (how far the alignment without it puts it from
its surveyed position), or, when a robust estimator rejected it as a reference, the larger
of that and the rejection distance. Unseen and suspect markers (``docs/vision.md``) give no
figure and keep their window.

A single frame proves nothing: a corner hidden by a passing robot that the pose quality
check did not catch, or a motion-blurred frame, gives one large figure; a marker moved on
the floor is off in every frame. So each marker keeps its last ``frames`` figures and

    offset    = median of its window                         (needs >= min(frames, 3))
    noise     = max(typical, own)
      typical = median over the OTHER map markers of their window medians (0 with fewer
                than 3 others): how large the error of a well-placed marker is with this
                camera, lens and floor right now
      own     = 1.4826 x the median absolute deviation of its own window: its own jitter
                (a marker far in the image corner wobbles more than one under the camera)
    floor     = min_offset x max(1, gsd / GSD_REF_M)
      gsd     = the marker's depth / the focal length: metres per pixel at the marker
    threshold = max(floor, factor x noise)
    moved     = offset > threshold

The floor scales with the image's resolution: a single marker's pose is off along its
viewing ray by about depth x depth x pixel noise / (focal length x side), linear in the
metres per pixel at the marker, and seen from the side that error lands on the floor. At
the reference resolution (1640x1232 from 1.35 m: about 1 mm per pixel, ``GSD_REF_M``)
``min_offset`` is the floor as set; at 820x616 (2 mm per pixel) twice that: below it a
move cannot be told from the pose noise of a 30-pixel marker.

The threshold scales with what it measures: on a well-surveyed floor seen by a calibrated
camera (errors ~1 mm) the floor (``stats.displaced_threshold``) decides; with a worse
camera or floor, where every marker is off by several millimetres, ``factor`` times that
level does, so noise is never called a move. The median keeps a few moved markers from
raising the typical level (fewer than half the markers are assumed moved).

The robust estimators' rejection (``kmea.estimators.robust``, ``corners``) is a different,
per-frame decision inside one estimate: a reference whose residual is too large is left out
of that frame's alignment so it cannot pull the others. It is an estimation detail (the
``R`` flag, ``rejection`` in the markers telemetry); its distance only feeds this monitor
as a figure. Whether the marker *moved* is decided here, and only here.
"""

from __future__ import annotations

import bisect
import collections
import statistics
from dataclasses import dataclass

__all__ = ["DEFAULT_FACTOR", "GSD_REF_M", "MovedEvidence", "MovedMonitor"]

# Threshold in units of the noise level: 3 sigma-like spreads of a well-placed marker.
DEFAULT_FACTOR = 3.0
# Metres per pixel at which min_offset applies as set: the reference rig (Pi Camera v2 at
# 1640x1232, fx 1357 px, 1.35 m above the floor).
GSD_REF_M = 0.001
# MAD -> standard deviation for normally distributed figures.
_MAD_TO_SIGMA = 1.4826
# Fewer other markers than this: no error level of the floor (min_offset and own jitter).
MIN_OTHERS = 3


@dataclass(frozen=True)
class MovedEvidence:
    """One marker's state. offset, threshold in metres (None until enough figures);
    frames: figures in the window."""

    moved: bool
    offset: float | None
    frames: int
    threshold: float | None


NO_EVIDENCE = MovedEvidence(False, None, 0, None)


def _median_without(ranked: list[float], i: int) -> float:
    """The median of sorted ``ranked`` without its element ``i`` (``statistics.median`` of
    the others, without copying them: this runs for every marker every frame)."""
    n = len(ranked) - 1

    def at(j: int) -> float:
        return ranked[j if j < i else j + 1]

    return at(n // 2) if n % 2 else (at(n // 2 - 1) + at(n // 2)) / 2


class MovedMonitor:
    """Per-marker windows of displacement figures (m) and the "moved" decision.

    min_offset: metres, the smallest offset ever called a move; frames: window length
    (frames where the marker was measured); factor: threshold in units of the noise level.
    """

    def __init__(self, min_offset: float, frames: int = 5,
                 factor: float = DEFAULT_FACTOR) -> None:
        if frames < 1:
            raise ValueError(f"moved-marker window: frames must be >= 1, got {frames}")
        if not min_offset > 0:
            raise ValueError(f"moved-marker threshold must be > 0 m, got {min_offset}")
        self.min_offset = float(min_offset)
        self.frames = int(frames)
        self.factor = float(factor)
        self.need = min(self.frames, 3)
        self.history: dict[int, collections.deque[float]] = {}
        self.evidence: dict[int, MovedEvidence] = {}
        self.gsd: dict[int, float] = {}  # id -> the last metres per pixel at the marker

    def _medians(self) -> dict[int, float]:
        return {mid: statistics.median(h) for mid, h in self.history.items()
                if len(h) >= self.need}

    def typical(self, exclude: int | None = None) -> float:
        """Median (m) of the window medians of the markers (but ``exclude``) with enough
        figures; 0 with fewer than :data:`MIN_OTHERS` of them."""
        meds = [m for mid, m in self._medians().items() if mid != exclude]
        return statistics.median(meds) if len(meds) >= MIN_OTHERS else 0.0

    def update(self, figures: dict[int, float],
               gsd: dict[int, float] | None = None) -> dict[int, MovedEvidence]:
        """Add one frame's figures (id -> m) and, where known, each marker's metres per
        pixel (``gsd``, id -> m/px: the floor's scale); return id -> evidence of the
        markers measured in this frame that have moved (every marker's evidence is in
        :attr:`evidence`)."""
        for mid, g in (gsd or {}).items():
            if g > 0 and g == g and g != float("inf"):
                self.gsd[mid] = float(g)
        for mid, e in figures.items():
            h = self.history.get(mid)
            if h is None:
                h = self.history[mid] = collections.deque(maxlen=self.frames)
            h.append(float(e))
        medians = self._medians()
        ranked = sorted(medians.values())
        for mid, h in self.history.items():
            if len(h) < self.need:
                self.evidence[mid] = MovedEvidence(False, None, len(h), None)
                continue
            offset = medians[mid]
            typical = (_median_without(ranked, bisect.bisect_left(ranked, offset))
                       if len(ranked) - 1 >= MIN_OTHERS else 0.0)
            own = _MAD_TO_SIGMA * statistics.median(abs(x - offset) for x in h)
            floor = self.min_offset * max(1.0, self.gsd.get(mid, 0.0) / GSD_REF_M)
            threshold = max(floor, self.factor * max(typical, own))
            self.evidence[mid] = MovedEvidence(offset > threshold, offset, len(h), threshold)
        return {mid: self.evidence[mid] for mid in figures if self.evidence[mid].moved}

    def get(self, marker_id: int) -> MovedEvidence:
        """The evidence of one marker (no figures yet: not moved, offset None)."""
        return self.evidence.get(marker_id, NO_EVIDENCE)

    def clear(self) -> None:
        self.history.clear()
        self.evidence.clear()
        self.gsd.clear()
