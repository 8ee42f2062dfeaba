"""Equilibrium fusion of linked arms (bayesrob.fusion) and predictions of assemblies before they
are built (bayesrob.assembly, ``bayesrob predict``).

Rigs: the simulator at seeds 601-606 (gravity sag and backlash, each arm's stiffnesses drawn
per seed with log sd 0.3) are the report rigs of the linked coverage figures, fixed before they
were first run; the stiffness prior was chosen on seeds 101-106 (drawn the same way), which no
test uses.
"""

from __future__ import annotations

import functools
import importlib.util
import json
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest
import scipy.stats

from bayesrob import fusion
from bayesrob import kinematics as kin
from bayesrob.assembly import predict_assembly, read_targets
from bayesrob.calibration import calibrate
from bayesrob.cli import main
from bayesrob.comparison import score_points
from bayesrob.noise_models import discover_models, fit_noise_models
from bayesrob.prediction import setup_rows
from bayesrob.rig import RigError, default_rig_dir, load_rig
from bayesrob.simulator import PhysicalRig, paper_truth, simulate_rig, three_arm_truth

ALPHA = 0.01
BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
IMPROVED = ("ind", "corr", "cond")
REPORT_SEEDS = range(601, 607)
# Two arms are not equally stiff: with one stiffness for every arm a prior that linked arms are
# alike would be right by construction (docs/fusion.md, "a trap")
REPORT_STIFFNESS_LOG_SD = 0.3
# Seed 1 was the check's first rig; 2 and 3 were added when one rig proved a noisy check, and
# 4-6 to reach the 96 linked points per model (each fixed before it was first run)
THREE_ARM_SEEDS = (1, 2, 3, 4, 5, 6)


@pytest.fixture(scope="module")
def sag_rig(tmp_path_factory):
    d = tmp_path_factory.mktemp("sag1")
    return simulate_rig(d, paper_truth(("gravity_sag", "backlash"), seed=1))


@pytest.fixture(scope="module")
def three_rigs(tmp_path_factory):
    """Three-arm rigs (sag and backlash, stiffnesses drawn), seeds ``THREE_ARM_SEEDS``."""
    return [simulate_rig(tmp_path_factory.mktemp(f"three{seed}"),
                         three_arm_truth(("gravity_sag", "backlash"), seed=seed,
                                         stiffness_log_sd=REPORT_STIFFNESS_LOG_SD))
            for seed in THREE_ARM_SEEDS]


def _fitted(rig, name):
    arms = {n: c.arm for n, c in calibrate(rig).items()}
    spec = [s for s in discover_models() if s.name == name]
    return arms, fit_noise_models(rig, arms, spec)[name]


# ------------------------------------------------------------------------------ physics


def test_linearised_equilibrium_matches_the_simulators_energy_minimum(sag_rig):
    """At the 16 linked commands of a rig with sag and backlash: each arm's free end point
    and the linked one from the simulator (noise off), against the stiffness balance of the
    free points with the true joint stiffnesses. Mean gap under 0.15 mm, a fifth of the
    linked error (about 0.8 mm); measured 0.07 mm. The same with equal stiffnesses (the
    prior's centre) stays under 0.15 mm too, and is far closer than the midpoint."""
    rig = load_rig(sag_rig)
    plant = PhysicalRig.from_rig_dir(sag_rig)
    arms = {n: c.arm for n, c in calibrate(rig).items()}
    rows = setup_rows(rig, arms, "top+bottom")
    cmds = rows["commands"]
    free = {a: np.array([plant.end_point({a: u}, noise=False) for u in cmds[a]])
            for a in ("top", "bottom")}
    linked = np.array([plant.end_point({a: cmds[a][t] for a in cmds}, noise=False)
                       for t in range(len(rows["targets"]))])

    def balance(k_of):
        springs = []
        for a in ("top", "bottom"):
            truth = plant.truth.arms[a]
            theta, _ = kin.inverse(truth.params, jnp.asarray(free[a]), truth.elbow)
            springs.append(fusion.cartesian_stiffness(truth.params, theta, k_of(truth)))
        return np.asarray(fusion.equilibrium_point(
            jnp.asarray(np.stack([free["top"], free["bottom"]])), jnp.stack(springs)))

    gap_true = np.linalg.norm(balance(lambda t: jnp.asarray(t.stiffness_nmm_per_rad))
                              - linked, axis=1).mean()
    gap_equal = np.linalg.norm(balance(lambda t: jnp.ones(2)) - linked, axis=1).mean()
    gap_mid = np.linalg.norm(0.5 * (free["top"] + free["bottom"]) - linked, axis=1).mean()
    linked_error = np.linalg.norm(linked - rows["targets"], axis=1).mean()
    assert gap_true < 0.15 and gap_equal < 0.15, (gap_true, gap_equal)
    assert gap_true < 0.2 * linked_error
    assert gap_mid > 3 * gap_equal, (gap_mid, gap_equal)


def test_known_stiffness_pins_the_balance():
    """Two springs on one axis each: the balance is the stiffness-weighted mean per axis."""
    free = jnp.asarray([[[0.0, 0.0]], [[3.0, 6.0]]])  # (A=2, T=1, 2)
    k = jnp.asarray([[[[1.0, 0.0], [0.0, 2.0]]], [[[2.0, 0.0], [0.0, 1.0]]]])
    d = np.asarray(fusion.equilibrium_point(free, k))[0]
    np.testing.assert_allclose(d, [2.0, 2.0])


# ------------------------------------------------------------------------------ densities


def test_kde_density_is_scipys_gaussian_kde():
    rng = np.random.default_rng(3)
    draws = rng.normal(size=(500, 2, 2)) @ np.array([[1.0, 0.3], [0.0, 0.5]])
    pts = np.array([[0.2, -0.1], [1.0, 0.4]])
    ours = fusion.kde_log_density(draws, pts)
    for t in range(2):
        ref = scipy.stats.gaussian_kde(draws[:, t].T, bw_method="scott")
        assert ours[t] == pytest.approx(np.log(ref(pts[t][:, None])[0]), rel=1e-9)


def test_draws_posterior_is_normalised_and_agrees_with_the_exact_kde():
    """The binned KDE on the zoomed grid: mass 1; at the cell centres within 3% of the exact
    KDE where the density is above a tenth of its peak (binning moves each draw by at most
    half a cell, ~0.03 kernel widths); its HDR levels of fresh draws of the same law are
    uniform (KS at 0.01, 400 points)."""
    rng = np.random.default_rng(5)
    draws = rng.normal(size=(4000, 3, 2)) * [1.0, 0.4] + [[[10.0, 0.0]]]
    targets = np.array([[10.0, 0.0]] * 3)
    post = fusion.draws_posterior(draws, targets)
    np.testing.assert_allclose(post.prob.sum(axis=1), 1.0)
    pts = post.points()[0]
    dens = post.prob[0] / (post.cell_mm[0, 0] * post.cell_mm[0, 1])
    big = dens > 0.1 * dens.max()
    exact = np.array([fusion.kde_log_density(draws[:, :1], p[None])[0] for p in pts[big][::50]])
    np.testing.assert_allclose(dens[big][::50], np.exp(exact), rtol=0.03)
    fresh = rng.normal(size=(400, 3, 2)) * [1.0, 0.4] + [[[10.0, 0.0]]]
    levels = np.concatenate([post.hdr_level(fusion.kde_log_density(draws, f)) for f in fresh])
    assert scipy.stats.kstest(levels, "uniform").pvalue > ALPHA


def test_equilibrium_program_and_grid_draws_agree_for_a_sampleable_model(sag_rig, monkeypatch):
    """The numpyro program (Predictive) and the grid route (free points drawn from each
    arm's single-arm grid prediction) are two samplers of the same law for a model with the
    Jacobian: their means agree within 0.05 mm and sds within 10% (4000 draws each; the
    Monte Carlo sd of a mean is ~0.015 mm here)."""
    rig = load_rig(sag_rig)
    arms, fitted = _fitted(rig, "ind")
    rows = setup_rows(rig, arms, "top+bottom")
    args = ([fitted["top"], fitted["bottom"]], [arms["top"], arms["bottom"]],
            [rows["commands"]["top"][:4], rows["commands"]["bottom"][:4]], rows["targets"][:4])
    program = fusion.equilibrium_draws(*args, seed=1)
    assert fitted["top"].spec.jacobian  # else the grid route draws another law
    monkeypatch.setattr(fusion, "is_sampleable", lambda m: False)
    grid = fusion.equilibrium_draws(*args, seed=2)
    np.testing.assert_allclose(program.mean(0), grid.mean(0), atol=0.05)
    np.testing.assert_allclose(program.std(0), grid.std(0), rtol=0.10)


def test_compare_scores_both_fusions(tmp_path):
    """``compare --json``: a product entry per model and an equilibrium entry per model, each
    saying its fusion; single arms are the same prediction under both."""
    out = tmp_path / "c.json"
    assert main(["compare", "--models", "ind", "cond", "--json", str(out),
                 "--no-progress"]) == 0
    doc = json.loads(out.read_text())
    models = doc["models"]
    assert models["ind"]["fusion"] == "product"
    eq = models["ind:equilibrium"]
    assert eq["fusion"] == "equilibrium" and eq["model"] == "ind"
    for cfg in ("top", "bottom"):
        assert eq["heldout"]["by_setup"][cfg] == models["ind"]["heldout"]["by_setup"][cfg]
    linked = eq["heldout"]["by_setup"]["top+bottom"]
    assert linked["n"] == 16 and 0 <= linked["coverage50"] <= linked["coverage90"] <= 1
    assert linked != models["ind"]["heldout"]["by_setup"]["top+bottom"]


# ------------------------------------------------------------------------------ predict


@functools.cache
def _bench_predict():
    """``benchmarks/bench_predict.py`` (the three-arm study), loaded once from its file so the
    tests' import path stays as it was."""
    spec = importlib.util.spec_from_file_location("bench_predict", BENCHMARKS / "bench_predict.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    return bench


def _single_arm_copy(rig_dir, out):
    """The rig with every linked row removed (the three-arm study's own helper)."""
    return _bench_predict().single_arm_copy(rig_dir, out)


def test_predict_needs_no_linked_rows_and_gives_the_same_answer(tmp_path):
    """The default rig without its linked rows predicts the linked assembly exactly as the
    full rig does (same seed): nothing linked is read."""
    full = default_rig_dir()
    single = _single_arm_copy(full, tmp_path / "single")
    targets = tmp_path / "t.csv"
    targets.write_text("x,y\n150,150\n200,220\n")
    docs = []
    for rig_dir in (full, single):
        out = tmp_path / f"{rig_dir.name}.json"
        assert main(["predict", str(rig_dir), "--config", "top+bottom", "--targets",
                     str(targets), "--model", "ind", "--json", str(out)]) == 0
        docs.append(json.loads(out.read_text()))
    a, b = docs
    assert a["fusion"] == "equilibrium" and len(a["targets"]) == 2
    for ta, tb in zip(a["targets"], b["targets"], strict=True):
        assert ta["expected_error_mm"] == pytest.approx(tb["expected_error_mm"], abs=1e-9)
        assert 0 < ta["hdr50_mm2"] < ta["hdr90_mm2"]
        assert np.linalg.norm(np.subtract(ta["expected_point"], ta["target"])) < 3.0


def test_predict_grid_plot_and_product(tmp_path):
    png = tmp_path / "p.png"
    out = tmp_path / "p.json"
    assert main(["predict", str(default_rig_dir()), "--config", "top+bottom", "--grid", "2",
                 "--fusion", "product", "--model", "ind", "--json", str(out), "--plot",
                 str(png)]) == 0
    doc = json.loads(out.read_text())
    assert doc["fusion"] == "product" and doc["summary"]["n_targets"] == 4
    assert png.stat().st_size > 10_000


def test_predict_says_where_commands_leave_the_calibrated_range(tmp_path, capsys):
    """A target inside the top arm's train commands gets no note and zeros; one whose elbow
    command lies beyond them is counted, its excess matches the train rows' range, and the
    terminal says which arm and column, once."""
    rig = load_rig(default_rig_dir())
    targets = tmp_path / "t.csv"
    targets.write_text("x,y\n200,250\n120,320\n")
    out = tmp_path / "p.json"
    assert main(["predict", str(default_rig_dir()), "--config", "top", "--targets",
                 str(targets), "--model", "ind", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    doc = json.loads(out.read_text())
    inside, outside = (t["beyond_train_range"]["top"] for t in doc["targets"])
    assert inside == [0.0, 0.0]
    u = rig.arm_rows("top", "train")[0]
    elbow = doc["targets"][1]["commands"]["top"][1]
    assert outside[0] == 0.0 and outside[1] == pytest.approx(elbow - u[:, 1].max())
    assert outside[1] > 50  # tens of us beyond: not rounding at the range's edge
    assert doc["summary"]["targets_beyond_train_range"] == 1
    notes = [ln for ln in text.splitlines() if ln.startswith("note:")]
    assert len(notes) == 1 and "1 of 2 targets" in notes[0] and "in top_u2" in notes[0]


@pytest.mark.parametrize("args, message", [
    (["--config", "top+nope", "--grid", "2"], "no arm 'nope'"),
    (["--config", "top+top", "--grid", "2"], "appears twice"),
    (["--config", "top+bottom", "--targets", "MISSING"], "file not found"),
    (["--config", "top+bottom", "--targets", "BAD"], "line 3: x, y must be numbers"),
    (["--config", "top+bottom", "--targets", "FAR"], "is out of reach of arm 'top'"),
    (["--config", "top+bottom", "--grid", "2", "--masses", "description"],
     "planar arms have no link masses to hold"),
    (["--config", "top+bottom", "--grid", "2", "--params", "frames,compliance", "--masses",
      "description"], "planar arms have no link masses to hold"),
    (["--config", "top", "--grid", "2", "--params", "frames,offsets", "--model", "cond"],
     "chain arms take the latent joint-error models"),
    (["--config", "bottom", "--targets", "LIMIT"], "outside its pulse_limits [600, 2400]"),
    (["--config", "bottom", "--targets", "LIMIT", "--params", "frames,offsets,geometric,servo"],
     "outside its pulse_limits [600, 2400]"),
])
def test_predict_bad_input_is_one_line_and_exit_2(tmp_path, capsys, args, message):
    (tmp_path / "BAD").write_text("x,y\n150,150\n150,abc\n")
    (tmp_path / "FAR").write_text("x,y\n2000,2000\n")
    (tmp_path / "LIMIT").write_text("x,y\n368,200\n")  # in reach, beyond a servo's pulses
    args = [str(tmp_path / a) if a in ("MISSING", "BAD", "FAR", "LIMIT") else a for a in args]
    assert main(["predict", str(default_rig_dir()), *args]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1, err


def test_predict_planar_arms_through_their_fitted_physics(tmp_path, capsys):
    """``--params`` on a planar rig predicts its arms as 2-joint chains with those groups:
    aimed through the calibrated physics (each arm's own point within 1 um of the target under
    its fitted model), the latent ``ind`` errors by default, stiffnesses from the prior
    scaled by the arms' fitted sags, and the draws' figure in the arms' plane. Beside the
    eight-parameter route at the same targets, the commands differ by what the fitted sag
    and play move (a few us, not tens) and the expected errors agree within a factor 2."""
    from bayesrob.calibration import calibrate_chain
    from bayesrob.chain_prediction import STIFFNESS_SOURCES

    targets = tmp_path / "t.csv"
    targets.write_text("x,y\n160,240\n200,200\n")
    out, png = tmp_path / "p.json", tmp_path / "p.png"
    groups = "frames,offsets,geometric,servo,compliance,backlash"
    assert main(["predict", str(default_rig_dir()), "--config", "top+bottom", "--targets",
                 str(targets), "--params", groups, "--json", str(out), "--plot",
                 str(png)]) == 0
    text = capsys.readouterr().out
    doc = json.loads(out.read_text())
    assert doc["model"] == "ind" and png.stat().st_size > 10_000
    assert {v["from"] for v in doc["stiffness"].values()} == {STIFFNESS_SOURCES[3]}
    assert "by its fitted sag" in text
    rig = load_rig(default_rig_dir())
    cal = calibrate_chain(rig, tuple(groups.split(",")))
    plain = predict_assembly(rig, "top+bottom", read_targets(targets), "ind")
    for arm in ("top", "bottom"):
        u = np.array([t["commands"][arm] for t in doc["targets"]])
        got = np.asarray(cal.robot.compiled_points(arm)(cal.x, u))
        assert np.abs(got - read_targets(targets)).max() < 1e-3
        assert 0.5 < np.abs(u - plain.commands[arm]).max() < 10
    errors = np.array([t["expected_error_mm"] for t in doc["targets"]])
    assert np.all((errors > plain.expected_error_mm / 2) & (errors < 2 * plain.expected_error_mm))


def test_read_targets_needs_x_and_y(tmp_path):
    p = tmp_path / "t.csv"
    p.write_text("a,b\n1,2\n")
    with pytest.raises(RigError, match="columns x,y"):
        read_targets(p)


# ------------------------------------------------------------------------------ coverage


def _levels_and_errors(rig_dir, config, model, fusion_rule):
    rig = load_rig(rig_dir)
    arms, fitted = _fitted(rig, model)
    rows = setup_rows(rig, arms, config)
    members = config.split("+")
    scores, post = score_points([fitted[a] for a in members], [arms[a] for a in members],
                                [rows["commands"][a] for a in members], rows["targets"],
                                rows["observed"], fusion_rule)
    dist = np.linalg.norm(post.points() - rows["targets"][:, None, :], axis=-1)
    predicted = np.einsum("tm,tm->t", post.prob, dist)
    observed = np.linalg.norm(rows["observed"] - rows["targets"], axis=1)
    return scores.hdr_level, predicted, observed


@pytest.fixture(scope="module")
def three_arm_results(three_rigs, tmp_path_factory):
    """Three arms linked at one point, predicted from the modules' single-arm rows only
    (``predict_assembly`` on a copy without linked rows) and compared with the simulator's
    measurements of the assembly on six rigs (96 test points): per model, the points' HDR
    levels and the predicted / observed mean error."""
    tmp = tmp_path_factory.mktemp("three_single")
    levels = {"ind": [], "cond": []}
    predicted, observed = {"ind": [], "cond": []}, {"ind": [], "cond": []}
    for k, rig_dir in enumerate(three_rigs):
        single = _single_arm_copy(rig_dir, tmp / f"rig{k}")
        rows = load_rig(rig_dir).config_rows("top+bottom+side", "test")
        for model in levels:
            pred = predict_assembly(load_rig(single), "top+bottom+side", rows["target"], model)
            lvl, _, obs = _levels_and_errors(rig_dir, "top+bottom+side", model, "equilibrium")
            levels[model].append(lvl)
            predicted[model].append(pred.expected_error_mm)
            observed[model].append(obs)
    ratios = {m: float(np.concatenate(predicted[m]).mean() / np.concatenate(observed[m]).mean())
              for m in levels}
    return {m: np.concatenate(v) for m, v in levels.items()}, ratios


@pytest.mark.slow
@pytest.mark.parametrize("model", [
    "ind",
    pytest.param("cond", marks=pytest.mark.xfail(strict=True, reason=(
        "measured on three-arm rigs 1-6: the 50% / 90% regions hold 0.49 / 0.80 of 96 points; "
        "three arms are predicted a little too accurate there (six three-arm tuning rigs: "
        "0.59 / 0.92); through their fitted physics they meet it "
        "(test_three_arms_predicted_through_their_fitted_physics)")))])
def test_three_arms_predicted_from_single_arm_rows_cover(three_arm_results, model,
                                                         record_property):
    """Issue target, as for two arms: the 50% / 90% regions hold 0.40-0.60 / 0.84-0.96 of the
    96 linked points (ind measured 0.458 / 0.844)."""
    levels = three_arm_results[0][model]
    cov = (float(np.mean(levels <= 0.5)), float(np.mean(levels <= 0.9)))
    record_property(f"three_arm_coverage_{model}", json.dumps(cov))
    assert levels.size == 96
    assert 0.40 <= cov[0] <= 0.60 and 0.84 <= cov[1] <= 0.96, cov


@pytest.mark.slow
@pytest.mark.parametrize("model", [
    pytest.param("ind", marks=pytest.mark.xfail(strict=True, reason=(
        "measured on three-arm rigs 1-6: predicted / observed mean error 0.840; through "
        "their fitted physics 1.083 (test_three_arms_predicted_through_their_fitted_physics)"))),
    "cond"])
def test_three_arms_predicted_from_single_arm_rows_error(three_arm_results, model,
                                                         record_property):
    """Issue target: each model's mean predicted error within [0.85, 1.15] of the observed
    (cond measured 0.926)."""
    _, ratios = three_arm_results
    record_property(f"three_arm_error_ratio_{model}", json.dumps(ratios[model]))
    assert 0.85 <= ratios[model] <= 1.15, ratios


@pytest.mark.slow
def test_three_arms_predicted_through_their_fitted_physics():
    """Item 4's three-arm check on the route that meets it: ``predict --params
    frames,offsets,geometric,servo,compliance,backlash`` from single-arm rows, the assembly
    then measured at predict's own commands (``bench_predict.py --three-arms report``: six
    report rigs fixed before their first run, 96 linked points; about 5 minutes on two cores).
    The groups were chosen on the tuning rigs 101-106 (compliance alone over-predicted there,
    1.25). Issue targets: 0.40-0.60 / 0.84-0.96 at 96 points and an error ratio in
    [0.85, 1.15]; the published figures (docs/fusion.md) to 2.5 points of 96 (a point at its
    region's edge flips with the compiled programs' rounding) and the ratio to 0.002.
    One test, so the study runs once whichever worker takes it."""
    bench = _bench_predict()
    got = bench.three_arm_study(bench.THREE_ARM_REPORT_SEEDS)
    assert got["points"] == 96
    assert got["coverage50"] == pytest.approx(0.531, abs=2.5 / 96)
    assert got["coverage90"] == pytest.approx(0.948, abs=2.5 / 96)
    assert got["error_ratio"] == pytest.approx(1.083, abs=2e-3)
    assert 0.40 <= got["coverage50"] <= 0.60 and 0.84 <= got["coverage90"] <= 0.96, got
    assert 0.85 <= got["error_ratio"] <= 1.15, got


@pytest.fixture(scope="module")
def report_levels(tmp_path_factory):
    """Equilibrium fusion on the report rigs (seeds 601-606, sag and backlash, stiffnesses
    drawn per seed): HDR levels and predicted / observed linked errors of the 96 linked end
    points, per improved model."""
    out = {m: ([], [], []) for m in IMPROVED}
    for seed in REPORT_SEEDS:
        d = simulate_rig(tmp_path_factory.mktemp(f"eq{seed}"),
                         paper_truth(("gravity_sag", "backlash"), seed=seed,
                                     stiffness_log_sd=REPORT_STIFFNESS_LOG_SD))
        for m in IMPROVED:
            for acc, x in zip(out[m], _levels_and_errors(d, "top+bottom", m, "equilibrium"),
                              strict=True):
                acc.append(x)
    return {m: tuple(np.concatenate(x) for x in v) for m, v in out.items()}


REPORT_SHORT = {
    "corr": "measured on the report rigs: the 50% / 90% regions hold 60.4% / 92.7% of the 96 "
            "linked end points, one point over the 50% range's 57 (the product: 43.8% / "
            "89.6%)",
}
RATIO_SHORT = {
    "cond": "measured on the report rigs: mean predicted linked error 0.972 mm against 0.841 "
            "observed, ratio 1.156 (the product: 1.18); the balance of independently drawn "
            "free points is a little too wide",
}


def _xfails(short: dict) -> list:
    return [pytest.param(m, marks=pytest.mark.xfail(strict=True, reason=short[m]))
            if m in short else m for m in IMPROVED]


@pytest.mark.slow
@pytest.mark.parametrize("model", _xfails(RATIO_SHORT))
def test_equilibrium_fusion_predicts_the_linked_error_on_report_rigs(report_levels, model,
                                                                     record_property):
    """Issue target: the mean predicted linked error within [0.85, 1.15] of the observed mean
    over the 96 linked end points (measured: ind 0.925 / 0.841 mm = 1.10, corr 0.962 / 0.841
    = 1.14)."""
    _, predicted, observed = report_levels[model]
    ratio = predicted.mean() / observed.mean()
    record_property(f"equilibrium_error_{model}",
                    json.dumps([float(predicted.mean()), float(observed.mean())]))
    assert 0.85 <= ratio <= 1.15, ratio


@pytest.mark.slow
@pytest.mark.parametrize("model", _xfails(REPORT_SHORT))
def test_equilibrium_fusion_covers_linked_points_on_report_rigs(report_levels, model,
                                                                record_property):
    """Issue target: pooled over the 96 linked end points, the 50% region holds 0.40-0.60 of
    them and the 90% region 0.84-0.96 (binomial 95% ranges of n = 96 around nominal)."""
    levels, _, _ = report_levels[model]
    cov = (float(np.mean(levels <= 0.5)), float(np.mean(levels <= 0.9)))
    record_property(f"equilibrium_coverage_{model}", json.dumps(cov))
    assert levels.size == 96
    assert 0.40 <= cov[0] <= 0.60 and 0.84 <= cov[1] <= 0.96, cov
