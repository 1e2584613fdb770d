"""``kmea experiment``'s two evaluation modes, the IIR option and the paper's tables beside
the project's (rendered frames, real detection)."""

from __future__ import annotations

import numpy as np
import pytest

from kmea.cli import main
from kmea.experiments.paper import paper_table
from kmea.experiments.parts import get_part
from kmea.experiments.run import ExperimentConfig, estimate_frame, iir_filter, run_modes
from kmea.stats.metrics import marker_metrics


def _config(part, algorithms=("kmea", "corner-pnp"), samples=2, **kw):
    return ExperimentConfig(part=get_part(part), algorithms=algorithms, samples=samples,
                            seed=5, chunk=2, width=820, height=616, **kw)


def test_modes_give_the_same_information_to_every_estimator():
    from kmea.estimators import get
    from kmea.experiments.run import _setup, _without
    from kmea.experiments.simscene import observe

    cfg = _config("I")
    st = _setup(cfg)
    obs = observe(st, 0)
    emap = st["estimator_map"]
    m = 22
    kmea = get("kmea")
    # plane-known: KMEA with the marker excluded, then slid along its ray onto its plane.
    fr = estimate_frame(0, obs, {"kmea": kmea}, emap, [m], planes={m: 0.0})
    ref = kmea.estimate(obs, emap, exclude={m}, plane_heights={m: 0.0})
    assert np.allclose(fr.positions[("kmea", m)], ref.markers[m].position)
    assert fr.positions[("kmea", m)][2] == pytest.approx(0.0, abs=1e-12)
    # off-map: the map without the marker, no plane.
    off = estimate_frame(0, obs, {"kmea": kmea}, emap, [m], mode="off-map")
    ref = kmea.estimate(obs, _without(emap, m))
    assert np.allclose(off.positions[("kmea", m)], ref.markers[m].position)
    assert abs(off.positions[("kmea", m)][2]) > 1e-6
    with pytest.raises(ValueError, match="mode"):
        estimate_frame(0, obs, {"kmea": kmea}, emap, [m], mode="both")


def test_both_modes_come_from_the_same_frames_and_plane_knowledge_helps_kmea():
    res = run_modes(_config("I", samples=2))
    known, off = res["plane-known"], res["off-map"]
    assert known.mode == "plane-known" and off.mode == "off-map"
    assert known.frames == off.frames == 2

    def mae(r, a):
        return np.mean([marker_metrics(r.samples[(a, m)], r.truth[m], 2.0).mae
                        for m in r.markers if len(r.samples[(a, m)])])

    assert mae(known, "kmea") < mae(off, "kmea")
    # corner-pnp puts an off-map floor marker back on the floor by itself.
    assert mae(off, "corner-pnp") < 2 * mae(known, "corner-pnp") + 2e-5


def test_iir_filter_is_the_daemons_filter():
    x = np.array([[0.0, 0, 0], [1.0, 0, 0], [1.0, 0, 0]])
    y = iir_filter(x, 0.5)
    assert np.allclose(y[:, 0], [0.0, 0.5, 0.75])
    assert iir_filter(x, 1.0) is x
    with pytest.raises(ValueError, match="alpha"):
        run_modes(_config("I", iir_alpha=0.0))


def test_cli_writes_both_modes_and_the_papers_table(tmp_path, capsys):
    out = tmp_path / "exp"
    rc = main(["experiment", "III", "-n", "1", "--size", "820x616", "-a", "kmea,lmea,lmea-printed",
               "--iir", "0.5", "--out", str(out), "--no-plots", "--quiet"])
    assert rc == 0
    md = (out / "part-III.md").read_text()
    assert "Mode **plane-known**" in md and "Mode **off-map**" in md
    assert "the paper's table beside the project's" in md
    kmea, lmea, _, _ = paper_table("III")["MAE"]
    assert f"{kmea * 1e3:.2f}" in md and f"{lmea * 1e3:.2f}" in md
    assert "LMEA as printed (off-map)" in md and "iir_alpha 0.5" in md
    assert (out / "part-III-off-map-markers.csv").is_file()
    assert (out / "part-III-markers.csv").is_file()


def test_bad_mode_is_one_clear_line(tmp_path, capsys):
    with pytest.raises(SystemExit, match="--modes"):
        main(["experiment", "I", "--modes", "sideways", "--out", str(tmp_path)])
