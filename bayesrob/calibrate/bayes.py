"""Bayesian calibration (numpyro NUTS): a posterior over the parameters the least squares fits.

Any robot (:func:`calibrate_bayes`, ``calibrate --params ... --method bayes``): the parameter
groups' identifiable columns, sampled in the coordinates the least-squares fit and its
covariance whiten. The paper's planar arms (``calibrate --method bayes``): each arm's eight
parameters under the priors of :class:`Priors`, below.

The model of one arm (rows i = 1..N of its ``train`` set, pulses u_i, observed end points d_i):

    z ~ Normal(0, 1)^8                          standardised parameters, in PARAM_NAMES order
    params = nominal + scale * z                 nominal: the arm's values in rig.toml
    noise_sd ~ HalfNormal(noise_scale_mm)        measurement noise, sd per axis (mm)
    d_i ~ Normal(f(g(u_i; params); params), noise_sd)   independently in x and y

so each parameter has the prior Normal(nominal, scale) with (class :class:`Priors`)

    base bx, by    5 mm              a person's tape-measure error (the simulator uses 2 mm)
    links l1, l2   5 mm              (simulator: 1.5 mm)
    gains a1, a2   5 % of nominal    (simulator: 2 %)
    offsets b1, b2 0.05 rad          (simulator: 0.02 rad)
    noise_sd       HalfNormal(5 mm)  95 % of its mass below 10 mm: room for unmodelled
                                     effects (sag, backlash) as well as the instrument

The scales are about 2.5 times the measuring errors the simulator assumes: the prior should
contain the truth comfortably without pretending to know the person's tools.

NUTS (numpyro) samples z and noise_sd. In z the prior is isotropic, but the data tie each gain
to its offset (they trade off at the mid-range pulse) and the base to the links, so the
sampler adapts a dense mass matrix; the chains start near the least-squares fit, overdispersed
by about one standard error. One sampler is compiled per (settings, number of rows) and reused
across arms, chains and data sets, which keeps an arm's fit to about a second once compiled
and makes simulation-based calibration (:func:`sbc`) affordable.

From the posterior:
- :func:`calibrate_arm_bayes` gives an :class:`~bayesrob.calibrate.arms.ArmCalibration` like the
  point-estimate methods (params = posterior mean, params_se = posterior sd, the errors of the
  posterior-mean prediction) plus a ``posterior`` block: R-hat, bulk ESS, the noise level and the
  posterior predictive coverage of the validation end points.
- :func:`predict_end_points` returns draws of the end point for given commands, mixing over the
  posterior of every arm involved (parameter uncertainty) and the noise; for arms linked at
  their end points, the product of the arms' Gaussian likelihoods (the same rule
  :mod:`bayesrob.predict.grid` uses for the joint-error models).
- :func:`predicted_accuracy` summarises those draws as the expected mean error of a setup with
  a 95 % interval, next to the error the noise alone would give.
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass, field, replace

import jax
import jax.numpy as jnp
import numpy as np
import scipy.stats

from bayesrob import robot as kin
from bayesrob.calibrate.arms import (
    ArmCalibration,
    calibrate_arm,
    calibrate_arms,
    mean_ci95,
    observed_errors,
    predicted_points,
)
from bayesrob.calibrate.least_squares import (
    Calibration,
    calibrate,
    marker_errors,
    parameter_covariance,
    residual_function,
    set_rows,
)
from bayesrob.data.rig import ArmSpec, Rig

N_PARAMS = len(kin.PARAM_NAMES)
COVERAGE_LEVELS = (0.5, 0.9, 0.95)


# ----------------------------------------------------------------------------- the model


@dataclass(frozen=True)
class Priors:
    """Prior scales around the nominal values (sd of the Normal priors, HalfNormal for noise)."""

    base_mm: float = 5.0
    links_mm: float = 5.0
    gain_rel: float = 0.05  # fraction of the nominal gain
    offset_rad: float = 0.05
    noise_mm: float = 5.0  # scale of the HalfNormal prior on the measurement-noise sd

    def scales(self, nominal: np.ndarray) -> np.ndarray:
        """Prior sd of the eight parameters (PARAM_NAMES order) for the given nominal vector."""
        nominal = np.asarray(nominal, float)
        return np.array([self.base_mm, self.base_mm, self.links_mm, self.links_mm,
                         self.gain_rel * abs(nominal[4]), self.gain_rel * abs(nominal[5]),
                         self.offset_rad, self.offset_rad])

    def as_dict(self) -> dict[str, float]:
        return {"base_mm": self.base_mm, "links_mm": self.links_mm, "gain_rel": self.gain_rel,
                "offset_rad": self.offset_rad, "noise_halfnormal_mm": self.noise_mm}


@dataclass(frozen=True)
class SamplerSettings:
    """NUTS settings; the defaults fit one 16-row arm in about a second once compiled."""

    num_warmup: int = 500
    num_samples: int = 500
    num_chains: int = 2
    dense_mass: bool = True
    target_accept_prob: float = 0.85
    max_tree_depth: int = 10


def arm_model(u, d, nominal, scale, noise_scale):
    """The numpyro model of one arm; ``d=None`` samples end points from the prior predictive."""
    import numpyro
    import numpyro.distributions as dist

    z = numpyro.sample("z", dist.Normal(jnp.zeros(N_PARAMS), 1.0).to_event(1))
    v = nominal + scale * z
    noise_sd = numpyro.sample("noise_sd", dist.HalfNormal(noise_scale))
    mu = kin.forward_u(kin.ArmParams.from_vector(v), u)
    numpyro.sample("d", dist.Normal(mu, noise_sd).to_event(2), obs=d)


def _potential_fn_gen(*model_args):
    from numpyro.infer.util import potential_energy

    return functools.partial(potential_energy, arm_model, model_args, {})


@functools.partial(jax.jit, static_argnames=("settings",))
def _nuts_chain(rng_key, init_params, model_args, settings: SamplerSettings):
    """One NUTS chain, warm-up and sampling, as a single compiled function.

    numpyro's ``MCMC.run`` re-traces and recompiles its sampling loop on every call (about
    10 s on this model); this uses the same NUTS kernel through numpyro's functional
    ``hmc`` interface with the data as arguments, so it compiles once per settings and
    number of rows and is reused across arms, chains and simulated data sets.
    """
    from numpyro.infer.hmc import hmc

    init_kernel, sample_kernel = hmc(potential_fn_gen=_potential_fn_gen, algo="NUTS")
    state = init_kernel(init_params, settings.num_warmup, dense_mass=settings.dense_mass,
                        target_accept_prob=settings.target_accept_prob,
                        max_tree_depth=settings.max_tree_depth, model_args=model_args,
                        rng_key=rng_key)

    def step(s, _):
        s = sample_kernel(s, model_args=model_args)
        return s, (s.z, s.diverging, s.num_steps)

    _, out = jax.lax.scan(step, state, None, length=settings.num_warmup + settings.num_samples)
    return jax.tree.map(lambda x: x[settings.num_warmup:], out)


# ----------------------------------------------------------------------------- posterior


@dataclass
class ArmPosterior:
    """Posterior draws of one arm's parameters and noise level, with the sampler's diagnostics."""

    name: str
    nominal: np.ndarray  # (8,)
    scale: np.ndarray  # (8,) prior sd
    z: np.ndarray  # (chains, draws, 8) standardised draws
    noise_sd: np.ndarray  # (chains, draws) mm
    elbow: int = 1
    pulse_limits: tuple = ((500.0, 2500.0),) * 2
    diagnostics: dict = field(default_factory=dict)
    seconds: float = 0.0  # sampling time of all chains
    compile_seconds: float = 0.0  # compiling the sampler, if this arm was the first to need it

    @property
    def draws(self) -> np.ndarray:
        """Parameter draws (chains * draws, 8) in PARAM_NAMES order."""
        return (self.nominal + self.scale * self.z).reshape(-1, N_PARAMS)

    @property
    def noise_draws(self) -> np.ndarray:
        return self.noise_sd.reshape(-1)

    @property
    def mean(self) -> np.ndarray:
        return self.draws.mean(axis=0)

    @property
    def sd(self) -> np.ndarray:
        return self.draws.std(axis=0, ddof=1)

    @property
    def arm(self) -> kin.Arm:
        """The arm at the posterior-mean parameters."""
        return kin.Arm(self.name, kin.ArmParams.from_vector(jnp.asarray(self.mean)), self.elbow,
                       self.pulse_limits)

    def forward_draws(self, u: np.ndarray) -> np.ndarray:
        """f(g(u)) under every draw: (draws, T, 2) for commands u (T, 2)."""
        return np.asarray(_forward_draws(jnp.asarray(self.draws), jnp.asarray(u, float)))

    def predictive(self, u: np.ndarray, seed: int = 0) -> np.ndarray:
        """Posterior predictive end points (draws, T, 2): parameter uncertainty plus noise."""
        mu = self.forward_draws(u)
        eps = np.random.default_rng(seed).standard_normal(mu.shape)
        return mu + self.noise_draws[:, None, None] * eps


@jax.jit
def _forward_draws(draws: jax.Array, u: jax.Array) -> jax.Array:
    return jax.vmap(lambda v: kin.forward_u(kin.ArmParams.from_vector(v), u))(draws)


def _initial_values(spec: ArmSpec, u: np.ndarray, d: np.ndarray, scale: np.ndarray,
                    nominal: np.ndarray, chains: int, rng: np.random.Generator) -> dict:
    """Unconstrained start points near the least-squares fit, one standard error apart."""
    try:
        ls = calibrate_arm(spec, u, d, "least-squares")
        v = np.asarray(ls.arm.params.to_vector())
        se = np.nan_to_num(np.asarray(ls.params_se), nan=0.0)
        resid = np.asarray(ls.arm.forward_u(jnp.asarray(u))) - d
        sigma = float(np.sqrt(np.mean(resid**2) * d.size / max(d.size - N_PARAMS, 1)))
    except (ValueError, np.linalg.LinAlgError):
        v, se, sigma = nominal, scale * 0.1, 1.0
    z0 = (v - nominal) / scale
    if not np.all(np.isfinite(z0)) or np.max(np.abs(z0)) > 20:
        z0, se = np.zeros(N_PARAMS), scale * 0.1  # a wild fit: start at the prior instead
    se_z = np.minimum(se / scale, 1.0)
    z = z0[None] + se_z[None] * rng.standard_normal((chains, N_PARAMS))
    log_sigma = np.log(max(sigma, 1e-3)) + 0.15 * rng.standard_normal(chains)
    return {"z": jnp.asarray(z), "noise_sd": jnp.asarray(log_sigma)}


_COMPILED: dict = {}
_COMPILE_SECONDS: dict = {}


def _compiled_chain(key, init, args, settings: SamplerSettings):
    """The compiled chain for these settings and data shapes (compiled ahead of time, timed)."""
    sig = (settings, tuple(a.shape for a in args))
    if sig not in _COMPILED:
        t0 = time.perf_counter()
        _COMPILED[sig] = _nuts_chain.lower(key, init, args, settings=settings).compile()
        _COMPILE_SECONDS[sig] = time.perf_counter() - t0
    return _COMPILED[sig]


def _run_chains(spec: ArmSpec, u: np.ndarray, d: np.ndarray, priors: Priors,
                settings: SamplerSettings, seed: int) -> tuple[np.ndarray, ...]:
    """Run the chains one after another: standardised draws (C, S, 8), noise (C, S), etc."""
    from numpyro.distributions import biject_to, constraints

    nominal = np.asarray(kin.ArmParams.from_spec(spec).to_vector())
    scale = priors.scales(nominal)
    rng = np.random.default_rng(seed)
    init = _initial_values(spec, u, d, scale, nominal, settings.num_chains, rng)
    args = (jnp.asarray(u, float), jnp.asarray(d, float), jnp.asarray(nominal),
            jnp.asarray(scale), jnp.asarray(float(priors.noise_mm)))
    keys = jax.random.split(jax.random.PRNGKey(seed), settings.num_chains)
    inits = [{k: v[c] for k, v in init.items()} for c in range(settings.num_chains)]
    chain = _compiled_chain(keys[0], inits[0], args, settings)
    outs = [chain(keys[c], inits[c], args) for c in range(settings.num_chains)]
    z = np.stack([np.asarray(o[0]["z"]) for o in outs])
    noise = np.stack([np.asarray(biject_to(constraints.positive)(o[0]["noise_sd"]))
                      for o in outs])
    diverging = np.stack([np.asarray(o[1]) for o in outs])
    steps = np.stack([np.asarray(o[2]) for o in outs])
    return nominal, scale, z, noise, diverging, steps


def _diagnostics(z: np.ndarray, noise: np.ndarray, diverging: np.ndarray,
                 steps: np.ndarray) -> dict:
    """R-hat and effective sample sizes from arviz, over z and the noise sd."""
    import arviz as az

    idata = az.from_dict(posterior={"z": z, "noise_sd": noise},
                         sample_stats={"diverging": diverging})
    summ = az.summary(idata, var_names=["z", "noise_sd"], kind="diagnostics")
    return {"r_hat_max": float(summ["r_hat"].max()),
            "ess_bulk_min": float(summ["ess_bulk"].min()),
            "ess_tail_min": float(summ["ess_tail"].min()),
            "divergences": int(diverging.sum()),
            "mean_leapfrog_steps": float(steps.mean())}


def sample_arm_posterior(spec: ArmSpec, u: np.ndarray, d: np.ndarray, priors: Priors = Priors(),
                         settings: SamplerSettings = SamplerSettings(), seed: int = 0,
                         diagnostics: bool = True) -> ArmPosterior:
    """NUTS posterior of one arm's parameters given its rows (u, d: (N, 2) each).

    The first call per settings and number of rows compiles the sampler (several seconds);
    later calls reuse it.
    """
    u = np.asarray(u, float)
    d = np.asarray(d, float)
    t0, c0 = time.perf_counter(), sum(_COMPILE_SECONDS.values())
    nominal, scale, z, noise, diverging, steps = _run_chains(spec, u, d, priors, settings, seed)
    compile_seconds = sum(_COMPILE_SECONDS.values()) - c0
    seconds = time.perf_counter() - t0 - compile_seconds
    diag = _diagnostics(z, noise, diverging, steps) if diagnostics else {
        "divergences": int(diverging.sum())}
    return ArmPosterior(name=spec.name, nominal=nominal, scale=scale, z=z, noise_sd=noise,
                        elbow=spec.elbow, pulse_limits=spec.pulse_limits, diagnostics=diag,
                        seconds=seconds, compile_seconds=compile_seconds)


# ----------------------------------------------------------------------------- calibration


@dataclass
class BayesArmCalibration(ArmCalibration):
    """An :class:`ArmCalibration` that also carries the posterior draws."""

    posterior: ArmPosterior | None = None


def predictive_coverage(posterior: ArmPosterior, u: np.ndarray, d: np.ndarray,
                        levels=COVERAGE_LEVELS, seed: int = 0) -> dict[str, float]:
    """Fraction of observed points inside the central posterior predictive region of each level.

    The region of a row is bounded by the Mahalanobis distance (under the predictive draws'
    own mean and covariance) that the given fraction of the draws falls within, so it needs no
    Gaussian assumption about the predictive distribution itself.
    """
    draws = posterior.predictive(u, seed)  # (S, T, 2)
    mean = draws.mean(axis=0)
    dev = draws - mean
    cov = np.einsum("sti,stj->tij", dev, dev) / (draws.shape[0] - 1)
    prec = np.linalg.inv(cov)
    m_draws = np.einsum("sti,tij,stj->st", dev, prec, dev)
    obs = np.asarray(d, float) - mean
    m_obs = np.einsum("ti,tij,tj->t", obs, prec, obs)
    depth = np.mean(m_draws <= m_obs[None], axis=0)  # predictive quantile of each observation
    return {f"p{round(q * 100)}": float(np.mean(depth <= q)) for q in levels}


def calibrate_arm_bayes(spec: ArmSpec, u: np.ndarray, d: np.ndarray,
                        u_val: np.ndarray | None = None, d_val: np.ndarray | None = None,
                        priors: Priors = Priors(), settings: SamplerSettings = SamplerSettings(),
                        seed: int = 0) -> BayesArmCalibration:
    """Bayesian calibration of one arm: posterior mean and sd, errors, diagnostics, coverage."""
    u = np.asarray(u, float)
    d = np.asarray(d, float)
    post = sample_arm_posterior(spec, u, d, priors, settings, seed)
    mean_params = kin.ArmParams.from_vector(jnp.asarray(post.mean))
    post.elbow = kin.choose_elbow(mean_params, u, d, spec.elbow)

    def error(uu, dd):
        pred = post.forward_draws(uu).mean(axis=0)  # the posterior-mean prediction
        return float(np.mean(np.linalg.norm(pred - dd, axis=-1)))

    has_val = u_val is not None and len(u_val) > 0
    info = {
        **post.diagnostics,
        "noise_sd_mm": {"mean": float(post.noise_draws.mean()),
                        "sd": float(post.noise_draws.std(ddof=1))},
        "draws": int(post.draws.shape[0]),
        "chains": int(post.z.shape[0]),
        "seconds": round(post.seconds, 3),
        "compile_seconds": round(post.compile_seconds, 3),
        "priors": priors.as_dict(),
        "validation_coverage": (predictive_coverage(post, u_val, d_val, seed=seed)
                                if has_val else None),
    }
    return BayesArmCalibration(
        arm=post.arm,
        method="bayes",
        params_se=post.sd,
        train_error_mm=error(u, d),
        validation_error_mm=error(np.asarray(u_val, float), np.asarray(d_val, float))
        if has_val else None,
        n_train=len(u),
        iterations=settings.num_warmup + settings.num_samples,
        extra={"posterior": info},
        posterior=post,
    )


def calibrate_arms_bayes(rig: Rig, priors: Priors = Priors(),
                         settings: SamplerSettings = SamplerSettings(), seed: int = 0
                         ) -> dict[str, BayesArmCalibration]:
    """Bayesian calibration of every arm of a rig on its ``train`` rows."""
    return calibrate_arms(rig, fit_arm=lambda spec, u, d, uv, dv: calibrate_arm_bayes(
        spec, u, d, uv, dv, priors, settings, seed))


# ----------------------------------------------------------------------------- prediction


def predict_end_points(posteriors: dict[str, ArmPosterior], commands: dict[str, np.ndarray],
                       noise: bool = True, seed: int = 0) -> np.ndarray:
    """Draws (S, T, 2) of the end point of a setup for commands (T, 2) per arm.

    One arm: f(g(u)) under each posterior draw, plus that draw's Gaussian noise if ``noise``.
    Several arms linked at their end points: each arm's draw says the end point is
    Normal(f_a(g_a(u_a)), sigma_a^2 I); their product (the rule :mod:`bayesrob.predict.grid`
    applies to the joint-error likelihoods) is Normal with the precision-weighted mean and
    variance 1 / sum_a sigma_a^-2. The arms' posteriors are independent, so their draws are
    paired by index (S = the fewest draws of any arm).
    """
    names = list(commands)
    n = min(posteriors[a].draws.shape[0] for a in names)
    mus = [posteriors[a].forward_draws(np.asarray(commands[a], float))[:n] for a in names]
    sds = [posteriors[a].noise_draws[:n, None, None] for a in names]
    if len(names) == 1:
        mean, sd = mus[0], sds[0]
    else:
        prec = [1.0 / s**2 for s in sds]
        total = sum(prec)
        mean = sum(p * m for p, m in zip(prec, mus, strict=True)) / total
        sd = 1.0 / np.sqrt(total)
    if not noise:
        return mean
    return mean + sd * np.random.default_rng(seed).standard_normal(mean.shape)


def predicted_accuracy(posteriors: dict[str, ArmPosterior], commands: dict[str, np.ndarray],
                       reference: np.ndarray | None = None, seed: int = 0) -> dict:
    """Predicted mean error of a setup, with the parameter uncertainty propagated.

    The error of a row is the distance from the point the setup is judged against
    (``reference``: e.g. the target for linked arms; default the posterior-mean prediction)
    to where the end point lands, drawn from :func:`predict_end_points`. Returned:
    ``expected_error_mm`` (mean over draws and rows), ``interval95_mm`` (2.5 and 97.5 % points
    of the mean over the rows in one draw: where the setup's observed mean error should fall),
    ``noise_only_error_mm`` (the same with every arm at its posterior-mean parameters, so the
    difference is what parameter uncertainty adds) and ``per_row_mm``.
    """
    draws = predict_end_points(posteriors, commands, noise=True, seed=seed)
    if reference is None:
        reference = predict_end_points(posteriors, commands, noise=False).mean(axis=0)
    reference = np.asarray(reference, float)
    err = np.linalg.norm(draws - reference[None], axis=-1)  # (S, T)
    per_draw = err.mean(axis=1)
    fixed = {a: _at_posterior_mean(p) for a, p in posteriors.items() if a in commands}
    err0 = np.linalg.norm(predict_end_points(fixed, commands, noise=True, seed=seed)
                          - reference[None], axis=-1)
    return {
        "expected_error_mm": float(err.mean()),
        "interval95_mm": [float(q) for q in np.quantile(per_draw, [0.025, 0.975])],
        "noise_only_error_mm": float(err0.mean()),
        "per_row_mm": [float(e) for e in err.mean(axis=0)],
    }


def _at_posterior_mean(post: ArmPosterior) -> ArmPosterior:
    """The same posterior with every parameter draw replaced by the posterior mean."""
    z_mean = (post.mean - post.nominal) / post.scale
    return replace(post, z=np.broadcast_to(z_mean, post.z.shape).copy())


def predicted_accuracy_document(rig: Rig, cal: dict[str, BayesArmCalibration],
                                seed: int = 0) -> dict:
    """Observed vs predicted mean error of every setup (single arms on validation rows,
    linked arms on test rows), in the shape of ``accuracy.json``'s ``setups``."""
    from bayesrob.predict.grid import setup_set, setups

    arms = {n: c.arm for n, c in cal.items()}
    posteriors = {n: c.posterior for n, c in cal.items()}
    out = {}
    for config in setups(rig):
        s = setup_set(config)
        rows = rig.config_rows(config, s)
        pred = predicted_accuracy(posteriors, rows["commands"],
                                  predicted_points(rig, arms, config, s), seed)
        pred.pop("per_row_mm")
        obs = mean_ci95(observed_errors(rig, arms, config, s))
        out[config] = {"set": s, "observed": obs, "predicted": pred}
    return out


def report_extras(rig: Rig, cal: dict[str, BayesArmCalibration]) -> dict:
    """Top-level keys the ``calibrate --method bayes`` report adds to the common ones."""
    return {"predicted_accuracy": predicted_accuracy_document(rig, cal)}


# ----------------------------------------------------------------------------- SBC


def draw_from_prior(spec: ArmSpec, u: np.ndarray, n: int, priors: Priors = Priors(),
                    seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``n`` data sets from the model itself (numpyro's prior predictive of :func:`arm_model`):
    parameters and noise sd from the prior, end points from the Gaussian likelihood at the
    commands u. Returns params (n, 8), noise sd (n,) and end points (n, N, 2)."""
    from numpyro.infer import Predictive

    nominal = np.asarray(kin.ArmParams.from_spec(spec).to_vector())
    scale = priors.scales(nominal)
    sim = Predictive(arm_model, num_samples=n)(
        jax.random.PRNGKey(seed), jnp.asarray(u, float), None, jnp.asarray(nominal),
        jnp.asarray(scale), jnp.asarray(float(priors.noise_mm)))
    return (nominal + scale * np.asarray(sim["z"]), np.asarray(sim["noise_sd"]),
            np.asarray(sim["d"]))


@dataclass
class SBCResult:
    """Simulation-based calibration: true values and thinned posterior draws per data set.

    Quantities (last axis): the eight parameters in PARAM_NAMES order, then the noise sd.
    """

    truth: np.ndarray  # (R, 9)
    draws: np.ndarray  # (R, L, 9)
    divergences: np.ndarray  # (R,)
    seconds: float

    names = (*kin.PARAM_NAMES, "noise_sd")

    @property
    def n_draws(self) -> int:
        return self.draws.shape[1]

    @property
    def ranks(self) -> np.ndarray:
        """(R, 9) ranks in 0..L: how many of the L draws lie below the true value."""
        return np.sum(self.draws < self.truth[:, None, :], axis=1)

    def uniformity(self, bins: int, ranks: np.ndarray | None = None) -> dict:
        """Chi-square test of uniform ranks per quantity, Bonferroni-combined over the nine.

        ``bins`` must divide L + 1 so every bin holds the same number of rank values.
        """
        ranks = self.ranks if ranks is None else ranks
        values = self.n_draws + 1
        if values % bins:
            raise ValueError(f"{bins} bins do not divide the {values} possible ranks")
        counts = np.stack([np.bincount(r * bins // values, minlength=bins) for r in ranks.T])
        chi2, p = scipy.stats.chisquare(counts, axis=1)
        return {"chi2": chi2, "p": p, "dof": bins - 1, "counts": counts,
                "p_min": float(p.min()), "p_bonferroni": float(min(1.0, p.min() * len(p)))}


def sbc(spec: ArmSpec, u: np.ndarray, n_datasets: int, n_draws: int = 49,
        priors: Priors = Priors(), settings: SamplerSettings = SamplerSettings(num_chains=1),
        seed: int = 0) -> SBCResult:
    """Simulation-based calibration (Talts et al. 2018) of the model at an arm's commands u.

    Each data set is drawn from the model's own prior and likelihood (:func:`draw_from_prior`),
    not from the physical simulator: only then are the ranks of the true values among the
    posterior draws exactly uniform when the sampler is right. The draws of each chain are
    thinned evenly to ``n_draws`` to make them nearly independent.
    """
    u = np.asarray(u, float)
    rng = np.random.default_rng(seed)
    total = settings.num_chains * settings.num_samples
    if n_draws > total:
        raise ValueError(f"n_draws {n_draws} exceeds the {total} posterior draws")
    keep = np.linspace(0, total - 1, n_draws).round().astype(int)
    params, noise_sd, data = draw_from_prior(spec, u, n_datasets, priors,
                                             seed=int(rng.integers(2**31)))
    draws, divs = [], []
    t0 = time.perf_counter()
    for d in data:
        nominal, scale, z, noise, diverging, _ = _run_chains(
            spec, u, d, priors, settings, seed=int(rng.integers(2**31)))
        flat = np.concatenate([(nominal + scale * z).reshape(-1, N_PARAMS),
                               noise.reshape(-1, 1)], axis=1)
        draws.append(flat[keep])
        divs.append(int(diverging.sum()))
    return SBCResult(np.column_stack([params, noise_sd]), np.array(draws), np.array(divs),
                     time.perf_counter() - t0)


# ----------------------------------------------------------------------------- any robot


@dataclass(frozen=True)
class GroupPriors:
    """Prior sd of each calibration group around the rig's nominal values (mm, rad)."""

    instrument_mm: float = 200.0  # a rough placement of the robot in the measuring frame
    instrument_rad: float = 0.2
    marker_mm: float = 50.0
    offset_rad: float = 0.05
    origin_mm: float = 5.0  # a drawing's tolerance on a joint origin
    origin_rad: float = 0.02
    gain_rel: float = 0.05
    noise_scale_mm: float = 20.0  # HalfNormal: room for unmodelled compliance as well
    # the encoder sinusoids, in their typical sizes (1e-3 rad): as weak as the planar effects'
    # penalty, it only decides what the rows cannot see (the sag groups are not sampled)
    effect_sizes: float = 10.0

    def sd(self, layout: kin.ParamLayout) -> np.ndarray:
        out = np.empty(len(layout.params))
        for i, p in enumerate(layout.params):
            rot = p.name.rsplit(".", 1)[-1] in ("rx", "ry", "rz")
            if ".instrument." in p.name:
                out[i] = self.instrument_rad if rot else self.instrument_mm
            elif ".marker." in p.name:
                out[i] = self.marker_mm
            elif p.group == "offsets":
                out[i] = self.offset_rad
            elif p.group == "geometric":
                out[i] = self.origin_rad if rot else self.origin_mm
            elif p.group in kin.OPTIONAL_GROUPS:
                out[i] = self.effect_sizes * layout.scales[i]
            else:
                out[i] = self.gain_rel * abs(p.nominal)
        return out


def calibrate_bayes(rig: Rig, groups: tuple[str, ...] = kin.GROUPS,
                    priors: GroupPriors = GroupPriors(), num_warmup: int = 400,
                    num_samples: int = 500, num_chains: int = 2, seed: int = 0,
                    progress=None) -> Calibration:
    """NUTS posterior of a chain rig's identifiable parameters (and the noise sd).

    The model: x_free ~ Normal(nominal, GroupPriors), noise_sd ~ HalfNormal, every measured
    coordinate ~ Normal(marker point, noise_sd); parameters the rank analysis fixes stay at
    nominal. NUTS runs in coordinates whitened by the least-squares fit (x = x_ls + L z, L the
    Cholesky factor of its covariance): there the posterior is close to a standard normal, so
    the trajectories are short however correlated the ~100 parameters are. Returns a
    :class:`~bayesrob.calibrate.least_squares.Calibration` whose x is the posterior mean and se the
    posterior sd, with R-hat, bulk ESS and the noise level from arviz.
    """
    import arviz as az
    import numpyro
    import numpyro.distributions as dist
    from numpyro.infer import MCMC, NUTS, init_to_value

    sags = [g for g in groups if g in kin.SAG_GROUPS]
    if sags:
        # masses times compliances: in the least-squares fit's whitened coordinates the
        # posterior is far from Gaussian, and NUTS did not mix there (simulated compliant
        # arm6, frames,geometric,compliance: r_hat 2.7, bulk ESS 2 after 5 minutes)
        raise ValueError(f"--method bayes does not sample {', '.join(sags)} (joints giving "
                         "way under gravity); calibrate them with --method least-squares")
    t0 = time.perf_counter()
    ls = calibrate(rig, groups, progress=progress)
    robot, free = ls.robot, ls.ident.free
    full_res, *_ = residual_function(robot, set_rows(rig, robot, "train"))
    r = np.asarray(full_res(jnp.asarray(ls.x)))
    s2 = float(r @ r) / max(r.size - int(free.sum()), 1)
    chol = np.linalg.cholesky(parameter_covariance(rig, ls)[np.ix_(free, free)])
    idx = jnp.asarray(np.flatnonzero(free))
    x_ls = jnp.asarray(ls.x)
    nominal = jnp.asarray(robot.layout.nominal[free])
    prior_sd = jnp.asarray(priors.sd(robot.layout)[free])
    chol_j = jnp.asarray(chol)
    k = int(free.sum())

    def model():
        z = numpyro.sample("z", dist.ImproperUniform(dist.constraints.real_vector, (), (k,)))
        x_free = x_ls[idx] + chol_j @ z
        numpyro.factor("prior", dist.Normal(nominal, prior_sd).log_prob(x_free).sum())
        noise = numpyro.sample("noise_sd", dist.HalfNormal(priors.noise_scale_mm))
        res = full_res(x_ls.at[idx].set(x_free))
        numpyro.factor("likelihood", dist.Normal(0.0, noise).log_prob(res).sum())

    if progress:
        progress(f"NUTS over {k} parameters")
    kernel = NUTS(model, init_strategy=init_to_value(
        values={"z": jnp.zeros(k), "noise_sd": jnp.sqrt(s2)}), max_tree_depth=6)
    mcmc = MCMC(kernel, num_warmup=num_warmup, num_samples=num_samples,
                num_chains=num_chains, chain_method="sequential", progress_bar=False)
    mcmc.run(jax.random.PRNGKey(seed))
    z = np.asarray(mcmc.get_samples()["z"])
    draws = np.asarray(ls.x[free])[None] + z @ chol.T
    x = ls.x.copy()
    x[free] = draws.mean(axis=0)
    se = np.full(len(x), np.nan)
    se[free] = draws.std(axis=0, ddof=1)
    summary = az.summary(az.from_numpyro(mcmc), var_names=["z", "noise_sd"])
    extra = {"posterior": {
        "r_hat_max": float(summary["r_hat"].max()),
        "ess_bulk_min": float(summary["ess_bulk"].min()),
        "noise_sd_mm": float(np.asarray(mcmc.get_samples()["noise_sd"]).mean()),
        "draws": int(draws.shape[0]), "chains": num_chains,
        "divergences": int(np.asarray(mcmc.get_extra_fields()["diverging"]).sum()),
        "least_squares_validation_mean_mm": ls.errors.get("validation", {}).get(
            "all", {}).get("mean_mm")}}
    full = np.repeat(ls.x[None], draws.shape[0], axis=0)
    full[:, free] = draws
    return Calibration(robot, x, ls.groups, ls.ident, se, marker_errors(rig, robot, x),
                       ls.nfev, time.perf_counter() - t0, method="bayes", extra=extra,
                       draws=full)
