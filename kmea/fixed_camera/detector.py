"""Tracking detection for a fixed camera: look where the markers are, detect what is new.

The camera is bolted above a static floor; only robots move. Full ``detectMarkers`` on
every 1640x1232 frame thresholds two million pixels three times to find markers whose
place is already known. :class:`FixedCameraDetector` keeps what the last frames found
(:class:`kmea.fixed_camera.tracks.Track`) and, per frame:

- **static markers** (the map's, minus robot markers): they are where they were, checked
  at their reference corners (:mod:`kmea.fixed_camera.floor`: code read, drift measured).
  A marker that moved gets a background look; when the camera was bumped a full detection
  runs at once (in that frame), every reference is replaced and the result carries a
  ``camera moved`` event (the pipeline then restarts its estimation). The reported
  corners of a static marker stay its reference corners while it does not move, so the
  pipeline can reuse its pose (:mod:`kmea.fixed_camera.session`).
- **moving markers** (robots, anything not in the map): followed from their prediction or
  detected around it (:mod:`kmea.fixed_camera.follow`). A moving marker lost there
  triggers one full detection in the same frame (a robot visible in the frame keeps its
  pose for the frame).
- **new markers**: a full detection (:mod:`kmea.fixed_camera.discovery`) every
  ``full_every`` frames and whenever a tracked marker is lost, run where the caller's
  :class:`~kmea.fixed_camera.discovery.Jobs` runs it (default: at once, in the calling
  thread; the library starts no thread). What it finds that is not tracked is checked in
  the current frame (a moving one detected around where it was found) and reported from
  then on (:meth:`FixedCameraDetector.merge`). At 30 frames/s, ``full_every`` = 6
  reports a marker entering the view within 0.2 s plus one discovery.

Stateful: one instance per live source, called on consecutive frames. For file sources
(frame-exact, reproducible results) the pipeline keeps full detection on every frame.
Pixel convention: OpenCV's (the top-left pixel's centre is (0, 0)).
"""

from __future__ import annotations

import numpy as np

from kmea.fixed_camera.codes import CodeBook, code_scores
from kmea.fixed_camera.discovery import Discovered, DiscoveryJob, Inline, Jobs, TunedDetectors
from kmea.fixed_camera.floor import Floor
from kmea.fixed_camera.follow import Follower
from kmea.fixed_camera.tracks import FixedCameraConfig, Track, averaged
from kmea.vision.detection import Detections, DetectorConfig, as_gray

__all__ = ["FixedCameraDetector"]


class FixedCameraDetector:
    """``detect(image) -> Detections`` like :class:`kmea.vision.detection.MarkerDetector`,
    tracking what it knows (see the module docstring). ``Detections.mode`` is "full" (a
    full detection answered) or "followed"; ``Detections.events`` carries "camera moved"
    and friends.

    Counters: ``followed_frames`` / ``full`` frames, ``background`` discoveries asked for,
    ``bumps``, ``followed`` moving markers refined from their prediction (no region
    detection).
    """

    def __init__(self, config: DetectorConfig, tracking: FixedCameraConfig | None = None,
                 jobs: Jobs | None = None) -> None:
        """jobs: where the discoveries run (the caller's; it closes them with
        :meth:`close`); None: :class:`~kmea.fixed_camera.discovery.Inline`, in the calling
        thread within ``detect``."""
        self.config = config
        self.settings = tracking or FixedCameraConfig()
        self.jobs: Jobs = jobs if jobs is not None else Inline()
        self.detectors = TunedDetectors(config)  # the calling thread's
        self.full_detector = self.detectors.full
        self.codes = CodeBook(self.full_detector.dictionary)
        self.floor = Floor(self.settings, self.codes)
        self.follower = Follower(self.settings, self.detectors, self.codes)
        # The discoveries' (one job at a time: see Jobs).
        self._discovery = TunedDetectors(config)
        self._half_ok = False
        self._side = 0.0  # median marker side (px) of the last full detection
        self.known: dict[int, Track] = {}  # id -> what is known of its corners
        self.frame = -1
        self.followed_frames = 0
        self.full = 0
        self.background = 0
        self.bumps = 0
        self._since_full = 0
        self._want_full = True

    @property
    def followed(self) -> int:
        return self.follower.followed

    @property
    def shape_px(self):
        """The last followed looks' shape residuals (px; see Follower.follow)."""
        return self.follower.shape_px

    def close(self) -> None:
        """No more discoveries (see :meth:`Jobs.close`)."""
        self.jobs.close()

    # ------------------------------------------------------------------ per frame
    def detect(self, image: np.ndarray) -> Detections:
        """Markers in ``image`` (the next frame of the fixed camera); see the module
        docstring."""
        gray = as_gray(image)
        self.jobs.frame_started()
        self.frame += 1
        self._since_full += 1
        events: list[str] = []
        if self._want_full or not self.known:
            return self._full(gray, events)
        out_ids: list[int] = []
        out_c: list[np.ndarray] = []
        lost = self._static(gray, out_ids, out_c, events)
        if lost is None:  # the camera was bumped
            return self._full(gray, events)
        if not self._moving(gray, out_ids, out_c):
            # A moving marker just lost: it may have outrun the prediction; a robot
            # visible in the frame must keep its pose, so look at the whole frame once.
            return self._full(gray, events)
        # ---- discoveries of the background detection
        got = self.jobs.take()
        if got is not None:
            self.merge(gray, got, out_ids, out_c)
        if lost or self._since_full >= self.settings.full_every:
            self._since_full = 0
            self._submit(gray, full_res=lost)
        self.followed_frames += 1
        return self._result_of(out_ids, out_c, "followed", events)

    def _static(self, gray: np.ndarray, out_ids: list[int], out_c: list[np.ndarray],
                events: list[str]) -> bool | None:
        """The static markers seen at their reference corners go to ``out_ids``/``out_c``;
        True when one was just hidden or moved (a background look follows), None when the
        camera was bumped (its event is in ``events``)."""
        st = [m for m, t in self.known.items() if t.static]
        if not st:
            return False
        look = self.floor.look(gray, st, [self.known[m] for m in st], self.frame)
        if look.bump is not None:
            self.bumps += 1
            events.append(look.bump)
            return None
        if look.moved:
            events.append("floor marker(s) " + ", ".join(map(str, look.moved))
                          + f" moved more than {self.settings.move_px:g} px in the image")
        lost = False
        for m, ok, f in zip(st, look.seen, look.far, strict=True):
            t = self.known[m]
            if ok and not f:
                out_ids.append(m)
                out_c.append(t.corners)
                t.seen = self.frame
            elif t.seen == self.frame - 1:
                # Just hidden or moved: one background look (a hidden one keeps its
                # place; a moved one gets its new place from the full detection).
                lost = True
        return lost

    def _moving(self, gray: np.ndarray, out_ids: list[int], out_c: list[np.ndarray]) -> bool:
        """The moving markers near their prediction go to ``out_ids``/``out_c`` (one
        detection per group of nearby regions: a robot's two markers share one crop);
        False when one seen in the last frame is lost."""
        fol = self.follower
        moving = [(m, t) for m, t in self.known.items() if not t.static]
        found: dict[int, np.ndarray] = {}
        others: dict[int, np.ndarray] = {}
        preds = {m: t.corners + t.velocity * (self.frame - t.seen) for m, t in moving}
        if self.settings.follow:
            steady = [m for m, t in moving if t.steady and t.seen == self.frame - 1]
            found = fol.follow(gray, {m: preds[m] for m in steady},
                               {m: self.known[m].corners for m in steady})
        for box, side, members in fol.groups({m: q for m, q in preds.items()
                                              if m not in found}):
            ids, cs = fol.detect_box(gray, box, side)
            for i, c in zip(ids.tolist(), cs, strict=True):
                (found if i in members else others)[i] = c
        for m, t in moving:
            c = found.get(m)
            if c is None:  # not where predicted: a wider look with the full parameters
                c, more = fol.find_moving(gray, m, preds[m], wide_only=True)
                others.update(more)
            if c is None:
                if t.seen == self.frame - 1:
                    return False
                if self.frame - t.seen > 30:
                    del self.known[m]
                continue
            t.steady = self.frame - t.seen == 1
            t.velocity = (c - t.corners) / max(1, self.frame - t.seen)
            t.corners, t.seen = c, self.frame
            out_ids.append(m)
            out_c.append(c)
        for i, oc in others.items():
            if i not in self.known:
                self.known[i] = Track(oc, np.zeros((4, 2)), self._is_static(i), self.frame)
        return True

    def _submit(self, image: np.ndarray, full_res: bool = False) -> None:
        """Ask for a discovery of ``image``: at half resolution, except every
        ``full_res_every``-th one and when ``full_res``."""
        self.background += 1
        half = (self._half_ok and not full_res
                and self.background % max(1, self.settings.full_res_every) != 0)
        # At half resolution one threshold window sized for the markers already seen (new
        # ones are the same markers on the same floor; the full-resolution looks keep all
        # three windows for anything else).
        win = max(3, round(self._side / 10.0) | 1) if half and self._side > 0 else 0
        self.jobs.submit(DiscoveryJob(self.frame, image, half, win, self._discovery))

    def merge(self, gray: np.ndarray, got: Discovered,
              out_ids: list[int], out_c: list[np.ndarray]) -> None:
        """Add what a discovery (``got``) found and is not tracked, detected again in this
        frame around where it was found (full resolution), to ``out_ids``/``out_c``."""
        frame_no, det, half = got
        have = set(out_ids)
        s = self.settings
        same_px = 2.0 if half else 0.5
        for mid, c0 in zip(det.ids.tolist(), det.corners, strict=True):
            t = self.known.get(mid)
            static = self._is_static(mid)
            if (static and not half and mid in have and t is not None
                    and np.abs(c0 - t.corners).max() < 1.5 * s.move_px):
                # Another full-resolution look at a fixed marker in place: averaged in.
                nt = averaged(t, c0, self.frame, s)
                if nt is not t:
                    self.known[mid] = nt
                    out_c[out_ids.index(mid)] = nt.corners
                continue
            if t is not None and (t.seen > frame_no or mid in have) and (
                    not static or np.abs(c0 - t.corners).max() < same_px):
                continue  # tracked since, or a fixed marker at its place: nothing new
            c, _ = self.follower.find_moving(gray, mid, c0)
            if c is None:
                continue  # not in this frame (any more)
            if static:
                if np.abs(c - c0).max() > same_px:
                    # A fixed marker found at two different places in two frames: part of
                    # it was covered in one of them (a robot passing): wait for a clean look.
                    continue
                new = float(code_scores(gray, c[None], self.codes(mid)[None])[0])
                if new < s.add_score:
                    continue  # half hidden now: wait for a clean look
                if mid in have:
                    # Reported at its reference, found elsewhere (> 0.5 px) by a full
                    # detection of the whole marker that reads at least as well: the
                    # reference was taken while something covered part of the marker.
                    if t is None:  # every reported id is tracked: cannot happen
                        raise RuntimeError(f"marker {mid} reported without a track")
                    if np.abs(c - t.corners).max() < 0.5:
                        continue
                    old = float(code_scores(gray, t.corners[None], self.codes(mid)[None])[0])
                    if new < old:
                        continue
                    out_c[out_ids.index(mid)] = c
                    self.known[mid] = Track(c.copy(), np.zeros((4, 2)), True, self.frame)
                    continue
                self.known[mid] = Track(c.copy(), np.zeros((4, 2)), True, self.frame)
            else:
                if mid in have:
                    continue
                vel = (c - c0) / max(1, self.frame - frame_no)
                self.known[mid] = Track(c, vel, False, self.frame)
            out_ids.append(mid)
            out_c.append(c)
            have.add(mid)

    def _full(self, gray: np.ndarray, events: list[str]) -> Detections:
        det = self.full_detector.detect(gray)
        self.full += 1
        bumped = any(e.startswith("camera moved") for e in events)
        if bumped:
            self.jobs.take()  # a background result of the old view is worthless
            self.known = {}
        self._reset_from(det)
        return Detections(det.ids, det.corners, det.rejected, mode="full",
                          events=tuple(events), restart=bumped)

    @staticmethod
    def _result_of(ids: list[int], corners: list[np.ndarray], mode: str, events: list[str]
                   ) -> Detections:
        if not ids:
            return Detections(np.zeros(0, np.int64), np.zeros((0, 4, 2)), 0, mode=mode,
                              events=tuple(events))
        order = np.argsort(ids, kind="stable")
        return Detections(np.asarray(ids, np.int64)[order], np.stack(corners)[order], 0,
                          mode=mode, events=tuple(events))

    def _is_static(self, mid: int) -> bool:
        return mid in self.settings.static_ids

    def _reset_from(self, det: Detections) -> None:
        """Every track from a full detection of the current frame."""
        old = self.known
        # A static marker the detection missed (hidden now) keeps its place.
        self.known = {m: t for m, t in old.items() if t.static}
        sides = []
        for mid, c in zip(det.ids.tolist(), det.corners, strict=True):
            prev = old.get(mid)
            sides.append(float(np.linalg.norm(c[0] - c[2])) / np.sqrt(2.0))
            if prev is not None and prev.static and self._is_static(mid):
                self.known[mid] = averaged(prev, c, self.frame, self.settings)
                continue
            vel = np.zeros((4, 2))
            if prev is not None and not prev.static and self.frame > prev.seen:
                vel = (c - prev.corners) / (self.frame - prev.seen)
            self.known[mid] = Track(c.copy(), vel, self._is_static(mid), self.frame,
                                    steady=prev is not None and not prev.static
                                    and self.frame - prev.seen == 1)
        if sides:
            # Half-resolution discovery only when markers stay >= 20 px wide there.
            self._side = float(np.median(sides))
            self._half_ok = self._side >= 40.0
        self._since_full = 0
        self._want_full = False

