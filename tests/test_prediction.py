"""Joint-error models and grid predictions: model files, push-forward, fusion of linked arms."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bayesrob import robot as kin
from bayesrob.calibrate.arms import calibrate_arms
from bayesrob.data.rig import default_rig_dir, load_rig
from bayesrob.errors.distributions import joint_error_distribution
from bayesrob.errors.noise_models import (
    ModelFileError,
    ModelSpec,
    discover_models,
    fit_noise_models,
    joint_errors,
    without_tracker_noise,
)
from bayesrob.predict.grid import Grid, predict, setup_rows, setups


@pytest.fixture(scope="module")
def default():
    rig = load_rig(default_rig_dir())
    arms = {n: c.arm for n, c in calibrate_arms(rig).items()}
    return rig, arms


def test_shipped_models_cover_every_family_in_both_variants():
    specs = discover_models()
    got = {(s.family, s.paper) for s in specs}
    assert got == {(f, p) for f in ("IND", "CORR", "COND") for p in (True, False)}
    cond = {s.name: s for s in specs if s.family == "COND"}
    assert cond["cond_paper"].conditioning == "histogram" and not cond["cond_paper"].jacobian
    assert cond["cond"].conditioning == "kernel" and cond["cond"].jacobian


def test_model_file_errors_name_file_and_key(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text('name = "x"\nfamily = "WIGGLE"\n')
    with pytest.raises(ModelFileError, match=r"bad\.toml.*family"):
        ModelSpec.from_file(bad)
    bad.write_text('name = "x"\nfamily = "IND"\nbandwith = "paper"\n')
    with pytest.raises(ModelFileError, match=r"bad\.toml.*unknown key 'bandwith'"):
        ModelSpec.from_file(bad)
    with pytest.raises(ModelFileError, match="no model named 'nope'"):
        discover_models(names=["nope"])
    bad.write_text('name = "x"\nfamily = "COND"\ncommand_bandwidth_floor = -1\n')
    with pytest.raises(ModelFileError, match=r"bad\.toml: command_bandwidth_floor must be"):
        ModelSpec.from_file(bad)


def test_new_variant_is_a_file_not_code(tmp_path, default):
    rig, arms = default
    (tmp_path / "corr_wide.toml").write_text(
        'name = "corr_wide"\nfamily = "CORR"\nbandwidth = 0.01\njacobian = true\n')
    (spec,) = discover_models(tmp_path)
    fitted = fit_noise_models(rig, arms, [spec])["corr_wide"]
    np.testing.assert_allclose(fitted["top"].bandwidth, [0.01, 0.01])


def test_joint_errors_invert_the_forward_model(default):
    rig, arms = default
    arm = arms["top"]
    u, _ = rig.rows("top", "train")
    err_true = np.random.default_rng(0).normal(0, 0.004, u.shape)
    d = np.asarray(kin.forward(arm.params, kin.servo(arm.params, jnp.asarray(u)) + err_true))
    np.testing.assert_allclose(joint_errors(arm, u, d), err_true, atol=1e-9)


def test_tracker_noise_is_taken_out_of_the_joint_errors(default):
    """Rows read off noisy measured points, deconvolved, have the joints' own spread.

    0.8 mrad per joint and 0.35 mm of tracker noise, as the simulator's rigs. The tracker's
    noise reaches the joints at about 2.3 mrad, so the joints' own variance is a small
    difference of two large ones: at 6,400 rows (the train commands 400 times) each joint's
    deconvolved sd has a standard error of about 7.5%, and 20% is about 2.7 of them. The raw
    rows are over twice too wide, so the test could fail.
    """
    rig, arms = default
    arm = arms["top"]
    u, _ = rig.rows("top", "train")
    u = np.tile(u, (400, 1))
    rng = np.random.default_rng(4)
    e = rng.normal(0, 0.0008, u.shape)
    d = np.asarray(kin.forward(arm.params, kin.servo(arm.params, jnp.asarray(u)) + e))
    raw = joint_errors(arm, u, d + rng.normal(0, 0.35, d.shape))
    clean = without_tracker_noise(arm, u, raw, 0.35)
    assert raw.std(axis=0).min() > 2 * 0.0008
    np.testing.assert_allclose(clean.std(axis=0), 0.0008, rtol=0.2)
    assert abs(np.corrcoef(clean.T)[0, 1]) < 0.1  # the joints' errors are independent
    # no tracker noise known: the rows are left as they are
    np.testing.assert_array_equal(without_tracker_noise(arm, u, raw, 0.0), raw)


def _grid_moments(pred, i):
    pts = pred.targets[i] + pred.grid.offsets
    mean = pred.prob[i] @ pts
    c = pts - mean
    return mean, (pred.prob[i][:, None] * c).T @ c


@pytest.mark.parametrize("model", ["ind", "corr", "cond"])
def test_improved_grid_density_is_the_push_forward_of_the_joint_error_density(default, model):
    """With the Jacobian, the grid density of d is exactly that of f(g(u) + theta_err)."""
    rig, arms = default
    (spec,) = discover_models(names=[model])
    fitted = fit_noise_models(rig, arms, [spec])[model]
    rows = setup_rows(rig, arms, "bottom")
    i = 5
    pred = predict("bottom", fitted, arms, rows["commands"], rows["targets"],
                   Grid(15.0, 300), model)
    mean, cov = _grid_moments(pred, i)
    u = jnp.asarray(rows["commands"]["bottom"][i])
    f = fitted["bottom"]
    err = joint_error_distribution(f, u).sample(jax.random.PRNGKey(0), (40000,))
    arm = arms["bottom"]
    d = np.asarray(kin.forward(arm.params, kin.servo(arm.params, u) + err))
    # 40000 draws: the Monte Carlo standard error of the mean is ~0.01 mm for a ~1.5 mm
    # spread; the 0.1 mm grid cell adds a bias of order cell^2/12 to the covariance.
    np.testing.assert_allclose(mean, d.mean(axis=0), atol=0.04)
    np.testing.assert_allclose(cov, np.cov(d.T), rtol=0.06, atol=0.01)


def test_linked_prediction_is_sharper_than_each_arm(default):
    rig, arms = default
    (spec,) = discover_models(names=["corr"])
    fitted = fit_noise_models(rig, arms, [spec])["corr"]
    rows = setup_rows(rig, arms, "top+bottom")
    linked = predict("top+bottom", fitted, arms, rows["commands"], rows["targets"])
    for a in ("top", "bottom"):
        alone = predict(a, fitted, arms, {a: rows["commands"][a]}, rows["targets"])
        assert linked.mean_expected_error_mm < alone.mean_expected_error_mm
        assert np.all(linked.hdr90_mm2 <= alone.hdr90_mm2 + 1e-9)
    np.testing.assert_allclose(linked.prob.sum(axis=1), 1.0, atol=1e-12)


def test_setups_are_single_arms_then_linked(default):
    rig, _ = default
    assert setups(rig) == ["top", "bottom", "top+bottom"]


def test_mass_cut_off_by_the_grid_is_reported(default):
    """Commands that do not aim at the targets push the mass to the grid edge: say so."""
    rig, arms = default
    (spec,) = discover_models(names=["ind"])
    fitted = fit_noise_models(rig, arms, [spec])["ind"]
    rows = setup_rows(rig, arms, "top")
    good = predict("top", fitted, arms, rows["commands"], rows["targets"])
    assert good.edge_mass.max() < 1e-6
    far = predict("top", fitted, arms, rows["commands"], rows["targets"] + [40.0, 0.0])
    assert far.edge_mass.min() > 0.5


def test_histogram_margin_keeps_every_training_point_inside(tmp_path, default):
    rig, arms = default
    (spec,) = discover_models(names=["cond_paper"])
    u, d = rig.rows("bottom", "train")
    err = joint_errors(arms["bottom"], u, d)
    widths = np.asarray(spec._bin_widths(err, u))
    x = np.hstack([err, u])
    lo = x.mean(axis=0) - widths * spec.bins / 2
    hi = x.mean(axis=0) + widths * spec.bins / 2
    span = x.max(axis=0) - x.min(axis=0)
    assert np.all(x.min(axis=0) - lo >= spec.bin_margin * span - 1e-9)
    assert np.all(hi - x.max(axis=0) >= spec.bin_margin * span - 1e-9)
