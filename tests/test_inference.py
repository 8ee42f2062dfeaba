"""The joint-error models as numpyro programs: densities, push-forwards, and samplers vs the grid.

Every NUTS run here uses one target and four chains on a two-arm COND program with 16
training points per arm, so they share one compiled sampler (the compilation dominates). Every
model against the grid at all 16 default targets is the validation study sampler_check.
"""

from __future__ import annotations

import dataclasses
import json

import arviz as az
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from numpyro.infer.util import log_density
from scipy.ndimage import maximum_filter

from bayesrob import robot as kin
from bayesrob.calibrate.arms import calibrate_arms
from bayesrob.cli import main
from bayesrob.data.rig import default_rig_dir, load_rig
from bayesrob.errors.distributions import (
    arm_log_density,
    is_sampleable,
    joint_error_distribution,
    joint_error_log_prob,
)
from bayesrob.errors.kde import ConditionalKDE
from bayesrob.errors.noise_models import FittedNoiseModel, ModelSpec, discover_models, joint_errors
from bayesrob.inference import sampling as inf
from bayesrob.predict.grid import Grid, GridPosterior, grid_posterior, predict
from bayesrob.report import tables

# Fixed bandwidths (rad; us for the commands) so the small-model tests need no selection.
FIXED = {
    "IND": ModelSpec("ind_fixed", "IND", bandwidth=0.0035),  # one width serves both joints
    "CORR": ModelSpec("corr_fixed", "CORR", bandwidth=(0.003, 0.004)),
    "COND": ModelSpec("cond_fixed", "COND", bandwidth=(0.003, 0.004, 80.0, 120.0)),
    "HIST": ModelSpec("hist", "COND", bandwidth="paper", conditioning="histogram",
                      jacobian=False),
}


@pytest.fixture(scope="module")
def rig():
    return load_rig(default_rig_dir())


@pytest.fixture(scope="module")
def arms(rig):
    return {n: c.arm for n, c in calibrate_arms(rig).items()}


@pytest.fixture(scope="module")
def errors(rig, arms):
    out = {}
    for name, arm in arms.items():
        u, d = rig.rows(name, "train")
        out[name] = (joint_errors(arm, u, d), u)
    return out


@pytest.fixture(scope="module")
def small_models(errors):
    """{kind: {arm: fitted}} for the four kinds at fixed bandwidths (fast to fit)."""
    return {k: {a: spec.fit(*errors[a]) for a in errors} for k, spec in FIXED.items()}


@pytest.fixture(scope="module")
def cond(rig, arms):
    """The shipped improved COND, fitted to the default rig (the `sample` default)."""
    spec = discover_models(names=["cond"])[0]
    return {a: spec.fit(*_train(rig, arms[a])) for a in arms}


def _train(rig, arm):
    u, d = rig.rows(arm.name, "train")
    return joint_errors(arm, u, d), u


# ------------------------------------------------------------------------------ densities


def _fitted_logpdf(model, theta_err, u):
    """The reference: log p(theta_err | u) by the fitted KDEs themselves, (M, 2) errors."""
    theta_err = jnp.atleast_2d(theta_err)
    if model.spec.family == "IND":
        return sum(p.logpdf(theta_err[:, j:j + 1]) for j, p in enumerate(model.parts))
    if model.spec.family == "CORR":
        return model.parts[0].logpdf(theta_err)
    return model.conditional.logpdf(theta_err, jnp.atleast_2d(u))


@pytest.mark.parametrize("kind", ["IND", "CORR", "COND", "HIST"])
def test_joint_error_log_prob_is_the_kde_density(small_models, kind):
    model = small_models[kind]["top"]
    rng = np.random.default_rng(0)
    err = model.theta_err[rng.integers(0, 16, 50)] + rng.normal(0, 0.004, (50, 2))
    u = model.u[rng.integers(0, 16, 50)] + rng.normal(0, 30, (50, 2))
    got = np.asarray(joint_error_log_prob(model, jnp.asarray(err), jnp.asarray(u)))
    want = np.asarray(_fitted_logpdf(model, jnp.asarray(err), jnp.asarray(u)))
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("kind", ["IND", "CORR", "COND"])
def test_distribution_samples_have_the_kde_moments(small_models, kind):
    model = small_models[kind]["bottom"]
    u = model.u[3]
    d = joint_error_distribution(model, u)
    x = np.asarray(d.sample(jax.random.PRNGKey(1), (40000,)))
    if kind == "COND":
        w = np.asarray(model.conditional.weights(u))
        data, bw = model.conditional.x_data, model.conditional.bw_x
    else:
        w = np.full(16, 1 / 16)
        data, bw = model.theta_err, model.bandwidth
    mean = w @ data
    cov = (data - mean).T @ np.diag(w) @ (data - mean) + np.diag(np.asarray(bw) ** 2)
    if kind == "IND":  # a product of the two marginals: no correlation at all
        cov = np.diag(np.diag(cov))
    # 40000 draws: the mean's standard error is sd / 200, the covariance's about 1%.
    sd = np.sqrt(np.diag(cov))
    assert np.all(np.abs(x.mean(0) - mean) < 5 * sd / 200)
    assert np.linalg.norm(np.cov(x.T) - cov) / np.linalg.norm(cov) < 0.05
    if kind == "IND":  # while the data themselves are correlated
        assert abs(np.corrcoef(x.T)[0, 1]) < 0.03 < abs(np.corrcoef(data.T)[0, 1])


def test_histogram_cond_is_scored_only(small_models, arms):
    model = small_models["HIST"]["top"]
    assert not is_sampleable(model)
    with pytest.raises(NotImplementedError, match="scored density only"):
        joint_error_distribution(model, model.u[0])
    with pytest.raises(NotImplementedError, match="cannot be forward-sampled"):
        inf.prior_predictive(model, arms["top"], model.u[:2], 10)


def arm_log_likelihood(model, arm, u, points):
    """The reference: the fitted model's own log density (not the numpyro distribution) of the
    joint errors that inverse kinematics gives at end points (T, M, 2), plus the log-Jacobian
    where the model applies it; -inf where the arm cannot reach."""
    t, m = points.shape[:2]
    theta, ok = kin.inverse(arm.params, jnp.asarray(points, float), arm.elbow)
    err = kin.wrap_angle(theta - kin.servo(arm.params, jnp.asarray(u, float))[:, None, :])
    u_rep = jnp.broadcast_to(jnp.asarray(u, float)[:, None, :], (t, m, 2)).reshape(-1, 2)
    lp = _fitted_logpdf(model, err.reshape(-1, 2), u_rep).reshape(t, m)
    if model.spec.jacobian:
        lp = lp + kin.log_abs_det_inverse_jacobian(arm.params, theta)
    return jnp.where(ok, lp, -jnp.inf)


@pytest.mark.parametrize("kind", ["IND", "CORR", "COND", "HIST"])
def test_arm_log_density_matches_the_grid_likelihood(small_models, arms, rig, kind):
    u, _ = rig.rows("bottom", "validation")
    arm = arms["bottom"]
    model = small_models[kind]["bottom"]
    target = np.asarray(arm.forward_u(jnp.asarray(u[:4])))
    pts = target[:, None, :] + np.random.default_rng(2).normal(0, 2.0, (4, 30, 2))
    got = arm_log_density(model, arm, jnp.asarray(u[:4]), jnp.asarray(pts.transpose(1, 0, 2)))
    want = arm_log_likelihood(model, arm, jnp.asarray(u[:4]), jnp.asarray(pts))
    np.testing.assert_allclose(np.asarray(got).T, np.asarray(want), rtol=1e-9, atol=1e-9)


# ------------------------------------------------------------------------------ push-forward


@pytest.mark.parametrize("kind", ["IND", "CORR", "COND"])
def test_prior_predictive_draws_match_the_grid_density(small_models, arms, rig, kind):
    """With the Jacobian, the grid density is exactly the push-forward of the joint errors.

    20000 Predictive draws per command: the mean's MC error is < 0.01 mm and the
    covariance's ~1%; tolerances 0.03 mm and 5% (Frobenius, relative).
    """
    model = small_models[kind]["top"]
    assert model.spec.jacobian
    arm = arms["top"]
    u, _ = rig.rows("top", "validation")
    u = u[[0, 5, 10, 15]]
    draws = inf.prior_predictive(model, arm, u, 20000, seed=3)["d"]  # (S, 4, 2)
    target = np.asarray(arm.forward_u(jnp.asarray(u)))
    post = grid_posterior([model], [arm], [u], target)
    dev = draws - draws.mean(0)
    cov = np.einsum("sti,stj->tij", dev, dev) / (len(draws) - 1)
    assert np.max(np.linalg.norm(draws.mean(0) - post.mean, axis=1)) < 0.03
    assert np.max(inf.cov_rel_error(cov, post.cov)) < 0.05
    # The Jacobian makes the density integrate to one over the plane by itself.
    np.testing.assert_allclose(np.exp(post.log_normaliser), 1.0, atol=1e-6)


def test_prior_predictive_with_measurement_noise_adds_its_variance(small_models, arms, rig):
    model, arm = small_models["CORR"]["top"], arms["top"]
    u = rig.rows("top", "validation")[0][:1]
    clean = inf.prior_predictive(model, arm, u, 20000, seed=4)["d"][:, 0]
    noisy = inf.prior_predictive(model, arm, u, 20000, seed=4, measurement_noise_mm=1.0)
    assert set(noisy) >= {"d", "d_true", "theta_err"}
    extra = np.cov(noisy["d"][:, 0].T) - np.cov(clean.T)
    np.testing.assert_allclose(np.diag(extra), [1.0, 1.0], atol=0.1)


def test_the_grid_zoom_agrees_with_the_paper_grid(small_models, arms, rig):
    """The zoomed moments equal those of the prediction on a fine plain grid."""
    ms = [small_models["CORR"][a] for a in ("top", "bottom")]
    am = [arms["top"], arms["bottom"]]
    rows = rig.config_rows("top+bottom", "test")
    cmds = [rows["commands"][a][:3] for a in ("top", "bottom")]
    target = rows["target"][:3]
    zoom = grid_posterior(ms, am, cmds, target)
    plain = predict("top+bottom", dict(zip(("top", "bottom"), ms, strict=True)),
                    {a.name: a for a in am}, dict(zip(("top", "bottom"), cmds, strict=True)),
                    target, Grid(15.0, 600))
    np.testing.assert_allclose(zoom.mean, plain.expected_point, atol=2e-3)
    assert np.all(zoom.edge_mass < 1e-12)
    assert np.all(zoom.cell_mm < 0.1)


# ------------------------------------------------------------------------------ linked program


def test_linked_program_density_is_the_product_of_likelihoods(handmade_rig_dir):
    """Three linked arms: log_density of the program = the grid's summed log-likelihoods."""
    rig3 = load_rig(handmade_rig_dir)
    arms3 = {n: c.arm for n, c in calibrate_arms(rig3).items()}
    names = ["left", "middle", "right"]
    models = [FIXED["CORR"].fit(*_train(rig3, arms3[a])) for a in names]
    rows = rig3.config_rows("left+middle+right", "test")
    cmds = [jnp.asarray(rows["commands"][a]) for a in names]
    d = jnp.asarray(rows["target"] + np.random.default_rng(5).normal(0, 1.0, (2, 2)))
    lp, trace = log_density(inf.linked_model, (cmds,), {"models": models,
                                                         "arms": [arms3[a] for a in names]},
                            {"d": d})
    assert {f"loglik_{a}" for a in names} <= set(trace)
    want = sum(arm_log_likelihood(m, arms3[a], c, d[:, None, :])
               for m, a, c in zip(models, names, cmds, strict=True))
    np.testing.assert_allclose(float(lp), float(jnp.sum(want)), rtol=1e-10)
    post = grid_posterior(models, [arms3[a] for a in names], cmds, rows["target"])
    assert np.all(np.isfinite(post.mean))


def test_emcee_log_density_is_the_programs(small_models, arms, rig):
    ms = [small_models["COND"][a] for a in ("top", "bottom")]
    am = [arms["top"], arms["bottom"]]
    rows = rig.config_rows("top+bottom", "test")
    cmds = [jnp.asarray(rows["commands"][a][:1]) for a in ("top", "bottom")]
    walkers = rows["target"][:1] + np.random.default_rng(6).normal(0, 0.5, (8, 2))
    fn = inf.linked_log_density(ms, am)
    got = np.asarray(fn(walkers, cmds))
    want = [float(log_density(inf.linked_model, (cmds,), {"models": ms, "arms": am},
                              {"d": jnp.asarray(w[None])})[0]) for w in walkers]
    np.testing.assert_allclose(got, want, rtol=1e-10)


# ------------------------------------------------------------------------------ samplers


def _setup(rig, arms, models, index):
    """(models, arms, commands, targets) for linked test target ``index`` (an int or a slice)."""
    rows = rig.config_rows("top+bottom", "test")
    target = rows["target"][slice(index, index + 1) if isinstance(index, int) else index]
    am = [arms["top"], arms["bottom"]]
    cmds = [np.asarray(a.command(jnp.asarray(target))) for a in am]
    return [models[a] for a in ("top", "bottom")], am, cmds, target


def _bimodal_models(rig):
    """COND models whose top arm's shoulder error has two clusters 4 mrad apart (10 + 6
    points); the bottom arm's errors are broad, so the linked posterior keeps both modes."""
    spec = discover_models(names=["cond"])[0]
    rng = np.random.default_rng(0)

    def fit(arm, x, bw):
        u, _ = rig.rows(arm, "train")
        c = ConditionalKDE.fit(x, u, "kernel", bandwidth=[*bw, 1e4, 1e4])
        return FittedNoiseModel(spec, x, u, conditional=c)

    two = np.concatenate([rng.normal(0, 3e-4, (10, 2)),
                          rng.normal(0, 3e-4, (6, 2)) + [4e-3, 0.0]])
    return {"top": fit("top", two, [1e-3, 1e-3]),
            "bottom": fit("bottom", rng.normal(0, 6e-3, (16, 2)), [4e-3, 4e-3])}


def _two_modes(grid: GridPosterior) -> tuple[float, float]:
    """(smaller peak / larger peak, lowest density between them / smaller peak)."""
    p = grid.prob[0].reshape(grid.n, grid.n)
    peaks = (p == maximum_filter(p, size=grid.n // 8)) & (p > 0.05 * p.max())
    iy, ix = np.nonzero(peaks)
    assert len(iy) == 2, f"expected two modes, found {len(iy)}"
    (y0, y1), (x0, x1) = iy[np.argsort(-p[iy, ix])], ix[np.argsort(-p[iy, ix])]
    s = np.linspace(0, 1, 400)
    line = p[np.round(y0 + s * (y1 - y0)).astype(int), np.round(x0 + s * (x1 - x0)).astype(int)]
    return p[y1, x1] / p[y0, x0], line.min() / p[y1, x1]


def test_samplers_agree_with_the_grid_on_a_bimodal_posterior(rig, arms):
    """Chains and walkers start around the target (the arms' prior spread, not the grid) and
    find both modes themselves: NUTS crosses the valley, emcee jumps with its KDE move."""
    ms, am, cmds, target = _setup(rig, arms, _bimodal_models(rig), 0)
    grid = grid_posterior(ms, am, cmds, target)
    ratio, valley = _two_modes(grid)
    assert 0.2 < ratio < 0.9 and valley < 0.6, (ratio, valley)
    nuts = inf.run_nuts(ms, am, cmds, inf.initial_points(ms, am, cmds, target, 4, 0), seed=0)
    emc = inf.run_emcee(ms, am, cmds, inf.initial_points(ms, am, cmds, target, 32, 1), seed=0,
                        n_steps=1500, burn=300)
    # Tolerances: CheckTolerances() = mean 0.1 mm, covariance 10%, r_hat 1.01, ESS 400.
    check = inf.cross_check(grid, [nuts, emc])
    assert check["passed"], check["failures"]
    assert isinstance(nuts.idata, az.InferenceData)
    assert nuts.idata.posterior["d"].shape == (4, inf.NUTS_SAMPLES, 1, 2)
    assert emc.idata.posterior["d"].shape == (32, 1200, 1, 2)
    for res in (nuts, emc):  # the diagnostics come from az.summary
        assert {"ess_bulk", "ess_tail", "r_hat"} <= set(res.summary.columns)


def test_starting_points_come_from_the_prior_spread_not_the_grid(rig, arms, cond):
    """Starts are centred on the target with the widest arm's own spread (over-dispersed
    twice), land only where the density is not nil, and need no grid to compute."""
    ms, am, cmds, target = _setup(rig, arms, cond, 5)
    init = inf.initial_points(ms, am, cmds, target, 400, seed=3)
    assert init.shape == (400, 1, 2)
    spread = inf.prior_spread(ms, am, target)[0]
    # 400 draws: the mean is within 4 standard errors of the target, plus 0.5 mm because the
    # density cut may trim one side's far tail; and the starts are wider than the posterior.
    sd = np.sqrt(np.diag(spread)) * inf.INIT_OVERDISPERSION
    assert np.all(np.abs(init[:, 0].mean(0) - target[0]) < 4 * sd / np.sqrt(400) + 0.5)
    grid = grid_posterior(ms, am, cmds, target)
    assert np.all(np.diag(np.cov(init[:, 0].T)) > np.diag(grid.cov[0]))
    lp = np.asarray(inf.linked_log_density(ms, am)(init[:, 0], [jnp.asarray(c) for c in cmds]))
    assert np.all(lp >= lp.max() - inf.INIT_LOG_DENSITY_DROP)


def _far_bimodal_models(rig):
    """Like :func:`_bimodal_models` with the top arm's clusters 8 mrad apart and tighter: two
    modes (the smaller about a quarter of the larger) with a valley no NUTS trajectory or
    emcee move crosses (density 1e-8 of the smaller peak)."""
    spec = discover_models(names=["cond"])[0]
    rng = np.random.default_rng(1)

    def fit(arm, x, bw):
        u, _ = rig.rows(arm, "train")
        c = ConditionalKDE.fit(x, u, "kernel", bandwidth=[*bw, 1e4, 1e4])
        return FittedNoiseModel(spec, x, u, conditional=c)

    two = np.concatenate([rng.normal(0, 2e-4, (10, 2)),
                          rng.normal(0, 2e-4, (6, 2)) + [8e-3, 0.0]])
    return {"top": fit("top", two, [6e-4, 6e-4]),
            "bottom": fit("bottom", rng.normal(0, 1.2e-2, (16, 2)), [8e-3, 8e-3])}


def test_cross_check_fails_when_the_samplers_miss_a_mode(rig, arms):
    """Samplers that never reach the second mode agree with each other (r_hat passes) but not
    with the grid: the check fails on their mean and covariance. Started from grid draws, as
    they were, the chains were handed both modes and such a miss could not show."""
    ms, am, cmds, target = _setup(rig, arms, _far_bimodal_models(rig), 0)
    grid = grid_posterior(ms, am, cmds, target)
    ratio, valley = _two_modes(grid)
    assert ratio > 0.2 and valley < 1e-6, (ratio, valley)
    peak = grid.points()[0, np.argmax(grid.prob[0])]
    rng = np.random.default_rng(2)
    one_mode = peak + rng.normal(0, 0.05, (32, 1, 2))  # every start in the denser mode
    nuts = inf.run_nuts(ms, am, cmds, one_mode[:4], seed=0)
    emc = inf.run_emcee(ms, am, cmds, one_mode, seed=0, n_steps=1000, burn=200)
    for res in (nuts, emc):  # the miss is invisible to the convergence diagnostics
        assert res.r_hat <= 1.01 and res.ess_bulk >= 400, (res.name, res.r_hat, res.ess_bulk)
    check = inf.cross_check(grid, [nuts, emc])
    assert not check["passed"]
    text = "\n".join(check["failures"])
    for name in ("nuts", "emcee"):
        assert f"{name}: mean" in text and f"{name}: covariance differs" in text, text
    # Started as `sample` starts them (around the target), NUTS's chains split between the
    # modes in no particular proportion: the moments fail as well as r_hat. Started at grid
    # draws, the chains were dealt the modes by their mass, so the pooled moments matched the
    # grid and only r_hat was left to notice.
    own = inf.run_nuts(ms, am, cmds, inf.initial_points(ms, am, cmds, target, 4, 0), seed=0)
    text = "\n".join(inf.cross_check(grid, [own])["failures"])
    assert "nuts: mean" in text and "nuts: r_hat" in text, text
    dealt = inf.run_nuts(ms, am, cmds, grid.sample(0, 4), seed=0)
    text = "\n".join(inf.cross_check(grid, [dealt])["failures"])
    assert "nuts: r_hat" in text and "nuts: mean" not in text, text


def test_nuts_on_the_paper_histogram_cond_passes_the_check(rig, arms, small_models):
    """The table is piecewise constant and zero outside its bins: NUTS moves by the guide's
    gradient and weighs by the exact table, so it must agree with the grid (same tolerances:
    mean 0.1 mm, covariance 10%, r_hat 1.01, ESS 400)."""
    ms, am, cmds, target = _setup(rig, arms, small_models["HIST"], 3)
    grid = grid_posterior(ms, am, cmds, target)
    # Acceptance 0.65 (the default is 0.8) takes steps long enough to cross the table's wall
    # at this target, so the run below meets the support's edge, as the check must survive.
    nuts = inf.run_nuts(ms, am, cmds, inf.initial_points(ms, am, cmds, target, 4, 0), seed=0,
                        target_accept_prob=0.65)
    check = inf.cross_check(grid, [nuts])
    assert check["passed"], check["failures"]
    # It really does meet the support's edge: divergences there are expected.
    assert int(nuts.idata.sample_stats["diverging"].values.sum()) > 0


def test_cross_check_reports_disagreement_with_figures(rig, arms, small_models):
    ms, am, cmds, target = _setup(rig, arms, small_models["CORR"], 2)
    grid = grid_posterior(ms, am, cmds, target)
    rng = np.random.default_rng(7)
    draws = rng.multivariate_normal(grid.mean[0] + [0.3, 0.0], 1.5 * grid.cov[0], (4, 50))
    idata = az.from_dict(posterior={"d": draws[:, :, None, :]}, dims={"d": ["target", "xy"]})
    fake = inf.SamplerResult("fake", idata, 1.0, az.summary(idata, kind="diagnostics"))
    check = inf.cross_check(grid, [fake])
    assert not check["passed"]
    text = "\n".join(check["failures"])
    assert "fake: mean" in text and "(> 0.1 mm)" in text
    assert "covariance differs from the grid's by" in text
    assert "bulk ESS" in text  # 200 draws cannot reach 400
    # A grid box that cuts the posterior off is a failure of the reference itself.
    cut = dataclasses.replace(grid, edge_mass=np.array([1e-3]))
    assert "truncates the posterior" in "\n".join(inf.cross_check(cut, [])["failures"])


# ------------------------------------------------------------------------------ command line


def test_sample_command_writes_the_documented_json(tmp_path, capsys):
    out = tmp_path / "sample.json"
    rc = main(["sample", "--config", "top+bottom", "--target", "140", "220", "--json",
               str(out)])
    printed = capsys.readouterr().out
    assert rc == 0, printed
    doc = json.loads(out.read_text())
    assert doc["target"] == [140.0, 220.0] and doc["config"] == "top+bottom"
    assert doc["model"] == "cond"
    assert set(doc["samplers"]) == {"grid", "nuts", "emcee"}
    for key in ("mean", "cov", "seconds"):
        assert key in doc["samplers"]["grid"]
    for name in ("nuts", "emcee"):
        s = doc["samplers"][name]
        for key in ("mean", "cov", "ess_bulk", "r_hat", "seconds", "ess_per_s"):
            assert key in s, (name, key)
        assert np.linalg.norm(np.subtract(s["mean"], doc["samplers"]["grid"]["mean"])) < 0.1
    assert doc["check"]["passed"] is True and doc["check"]["failures"] == []
    assert "check PASSED" in printed and "ess_bulk" in printed
    assert doc["samplers"]["nuts"]["divergences"] == 0
    # Per second of sampling (compilation excluded) NUTS is the more efficient sampler.
    assert doc["samplers"]["nuts"]["ess_per_s"] > doc["samplers"]["emcee"]["ess_per_s"]


def test_sample_command_exits_1_when_the_check_fails(monkeypatch, capsys):
    def failing(*args, **kwargs):
        doc = {"check": {"passed": False, "failures": ["nuts: r_hat 1.2000 > 1.01"]}}
        return inf.SampleReport(doc, None, {})

    monkeypatch.setattr(inf, "sample_linked", failing)
    monkeypatch.setattr(tables, "format_sample", lambda r: "check FAILED")
    assert main(["sample", "--target", "140", "220", "--json", "-"]) == 1


@pytest.mark.parametrize("argv, message", [
    (["--config", "top+elbow"], "no arm 'elbow'"),
    (["--model", "nope"], "no model named 'nope'"),
])
def test_sample_command_usage_errors_exit_2(argv, message, capsys):
    rc = main(["sample", "--target", "140", "220", "--sampler", "grid", *argv])
    assert rc == 2
    assert message in capsys.readouterr().err


@pytest.mark.parametrize("target, arm, distance", [
    (("400", "220"), "bottom", "442.6"),
    (("1000", "1000"), "top", "1128.8"),
])
def test_sample_refuses_an_unreachable_target_before_fitting_anything(
        target, arm, distance, capsys, monkeypatch):
    """One line naming the target, the arm and its reach; exit 2; no model fitted (so
    nothing compiled or sampled)."""
    import bayesrob.errors.noise_models

    def no_fit(*args, **kwargs):
        raise AssertionError("a model was fitted for an unreachable target")

    monkeypatch.setattr(bayesrob.errors.noise_models, "fit_noise_models", no_fit)
    for sampler in ("grid", "all"):
        assert main(["sample", "--target", *target, "--sampler", sampler]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1, err
        assert (f"target ({target[0]}, {target[1]}) is out of reach of arm {arm!r}: it is "
                f"{distance} mm from the arm's base") in err
        assert "which reaches" in err and " to " in err


def test_sample_refuses_a_target_beyond_the_pulse_limits(capsys):
    """In reach (405 mm of the bottom arm's 407.5) but only with its elbow past its limit."""
    assert main(["sample", "--target", "368", "200", "--sampler", "grid"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert ("target (368, 200) is outside the workspace of arm 'bottom': aiming at it needs "
            "pulse 2 = ") in err and "outside its pulse_limits [600, 2400]" in err


def test_sample_fails_when_the_grid_box_truncates_the_posterior(tmp_path, capsys):
    """A model so wide that the +-30 mm box holds only part of the posterior: the reference is
    wrong, so every sampler choice exits 1, --sampler grid included, and no sampler runs."""
    models = tmp_path / "models"
    models.mkdir()
    (models / "wide.toml").write_text('name = "wide"\nfamily = "IND"\nbandwidth = 0.2\n'
                                      "jacobian = true\n")
    for sampler in ("grid", "nuts", "all"):
        out = tmp_path / f"{sampler}.json"
        rc = main(["sample", "--target", "140", "220", "--model", "wide", "--models-dir",
                   str(models), "--sampler", sampler, "--json", str(out)])
        printed = capsys.readouterr().out
        assert rc == 1, (sampler, printed)
        doc = json.loads(out.read_text())
        assert doc["check"]["passed"] is False and doc["check"]["compared"] == []
        assert set(doc["samplers"]) == {"grid"}
        assert doc["samplers"]["grid"]["edge_mass"] > 1e-6
        assert "truncates the posterior" in doc["check"]["failures"][0]
        assert "check FAILED" in printed
