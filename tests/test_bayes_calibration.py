"""Bayesian calibration: the posterior covers the truth, the sampler is calibrated (SBC), and
``bayesrob calibrate --method bayes`` writes the common report keys plus the posterior's.

Everything is seeded, so each test is deterministic; the tolerances are stated as the
probability that a correct implementation would fail them if the seed were drawn at random.
"""

import json
import subprocess
import sys

import numpy as np
import pytest
from bayesrob.validation.calibration_sbc import narrowed_ranks

from bayesrob.calibrate import bayes as bc
from bayesrob.data.rig import load_rig
from bayesrob.report.outputs import CALIBRATION_METHODS, calibrate_rig, calibration_report
from bayesrob.sim.truth import Truth

ARMS = ("top", "bottom")


@pytest.fixture(scope="module")
def clean(clean_rig_dir):
    """The session's clean rig (grid 4, no effects), its truth and its Bayesian calibration."""
    rig = load_rig(clean_rig_dir)
    truth = Truth.from_toml(clean_rig_dir / "truth.toml")
    return rig, truth, bc.calibrate_arms_bayes(rig)


def test_posterior_contains_true_parameters_on_clean_rig(clean):
    rig, truth, cal = clean
    for name in ARMS:
        post = cal[name].posterior
        true = np.asarray(truth.arms[name].params.to_vector())
        z = (post.mean - true) / post.sd
        # A calibrated posterior puts each true value within 3 sd with probability 0.997;
        # all 16 at once with probability 0.96. (Seed 0 gives max |z| = 1.4.) The clean rig's
        # joint noise makes the errors slightly heteroscedastic, which the iid Gaussian
        # likelihood ignores; 3 sd leaves room for that.
        assert np.all(np.abs(z) < 3.0), (name, z)
        # and the data, more than the prior, decide: the posterior is at least twice as narrow
        # as the prior for every parameter (seed 0: 0.12..0.40 of the prior sd; the base and
        # the offsets are the least determined by a 180 mm square of 16 points).
        assert np.all(post.sd < post.scale / 2), (name, post.sd / post.scale)


def test_sampler_diagnostics_on_clean_rig(clean):
    _, _, cal = clean
    for name in ARMS:
        diag = cal[name].extra["posterior"]
        # 2 chains x 500 draws of a well-conditioned 9-dimensional posterior: split R-hat at
        # or below 1.01 (arviz rounds to 2 decimals), no divergent transitions, and a bulk
        # ESS of at least 300 (so Monte Carlo error of a posterior mean < 0.06 sd).
        assert diag["r_hat_max"] <= 1.01, diag
        assert diag["divergences"] == 0, diag
        assert diag["ess_bulk_min"] >= 300, diag
        assert diag["draws"] == 1000 and diag["chains"] == 2


def test_noise_and_validation_errors_match_the_simulator(clean):
    rig, truth, cal = clean
    ls = calibration_report(rig)["arms"]
    for name in ARMS:
        c = cal[name]
        noise = c.extra["posterior"]["noise_sd_mm"]
        # the simulator's scatter per axis is sqrt(0.35^2 + (0.0008 rad * ~300 mm)^2) ~ 0.42
        # mm; the posterior of a 32-number sample has sd ~0.07, so 0.25..0.65 is > 2.5 sd.
        assert 0.25 < noise["mean"] < 0.65, noise
        # with 16 rows the prior hardly matters: the posterior-mean prediction is as good as
        # least squares (within 0.05 mm of its mean validation error of ~0.55 mm)
        assert abs(c.validation_error_mm - ls[name]["validation_error_mm"]) < 0.05
        assert abs(c.train_error_mm - ls[name]["train_error_mm"]) < 0.05


def test_validation_end_points_are_covered_by_the_posterior_predictive(clean):
    _, _, cal = clean
    cov = [cal[n].extra["posterior"]["validation_coverage"] for n in ARMS]
    n = 32  # 16 validation rows per arm
    p90 = sum(c["p90"] for c in cov) / 2 * n
    p50 = sum(c["p50"] for c in cov) / 2 * n
    # If the predictive regions are right the counts are Binomial(32, q): 90 % regions hold
    # >= 24 of 32 points with probability 0.998; 50 % regions hold 8..24 (+-2.8 sd).
    assert p90 >= 24, cov
    assert 8 <= p50 <= 24, cov


def test_predicted_accuracy_propagates_parameter_uncertainty(clean):
    rig, _, cal = clean
    doc = bc.predicted_accuracy_document(rig, cal)
    assert set(doc) == {"top", "bottom", "top+bottom"}
    for config, entry in doc.items():
        pred, obs = entry["predicted"], entry["observed"]
        # parameter uncertainty can only add error to what the noise alone gives
        assert pred["expected_error_mm"] > pred["noise_only_error_mm"], (config, pred)
        lo, hi = pred["interval95_mm"]
        # on a clean rig the model is nearly right, so the observed mean error falls inside
        # the predicted 95 % interval (each with probability 0.95; all 3 with ~0.86 -- seed 0
        # passes, and a miss by more than 30 % of the interval's width would be a real error)
        assert lo <= obs["mean_mm"] <= hi, (config, pred, obs)


def test_linked_prediction_is_the_product_of_the_arms_gaussians(clean):
    rig, _, cal = clean
    post = {n: cal[n].posterior for n in ARMS}
    rows = rig.config_rows("top+bottom", "test")
    linked = bc.predict_end_points(post, rows["commands"], noise=True, seed=1)
    mean = bc.predict_end_points(post, rows["commands"], noise=False)
    assert linked.shape == mean.shape == (1000, len(rows["target"]), 2)
    singles = [bc.predict_end_points({n: post[n]}, {n: rows["commands"][n]}, seed=1)
               for n in ARMS]
    # the product of two Gaussians is narrower than either: the scatter of linked draws
    # about their mean is below each arm's alone (by a factor ~1/sqrt(2) for equal noise)
    spread = np.std(linked - mean)
    for s in singles:
        assert spread < 0.9 * np.std(s - s.mean(axis=0)), (spread, np.std(s - s.mean(axis=0)))
    # and the linked mean lies between the two arms' predictions, row by row
    f = [post[n].forward_draws(rows["commands"][n]).mean(axis=0) for n in ARMS]
    m = mean.mean(axis=0)
    t = np.sum((m - f[0]) * (f[1] - f[0]), -1) / np.sum((f[1] - f[0]) ** 2, -1)
    assert np.all((t > -1e-9) & (t < 1 + 1e-9)), t


def test_calibrate_rig_dispatches_to_bayes(clean):
    rig, _, cal = clean
    assert "bayes" in CALIBRATION_METHODS
    c = calibrate_rig(rig, "bayes")["bottom"]
    assert c.method == "bayes"
    # same default seed, same compiled sampler: the very same draws
    np.testing.assert_array_equal(c.posterior.draws, cal["bottom"].posterior.draws)
    np.testing.assert_allclose(c.params_se, cal["bottom"].posterior.sd)


def test_calibrate_command_bayes_json(clean, tmp_path):
    rig, _, _ = clean
    out = tmp_path / "bayes.json"
    r = subprocess.run([sys.executable, "-m", "bayesrob", "calibrate", str(rig.path),
                        "--method", "bayes", "--json", str(out)],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    assert "calibration: bayes" in r.stdout
    doc = json.loads(out.read_text())
    ls = calibration_report(rig)
    # the common schema is kept: the same top-level and per-arm keys as least squares ...
    assert set(ls) <= set(doc) and doc["method"] == "bayes"
    assert set(doc) - set(ls) == {"predicted_accuracy"}
    for name in ARMS:
        arm = doc["arms"][name]
        assert set(arm) - set(ls["arms"][name]) == {"posterior"}
        assert set(arm["params"]) == set(arm["params_se"]) == {"base", "links", "gain", "offset"}
        # ... plus the posterior block
        p = arm["posterior"]
        assert {"r_hat_max", "ess_bulk_min", "noise_sd_mm", "draws", "divergences",
                "validation_coverage", "priors", "seconds"} <= set(p)
        assert set(p["noise_sd_mm"]) == {"mean", "sd"} and p["draws"] == 1000
        assert p["r_hat_max"] <= 1.01
    assert set(doc["predicted_accuracy"]["top+bottom"]["predicted"]) == {
        "expected_error_mm", "interval95_mm", "noise_only_error_mm"}


# ----------------------------------------------------------------------------- SBC
# Simulation-based calibration (Talts et al. 2018). The data sets are drawn from the model's
# OWN prior and Gaussian likelihood at the rig's training commands (bc.draw_from_prior, the
# numpyro prior predictive of the model), not from the physical simulator: only then must the
# rank of each true value among its posterior draws be uniform, whatever the data. A wrong
# likelihood, prior, parameter transform or a sampler that has not converged shows up as
# non-uniform ranks. The test uses the sampler settings of the calibration itself (500 warm-up
# + 500 draws, dense mass), one chain per data set, thinned to 49 draws (ranks 0..49). The full
# check, 200 data sets, is the validation suite's study calibration_sbc.


def test_sbc_quick(clean):
    rig, _, _ = clean
    u, _ = rig.rows("top", "train")
    res = bc.sbc(rig.arms["top"], u, 25, n_draws=49, seed=1)
    un = res.uniformity(bins=5)
    # 25 data sets, 5 bins of 10 rank values (5 expected per bin), a chi-square test per
    # quantity (8 parameters + noise sd) Bonferroni-combined: a correct sampler fails at the
    # 1 % level one time in a hundred. With 25 data sets this only catches gross errors ...
    assert un["p_bonferroni"] > 0.01, un
    # ... such as a posterior 2.5 times too narrow, which it does reject (seeds 1, 3, 4:
    # p = 0.004, 0.0003, 0.0007; half as wide is caught only about half the time at n = 25).
    assert res.uniformity(5, narrowed_ranks(res, 0.4))["p_bonferroni"] < 0.01
    # draws from the prior include near-noiseless data sets; still (almost) no divergences
    assert res.divergences.sum() <= 0.001 * 25 * 500, res.divergences
