"""IND, CORR and COND on URDF/DH arms as marker densities (bayesrob.errors.marker_density), and the
commands that use them: `compare` and `sample` on a simulated 6-joint arm."""

from __future__ import annotations

import json

import numpy as np
import pytest
import scipy.stats

from bayesrob.cli import main
from bayesrob.errors.kde import ConditionalKDE
from bayesrob.errors.marker_density import MarkerDensity, MarkerModel, loo_marker_scores
from bayesrob.sim.rigs import simulate_arm6_rig
from bayesrob.sim.truth import Arm6Truth


def _two_components() -> MarkerDensity:
    chol = np.linalg.cholesky(np.array([[[[2.0, 0.3, 0.0], [0.3, 1.0, 0.2], [0.0, 0.2, 0.5]],
                                          [[0.5, 0.0, 0.0], [0.0, 0.8, -0.1],
                                           [0.0, -0.1, 1.5]]]]))
    means = np.array([[[0.0, 0.0, 0.0], [1.5, -1.0, 0.5]]])
    return MarkerDensity(np.array([[10.0, 20.0, 30.0]]), np.log([[0.3, 0.7]]), means, chol)


def test_a_marker_density_is_its_gaussian_mixture():
    dens = _two_components()
    pts = np.random.default_rng(0).normal([10.0, 20.0, 30.0], 1.5, (50, 3))
    want = np.log(sum(w * scipy.stats.multivariate_normal(dens.centre[0] + m, c @ c.T).pdf(pts)
                      for w, m, c in zip((0.3, 0.7), dens.means[0], dens.chol[0], strict=True)))
    got = dens.logpdf(pts[:, None, :])[:, 0]
    np.testing.assert_allclose(got, want, rtol=1e-10)
    # 20000 draws: the mean's Monte Carlo sd is below 0.011 mm per axis, 0.05 is 4.5 sd
    draws = dens.sample(3, 20000)[:, 0]
    mean = dens.centre[0] + 0.3 * dens.means[0, 0] + 0.7 * dens.means[0, 1]
    np.testing.assert_allclose(draws.mean(0), mean, atol=0.05)
    # a point at the centre of the heavier component is inside the 50% region; one far out
    # is outside the 99% region
    levels = dens.hdr_level(np.array([dens.centre[0] + dens.means[0, 1]]))
    assert levels[0] < 0.5
    assert dens.hdr_level(np.array([dens.centre[0] + 8.0]))[0] > 0.99


def test_draws_pick_each_rows_components_by_that_rows_weights():
    # components 100 mm apart with 1 um kernels, so each draw names the component it came from;
    # rows with different weights, a zero weight and a shared kernel (T | 1 broadcasting)
    w = np.array([[0.1, 0.2, 0.3, 0.4], [0.97, 0.01, 0.01, 0.01], [0.0, 0.0, 0.5, 0.5]])
    means = np.zeros((3, 4, 1))
    means[..., 0] = 100.0 * np.arange(4)
    with np.errstate(divide="ignore"):
        dens = MarkerDensity(np.zeros((3, 1)), np.log(w), means, np.full((1, 1, 1, 1), 1e-3))
    which = np.rint(dens.sample(5, 40000)[..., 0] / 100.0).astype(int)  # (n, T)
    freq = np.stack([np.bincount(which[:, t], minlength=4) / 40000 for t in range(3)])
    # 40000 draws: a frequency's sd is at most 0.0025, 0.0125 is 5 sd
    np.testing.assert_allclose(freq, w, atol=0.0125)
    assert np.all(freq[2, :2] == 0.0)


def test_cond_leave_one_out_is_the_density_fitted_without_the_row():
    rng = np.random.default_rng(1)
    u = rng.uniform(-1, 1, (25, 4))
    r = rng.normal(0, 0.3, (25, 3)) + 0.5 * u[:, :1]
    bw = [0.2, 0.25, 0.3, 0.5, 0.6, 0.7, 0.8]
    cond = ConditionalKDE.fit(r, u, "kernel", bw)
    model = MarkerModel("arm", "cond", None, r, u, conditional=cond)
    loo, in_sample = loo_marker_scores(None, model)
    for i in (0, 7, 24):
        keep = np.arange(25) != i
        without = ConditionalKDE.fit(r[keep], u[keep], "kernel", bw)
        assert loo[i] == pytest.approx(float(without.logpdf(r[i], u[i])), rel=1e-9)
    np.testing.assert_allclose(in_sample, np.asarray(cond.logpdf(r, u)), rtol=1e-9)


@pytest.fixture(scope="module")
def small_arm6(tmp_path_factory):
    # joints five times the default repeatability, so the joints, not the instrument, carry
    # the error the models must find
    d = tmp_path_factory.mktemp("arm6")
    return simulate_arm6_rig(d, Arm6Truth(seed=11, joint_noise_rad=5e-4, n_holdout=20))


def test_compare_scores_every_model_on_a_6_joint_arm(small_arm6, tmp_path):
    out = tmp_path / "cmp.json"
    # corr is ind's code with a full covariance, and its fit is the slow one: left out here
    assert main(["compare", str(small_arm6), "--models", "ind", "cond", "--json",
                 str(out)]) == 0
    doc = json.loads(out.read_text())
    assert list(doc["models"]) == ["ind", "cond"]
    assert {m["marker_model"] for m in doc["models"].values()} == {"ind", "cond"}
    assert doc["heldout_rows"] == {"arm": 40} and doc["holdout_rows"] == {"arm": 20}
    assert "per mm^3" in doc["score"] and (tmp_path / "cmp.png").is_file()
    for name, m in doc["models"].items():
        assert m["loo_train"]["n"] == 80
        assert np.isfinite(m["heldout"]["elpd"]) and np.isfinite(m["loo_train"]["elpd"])
        # 40 validation rows: a calibrated model's 90% coverage has sd 0.047; 0.7 is 4 sd
        # below, so only a badly miscalibrated model fails
        assert m["heldout"]["by_setup"]["arm"]["coverage90"] >= 0.7, name
    # the latent joint errors are how this arm's error arises: they beat the residual
    # kernel conditional on its new poses (by 10 elpd on the tuning seed 3, dse 5)
    held = {r["model"]: r for r in doc["heldout_compare"]}
    assert held["ind"]["elpd"] > held["cond"]["elpd"]


def test_compare_refuses_the_papers_estimators_on_a_chain(small_arm6, capsys):
    assert main(["compare", str(small_arm6), "--models", "ind_paper"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "ind_paper" in err[0] and "planar" in err[0]


def test_sample_checks_nuts_and_emcee_on_the_grid_in_3d(small_arm6, tmp_path):
    out = tmp_path / "s.json"
    rc = main(["sample", str(small_arm6), "--config", "arm", "--target", "850", "-400", "700",
               "--model", "cond", "--json", str(out)])
    doc = json.loads(out.read_text())
    assert rc == 0, doc["check"]["failures"]
    assert set(doc["samplers"]) == {"grid", "nuts", "emcee"}
    for s in doc["samplers"].values():
        assert len(s["mean"]) == 3
        # the arm is aimed at the target: the point lands there to a tenth of a millimetre
        assert np.linalg.norm(np.subtract(s["mean"], [850, -400, 700])) < 0.5


def test_sample_needs_three_coordinates_on_a_3d_rig(small_arm6, capsys):
    assert main(["sample", str(small_arm6), "--config", "arm", "--target", "850", "-400"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--target needs 3 numbers" in err[0]


def test_a_planar_rig_given_params_is_compared_and_sampled_as_2_joint_chains(tmp_path):
    from bayesrob.compare.comparison import compare_models
    from bayesrob.data.rig import default_rig_dir, load_rig
    from bayesrob.inference.sampling import sample_linked

    rig = load_rig(default_rig_dir())
    groups = ("frames", "offsets", "geometric", "servo")
    doc = compare_models(rig, ["cond"], groups=groups).to_dict()
    assert doc["heldout_rows"] == {"top": 16, "bottom": 16}
    assert doc["models"]["cond"]["marker_model"] == "cond" and "per mm^2" in doc["score"]
    report = sample_linked(rig, "top+bottom", [140.0, 220.0], model="cond", groups=groups)
    assert report.passed, report.document["check"]["failures"]
    assert len(report.document["samplers"]["nuts"]["mean"]) == 2
