"""The fixed camera's session (kmea.fixed_camera.session) through the pipeline: robots placed
before the poses, warm starts, paced refits."""

from __future__ import annotations

import itertools
import math
from dataclasses import replace

import numpy as np
from fixed_camera_helpers import (
    frames_of,
    tracked_pipeline,
)

from kmea.pipeline import FrameInput, Pipeline, PipelineSettings


def test_robots_are_sent_before_the_floor_is_refitted(default_frames):
    # Every background detection at full resolution: each one averages the floor's
    # reference corners, so the floor's poses and the camera fit change in those frames.
    frames, src = default_frames
    specs = tuple(src.scene.robot_specs())
    p = tracked_pipeline(src, "corner-pnp", full_res_every=1)
    ref = Pipeline(src.camera, src.world_map, PipelineSettings(robots=specs,
                                                               algorithm="corner-pnp"))
    early = 0
    for f in frames:
        det = p.detector.detect(f.image)
        sent: list[tuple[bool, dict]] = []
        # When the relay runs: is the floor of this frame still waiting to be posed?
        def relay(t, fx, sent=sent, det=det):
            sent.append((p.session.poses.fixed_changed(det.ids, det.corners), dict(fx)))

        r = p.process(FrameInput(f.index, f.timestamp, f.image, detections=det),
                      on_robots=relay)
        assert len(sent) == 1, f.index  # one relay call per frame
        pending, fixes = sent[0]
        assert fixes.keys() == r.robots.keys()
        early += pending
        s = ref.process(FrameInput(f.index, f.timestamp, f.image, ids=r.ids,
                                   corners=r.corners,
                                   observations=ref.poses(r.ids, r.corners)[0]))
        for name, fix in fixes.items():
            other = s.robots[name]
            assert math.hypot(fix.x - other.x, fix.y - other.y) < 1e-3, (f.index, name)
    assert early >= 2  # the floor changed in some frames, and the robots went first


def test_corner_pnp_warm_start_gives_the_fresh_solve(default_frames):
    from kmea.estimators.corner_pnp import CornerPnP

    frames, src = default_frames
    p = tracked_pipeline(src, "corner-pnp")
    assert p.estimator.warm_start
    fresh = CornerPnP()
    intr = p.camera.intrinsics
    heights = p.plane_heights
    warm_used = 0
    for f in frames[:10]:
        before = p.estimator._warm
        r = p.process(FrameInput(f.index, f.timestamp, f.image))
        # Started from the previous fit: the same fit returned (the floor unchanged) or a
        # warm solve that replaced it.
        warm_used += before is not None and (p.estimator._warm is not before
                                             or p.estimator._warm.fit is before.fit)
        s = fresh.estimate(r.observations, src.world_map, camera=intr, plane_heights=heights)
        assert r.estimate.ok and s.ok
        assert set(r.estimate.references) == set(s.references)
        for mid, me in s.markers.items():
            d = np.linalg.norm(r.estimate.markers[mid].position - me.position)
            assert d < 2e-5, (f.index, mid, d)  # 20 um: the same optimum
            a, b = r.estimate.markers[mid].sigma, me.sigma
            assert (a is None) == (b is None) and (a is None or abs(a - b) < 1e-6), (mid, a, b)
    assert warm_used >= 1  # some frames started from the previous fit


def _refits(src, frames, **settings) -> tuple[list[int], list]:
    """Frames at which a tracking pipeline (corner-pnp) refitted the floor's camera, and
    its results."""

    p = tracked_pipeline(src, "corner-pnp")
    p.settings = replace(p.settings, **settings)
    refits, results, fit = [], [], None
    for f in frames:
        results.append(p.process(FrameInput(f.index, f.timestamp, f.image)))
        if p.estimator._warm.fit is not fit:
            fit = p.estimator._warm.fit
            refits.append(f.index)
    p.close()
    return refits, results


def test_floor_refits_are_paced_and_new_floor_markers_placed_meanwhile():
    from kmea.estimators.corner_pnp import CornerPnP

    frames, src = frames_of("sim:default", 46)
    every, paced = _refits(src, frames, refit_every=1)
    refits, results = _refits(src, frames, refit_every=20)
    assert len(refits) < len(every), (refits, every)
    # after the first frame's fit, at most one refit per 20 frames
    assert all(b - a >= 20 for a, b in itertools.pairwise(refits[1:])), refits
    fresh = CornerPnP()
    deferred = 0
    for r in results:
        for m in r.deferred:  # a fixed marker new to the floor: reported, not a reference
            deferred += 1
            assert m in r.estimate.markers and m not in r.estimate.references
        if r.deferred:
            # The same as a solve told to leave them out (the last fit, to micrometres).
            s = fresh.estimate(r.observations, src.world_map, exclude=r.deferred,
                               camera=src.camera.intrinsics, plane_heights={})
            for m in r.deferred:
                d = np.linalg.norm(r.estimate.markers[m].position - s.markers[m].position)
                assert d < 2e-4, (r.index, m, d)
    assert deferred >= 1
    # Every frame's robots and markers agree with refitting at every change within 1 mm.
    for a, b in zip(results, paced, strict=True):
        for m, me in b.estimate.markers.items():
            if m in a.estimate.markers:
                d = np.linalg.norm(a.estimate.markers[m].position - me.position)
                assert d < 1e-3, (a.index, m, d)


def test_a_refit_keeps_the_intrinsics_model_unless_the_references_changed_much(pi_frames,
                                                                               monkeypatch):

    from kmea.estimators.corner_pnp import CornerPnP
    from kmea.estimators.corner_pnp import estimator as estimator_mod

    frames, src = pi_frames
    p = Pipeline(src.camera, src.world_map, PipelineSettings(robots=(), fixed_camera=False))
    r = p.process(FrameInput(0, 0.0, frames[0].image))
    p.close()
    floor = [o for o in r.observations if o.id in src.world_map]
    assert len(floor) >= 20
    est = CornerPnP()
    est.warm_start = True
    tested = []
    orig = estimator_mod.select_model
    monkeypatch.setattr(estimator_mod, "select_model",
                        lambda *a, **k: (tested.append(1), orig(*a, **k))[1])
    intr = src.camera.intrinsics

    def nudged(obs):  # one more averaged look: every reference's corners move a little
        return [replace(o, corners=np.asarray(o.corners) + 0.02) for o in obs]

    assert est.estimate(floor, src.world_map, camera=intr).ok and tested  # cold: tested
    tested.clear()
    assert est.estimate(nudged(floor[1:]), src.world_map, camera=intr).ok
    assert not tested  # one reference fewer, corners moved: the model choice stands
    keep = floor[: len(floor) // 2]
    assert est.estimate(nudged(keep), src.world_map, camera=intr).ok
    assert tested  # half the references gone: tested again


def test_kmea_warm_start_gives_the_cold_estimate(default_frames, monkeypatch):
    """KMEA on a fixed camera: while the references are the very observations of the last
    frame their alignment is reused (fewer alignments than frames), with the estimate of a
    cold KMEA, bit for bit."""
    from kmea.estimators import kmea as kmea_mod

    frames, src = default_frames
    p = tracked_pipeline(src, "kmea")
    assert p.estimator.warm_start
    aligned = []
    orig = kmea_mod.kmea_align
    monkeypatch.setattr(kmea_mod, "kmea_align", lambda *a: (aligned.append(1), orig(*a))[1])
    cold = kmea_mod.KMEA(unknown_plane=p.settings.unknown_plane)
    n = 0
    for f in frames[:12]:
        before = len(aligned)
        r = p.process(FrameInput(f.index, f.timestamp, f.image))
        n += len(aligned) > before
        s = cold.estimate(r.observations, src.world_map, camera=p.camera.intrinsics,
                          plane_heights=p.plane_heights)
        assert r.estimate.ok and s.ok and r.estimate.references == s.references
        assert np.array_equal(r.estimate.cam2world, s.cam2world)
        for mid, me in s.markers.items():
            assert np.array_equal(r.estimate.markers[mid].position, me.position), (f.index, mid)
    p.close()
    assert n < 12  # some frames reused the alignment


def test_robots_are_placed_from_their_corners_before_any_pose(default_frames, monkeypatch):
    """With the floor of the last camera fit, corner-pnp places the robots from their corners
    and the relay runs before the frame's markers are posed; the fixes equal those of the
    full path (placements from the same fit) to 1e-9."""
    from kmea.estimators.corner_pnp import CornerPnP

    frames, src = default_frames

    def run(early: bool):
        p = tracked_pipeline(src, "corner-pnp")
        if not early:
            monkeypatch.setattr(p.estimator, "place_on_planes", lambda *a, **k: None)
        out, before_pose = [], 0
        for f in frames[:16]:
            posed = p.session.poses.posed
            got = []

            def relay(t, fixes, got=got, posed=posed):
                got.append(({n: (x.x, x.y, x.theta, x.sigma) for n, x in fixes.items()},
                            p.session.poses.posed == posed))

            p.process(FrameInput(f.index, f.timestamp, f.image), on_robots=relay)
            assert len(got) == 1
            out.append(got[0][0])
            before_pose += got[0][1]
        p.close()
        return out, before_pose

    fast, n_fast = run(True)
    slow, n_slow = run(False)
    assert n_fast >= 10 and n_slow == 0, (n_fast, n_slow)
    assert isinstance(CornerPnP().place_on_planes([40], np.zeros((1, 4, 2)), [0.06],
                                                  src.world_map, {40: 0.1}), type(None))
    for a, b in zip(fast, slow, strict=True):
        assert a.keys() == b.keys()
        for name in a:
            np.testing.assert_allclose(a[name], b[name], rtol=0, atol=1e-9)


def test_the_robots_placed_early_are_not_placed_again(default_frames, monkeypatch):
    """The frame's estimate takes the placements made from the robots' corners before the
    relay (same fit, same corners): one placement of the robots per frame, not two."""
    from kmea.estimators.corner_pnp import estimator as estimator_mod

    frames, src = default_frames
    p = tracked_pipeline(src, "corner-pnp")
    calls: list[set] = []
    orig = estimator_mod.place_markers

    def spy(s, planes, fit, obs, *a, only=None, **k):
        calls.append(set(obs if only is None else only))
        return orig(s, planes, fit, obs, *a, only=only, **k)

    monkeypatch.setattr(estimator_mod, "place_markers", spy)
    once = 0
    for f in frames[:16]:
        calls.clear()
        p.process(FrameInput(f.index, f.timestamp, f.image), on_robots=lambda t, fixes: None)
        robots = [c for c in calls if c & {40, 41, 42}]
        once += len(robots) == 1
    p.close()
    assert once >= 10, once


def test_robot_observations_come_from_their_placements_not_a_pose(default_frames, monkeypatch):
    """With the floor of the last camera fit, the robots' markers are not posed (no IPPE):
    their observations are their placements seen from the fit's camera, within a few mm and
    degrees of IPPE's pose of the same corners (whose depth scatters by ~1 % at 30 px), with a
    sub-pixel reprojection error; and the
    frame's result is the same with and without a relay."""
    frames, src = default_frames
    robot_ids = {m for r in src.scene.robot_specs() for m in r.markers}

    def run(relay: bool):
        p = tracked_pipeline(src, "corner-pnp")
        posed_robots, placed, results = 0, [], []
        orig = p.observer.poses

        def spy(ids, corners, *a, **k):
            nonlocal posed_robots
            posed_robots += len(robot_ids & set(np.asarray(ids).tolist()))
            return orig(ids, corners, *a, **k)

        monkeypatch.setattr(p.observer, "poses", spy)
        for f in frames[:16]:
            before = posed_robots
            res = p.process(FrameInput(f.index, f.timestamp, f.image),
                            on_robots=(lambda t, fixes: None) if relay else None)
            results.append(res)
            if f.index >= 4 and posed_robots == before:
                placed += [o for o in res.observations if o.id in robot_ids]
        ref = {}
        for o in placed:  # IPPE of the very corners, for comparison
            got, _ = orig(np.array([o.id]), o.corners[None])
            ref[id(o)] = got[0]
        p.close()
        return placed, ref, results

    placed, ref, with_relay = run(True)
    assert len(placed) >= 20, len(placed)
    for o in placed:
        r = ref[id(o)]
        assert np.linalg.norm(o.marker2cam_t - r.marker2cam_t) < 0.02 * np.linalg.norm(
            r.marker2cam_t)
        cos = (np.trace(o.marker2cam_R.T @ r.marker2cam_R) - 1.0) / 2.0
        assert math.degrees(math.acos(min(1.0, cos))) < 5.0
        assert 0.0 <= o.reproj_error < 0.5 and not o.ambiguous and o.alt_R is None
    _, _, without = run(False)
    for a, b in zip(with_relay, without, strict=True):
        assert a.robots.keys() == b.robots.keys()
        for name in a.robots:
            assert (a.robots[name].x, a.robots[name].y) == (b.robots[name].x, b.robots[name].y)
