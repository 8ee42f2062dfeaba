"""Posterior checks: do the models' predictive regions hold the end points they should?

Coverage: each model's 50% and 90% highest-density regions against held-out end points (each
arm's validation rows, the linked test rows) of simulated rigs, whose truth is known; and,
beside them, against the ``holdout`` rows: new poses between the training grid's (each arm
alone, and the arms linked at targets off the grid). Validation rows repeat the training
commands, so they reward a model that remembers the training poses; the holdout rows ask
for accuracy where nothing was measured. For the
improved variants the requirement is nominal coverage within binomial error: a two-sided
binomial test at level 0.01 per mass, on the points pooled over the rigs. Where the measured
coverage falls short, the test is an expected failure (strict, so a fix shows up) whose
reason gives the figures; the paper-faithful variants' coverage is measured and recorded,
not asserted. The default run uses the embedded default rig (gravity sag and backlash, seed
2009) and the session's clean rig (no effects, seed 0); ``-m slow`` adds six more seeds.

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

from bayesrob import inference as inf
from bayesrob.calibration import calibrate, predicted_points
from bayesrob.comparison import PointScores, heldout_scores, score_points
from bayesrob.noise_models import ModelSpec, discover_models, fit_noise_models, joint_errors
from bayesrob.rig import default_rig_dir, load_rig
from bayesrob.simulator import paper_truth, simulate_rig

ALPHA = 0.01
MASSES = (0.5, 0.9)
IMPROVED = ("ind", "corr", "cond")


def _levels(scores: list[dict[str, dict[str, PointScores]]], model: str, kind: str
            ) -> np.ndarray:
    """HDR levels pooled over rigs: kind "single" (validation rows) or "linked" (test rows)."""
    return np.concatenate([s.hdr_level for by_setup in scores
                           for config, s in by_setup[model].items()
                           if ("+" in config) == (kind == "linked")])


def _binom_p(levels: np.ndarray, mass: float) -> float:
    k = int(np.sum(levels <= mass))
    return float(scipy.stats.binomtest(k, levels.size, mass).pvalue)


def _table(scores, record, title: str) -> dict:
    """Coverage per model and kind of point, printed (pytest -s) and recorded (junit)."""
    out = {}
    for model in scores[0]:
        out[model] = {}
        for kind in ("single", "linked"):
            lv = _levels(scores, model, kind)
            out[model][kind] = {"n": int(lv.size), **{
                f"coverage{int(m * 100)}": float(np.mean(lv <= m)) for m in MASSES}}
    print(f"\n{title}\n" + "\n".join(f"{m:11s} {json.dumps(r)}" for m, r in out.items()))
    record(title, json.dumps(out))
    return out


def _coverage_failures(scores, model: str, kind: str) -> list[str]:
    levels = _levels(scores, model, kind)
    out = []
    for mass in MASSES:
        p = _binom_p(levels, mass)
        if not p > ALPHA:
            out.append(f"{model} {kind}: {mass:.0%} region holds "
                       f"{np.mean(levels <= mass):.0%} of {levels.size} (binomial p={p:.1g})")
    return out


def _holdout_scores(rig, specs) -> dict[str, dict[str, PointScores]]:
    """Scores {model: {config: scores}} of every config's holdout rows, models fitted on the
    train rows as for the held-out scores; the prediction of each row is centred where the
    calibrated model says it lands (f(g(u)) for one arm, the aimed-at target when linked)."""
    arms = {n: c.arm for n, c in calibrate(rig).items()}
    configs = [c for c in rig.configs if rig.measurements.mask(c, "holdout").any()]
    out: dict[str, dict[str, PointScores]] = {}
    for spec in specs:
        fitted = fit_noise_models(rig, arms, [spec])[spec.name]
        out[spec.name] = {}
        for config in configs:
            rows = rig.config_rows(config, "holdout")
            members = config.split("+")
            out[spec.name][config], _ = score_points(
                [fitted[a] for a in members], [arms[a] for a in members],
                [rows["commands"][a] for a in members],
                predicted_points(rig, arms, config, "holdout"), rows["observed"])
    return out


@pytest.fixture(scope="module")
def scores():
    return [heldout_scores(load_rig(default_rig_dir()), discover_models())]


@pytest.fixture(scope="module")
def holdout():
    return [_holdout_scores(load_rig(default_rig_dir()), discover_models())]


# ------------------------------------------------------------------------------ machinery


def test_hdr_levels_of_the_models_own_draws_are_uniform():
    """The check's machinery: end points drawn from a model's own predictive distribution
    must have uniform HDR levels (KS at 0.01) and nominal coverage (binomial at 0.01).
    400 draws: 25 at each of 16 commands of the default rig's top arm."""
    rig = load_rig(default_rig_dir())
    arm = calibrate(rig)["top"].arm
    u, d = rig.arm_rows("top", "train")
    model = ModelSpec("corr_fixed", "CORR", bandwidth=(0.003, 0.004)).fit(
        joint_errors(arm, u, d), u)
    draws = inf.prior_predictive(model, arm, u, 25, seed=11)["d"]  # (25, 16, 2)
    target = np.asarray(arm.forward_u(jnp.asarray(u)))
    post = inf.grid_posterior([model], [arm], [u], target)
    levels = np.concatenate([
        post.hdr_level(inf.point_log_density(post, [model], [arm], [u], draws[k]))
        for k in range(draws.shape[0])])
    assert scipy.stats.kstest(levels, "uniform").pvalue > ALPHA
    for mass in MASSES:
        assert _binom_p(levels, mass) > ALPHA, (mass, np.mean(levels <= mass))


# ------------------------------------------------------------------------------ coverage


def _cases(short: dict) -> list:
    return [pytest.param(m, k, marks=pytest.mark.xfail(strict=True, reason=short[m, k]))
            if (m, k) in short else pytest.param(m, k)
            for m in IMPROVED for k in ("single", "linked")]


@pytest.mark.parametrize("model, kind", _cases({}))
def test_improved_models_cover_held_out_points_at_nominal_rates(scores, model, kind):
    """Default rig: 32 validation end points (16 per arm) and 16 linked test end points."""
    failures = _coverage_failures(scores, model, kind)
    assert not failures, failures


def test_coverage_of_every_model_is_recorded(scores, record_property):
    """The paper-faithful variants' over-coverage is measured here, not asserted away."""
    table = _table(scores, record_property, "coverage on the default rig")
    assert set(table) == {s.name for s in discover_models()}
    for rows in table.values():
        assert rows["single"]["n"] == 32 and rows["linked"]["n"] == 16
        for r in rows.values():
            assert 0.0 <= r["coverage50"] <= r["coverage90"] <= 1.0




@pytest.mark.parametrize("model, kind", _cases({}))
def test_improved_models_cover_new_poses_at_nominal_rates(holdout, model, kind):
    """Default rig's holdout rows: 18 single-arm end points (9 per arm) and 9 linked ones,
    each at a pose the training grid does not have; same binomial test at 0.01."""
    failures = _coverage_failures(holdout, model, kind)
    assert not failures, failures


def test_holdout_coverage_of_every_model_is_recorded(scores, holdout, record_property):
    """Beside the validation/test figures: each model's regions at new poses (the default
    rig's 18 single-arm and 9 linked holdout end points), measured and recorded."""
    val = _table(scores, record_property, "coverage on the default rig")
    hold = _table(holdout, record_property,
                  "coverage at new poses (holdout rows) on the default rig")
    assert set(hold) == set(val) == {s.name for s in discover_models()}
    for rows in hold.values():
        assert rows["single"]["n"] == 18 and rows["linked"]["n"] == 9
        for r in rows.values():
            assert 0.0 <= r["coverage50"] <= r["coverage90"] <= 1.0


# ------------------------------------------------------------------------------ linked PPC



@pytest.mark.parametrize("model", IMPROVED)
def test_linked_end_points_are_plausible_under_the_linked_prediction(scores, model,
                                                                     record_property):
    """PIT of the 16 linked test rows: KS against uniform at 0.01; and the observed mean
    distance from the targets inside the central 99% of its predictive distribution."""
    linked = [s for by in scores for c, s in by[model].items() if "+" in c]
    ppcs = [s.ppc(seed=1) for s in linked]
    record_property(f"ppc_{model}", json.dumps([{k: v for k, v in p.items()
                                                 if k != "hdr_levels"} for p in ppcs]))
    for p in ppcs:
        assert p["ks_pvalue"] > ALPHA, p
        assert 0.005 < p["ppp"] < 0.995, p


# ------------------------------------------------------------------------------ slow

SLOW_SHORT = {
    ("cond", "single"): "measured on six rigs with sag and backlash: the 50% / 90% regions hold "
                        "63% / 94% of the 192 validation end points (binomial p 0.0004 at "
                        "50%). Validation rows repeat the training commands; with its command "
                        "widths at least the grid spacing COND no longer remembers each "
                        "training pose's error, and at new poses (the holdout rows of the same "
                        "rigs) its regions hold what they state",
}


@pytest.fixture(scope="module")
def effect_rigs(tmp_path_factory):
    """Six rigs with gravity sag and backlash (seeds 1-6)."""
    return [load_rig(simulate_rig(tmp_path_factory.mktemp(f"effects{seed}"),
                                  paper_truth(("gravity_sag", "backlash"), seed=seed)))
            for seed in range(1, 7)]


@pytest.fixture(scope="module")
def effect_scores(effect_rigs):
    """192 validation and 96 linked end points per model."""
    specs = discover_models()
    return [heldout_scores(rig, specs) for rig in effect_rigs]


@pytest.fixture(scope="module")
def effect_holdout(effect_rigs):
    """The same rigs' holdout rows: 108 single-arm and 54 linked end points at new poses."""
    specs = discover_models(names=list(IMPROVED))
    return [_holdout_scores(rig, specs) for rig in effect_rigs]


@pytest.mark.slow
@pytest.mark.parametrize("model, kind", _cases(SLOW_SHORT))
def test_coverage_on_six_rigs_with_sag_and_backlash(effect_scores, model, kind):
    failures = _coverage_failures(effect_scores, model, kind)
    assert not failures, failures


@pytest.mark.slow
@pytest.mark.parametrize("model, kind", _cases({}))
def test_coverage_at_new_poses_on_six_rigs(effect_holdout, model, kind, record_property):
    """New poses between the training grid's (holdout rows), where a model that remembered
    the training poses would be found out; same binomial test at 0.01."""
    levels = _levels(effect_holdout, model, kind)
    record_property(f"holdout_{model}_{kind}", json.dumps(
        [int(levels.size), *(float(np.mean(levels <= m)) for m in MASSES)]))
    failures = _coverage_failures(effect_holdout, model, kind)
    assert not failures, failures


@pytest.mark.slow
def test_paper_variants_over_cover_on_six_rigs(effect_scores, record_property):
    """The paper found its models conservative; measured here: their 50% regions hold far
    more than half of the held-out points (binomial p < 0.01, in that direction)."""
    table = _table(effect_scores, record_property, "coverage on six rigs with sag and backlash")
    for fam in ("ind", "corr", "cond"):
        levels = np.concatenate([_levels(effect_scores, f"{fam}_paper", k)
                                 for k in ("single", "linked")])
        k = int(np.sum(levels <= 0.5))
        p = scipy.stats.binomtest(k, levels.size, 0.5, alternative="greater").pvalue
        assert p < ALPHA, (fam, table[f"{fam}_paper"])
