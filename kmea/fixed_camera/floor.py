"""The fixed markers' per-frame check: seen at their place, drifted, or the camera bumped.

The camera is bolted above a static floor. A fixed marker's reference corners (from the
full detections, averaged: :func:`kmea.fixed_camera.tracks.averaged`) are checked, not
searched:

- its code is read at the reference quadrilateral every frame
  (:class:`kmea.fixed_camera.codes.CodeSampler`: a hidden marker fails and is not reported
  in that frame);
- ``cv2.cornerSubPix`` from the reference corners measures how far each corner drifted,
  for a rotating share of the markers a frame (``drift_every``; it is the check's largest
  cost). A marker with three corners drifted more than ``move_px`` moved;
- when most fixed markers drifted or fail their code, the camera was bumped
  (:attr:`FloorLook.bump`: the detector then detects the whole frame and restarts).

:class:`Floor` keeps what the check needs while the references hold (sample points, the
refinement at the reference); :meth:`Floor.look` reads one frame.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from kmea.fixed_camera.codes import CodeBook, CodeSampler
from kmea.fixed_camera.tracks import FixedCameraConfig, Track

__all__ = ["Floor", "FloorLook", "drift_share", "subpix", "subpix_window"]


def subpix_window(ref: np.ndarray) -> int:
    """The floor check's ``cornerSubPix`` half-window (px) for reference corners ref
    (N, 4, 2) px: 0.3 of the median marker's module (7 modules a side), 2 to 6 px."""
    side = np.linalg.norm(ref[:, 0] - ref[:, 2], axis=1) / np.sqrt(2.0)
    module = float(np.median(side)) / 7.0
    return int(min(6, max(2, round(0.3 * module))))


def subpix(gray: np.ndarray, ref: np.ndarray, win: int) -> np.ndarray:
    """(N, 4, 2) ``cornerSubPix`` of the reference corners (N, 4, 2) px, half-window
    ``win`` px (:func:`subpix_window`)."""
    pts = ref.reshape(-1, 1, 2).astype(np.float32)
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 20, 0.01)
    refined = cv2.cornerSubPix(gray, pts, (win, win), (-1, -1), crit)
    return refined.reshape(-1, 4, 2).astype(np.float64)


def drift_share(n: int, frame: int, settings: FixedCameraConfig) -> np.ndarray:
    """Indices of the n static markers whose drift is measured in ``frame``: every
    ``drift_every``-th from a start that rotates frame by frame (all when that is fewer
    than ``drift_min``)."""
    every = max(1, int(settings.drift_every))
    if every == 1 or n <= settings.drift_min:
        return np.arange(n)
    chk = np.arange(frame % every, n, every)
    return chk if len(chk) >= settings.drift_min else np.arange(n)


@dataclass(eq=False)
class _Check:
    """What the static markers' per-frame check needs while their references hold."""

    key: tuple                              # (ids, their tracks, image shape)
    ref: np.ndarray                         # (n, 4, 2) reference corners, px
    win: int                                # cornerSubPix half-window, px
    sampler: CodeSampler                    # their codes at the references
    sub0: np.ndarray                        # (n, 4, 2) first look's cornerSubPix; NaN: none


@dataclass
class FloorLook:
    """One frame's check of the fixed markers ``ids`` (in the order given to
    :meth:`Floor.look`): ``seen`` (n,) their code reads at the reference; ``far`` (n,) they
    drifted (measured in this frame only); ``moved`` the ids seen and drifted; ``bump``
    the "camera moved" event when the camera was bumped, else None."""

    ids: list[int]
    seen: np.ndarray
    far: np.ndarray
    moved: list[int]
    bump: str | None


class Floor:
    """The fixed markers' check (see the module docstring); ``codes``: the dictionary's."""

    def __init__(self, settings: FixedCameraConfig, codes: CodeBook) -> None:
        self.settings = settings
        self.codes = codes
        self._check: _Check | None = None

    def check_for(self, ids: list[int], tracks: Sequence[Track],
                  shape: tuple[int, ...]) -> _Check:
        """The check of the static markers ``ids`` (their ``tracks`` as they are now), built
        again when a reference changed; a marker whose track did not change keeps its first
        look's refinement."""
        key = (tuple(ids), tuple(tracks), shape)
        fc = self._check
        if fc is not None and fc.key == key:
            return fc
        ref = np.stack([t.corners for t in tracks])
        sub0 = np.full(ref.shape, np.nan)
        if fc is not None:
            old = {t: k for k, t in enumerate(fc.key[1])}
            for k, t in enumerate(key[1]):
                j = old.get(t)
                if j is not None:
                    sub0[k] = fc.sub0[j]
        # The cornerSubPix window of these references (the same for a marker at every
        # look, whichever share is measured).
        self._check = fc = _Check(key, ref, subpix_window(ref), CodeSampler(
            ref, np.stack([self.codes(m) for m in ids]), (shape[0], shape[1])), sub0)
        return fc

    def look(self, gray: np.ndarray, ids: list[int], tracks: Sequence[Track],
             frame: int) -> FloorLook:
        """Check the static markers ``ids`` with ``tracks`` in ``gray``, frame ``frame``."""
        s = self.settings
        fc = self.check_for(ids, tracks, gray.shape)
        seen = fc.sampler.scores(gray) >= s.min_score
        # The drift of a rotating share of them (cornerSubPix is the floor check's
        # largest cost): a bump moves every marker, so any share shows it at once; a
        # single marker pushed by less than its code's tolerance shows within
        # drift_every frames.
        chk = drift_share(len(ids), frame, s)
        refined = subpix(gray, fc.ref[chk], fc.win)
        first = np.isnan(fc.sub0[chk, 0, 0])
        if first.any():  # first look since the reference
            fc.sub0[chk[first]] = refined[first]
        # Drift of the refinement from the refinement at the reference (same method on
        # both sides: the detector's own refinement differs by up to ~1 px on oblique
        # wall markers).
        # Moved: at least 3 corners drifted (a robot's plate over one corner pulls only
        # that corner; the reference stays right for a marker that did not move).
        d = refined - fc.sub0[chk]
        far = np.zeros(len(ids), dtype=bool)
        far[chk] = np.add.reduce(np.add.reduce(d * d, axis=2) > s.move_px ** 2,
                                 axis=1) >= 3
        moved = [m for m, ok, f in zip(ids, seen, far, strict=True) if ok and f]
        missing = int((~seen).sum())
        bad_chk = int((~seen[chk]).sum()) + len(moved)
        bump = None
        if len(ids) >= s.bump_min and (
                missing >= max(s.bump_min, s.bump_fraction * len(ids))
                or (len(chk) >= s.bump_min
                    and bad_chk >= max(s.bump_min, s.bump_fraction * len(chk)))):
            bump = (f"camera moved: {len(moved)} of {len(chk)} floor markers "
                    f"measured moved, {missing} of {len(ids)} missing at their "
                    "place in the image; full detection and estimation restart")
        return FloorLook(ids, seen, far, moved, bump)
