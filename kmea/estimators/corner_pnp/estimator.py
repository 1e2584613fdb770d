"""The ``corner-pnp`` estimator: the coordinator of the fit, the consensus, the warm start
and the placements (the package docstring says what it computes)."""

from __future__ import annotations

import math
from collections.abc import Collection, Mapping, Sequence
from dataclasses import replace
from typing import NamedTuple

import numpy as np

from kmea.estimators import unknown_plane as unknown_plane_mod
from kmea.estimators.base import (
    CheckedObservations,
    Estimate,
    EstimateWithLoo,
    EstimatorBase,
    MarkerEstimate,
    MarkerObservation,
    check_observations,
    loo_by_exclusion,
    loo_candidates,
)
from kmea.estimators.common import reference_problem
from kmea.estimators.corner_pnp.consensus import ConsensusSettings, consensus
from kmea.estimators.corner_pnp.fit import CameraFit, FitSettings, fit_lm, select_model
from kmea.estimators.corner_pnp.loo import fast_loo
from kmea.estimators.corner_pnp.placement import PlacementSettings, place_markers
from kmea.estimators.corner_pnp.planes import CornerPlanes, disagreement, stack_corners
from kmea.estimators.corner_pnp.warm import SameCamera, WarmFit, warm_subset
from kmea.estimators.robust import KMEARobust, describe_rejected, footprints
from kmea.geometry import (
    check_distortion,
    make_transform,
    marker_corners_local,
    project,
    undistort,
)
from kmea.geometry.camera import CameraIntrinsics
from kmea.maps.model import MarkerMap
from kmea.stats.chi2 import chi2_quantile

# Placeholders of place_on_planes' observations: markers of known plane are placed from
# their corners; their PnP pose is never read.
_NO_POSE_R = np.eye(3)
_NO_POSE_T = np.array([0.0, 0.0, 1.0])


class Solution(NamedTuple):
    """A camera fit and what it was made of: the references with corners (sorted ids), the
    consensus, each reference's disagreement (m), the checked observations by id."""

    fit: CameraFit
    refs: list[int]
    inliers: list[int]
    dis: dict[int, float]
    obs: dict[int, MarkerObservation]


class _Placement(NamedTuple):
    """A marker placed with a fit: the observation and plane height it was placed from."""

    obs: MarkerObservation
    height: float | None
    estimate: MarkerEstimate
    plane: unknown_plane_mod.PlaneChoice | None
    dropped: int  # the corner its own square contradicts, -1: none


class _Report(NamedTuple):
    rejected: dict[int, float]
    turned: dict[int, float]
    displaced: list[str]
    threshold: float
    cam2world: np.ndarray

    def copy(self) -> _Report:
        return _Report(dict(self.rejected), dict(self.turned), list(self.displaced),
                       self.threshold, self.cam2world.copy())


def _same_square(a: MarkerObservation, b: MarkerObservation) -> bool:
    """The same corners and side: a marker of given plane height is placed from these alone
    (its PnP pose is not read), so either observation gives the same placement."""
    return (a.length == b.length and a.corners is not None and b.corners is not None
            and np.array_equal(a.corners, b.corners))


class CornerPnP(EstimatorBase):
    """All-corner camera pose + ray-plane marker estimator (see the package docstring).

    Options:
        threshold: None (default): references are rejected by the chi-square test on the
            measured corner noise; a number (m): the RMS corner disagreement on its map
            plane beyond which a reference is rejected instead.
        start_threshold: consensus threshold (m) of the robust KMEA start; None (default):
            scaled by the references' own residual level (:class:`KMEARobust`).
        corner_level, reference_level: levels of the corner and reference tests.
        huber_px: Huber loss knee, pixels.
        refine_intrinsics: False, True or "auto".
        refine_level: "auto" refines when the likelihood-ratio test of the refined model
            against the calibrated one passes at this level.
        unknown_plane: "auto", "floor" or "free": markers without a known plane
            (:mod:`kmea.estimators.unknown_plane`); plane_level: that test's level.
        max_iterations: LM iterations per fit.
        min_references: fewer consensus references give "not estimated" (>= 3).
        prior_f, prior_k1: 1-sigma of the intrinsics prior (relative focal length, k1).
        prior_px: corner noise (px) the prior is weighed against.
        warm_start: start from the previous call's fit (see the package docstring).
    """

    name = "corner-pnp"
    # The fit reads the references' corners, not their poses (a pose only seeds a cold
    # fit and the depth scale of markers off the map's planes).
    fits_corners = True

    def __init__(self, threshold: float | None = None, start_threshold: float | None = None,
                 huber_px: float = 1.0, refine_intrinsics: bool | str = "auto",
                 max_iterations: int = 50,
                 min_references: int = 3, prior_f: float = 0.05, prior_k1: float = 0.1,
                 prior_px: float = 0.5, unknown_plane: str = "auto",
                 plane_level: float = 0.999, refine_level: float = 0.999,
                 corner_level: float = 0.99999, reference_level: float = 0.9999,
                 warm_start: bool = False) -> None:
        if unknown_plane not in unknown_plane_mod.MODES:
            raise ValueError(f"corner-pnp: unknown_plane must be one of "
                             f"{', '.join(unknown_plane_mod.MODES)}, got {unknown_plane!r}")
        if refine_intrinsics not in (True, False, "auto"):
            raise ValueError(f"corner-pnp: refine_intrinsics must be true, false or 'auto', "
                             f"got {refine_intrinsics!r}")
        if not (all(v is None or v > 0 for v in (threshold, start_threshold))
                and huber_px > 0):
            raise ValueError("corner-pnp: threshold, start_threshold and huber_px must be > 0")
        self.unknown_plane = unknown_plane
        self.plane_level = float(plane_level)
        self.refine_level = float(refine_level)
        self.threshold = None if threshold is None else float(threshold)
        self.corner_level = float(corner_level)
        self.reference_level = float(reference_level)
        self.huber_px = float(huber_px)
        self.refine_intrinsics = refine_intrinsics
        self.max_iterations = int(max_iterations)
        self.min_references = max(3, int(min_references))
        corner_q = chi2_quantile(self.corner_level, 2)
        self._fit = FitSettings(self.huber_px, float(prior_f), float(prior_k1), float(prior_px),
                                self.max_iterations, chi2_quantile(self.refine_level, 2))
        self._consensus = ConsensusSettings(self.threshold, corner_q,
                                            chi2_quantile(self.reference_level, 2))
        self._placing = PlacementSettings(corner_q, self.unknown_plane, self.plane_level)
        # The start only has to find a consensus; the corner stage re-checks every reference.
        self._start = KMEARobust(threshold=start_threshold, trials=50,
                                 min_references=self.min_references)
        self.warm_start = bool(warm_start)
        self._warm: WarmFit | None = None
        # Placements of the last fit: (fit version, world_map, id -> _Placement). A marker's
        # placement depends only on the fit, its own observation and its plane, so while the
        # warm start returns the same fit, a fixed marker reported with the same observation
        # object is not placed again (only the robots are).
        self._placed: tuple[int, MarkerMap, dict[int, _Placement]] | None = None
        # The last report: (fit version, world_map, rejected ids, their placements, report).
        self._last_report: tuple[int, MarkerMap, tuple[int, ...], tuple[MarkerEstimate, ...],
                                 _Report] | None = None
        self._check = CheckedObservations()
        self._same_camera = SameCamera()
        self._corner_planes = CornerPlanes()

    def reset_warm(self) -> None:
        """Forget the previous fit (the view changed: the next call solves afresh)."""
        self._warm = None
        self._placed = None
        self._last_report = None
        self._check.reset()

    @property
    def warm_fit(self) -> CameraFit | None:
        """The fit the warm start keeps (None: none yet, or the warm start is off)."""
        return None if self._warm is None else self._warm.fit

    # ------------------------------------------------------------------ the camera fit
    def _solve(self, observations: Sequence[MarkerObservation], world_map: MarkerMap,
               exclude: Collection[int], camera: CameraIntrinsics | None
               ) -> Solution | Estimate:
        """The camera fit, or an ``Estimate.failed``."""
        if camera is None:
            return Estimate.failed(self.name, "corner-pnp needs the camera intrinsics "
                                              "(camera matrix and distortion)")
        excl = set(exclude)
        obs = {o.id: o for o in (self._check(observations) if self.warm_start
                                 else check_observations(observations))}
        in_map = world_map.markers  # (MarkerMap's membership, without a method call each)
        refs = sorted(i for i, o in obs.items()
                      if i in in_map and i not in excl and o.corners is not None
                      and not o.suspect)
        if len(refs) < self.min_references:
            return Estimate.failed(self.name, f"{len(refs)} reference marker(s) with corners "
                                              f"visible, need {self.min_references}")
        ref_obs = tuple(obs[i] for i in refs)
        w = self._warm
        # Excluded markers new to the last fit (a floor marker waiting for the next paced
        # refit, kmea.pipeline) do not change it; excluding one of its references does
        # (leave-one-out), so that is solved afresh.
        if not self.warm_start or (excl and w is not None and excl & set(w.refs)):
            w = None
        if (w is not None and w.map_id == id(world_map) and len(w.ref_obs) == len(ref_obs)
                and all(a is b for a, b in zip(w.ref_obs, ref_obs, strict=True))
                and self._same_camera(w, camera)):
            # The very observations of the last fit (a fixed camera's floor, reused by
            # kmea.fixed_camera): the same fit, nothing to check or stack again.
            return Solution(w.fit, refs, list(w.inliers), w.dis, obs)
        for i in refs:
            c = np.asarray(obs[i].corners, dtype=float)
            if c.size != 8 or not np.all(np.isfinite(c)):
                raise ValueError(f"observation id {i}: corners must be 4 finite (x, y) pixels")
        try:
            K0 = np.asarray(camera.camera_matrix, dtype=float)
            d0 = check_distortion(camera.dist_coeffs)
        except ValueError as e:
            return Estimate.failed(self.name, f"camera: {e}")
        uv_refs = stack_corners(refs, obs)
        warm: WarmFit | None = None
        # A fit is kept for the next call only when nothing was excluded.
        cam_key = (K0.tobytes(), d0.tobytes())
        keep_fit = self.warm_start and not excl
        if w is not None and w.map_id == id(world_map) and w.camera == cam_key:
            if w.refs == refs and np.array_equal(w.uv, uv_refs):
                if keep_fit:
                    self._warm = replace(w, ref_obs=ref_obs, intrinsics=camera)
                return Solution(w.fit, refs, list(w.inliers), w.dis, obs)  # the same fit
            same = warm_subset(w, refs, uv_refs, self.min_references)
            if same is not None:
                return Solution(w.fit, refs, same, {i: w.dis[i] for i in refs}, obs)
            if keep_fit:
                warm = w  # a few iterations from it
        keep_model = False
        start: tuple[np.ndarray, np.ndarray, list[int]] | None = None
        if warm is not None:
            # A few iterations from the previous fit; references new to the fit are tried.
            # The intrinsics model (refined or not) is the camera's: a reference set that
            # differs by a few markers (found, uncovered, hidden) keeps the previous choice
            # (its likelihood-ratio test costs a second fit); a larger change tests again.
            changed = len(set(warm.refs) ^ set(refs))
            keep_model = changed <= max(2, len(warm.refs) // 10)
            inliers = [i for i in refs if i in warm.inliers or i not in warm.refs]
            if len(inliers) >= self.min_references:
                start = (warm.fit.R, warm.fit.t, inliers)
            else:
                warm, keep_model = None, False
        if start is None:
            cold = self._cold_start(obs, refs, world_map)
            if isinstance(cold, Estimate):
                return cold
            start = cold
        R, t, inliers = start
        return self._iterate(world_map, obs, refs, inliers, uv_refs, R, t, K0, d0, warm,
                             keep_model, keep_fit, ref_obs, camera, cam_key)

    def _cold_start(self, obs: dict[int, MarkerObservation], refs: list[int],
                    world_map: MarkerMap) -> tuple[np.ndarray, np.ndarray, list[int]] | Estimate:
        """The robust KMEA start: a world2cam pose (R, t) and a consensus of references."""
        P = np.array([obs[i].marker2cam_t for i in refs], dtype=float)
        Q = world_map.positions(refs)
        problem = reference_problem(Q, P, self.min_references)
        if problem:
            return Estimate.failed(self.name, f"robust start: {problem}")
        try:
            start_inl, (_, Rc2w, C), _ = self._start.consensus(
                P, Q, refs, world_map.origin_id,
                np.array([world_map[i].normal for i in refs]),
                footprints(list(obs.values()), world_map, refs))
        except ValueError as e:
            return Estimate.failed(self.name, f"robust start: {e}")
        # The similarity maps the camera origin to C; its rotation is the camera's.
        return Rc2w.T, -Rc2w.T @ C, [i for i, k in zip(refs, start_inl, strict=True) if k]

    def _iterate(self, world_map: MarkerMap, obs: dict[int, MarkerObservation],
                 refs: list[int], inliers: list[int], uv_refs: np.ndarray, R: np.ndarray,
                 t: np.ndarray, K0: np.ndarray, d0: np.ndarray, warm: WarmFit | None,
                 keep_model: bool, keep_fit: bool, ref_obs: tuple[MarkerObservation, ...],
                 camera: CameraIntrinsics, cam_key: tuple[bytes, bytes]
                 ) -> Solution | Estimate:
        """Fit and consensus in turn until the consensus is stable (at most 8 rounds)."""
        row = {i: k for k, i in enumerate(refs)}
        X_refs = np.concatenate([world_map[i].corners_world() for i in refs])
        xy_refs = None
        fit: CameraFit | None = None
        dis: dict[int, float] = {}
        keep = {i: np.ones(4, bool) for i in refs}
        if warm is not None and warm.fit.keep is not None:
            keep.update({i: k.copy() for i, k in warm.fit.keep.items() if i in keep})
        for _ in range(8):
            sel = np.concatenate([4 * row[i] + np.flatnonzero(keep[i]) for i in inliers])
            prev = (fit.K, fit.d) if fit is not None else (
                (warm.fit.K, warm.fit.d) if warm is not None and warm.fit.refine else None)
            if self.refine_intrinsics == "auto" and keep_model and warm is not None:
                # The same references, their corners moved a little (a reference's corners
                # averaged over one more look): the previous model choice stands; a few LM
                # iterations from the previous fit, no second model.
                fit = fit_lm(self._fit, X_refs[sel], uv_refs[sel], R, t, K0, d0,
                             warm.fit.refine, prev)
                if fit is not None:
                    fit.refine_test = warm.fit.refine_test
            elif self.refine_intrinsics == "auto":
                fit, test = select_model(self._fit, X_refs[sel], uv_refs[sel], R, t, K0, d0)
                if fit is not None:
                    fit.refine_test = test
            else:
                fit = fit_lm(self._fit, X_refs[sel], uv_refs[sel], R, t, K0, d0,
                             bool(self.refine_intrinsics), prev)
            if fit is None:
                return Estimate.failed(self.name, "reprojection fit failed (camera behind markers)")
            R, t = fit.R, fit.t
            if fit.refine:
                xy = undistort(uv_refs, fit.K, fit.d)
            else:
                xy = xy_refs = undistort(uv_refs, K0, d0) if xy_refs is None else xy_refs
            dis = disagreement(fit.R, fit.t, refs, xy, world_map)
            new, new_keep = consensus(self._consensus, fit, refs, inliers, X_refs, uv_refs, xy,
                                      dis, world_map)
            if new == inliers and all(np.array_equal(new_keep[i], keep[i]) for i in new):
                break
            keep = new_keep
            if len(new) < self.min_references:
                rule = (f"within {self.threshold * 1e3:.0f} mm" if self.threshold is not None
                        else f"within their corner noise ({fit.corner_sigma:.2f} px)")
                return Estimate.failed(
                    self.name, f"no consensus: {len(new)} of {len(refs)} references agree "
                               f"{rule}")
            inliers = new
        assert fit is not None  # the loop ran at least once
        fit.keep = {i: keep[i] for i in inliers}
        if keep_fit:
            self._warm = WarmFit(id(world_map), cam_key, refs, uv_refs, fit, tuple(inliers),
                                 dis, ref_obs, camera)
        return Solution(fit, refs, inliers, dis, obs)

    # ------------------------------------------------------------------ the estimate
    def estimate(
        self,
        observations: Sequence[MarkerObservation],
        world_map: MarkerMap,
        exclude: Collection[int] = (),
        camera: CameraIntrinsics | None = None,
        plane_heights: Mapping[int, float] | None = None,
    ) -> Estimate:
        """World pose of every observed marker; see the package docstring.

        camera is required; plane_heights: id -> height (m) of horizontal non-map markers.
        """
        return self._estimate_from(self._solve(observations, world_map, exclude, camera),
                                   world_map, plane_heights)

    def _estimate_from(self, res: Solution | Estimate, world_map: MarkerMap,
                       plane_heights: Mapping[int, float] | None) -> Estimate:
        """The Estimate of a camera fit (:meth:`_solve`'s result)."""
        if isinstance(res, Estimate):
            return res
        fit, refs, inliers, dis, obs = res
        planes: dict[int, unknown_plane_mod.PlaneChoice] = {}
        heights = dict(plane_heights or {})
        dropped: dict[int, int] = {}
        markers = self._placed_markers(fit, obs, world_map, heights, inliers, planes, dropped,
                                       refs)
        rep = self._report(fit, refs, inliers, markers, world_map)
        info = {"displaced": rep.displaced, "turned": rep.turned,
                "reprojection_rms_px": fit.rms_px,
                "sigma_px": fit.sigma_px, "corner_sigma_px": fit.corner_sigma,
                "iterations": fit.iterations, "threshold": rep.threshold,
                "thresholds": dict(fit.thresholds or {}), "corners_dropped": dropped,
                "intrinsics_refined": fit.refine}
        if math.isfinite(fit.refine_test):
            info["intrinsics_test"] = fit.refine_test
        if planes:
            info["unknown_planes"] = {i: c.kind for i, c in planes.items()}
            info["plane_statistics"] = {i: c.statistic for i, c in planes.items()}
            info["plane_geometry"] = {i: c.plane for i, c in planes.items()}
        if fit.refine:
            info.update(fx=float(fit.K[0, 0]), fy=float(fit.K[1, 1]), k1=float(fit.d[0]))
        return Estimate(
            algorithm=self.name, ok=True, markers=markers, references=tuple(inliers),
            cam2world=rep.cam2world, scale=1.0,
            residuals={i: dis[i] for i in inliers}, rejected=rep.rejected, info=info)

    def _report(self, fit: CameraFit, refs: Sequence[int], inliers: Sequence[int],
                markers: Mapping[int, MarkerEstimate], world_map: MarkerMap) -> _Report:
        """What an Estimate says of the rejected references: how far each one's centre moved
        in its map plane and how much it turned there (it was rejected on its corners' RMS
        disagreement), and the camera pose. With the warm start the last report is reused
        (copied) while the fit, the map and the rejected references' placements are the
        same."""
        inl = set(inliers)
        out_ids = tuple(i for i in refs if i not in inl)
        placed = tuple(markers[i] for i in out_ids)
        last = self._last_report
        if (self.warm_start and last is not None and last[0] == fit.version
                and last[1] is world_map and last[2] == out_ids
                and all(a is b for a, b in zip(last[3], placed, strict=True))):
            return last[4].copy()
        rejected, turned = {}, {}
        for i, me in zip(out_ids, placed, strict=True):
            mk = world_map[i]
            rejected[i] = float(np.linalg.norm(me.position - mk.position))
            M = mk.rotation.T @ me.rotation
            turned[i] = math.atan2(M[1, 0], M[0, 0])
        threshold = (self.threshold if self.threshold is not None
                     else float(np.median(list((fit.thresholds or {}).values()))))
        Rc2w = fit.R.T
        report = _Report(rejected, turned, describe_rejected(rejected, turned), threshold,
                         make_transform(Rc2w, -Rc2w @ fit.t))
        if self.warm_start:
            self._last_report = (fit.version, world_map, out_ids, placed, report)
            return report.copy()
        return report

    # ------------------------------------------------------------------ placements
    def place_on_planes(self, ids: Sequence[int], corners: np.ndarray,
                        lengths: Sequence[float], world_map: MarkerMap,
                        plane_heights: Mapping[int, float]) -> dict[int, MarkerEstimate] | None:
        """With the warm start's last camera fit: world poses and sigmas of markers of known
        plane height (``plane_heights``; a fixed camera's robots) from their corners alone,
        as :meth:`estimate` places them with that fit (ray-plane points, corner test, square
        fit; no IPPE pose needed). ids (n,); corners (n, 4, 2) px; lengths (n,) m. None
        without a last fit, or when a marker is in the map or has no known height."""
        w = self._warm
        if (not self.warm_start or w is None or not len(ids)
                or any(i in world_map or i not in plane_heights for i in ids)):
            return None
        obs = {i: MarkerObservation(i, _NO_POSE_R, _NO_POSE_T,
                                    np.asarray(c, dtype=float).reshape(4, 2), float(L))
               for i, c, L in zip(ids, corners, lengths, strict=True)}
        dropped: dict[int, int] = {}
        out = place_markers(self._placing, self._corner_planes, w.fit, obs, world_map,
                            plane_heights, dropped=dropped)
        # Entered as placements of this fit: the frame's estimate, placing the same markers
        # with the same corners from the same fit, takes them (see _placed_markers).
        old = self._placements(w.fit, world_map)
        for i, me in out.items():
            old[i] = _Placement(obs[i], plane_heights.get(i), me, None, dropped.get(i, -1))
        return out

    def placed_observations(self, placed: Mapping[int, MarkerEstimate], ids: Sequence[int],
                            corners: np.ndarray, lengths: Sequence[float]
                            ) -> dict[int, MarkerObservation]:
        """Camera-frame observations of markers :meth:`place_on_planes` placed (``placed``,
        for its ``ids`` (n,), ``corners`` (n, 4, 2) px, ``lengths`` (n,) m), from those
        placements and the last camera fit instead of an IPPE pose per marker: marker2cam =
        world2cam of the fit after the placement's marker2world, the reprojection error of the
        placed square against the corners (px, RMS), one solution, not ambiguous (the plane
        is known). Markers not placed are left out; {} without a last fit."""
        w = self._warm
        sel = [k for k, i in enumerate(ids) if i in placed]
        if w is None or not sel:
            return {}
        fit = w.fit
        R = np.stack([fit.R @ placed[ids[k]].rotation for k in sel])            # (m, 3, 3)
        t = np.stack([fit.R @ placed[ids[k]].position + fit.t for k in sel])    # (m, 3)
        local = np.stack([marker_corners_local(float(lengths[k])) for k in sel])  # (m, 4, 3)
        cam = np.einsum("mij,mkj->mki", R, local) + t[:, None, :]
        uv = project(cam.reshape(-1, 3), fit.K, fit.d).reshape(-1, 4, 2)
        c = np.asarray(corners, dtype=float)[sel].reshape(-1, 4, 2)
        err = np.sqrt(((uv - c) ** 2).sum(axis=2).mean(axis=1))
        return {ids[k]: MarkerObservation(ids[k], R[j], t[j], c[j], float(lengths[k]),
                                          float(err[j]))
                for j, k in enumerate(sel)}

    def _placements(self, fit: CameraFit, world_map: MarkerMap) -> dict[int, _Placement]:
        """The placements entered for ``fit`` and ``world_map`` (a new, empty table when the
        fit or the map changed)."""
        if (self._placed is None or self._placed[0] != fit.version
                or self._placed[1] is not world_map):
            self._placed = (fit.version, world_map, {})
        return self._placed[2]

    def _placed_markers(self, fit: CameraFit, obs: Mapping[int, MarkerObservation],
                        world_map: MarkerMap, plane_heights: Mapping[int, float],
                        inliers: Sequence[int],
                        planes: dict[int, unknown_plane_mod.PlaneChoice],
                        dropped: dict[int, int], scale_refs: Sequence[int]
                        ) -> dict[int, MarkerEstimate]:
        """:func:`place_markers`, reusing the placements of the same fit for markers whose
        observation has the same version (warm start only; see ``_placed``)."""
        if not self.warm_start or self._warm is None or self._warm.fit is not fit:
            return place_markers(self._placing, self._corner_planes, fit, obs, world_map,
                                 plane_heights, inliers, planes, dropped=dropped,
                                 scale_refs=scale_refs)
        old = self._placements(fit, world_map)
        out: dict[int, MarkerEstimate] = {}
        todo: set[int] = set()
        for i, o in obs.items():
            hit = old.get(i)
            if hit is not None and hit.height == plane_heights.get(i) and (
                    hit.obs.version == o.version
                    or (hit.height is not None and _same_square(hit.obs, o))):
                out[i] = hit.estimate
                if hit.plane is not None:
                    planes[i] = hit.plane
                if hit.dropped >= 0:
                    dropped[i] = hit.dropped
            else:
                todo.add(i)
        if todo:
            out.update(place_markers(self._placing, self._corner_planes, fit, obs, world_map,
                                     plane_heights, inliers, planes, only=todo,
                                     dropped=dropped, scale_refs=scale_refs))
        # Only the new placements are entered (the others are there already); an entry of
        # a marker out of view stays: it is reused only for the very same observation object
        # (or, of a marker of given height, the same corners and side).
        for i in todo:
            if i in out:
                old[i] = _Placement(obs[i], plane_heights.get(i), out[i], planes.get(i),
                                    dropped.get(i, -1))
        return {i: out[i] for i in obs if i in out}

    # ------------------------------------------------------------------ leave-one-out
    def estimate_with_loo(
        self,
        observations: Sequence[MarkerObservation],
        world_map: MarkerMap,
        exclude: Collection[int] = (),
        camera: CameraIntrinsics | None = None,
        plane_heights: Mapping[int, float] | None = None,
        loo_ids: Collection[int] | None = None,
    ) -> EstimateWithLoo:
        """The estimate and its leave-one-out (:mod:`kmea.estimators.base`) from ONE camera
        fit, held by the returned object (no cache in the estimator).

        Leave-one-out of a reference j of the fit, by the definition ``estimate(exclude={j})``
        computed fast: one Gauss-Newton step from the full solution with j's rows removed
        (H - J_j^T W_j J_j, g - J_j^T W_j r_j), a 6x6 (8x8) solve for all references at once,
        instead of a robust start and an LM per marker. Removing one of many references
        moves the optimum little, so one step lands on it to second order (under 1e-6 m on
        the simulated floor with 0.2 px of corner noise; the tests compare with
        ``estimate(exclude={j})``). A rejected reference is not in the fit, so its position
        is the full fit's. Every other marker (no corners, a known plane height, too few
        references left, a failed fit) goes through ``estimate(exclude={j})`` itself.
        """
        res = self._solve(observations, world_map, exclude, camera)
        est = self._estimate_from(res, world_map, plane_heights)

        def loo() -> tuple[dict[int, np.ndarray], dict[int, str]]:
            # Computed when asked for (a tracked frame whose floor did not change never is).
            ids = (loo_candidates(observations, world_map, exclude) if loo_ids is None
                   else sorted(set(loo_ids)))
            fast = {} if isinstance(res, Estimate) else fast_loo(
                self._fit, self._placing.corner_q, self.min_references, res.fit, res.refs,
                res.inliers, res.obs, world_map)
            heights = plane_heights or {}
            fast = {i: p for i, p in fast.items() if i in set(ids) and i not in heights}
            pos, fail = loo_by_exclusion(self, observations, world_map,
                                         [i for i in ids if i not in fast], exclude, camera,
                                         plane_heights)
            pos.update(fast)
            return pos, fail

        return EstimateWithLoo(est, world_map, loo)
