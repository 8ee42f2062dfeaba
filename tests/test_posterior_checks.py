"""Posterior checks: do the models' predictive regions hold the end points they should?

Coverage: each improved model's 50% and 90% highest-density regions against end points of
simulated rigs whose truth is known, pooled over three rigs with gravity sag and backlash (the
embedded default rig, seed 2009, and seeds 41-42): each arm's validation rows and the linked
test rows (which repeat the training commands) and the holdout rows (new poses between the
training grid's, alone and linked), 225 end points a model. The requirement is nominal
coverage within binomial error (two-sided, level 0.01), and the test states its power: with
225 points it finds a 50% region that holds 35% or 65%, or a 90% region that holds 80% or 99%,
with probability at least 0.8 (computed in the test). The points of one rig share its
calibration, so they are not quite independent; level 0.01 leaves room for that. The six-rig
figures, the paper-faithful variants' over-coverage among them, are the validation suite's
``model_coverage`` study.

Posterior predictive checks of the linked arms: the HDR levels of the observed linked end
points (a 2-D PIT, uniform when calibrated; Kolmogorov-Smirnov at 0.01) and the paper's
accuracy statistic, the mean distance from the targets, against its predictive distribution.
"""

from __future__ import annotations

import json

import jax.numpy as jnp
import numpy as np
import pytest
import scipy.stats
from bayesrob.validation.model_coverage import holdout_scores
from bayesrob.validation.model_coverage import levels as pooled_levels

from bayesrob.calibrate.arms import calibrate_arms
from bayesrob.compare.comparison import heldout_scores
from bayesrob.data.rig import default_rig_dir, load_rig
from bayesrob.errors.noise_models import ModelSpec, discover_models, joint_errors
from bayesrob.inference import sampling as inf
from bayesrob.predict.grid import grid_posterior, point_log_density
from bayesrob.sim.rigs import simulate_rig
from bayesrob.sim.truth import paper_truth

ALPHA = 0.01
MASSES = (0.5, 0.9)
IMPROVED = ("ind", "corr", "cond")
# Seeds of the two simulated rigs beside the default rig (used by no study or tuning set).
COVERAGE_SEEDS = (41, 42)
# The coverages a check must tell from nominal (the figures), and the power it needs.
MISSES = {0.5: (0.35, 0.65), 0.9: (0.80, 0.99)}
POWER = 0.8


def _binom_p(levels: np.ndarray, mass: float) -> float:
    k = int(np.sum(levels <= mass))
    return float(scipy.stats.binomtest(k, levels.size, mass).pvalue)


def _power(n: int, mass: float, true: float) -> float:
    """P(the binomial test at ALPHA rejects | the region really holds ``true``), n points."""
    accept = [k for k in range(n + 1) if scipy.stats.binomtest(k, n, mass).pvalue > ALPHA]
    dist = scipy.stats.binom(n, true)
    return float(1.0 - (dist.cdf(max(accept)) - dist.cdf(min(accept) - 1)))


@pytest.fixture(scope="module")
def coverage_rigs(tmp_path_factory):
    rigs = [load_rig(default_rig_dir())]
    for seed in COVERAGE_SEEDS:
        rigs.append(load_rig(simulate_rig(tmp_path_factory.mktemp(f"cov{seed}"),
                                          paper_truth(("gravity_sag", "backlash"), seed=seed))))
    return rigs


@pytest.fixture(scope="module")
def scores(coverage_rigs):
    """Held-out scores (validation and linked test rows) per rig; the default rig first."""
    specs = discover_models(names=list(IMPROVED))
    return [heldout_scores(rig, specs) for rig in coverage_rigs]


@pytest.fixture(scope="module")
def holdout(coverage_rigs):
    specs = discover_models(names=list(IMPROVED))
    return [holdout_scores(rig, specs) for rig in coverage_rigs]


# ------------------------------------------------------------------------------ machinery


def test_hdr_levels_of_the_models_own_draws_are_uniform():
    """The check's machinery: end points drawn from a model's own predictive distribution
    must have uniform HDR levels (KS at 0.01) and nominal coverage (binomial at 0.01).
    400 draws: 25 at each of 16 commands of the default rig's top arm."""
    rig = load_rig(default_rig_dir())
    arm = calibrate_arms(rig)["top"].arm
    u, d = rig.rows("top", "train")
    model = ModelSpec("corr_fixed", "CORR", bandwidth=(0.003, 0.004)).fit(
        joint_errors(arm, u, d), u)
    draws = inf.prior_predictive(model, arm, u, 25, seed=11)["d"]  # (25, 16, 2)
    target = np.asarray(arm.forward_u(jnp.asarray(u)))
    post = grid_posterior([model], [arm], [u], target)
    levels = np.concatenate([
        post.hdr_level(point_log_density(post, [model], [arm], [u], draws[k]))
        for k in range(draws.shape[0])])
    assert scipy.stats.kstest(levels, "uniform").pvalue > ALPHA
    for mass in MASSES:
        assert _binom_p(levels, mass) > ALPHA, (mass, np.mean(levels <= mass))


# ------------------------------------------------------------------------------ coverage


def test_the_coverage_check_has_the_power_it_claims():
    """225 points: a 50% region holding 35% or 65%, or a 90% region holding 80% or 99%, is
    rejected with probability at least 0.8 (and nominal coverage accepted 99% of the time)."""
    for mass, misses in MISSES.items():
        for true in misses:
            assert _power(225, mass, true) >= POWER, (mass, true, _power(225, mass, true))


@pytest.mark.parametrize("model", IMPROVED)
def test_improved_models_regions_hold_their_mass(scores, holdout, model, record_property):
    """Validation, linked test and holdout end points of three rigs with sag and backlash,
    pooled: each region's share within binomial error of its mass (see the module's note)."""
    pooled = np.concatenate([pooled_levels(group, model, kind) for group in (scores, holdout)
                             for kind in ("single", "linked")])
    assert pooled.size == 225
    record_property(f"coverage_{model}", json.dumps(
        {f"coverage{int(m * 100)}": float(np.mean(pooled <= m)) for m in MASSES}))
    for mass in MASSES:
        assert _binom_p(pooled, mass) > ALPHA, (mass, float(np.mean(pooled <= mass)))


# ------------------------------------------------------------------------------ linked PPC


@pytest.mark.parametrize("model", IMPROVED)
def test_linked_end_points_are_plausible_under_the_linked_prediction(scores, model,
                                                                     record_property):
    """PIT of the 16 linked test rows: KS against uniform at 0.01; and the observed mean
    distance from the targets inside the central 99% of its predictive distribution."""
    linked = [s for c, s in scores[0][model].items() if "+" in c]
    ppcs = [s.ppc(seed=1) for s in linked]
    record_property(f"ppc_{model}", json.dumps([{k: v for k, v in p.items()
                                                 if k != "hdr_levels"} for p in ppcs]))
    for p in ppcs:
        assert p["ks_pvalue"] > ALPHA, p
        assert 0.005 < p["ppp"] < 0.995, p
