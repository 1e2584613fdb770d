"""``kmea experiment``: every Part runs end to end on rendered frames (real detection, real
per-marker PnP, the registered estimators), writes its table, CSVs and figures, and its
numbers are the core's metrics of the samples it returns."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest

from kmea.cli import main
from kmea.cli.experiment import write_outputs
from kmea.experiments import tables
from kmea.experiments.parts import PARTS, get_part
from kmea.experiments.plots import confidence_ellipse, have_matplotlib
from kmea.experiments.run import ExperimentConfig, estimate_frame, run_simulation
from kmea.stats.metrics import marker_metrics, mean_metrics, percent_change

SMALL = dict(width=640, height=480)


def _config(part: str, algorithms=("kmea", "lmea"), samples=4, **kw) -> ExperimentConfig:
    return ExperimentConfig(part=get_part(part), algorithms=algorithms, samples=samples,
                            seed=3, chunk=2, **{**SMALL, **kw})


def _read_csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


# Part IV's far markers are ~12 px wide at 640x480, below what ArUco detects: larger frames.
@pytest.mark.parametrize(("part", "size"), [("I", "640x480"), ("II", "640x480"),
                                            ("III", "640x480"), ("IV", "1280x960")])
def test_each_part_runs_from_the_cli_and_writes_its_outputs(part, size, tmp_path, capsys):
    rc = main(["experiment", part, "--samples", "3", "--size", size, "--seed", "1",
               "--algorithms", "kmea,lmea", "--out", str(tmp_path), "--quiet"])
    assert rc == 0
    out = capsys.readouterr().out
    assert f"Part {part}:" in out and "| kmea |" in out and "| lmea |" in out
    md = (tmp_path / f"part-{part}.md").read_text()
    assert "Per marker:" in md and "ΔMAE" in md
    rows = _read_csv(tmp_path / f"part-{part}-markers.csv")
    spec = get_part(part)
    assert {(r["algorithm"], int(r["marker"])) for r in rows} == {
        (a, m) for a in ("kmea", "lmea") for m in spec.evaluated}
    # Every evaluated marker is in view in every Part: a sample in every frame.
    assert all(int(r["n"]) == 3 for r in rows), [(r["marker"], r["n"]) for r in rows]
    samples = _read_csv(tmp_path / f"part-{part}-samples.csv")
    assert len(samples) == 3 * len(rows)
    if have_matplotlib():
        pngs = sorted(p.name for p in tmp_path.glob(f"part-{part}-*.png"))
        for metric in ("rmse", "std", "mae", "maxae", "mre"):
            assert f"part-{part}-bars-{metric}.png" in pngs
        assert f"part-{part}-scatter.png" in pngs
        assert any(n.startswith(f"part-{part}-zoom-") for n in pngs)
        assert all((tmp_path / n).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for n in pngs)


def test_csv_and_table_are_the_core_metrics_of_the_returned_samples(tmp_path):
    result = run_simulation(_config("III", samples=4))
    paths = write_outputs(result, tmp_path, plots=False)
    rows = _read_csv(paths["csv"])
    assert len(rows) == len(result.algorithms) * len(result.markers)
    for r in rows:
        a, m = r["algorithm"], int(r["marker"])
        s = result.samples[(a, m)]
        assert s.shape == (4, 2)
        want = marker_metrics(s, result.truth[m], result.reference_length)
        for col, f in (("rmse_m", "rmse"), ("std_m", "std"), ("mae_m", "mae"),
                       ("maxae_m", "maxae"), ("mre_pct", "mre")):
            assert float(r[col]) == getattr(want, f)
        assert float(r["truth_x_m"]) == result.truth[m][0]
    # The raw samples file holds exactly the returned samples.
    got = _read_csv(paths["samples"])
    for a in result.algorithms:
        for m in result.markers:
            xy = np.array([[float(g["x_m"]), float(g["y_m"])] for g in got
                           if g["algorithm"] == a and int(g["marker"]) == m])
            np.testing.assert_array_equal(xy, result.samples[(a, m)])
    # The table's averages and % change are mean_metrics / percent_change of those.
    sc = tables.score(result)
    for a in result.algorithms:
        avg = mean_metrics(sc.per_marker[(a, m)] for m in result.markers)
        assert sc.average[a] == avg
        assert sc.change[a]["mae"] == percent_change(avg.mae, sc.average["lmea"].mae)
    h, table = tables.summary_rows(result, sc)
    kmea_row = next(t for t in table if t[0] == "kmea")
    assert kmea_row[h.index("MAE (mm)")] == f"{sc.average['kmea'].mae * 1e3:.2f}"
    changes = [percent_change(getattr(sc.average["kmea"], f), getattr(sc.average["lmea"], f))
               for f in ("rmse", "std", "mae", "maxae", "mre")]
    assert kmea_row[h.index("mean Δ")] == f"{np.mean(changes):+.1f} %"


def test_part_three_shows_the_papers_conclusion_and_flags_the_displaced_anchors(tmp_path):
    # Anchors 4, 13, 16 are displaced by a few cm: LMEA, built on them, fails by centimetres;
    # KMEA, using every reference, stays far below it; the robust estimators reject them.
    result = run_simulation(_config("III", algorithms=("kmea", "lmea", "kmea-robust"),
                                    samples=3))
    sc = tables.score(result)
    assert sc.average["lmea"].mae > 0.02
    assert sc.change["kmea"]["mae"] < -70.0
    rej = dict((i, d) for i, d, _ in tables.rejected_summary(result)["kmea-robust"])
    for anchor in (4, 13, 16):
        assert anchor in rej and 0.02 < rej[anchor] < 0.06
    rows = _read_csv(write_outputs(result, tmp_path, plots=False)["csv"])
    flagged = next(r for r in rows if r["algorithm"] == "kmea-robust")["rejected_refs"]
    assert {int(t.split(":")[0]) for t in flagged.split(";")} >= {4, 13, 16}


def test_part_two_markers_are_really_raised_and_scored_on_their_floor_position():
    result = run_simulation(_config("II", samples=2))
    spec = get_part("II")
    from kmea.maps.files import default_map

    m = default_map()
    for mid in spec.evaluated:
        np.testing.assert_allclose(result.truth[mid], m[mid].position[:2])
        # Not references, not in the estimators' map: KMEA places each marker from its own
        # PnP pose and sees it 20 cm up.
        z = result.heights[("kmea", mid)]
        assert abs(z.mean() - 0.20) < 0.03 and np.all(z != 0.20)
    known = run_simulation(_config("II", samples=2, known_heights=True))
    for mid in spec.evaluated:
        # Told the height, KMEA slides the marker along its ray onto that plane.
        np.testing.assert_allclose(known.heights[("kmea", mid)], 0.20, atol=1e-9)


def test_miscalibration_is_given_to_the_estimators_only():
    # The image does not change with the believed calibration; the estimates do.
    base = run_simulation(_config("I", algorithms=("kmea",), samples=2))
    off = run_simulation(_config("I", algorithms=("kmea",), samples=2, focal_error=0.02,
                                 k1_error=0.02))
    diffs = [np.abs(base.samples[("kmea", m)] - off.samples[("kmea", m)]).max()
             for m in base.markers]
    assert max(diffs) > 1e-5
    assert off.settings["focal_error"] == 0.02


def test_floor_only_keeps_wall_markers_out_of_the_references():
    from kmea.experiments import simscene
    from kmea.maps.files import default_map

    cfg = _config("IV", floor_only=True)
    emap = simscene.estimator_map(cfg, default_map())
    assert set(emap.ids) == {i for i, m in default_map().markers.items() if m.on_floor}
    assert len(emap) < len(default_map())


def test_jobs_do_not_change_the_results():
    one = run_simulation(_config("I", algorithms=("kmea",), samples=4))
    two = run_simulation(_config("I", algorithms=("kmea",), samples=4, jobs=2))
    for key, s in one.samples.items():
        np.testing.assert_array_equal(s, two.samples[key])


def test_replay_scores_a_recording_against_the_map(tmp_path, capsys):
    from kmea.experiments import simscene
    from kmea.experiments.run import _setup
    from kmea.recordings.format import Recorder

    cfg = _config("I", samples=3)
    st = _setup(cfg)
    rec_path = tmp_path / "run.jsonl"
    rec = Recorder(rec_path, st["believed"], st["estimator_map"], "sim:test", {})
    frames_obs = []
    for i in range(3):
        obs = simscene.observe(st, i)
        frames_obs.append(obs)
        ids = np.array([o.id for o in obs])
        corners = np.array([o.corners for o in obs])
        rec.write_frame(i, i / 30.0, ids, corners, obs, {})
    rec.close()

    out = tmp_path / "out"
    rc = main(["experiment", "--replay", str(rec_path), "--algorithms", "kmea,lmea",
               "--out", str(out), "--no-plots", "--quiet"])
    assert rc == 0
    assert "Replay of run.jsonl" in capsys.readouterr().out
    rows = _read_csv(out / "part-replay-markers.csv")
    ids = {int(r["marker"]) for r in rows}
    # Every detected map marker but LMEA's anchors is evaluated.
    detected = {o.id for obs in frames_obs for o in obs}
    assert ids == {i for i in detected if i in st["estimator_map"]} - {4, 13, 16}
    # The replayed estimates are those of the in-memory observations (floats round-trip).
    ests = {a: st["estimators"][a] for a in ("kmea", "lmea")}
    emap = st["estimator_map"]
    planes = {i: float(emap[i].position[2]) for i in ids if emap[i].rotation[2, 2] > 1 - 1e-9}
    direct = [estimate_frame(k, obs, ests, emap, sorted(ids),
                             camera=st["believed"].intrinsics, planes=planes)
              for k, obs in enumerate(frames_obs)]
    for r in rows:
        a, m = r["algorithm"], int(r["marker"])
        xy = np.array([f.positions[(a, m)][:2] for f in direct if (a, m) in f.positions])
        want = marker_metrics(xy, st["estimator_map"][m].position[:2], 2.081)
        assert float(r["mae_m"]) == want.mae and int(r["n"]) == len(xy)


def test_bad_inputs_give_one_clear_line(tmp_path, capsys):
    with pytest.raises(SystemExit, match="unknown Part 'V'"):
        main(["experiment", "V", "--out", str(tmp_path)])
    with pytest.raises(SystemExit, match="unknown 'nope'"):
        main(["experiment", "I", "--algorithms", "kmea,nope", "--out", str(tmp_path)])
    bogus = tmp_path / "not-a-recording.jsonl"
    bogus.write_text('{"hello": 1}\n')
    assert main(["experiment", "--replay", str(bogus), "--out", str(tmp_path)]) == 2
    assert "not a kmead recording" in capsys.readouterr().err


def test_confidence_ellipse_is_the_three_sigma_mahalanobis_contour():
    rng = np.random.default_rng(0)
    C = np.array([[4.0, 1.5], [1.5, 1.0]])
    pts = rng.multivariate_normal([1.0, -2.0], C, size=200)
    ell = confidence_ellipse(pts, 3.0)
    d = ell - pts.mean(axis=0)
    maha = np.einsum("ij,jk,ik->i", d, np.linalg.inv(np.cov(pts.T)), d)
    np.testing.assert_allclose(maha, 9.0, rtol=1e-9)
    assert confidence_ellipse(pts[:2]) is None


def test_displacement_scale_and_part_aliases():
    p = get_part("3").scaled(2.0)
    assert p.name == "III"
    assert math.isclose(p.displaced[13].dx, 2 * PARTS["III"].displaced[13].dx)
    assert get_part("iv") is PARTS["IV"]
