"""Equilibrium fusion of linked arms (bayesrob.predict.fusion) and predictions of assemblies
before they are built (bayesrob.predict.assembly, ``bayesrob predict``).

How often the linked predictions hold on report rigs is measured by the validation suite
(``bayesrob validate linked_planar linked_planar_three linked_planar_physics``), not here.
"""

from __future__ import annotations

import json
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest
import scipy.stats
from bayesrob.validation.linked_planar import single_arm_copy

from bayesrob import robot as kin
from bayesrob.calibrate.arms import calibrate_arms
from bayesrob.cli import main
from bayesrob.data.rig import RigError, default_rig_dir, load_rig
from bayesrob.errors.noise_models import discover_models, fit_noise_models
from bayesrob.predict import fusion
from bayesrob.predict.assembly import predict_assembly, read_targets
from bayesrob.predict.grid import setup_rows
from bayesrob.predict.regions import kde_log_density
from bayesrob.sim.equilibrium import PhysicalRig
from bayesrob.sim.rigs import simulate_rig
from bayesrob.sim.truth import paper_truth

ALPHA = 0.01


@pytest.fixture(scope="module")
def sag_rig(tmp_path_factory):
    d = tmp_path_factory.mktemp("sag1")
    return simulate_rig(d, paper_truth(("gravity_sag", "backlash"), seed=1))


def _fitted(rig, name):
    arms = {n: c.arm for n, c in calibrate_arms(rig).items()}
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
    arms = {n: c.arm for n, c in calibrate_arms(rig).items()}
    rows = setup_rows(rig, arms, "top+bottom")
    cmds = rows["commands"]
    free = {a: np.array([plant.end_point({a: u}, noise=False) for u in cmds[a]])
            for a in ("top", "bottom")}
    linked = np.array([plant.end_point({a: cmds[a][t] for a in cmds}, noise=False)
                       for t in range(len(rows["targets"]))])

    def balance(k_of):
        held = []
        for a in ("top", "bottom"):
            truth = plant.truth.arms[a]
            theta, _ = kin.inverse(truth.params, jnp.asarray(free[a]), truth.elbow)
            held.append(fusion.springs(kin.jacobian(truth.params, theta),
                                       jnp.log(k_of(truth))))
        return np.asarray(fusion.balance(
            jnp.asarray(np.stack([free["top"], free["bottom"]])), jnp.stack(held)))

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
    d = np.asarray(fusion.balance(free, k))[0]
    np.testing.assert_allclose(d, [2.0, 2.0])


# ------------------------------------------------------------------------------ densities


def test_kde_density_is_scipys_gaussian_kde():
    rng = np.random.default_rng(3)
    draws = rng.normal(size=(500, 2, 2)) @ np.array([[1.0, 0.3], [0.0, 0.5]])
    pts = np.array([[0.2, -0.1], [1.0, 0.4]])
    ours = kde_log_density(draws, pts)
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
    exact = np.array([kde_log_density(draws[:, :1], p[None])[0] for p in pts[big][::50]])
    np.testing.assert_allclose(dens[big][::50], np.exp(exact), rtol=0.03)
    fresh = rng.normal(size=(400, 3, 2)) * [1.0, 0.4] + [[[10.0, 0.0]]]
    levels = np.concatenate([post.hdr_level(kde_log_density(draws, f)) for f in fresh])
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


def test_compare_scores_both_fusions(clean_rig_dir):
    """``compare``'s document (what ``compare --json`` writes): a product entry per model and
    an equilibrium entry per model, each saying its fusion; single arms are the same
    prediction under both. From the library on the session's clean rig: the command's own
    JSON, plot and holdout rows are test_inference_compare's (its two models each get both
    fusions there too), and the leave-one-out refits of the calibration (recalibrate), which
    only the LOO scores see, are left out: every entry checked here is a held-out score."""
    from bayesrob.compare.comparison import compare_models

    comparison = compare_models(load_rig(clean_rig_dir), ["ind", "cond"], recalibrate=False)
    doc = json.loads(json.dumps(comparison.document(), allow_nan=True))  # as the command writes
    models = doc["models"]
    assert {name: m["fusion"] for name, m in models.items()} == {
        "ind": "product", "cond": "product", "ind:equilibrium": "equilibrium",
        "cond:equilibrium": "equilibrium"}
    eq = models["ind:equilibrium"]
    assert eq["fusion"] == "equilibrium" and eq["model"] == "ind"
    for cfg in ("top", "bottom"):
        assert eq["heldout"]["by_setup"][cfg] == models["ind"]["heldout"]["by_setup"][cfg]
    linked = eq["heldout"]["by_setup"]["top+bottom"]
    assert linked["n"] == 16 and 0 <= linked["coverage50"] <= linked["coverage90"] <= 1
    assert linked != models["ind"]["heldout"]["by_setup"]["top+bottom"]


# ------------------------------------------------------------------------------ predict


def test_predict_needs_no_linked_rows_and_gives_the_same_answer(tmp_path):
    """The default rig without its linked rows predicts the linked assembly exactly as the
    full rig does (same seed): nothing linked is read."""
    full = default_rig_dir()
    single = single_arm_copy(full, tmp_path / "single")
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
    u = rig.rows("top", "train")[0]
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
    # the error in one line; the clock's lines ("predict: ...") may precede it when the
    # error shows only after the calibration
    err = [x for x in capsys.readouterr().err.strip().splitlines()
           if not x.startswith("predict: ")]
    assert len(err) == 1 and message in err[0], err


def test_predict_planar_arms_through_their_fitted_physics(tmp_path, capsys, monkeypatch):
    """``--params`` on a planar rig predicts its arms as 2-joint chains with those groups:
    aimed through the calibrated physics (each arm's own point within 1 um of the target under
    its fitted model), the latent ``ind`` errors by default, stiffnesses from the prior
    scaled by the arms' fitted sags, and the draws' figure in the arms' plane. Beside the
    eight-parameter route at the same targets, the commands differ by what the fitted sag
    and play move (a few us, not tens) and the expected errors agree within a factor 2.

    The calibrated model the commands are checked under is the one the command fitted, kept
    as it returns (not fitted a second time): the command must have made exactly one
    calibration, of the default rig with the groups asked and otherwise calibrate's
    defaults, i.e. the fit ``calibrate(rig, groups)`` computes (it is deterministic)."""
    import inspect

    import bayesrob.calibrate.least_squares
    import bayesrob.predict.draws
    from bayesrob.predict.stiffness import STIFFNESS_SOURCES

    real, fits = bayesrob.calibrate.least_squares.calibrate, []

    def kept(*args, **kwargs):
        fits.append((inspect.signature(real).bind(*args, **kwargs), real(*args, **kwargs)))
        return fits[-1][1]

    # wherever the prediction calls it from: the module that defines it, or one that imported it
    for module in (bayesrob.calibrate.least_squares, bayesrob.predict.draws):
        monkeypatch.setattr(module, "calibrate", kept)
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
    ((call, cal),) = fits
    call.apply_defaults()
    expected = inspect.signature(real).bind(rig, tuple(groups.split(",")))
    expected.apply_defaults()
    same_rig = [Path(b.arguments.pop("rig").path).resolve() for b in (call, expected)]
    assert same_rig[0] == same_rig[1], same_rig
    assert call.arguments == expected.arguments
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
