"""``corner-pnp``: the camera pose from the corners of all reference markers, then ray-plane.

The package: :mod:`.fit` (the camera fit and its model selection), :mod:`.consensus`
(which references and corners agree), :mod:`.planes` (rays meet planes), :mod:`.placement`
(every marker from its corners), :mod:`.uncertainty` (sigmas), :mod:`.loo` (leave-one-out
from one fit), :mod:`.warm` (the fixed camera's warm start), :mod:`.estimator` (the
coordinator, :class:`CornerPnP`).

KMEA aligns the *centres* of per-marker PnP poses; the depth of one small marker is its
noisiest coordinate and leaks sideways off the optical axis. Here instead:

1. **Robust start**: :class:`kmea.estimators.robust.KMEARobust` on the per-marker poses
   gives a consensus of references and a rough camera pose (its similarity's rotation,
   and the camera centre where the similarity puts the camera origin).
2. **Levenberg-Marquardt** on the reprojection error of every corner of every consensus
   reference (map corners projected with K and the OpenCV distortion model, numpy), with
   a Huber loss (``huber_px``) so one bad corner cannot dominate.
3. **Rejection**, scaled by the corner noise the frame shows (:mod:`kmea.estimators.
   corner_noise`): ``sigma_px``, the median-based level of the consensus references'
   reprojection residuals (floored at 0.01 px). A corner whose residual ``|e|^2 /
   sigma_px^2`` exceeds the chi-square (2 dof) ``corner_level`` quantile is dropped (one of
   a reference's 4 at most: an outline drawn across it, a glare); a reference is rejected
   as displaced when two or more of its corners are, or when its kept corners' sum of
   ``|e|^2 / sigma_px^2`` exceeds the chi-square (2 x corners) ``reference_level``
   quantile; then LM again, until the consensus is stable. In metres the threshold is
   ``sigma_px sqrt(q / corners)`` times the marker's footprint (its side in metres over its
   side in pixels): a far, small marker gets a larger one than a near, big marker, in
   proportion (``info["thresholds"]``, RMS corner distance). ``threshold`` (metres) gives
   the former fixed rule instead (RMS corner distance on the map plane). Rejected
   references are reported in ``Estimate.rejected`` (id -> how far their centre moved in
   their map plane, m) and ``info["displaced"]``.
4. **Every marker from its corners**: the rays of its 4 corners (pixel -> undistorted
   normalized ray) intersect its plane: ``z = plane_heights[id]`` when the caller gives a
   height (a robot's top plate), else its map plane for a map marker (what leave-one-out
   evaluates); centre = mean of the 4 points, in-plane rotation from a 2D Procrustes fit of
   the square. A corner the marker's own square contradicts (leave-one-corner-out test at
   ``corner_level`` against ``sigma_px``) is left out of that fit. A marker with no known
   plane (not in the map, no height given) is put on a plane of the map when its corners
   are consistent with it (the same corner test first), else estimated free with its
   depth corrected by the references (:mod:`kmea.estimators.unknown_plane`, option
   ``unknown_plane``); a marker without corners gets its own PnP pose moved by the fitted
   camera pose.

Optional intrinsics refinement (``refine_intrinsics``): a common multiplier of fx and fy
and k1 join the LM, with a weak Gaussian prior at the calibrated values (``f`` 5 %, k1
0.1: real calibrations are a few percent off, and the prior keeps a fronto-parallel
view, where focal length and camera height are not separable, well-posed). ``"auto"`` (the
default) refines only when the data call for it: a likelihood-ratio test of the refined
model against the calibrated one (:func:`.fit.select_model`; 2 extra parameters, chi-square level
``refine_level`` 0.999). Refining an exact calibration anyway moves the focal length by a
few tenths of a percent (it trades against the camera height in a near fronto-parallel
view): harmless on the floor, but it biases markers at another height (a robot's top plate)
by about 1e-3 of their distance from the nadir. With a calibration 1-3 % off, or the
tutorial photo's rough one, the test passes by orders of magnitude.

Warm start (``warm_start``, off by default; the daemon's tracking mode for a fixed live
camera turns it on): the fit of the previous call is kept; when the references and their
corners are the same (a tracked fixed floor), that fit is the answer (a fresh solve would
compute the same numbers); when they changed (a marker hidden, one more found), the
Levenberg-Marquardt starts from the previous pose and intrinsics with the previous
consensus instead of a robust start: a few iterations, not a fresh solve. Calls with
``exclude`` (leave-one-out by exclusion) never use nor change it. With the same fit only
the markers with new observations (the robots) are placed again, and what their placement
needs from the fit alone (its covariance, the perturbed poses of the uncertainty's
derivatives, the camera centre: :class:`.fit.FitConsts`) is computed once per fit, keyed on
the fit's version,; the numbers are
those of a computation from scratch (``tests/test_corner_fast.py``).

Uncertainty (``MarkerEstimate.sigma``, m): the RMS position error predicted by first-order
propagation of (a) the pose (and intrinsics) covariance ``sigma_px^2 (J^T J)^-1`` of the LM
and (b) the marker's own corner noise ``sigma_px``, through the ray-plane intersection;
``sigma_px^2`` is the residual variance of the fit (sum of squared pixel residuals over
their degrees of freedom). ``sigma = sqrt(trace(Cov))``. Markers placed by their own PnP
pose get ``None``.
"""

from kmea.estimators.corner_pnp.estimator import CornerPnP

__all__ = ["CornerPnP"]
