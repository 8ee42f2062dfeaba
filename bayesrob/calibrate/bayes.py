"""Bayesian calibration (numpyro NUTS): the posterior of the parameters the least squares fits.

One model (:func:`calibration_model`) for every robot: Normal priors around nominal by group
(:class:`Priors`; docs/bayesian-calibration.md gives their reasons), a HalfNormal noise sd,
every measured coordinate Normal about the marker point. A rig's groups
(:func:`calibrate_bayes`) sample the columns the rank analysis keeps; a planar arm
(:func:`calibrate_arms_bayes`) the eight columns of its 2-joint chain. NUTS samples in
coordinates whitened at the least-squares fit by its Laplace approximation, where the
posterior is close to a standard normal however correlated the parameters, so trajectories
are short; one compiled program per robot structure, settings and data shapes.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import scipy.stats

from bayesrob import robot as kin
from bayesrob.calibrate.arms import (
    ARM,
    ArmCalibration,
    arm_fit,
    arm_robot,
    calibrate_arms,
    mean_ci95,
    observed_errors,
    predicted_points,
)
from bayesrob.calibrate.least_squares import (
    Calibration,
    Rows,
    calibrate,
    covariance,
    marker_errors,
    residual_function,
    set_rows,
)
from bayesrob.data.rig import ArmSpec, Rig

COVERAGE_LEVELS = (0.5, 0.9, 0.95)


@dataclass(frozen=True)
class Priors:
    """Prior sd of each group around nominal (mm, rad) and the noise sd's HalfNormal scale."""

    instrument_mm: float = 200.0  # a rough placement of the robot in the measuring frame
    instrument_rad: float = 0.2
    marker_mm: float = 50.0
    offset_rad: float = 0.05
    origin_mm: float = 5.0  # a drawing's tolerance on a joint origin
    origin_rad: float = 0.02
    base_mm: float | None = None  # a chain's first origin, where it stands: origin_mm if None
    gain_rel: float = 0.05  # fraction of the nominal gain
    noise_mm: float = 20.0  # room for unmodelled compliance as well
    # the encoder sinusoids, in their typical sizes (1e-3 rad): as weak as the planar effects'
    # penalty, it only decides what the rows cannot see (the sag groups are not sampled)
    effect_sizes: float = 10.0

    def sd(self, layout: kin.ParamLayout) -> np.ndarray:
        base = {sl.start + k for (_, part), sl in layout.slices.items() if part == "origins"
                for k in range(3)}  # the first origin's position
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
                out[i] = self.origin_rad if rot else (
                    self.base_mm if i in base and self.base_mm is not None else self.origin_mm)
            elif p.group in kin.OPTIONAL_GROUPS:
                out[i] = self.effect_sizes * layout.scales[i]
            else:
                out[i] = self.gain_rel * abs(p.nominal)
        return out

    def arm_dict(self) -> dict[str, float]:
        return {"base_mm": self.origin_mm if self.base_mm is None else self.base_mm,
                "links_mm": self.origin_mm, "gain_rel": self.gain_rel,
                "offset_rad": self.offset_rad, "noise_halfnormal_mm": self.noise_mm}


ARM_PRIORS = Priors(noise_mm=5.0)  # a planar arm's: the rest of its priors are the defaults


@dataclass(frozen=True)
class SamplerSettings:
    num_warmup: int = 500
    num_samples: int = 500
    num_chains: int = 2
    dense_mass: bool = False
    target_accept_prob: float = 0.85
    max_tree_depth: int = 10


def calibration_model(structure: kin.RobotStructure, arms: tuple[str, ...], values: dict,
                      data: tuple, x: jax.Array, idx: jax.Array, prior_sd: jax.Array,
                      noise_mm: jax.Array) -> None:
    """The model of a robot's rows ``data`` ((u, d, side) per arm; d None: prior predictive):
    ``x`` at the prior's mean where sampled (``idx``), held elsewhere."""
    import numpyro
    import numpyro.distributions as dist

    free = numpyro.sample("x", dist.Normal(x[idx], prior_sd).to_event(1))
    noise_sd = numpyro.sample("noise_sd", dist.HalfNormal(noise_mm))
    robot, x = structure.robot(values), x.at[idx].set(free)
    for a, (u, d, side) in zip(arms, data, strict=True):
        numpyro.sample(f"d.{a}", dist.Normal(robot.marker_points(x, a, u, side=side),
                                             noise_sd).to_event(2), obs=d)


def _potential_fn_gen(structure, arms, centre, chol, s, *model_args):
    from numpyro.infer.util import potential_energy

    def potential(p):
        # the parameters' spread scales with the noise sd (its value s at the fit): so scaled,
        # z stays near a standard normal whatever the noise, at the cost of the Jacobian term
        scale = jnp.exp(p["noise_sd"]) / s
        return potential_energy(calibration_model, (structure, arms, *model_args), {}, {
            "x": centre + scale * (chol @ p["z"]), "noise_sd": p["noise_sd"]}
        ) - p["z"].size * jnp.log(scale)
    return potential


@functools.partial(jax.jit, static_argnames=("structure", "arms", "settings"))
def _nuts_chain(rng_key, init_params, model_args, *, structure: kin.RobotStructure,
                arms: tuple[str, ...], settings: SamplerSettings):
    """One NUTS chain through numpyro's functional ``hmc`` (``MCMC.run`` recompiles its loop on
    every call); the robot's numbers and the data are arguments, so a robot structure,
    settings and data shapes compile once."""
    from numpyro.infer.hmc import hmc

    init_kernel, sample_kernel = hmc(
        potential_fn_gen=functools.partial(_potential_fn_gen, structure, arms), algo="NUTS")
    state = init_kernel(init_params, settings.num_warmup, dense_mass=settings.dense_mass,
                        target_accept_prob=settings.target_accept_prob,
                        max_tree_depth=settings.max_tree_depth, model_args=model_args,
                        rng_key=rng_key)

    def step(s, _):
        s = sample_kernel(s, model_args=model_args)
        return s, (s.z, s.diverging, s.num_steps)

    _, out = jax.lax.scan(step, state, None, length=settings.num_warmup + settings.num_samples)
    return jax.tree.map(lambda x: x[settings.num_warmup:], out)


def _compile_seconds(run: Callable[[], Any]) -> tuple[Any, float]:
    """``run()`` and the seconds JAX spent in it tracing, lowering and compiling (or reading
    from the persistent cache) :func:`_nuts_chain`: jit's own cache holds the program, so
    ``release_compiled_programs`` drops it and the first call of a structure pays for it."""
    spent = []

    def listen(event: str, seconds: float, **kw: Any) -> None:
        if event.startswith("/jax/core/compile/") and "_nuts_chain" in kw.get("fun_name", ""):
            spent.append(seconds)

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        return run(), float(sum(spent))
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)


@dataclass
class Posterior:
    """Posterior draws of the sampled parameters and the noise sd, with diagnostics."""

    x: np.ndarray  # (chains, draws, k) the sampled parameters
    noise_sd: np.ndarray  # (chains, draws) mm
    diagnostics: dict = field(default_factory=dict)
    seconds: float = 0.0  # sampling time of all chains
    compile_seconds: float = 0.0  # compiling the sampler, if these rows were the first to

    @property
    def draws(self) -> np.ndarray:
        return self.x.reshape(-1, self.x.shape[-1])

    @property
    def noise_draws(self) -> np.ndarray:
        return self.noise_sd.reshape(-1)

    @property
    def mean(self) -> np.ndarray:
        return self.draws.mean(axis=0)

    @property
    def sd(self) -> np.ndarray:
        return self.draws.std(axis=0, ddof=1)


def _whitening(res, jac, x_fit: np.ndarray, idx: np.ndarray, prior_mean: np.ndarray,
               prior_sd: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Centre and square root L (k, k) of the Laplace approximation at ``x_fit`` and the
    residuals' rms s; the prior's where the rows leave no degree of freedom or the fit is
    wild (20 prior sd out)."""
    r = np.asarray(res(jnp.asarray(x_fit)))
    s = max(float(np.sqrt(r @ r / max(r.size - idx.size, 1))), 1e-3)
    free = np.zeros(x_fit.size, bool)
    free[idx] = True
    penalty = np.zeros(x_fit.size)
    penalty[idx] = s / prior_sd  # the prior's information, in the residuals' units
    cov = covariance(res, jac, x_fit, free, penalty)[np.ix_(idx, idx)]
    if np.all(np.isfinite(cov)) and np.all(np.abs(x_fit[idx] - prior_mean) < 20 * prior_sd):
        return x_fit[idx], np.linalg.cholesky(cov), s  # positive definite: the prior's rows
    return prior_mean, np.diag(prior_sd), s


def _diagnostics(x: np.ndarray, noise: np.ndarray, diverging: np.ndarray,
                 steps: np.ndarray) -> dict:
    import arviz as az

    idata = az.from_dict(posterior={"x": x, "noise_sd": noise},
                         sample_stats={"diverging": diverging})
    summ = az.summary(idata, var_names=["x", "noise_sd"], kind="diagnostics")
    return {"r_hat_max": float(summ["r_hat"].max()),
            "ess_bulk_min": float(summ["ess_bulk"].min()),
            "ess_tail_min": float(summ["ess_tail"].min()),
            "divergences": int(diverging.sum()),
            "mean_leapfrog_steps": float(steps.mean())}


def _model_args(robot: kin.Robot, rows: Rows, x: np.ndarray, idx: np.ndarray,
                priors: Priors) -> tuple:
    data = tuple((jnp.asarray(u, float), None if d is None else jnp.asarray(d, float), side)
                 for u, d, side in rows.values())
    return (robot.nominal_values, data, jnp.asarray(x), jnp.asarray(idx),
            jnp.asarray(priors.sd(robot.layout)[idx]), jnp.asarray(priors.noise_mm))


def sample_posterior(robot: kin.Robot, rows: Rows, x: np.ndarray, idx: np.ndarray,
                     x_fit: np.ndarray, priors: Priors = Priors(),
                     settings: SamplerSettings = SamplerSettings(), seed: int = 0,
                     diagnostics: bool = True) -> Posterior:
    """NUTS posterior of the parameters ``idx`` of ``robot`` given its ``rows`` (``x`` as in
    :func:`calibration_model`), whitened at the least-squares fit ``x_fit``. ``diagnostics``
    off: the divergences alone (arviz's R-hat needs two chains)."""
    from numpyro.distributions import biject_to, constraints

    t0 = time.perf_counter()
    idx = np.asarray(idx)
    res, jac, *_ = residual_function(robot, rows)
    centre, chol, s = _whitening(res, jac, np.asarray(x_fit, float), idx, x[idx],
                                 priors.sd(robot.layout)[idx])
    args = (jnp.asarray(centre), jnp.asarray(chol), jnp.asarray(s),
            *_model_args(robot, rows, x, idx, priors))
    rng = np.random.default_rng(seed)
    keys = jax.random.split(jax.random.PRNGKey(seed), settings.num_chains)
    inits = [{"z": jnp.asarray(rng.standard_normal(idx.size)),
              "noise_sd": jnp.asarray(np.log(s) + 0.15 * rng.standard_normal())}
             for _ in keys]
    chain = functools.partial(_nuts_chain, structure=robot.structure, arms=tuple(rows),
                              settings=settings)
    outs, compile_seconds = _compile_seconds(lambda: [
        chain(k, init, args) for k, init in zip(keys, inits, strict=True)])
    z = np.stack([np.asarray(o[0]["z"]) for o in outs])
    noise = np.stack([np.asarray(biject_to(constraints.positive)(o[0]["noise_sd"]))
                      for o in outs])
    diverging, steps = (np.stack([np.asarray(o[i]) for o in outs]) for i in (1, 2))
    draws = centre + noise[..., None] / s * (z @ chol.T)
    return Posterior(draws, noise, _diagnostics(draws, noise, diverging, steps) if diagnostics
                     else {"divergences": int(diverging.sum())},
                     time.perf_counter() - t0 - compile_seconds, compile_seconds)


@dataclass
class ArmPosterior(Posterior):
    """The posterior of a planar arm: ``x`` its eight parameters in PARAM_NAMES order."""

    name: str = ARM
    scale: np.ndarray | None = None  # (8,) prior sd
    elbow: int = 1
    pulse_limits: tuple = ((500.0, 2500.0),) * 2

    @property
    def arm(self) -> kin.Arm:
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


def _arm_problem(spec: ArmSpec, u: np.ndarray, d: np.ndarray | None
                 ) -> tuple[kin.Robot, np.ndarray, Rows, np.ndarray]:
    """A planar arm as its chain: robot, the eight's indices, rows, and the shift from the
    chain's values of the eight to the arm's."""
    v0 = np.asarray(kin.ArmParams.from_spec(spec).to_vector())
    robot, idx = arm_robot(v0)
    rows = {ARM: (np.asarray(u, float), None if d is None else np.asarray(d, float), None)}
    return robot, idx, rows, v0 - robot.layout.nominal[idx]


def sample_arm_posterior(spec: ArmSpec, u: np.ndarray, d: np.ndarray,
                         priors: Priors = ARM_PRIORS,
                         settings: SamplerSettings = SamplerSettings(), seed: int = 0,
                         diagnostics: bool = True) -> ArmPosterior:
    """NUTS posterior of one arm's eight parameters given its rows (u, d: (N, 2) each)."""
    robot, idx, rows, shift = _arm_problem(spec, u, d)
    nominal = robot.layout.nominal
    try:
        x_fit = arm_fit(robot, idx, *rows[ARM][:2]).x
    except (ValueError, np.linalg.LinAlgError):  # too few rows: whitened by the prior
        x_fit = nominal
    post = sample_posterior(robot, rows, nominal, idx, x_fit, priors, settings, seed,
                            diagnostics)
    return ArmPosterior(**{**vars(post), "x": post.x + shift}, name=spec.name,
                        scale=priors.sd(robot.layout)[idx], elbow=spec.elbow,
                        pulse_limits=spec.pulse_limits)


@dataclass
class BayesArmCalibration(ArmCalibration):
    posterior: ArmPosterior | None = None


def predictive_coverage(posterior: ArmPosterior, u: np.ndarray, d: np.ndarray,
                        levels=COVERAGE_LEVELS, seed: int = 0) -> dict[str, float]:
    """Fraction of observed points inside the central posterior predictive region of each
    level, bounded by the Mahalanobis distance the level's fraction of draws falls within (no
    Gaussian assumption about the predictive itself)."""
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
                        priors: Priors = ARM_PRIORS,
                        settings: SamplerSettings = SamplerSettings(),
                        seed: int = 0) -> BayesArmCalibration:
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
        "chains": int(post.x.shape[0]),
        "seconds": round(post.seconds, 3),
        "compile_seconds": round(post.compile_seconds, 3),
        "priors": priors.arm_dict(),
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


def calibrate_arms_bayes(rig: Rig, priors: Priors = ARM_PRIORS,
                         settings: SamplerSettings = SamplerSettings(), seed: int = 0
                         ) -> dict[str, BayesArmCalibration]:
    """Bayesian calibration of every arm of a rig on its ``train`` rows."""
    return calibrate_arms(rig, fit_arm=lambda spec, u, d, uv, dv: calibrate_arm_bayes(
        spec, u, d, uv, dv, priors, settings, seed))


def predict_end_points(posteriors: dict[str, ArmPosterior], commands: dict[str, np.ndarray],
                       noise: bool = True, seed: int = 0) -> np.ndarray:
    """Draws (S, T, 2) of a setup's end point for commands (T, 2) per arm: f(g(u)) per
    posterior draw (plus its noise if ``noise``); linked arms' Normal(f_a(g_a(u_a)), sigma_a^2)
    multiplied, the precision-weighted mean, their independent draws paired by index."""
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
    """Predicted mean error of a setup from ``reference`` (default the posterior-mean
    prediction), parameter uncertainty propagated: ``expected_error_mm``, ``interval95_mm``
    (where the observed mean error should fall), ``noise_only_error_mm`` (every arm at its
    posterior mean: the difference is what parameter uncertainty adds) and ``per_row_mm``."""
    draws = predict_end_points(posteriors, commands, noise=True, seed=seed)
    if reference is None:
        reference = predict_end_points(posteriors, commands, noise=False).mean(axis=0)
    reference = np.asarray(reference, float)
    err = np.linalg.norm(draws - reference[None], axis=-1)  # (S, T)
    per_draw = err.mean(axis=1)
    fixed = {a: replace(p, x=np.broadcast_to(p.mean, p.x.shape).copy())
             for a, p in posteriors.items() if a in commands}
    err0 = np.linalg.norm(predict_end_points(fixed, commands, noise=True, seed=seed)
                          - reference[None], axis=-1)
    return {
        "expected_error_mm": float(err.mean()),
        "interval95_mm": [float(q) for q in np.quantile(per_draw, [0.025, 0.975])],
        "noise_only_error_mm": float(err0.mean()),
        "per_row_mm": [float(e) for e in err.mean(axis=0)],
    }


def predicted_accuracy_document(rig: Rig, cal: dict[str, BayesArmCalibration],
                                seed: int = 0) -> dict:
    """Observed vs predicted mean error of every setup, as ``accuracy.json``'s ``setups``."""
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
    return {"predicted_accuracy": predicted_accuracy_document(rig, cal)}


def draw_from_prior(spec: ArmSpec, u: np.ndarray, n: int, priors: Priors = ARM_PRIORS,
                    seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``n`` data sets from the model's own prior predictive at commands u: params (n, 8),
    noise sd (n,) and end points (n, N, 2)."""
    from numpyro.infer import Predictive

    robot, idx, rows, shift = _arm_problem(spec, u, None)
    sim = Predictive(calibration_model, num_samples=n)(
        jax.random.PRNGKey(seed), robot.structure, (ARM,),
        *_model_args(robot, rows, robot.layout.nominal, idx, priors))
    return (np.asarray(sim["x"]) + shift, np.asarray(sim["noise_sd"]),
            np.asarray(sim[f"d.{ARM}"]))


@dataclass
class SBCResult:
    """Simulation-based calibration: true values and thinned posterior draws per data set,
    of the eight parameters in PARAM_NAMES order, then the noise sd."""

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
        """(R, 9): how many of the L draws lie below the true value."""
        return np.sum(self.draws < self.truth[:, None, :], axis=1)

    def uniformity(self, bins: int, ranks: np.ndarray | None = None) -> dict:
        """Chi-square test of uniform ranks per quantity, Bonferroni-combined; ``bins`` must
        divide L + 1 so every bin holds as many rank values."""
        ranks = self.ranks if ranks is None else ranks
        values = self.n_draws + 1
        if values % bins:
            raise ValueError(f"{bins} bins do not divide the {values} possible ranks")
        counts = np.stack([np.bincount(r * bins // values, minlength=bins) for r in ranks.T])
        chi2, p = scipy.stats.chisquare(counts, axis=1)
        return {"chi2": chi2, "p": p, "dof": bins - 1, "counts": counts,
                "p_min": float(p.min()), "p_bonferroni": float(min(1.0, p.min() * len(p)))}


def sbc(spec: ArmSpec, u: np.ndarray, n_datasets: int, n_draws: int = 49,
        priors: Priors = ARM_PRIORS, settings: SamplerSettings = SamplerSettings(num_chains=1),
        seed: int = 0) -> SBCResult:
    """Simulation-based calibration (Talts et al. 2018) at an arm's commands u: data sets from
    the model's own prior (not the simulator: only then are the true values' ranks exactly
    uniform when the sampler is right), draws thinned evenly to ``n_draws``."""
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
        post = sample_arm_posterior(spec, u, d, priors, settings, int(rng.integers(2**31)),
                                    diagnostics=False)
        draws.append(np.column_stack([post.draws, post.noise_draws])[keep])
        divs.append(post.diagnostics["divergences"])
    return SBCResult(np.column_stack([params, noise_sd]), np.array(draws), np.array(divs),
                     time.perf_counter() - t0)


def calibrate_bayes(rig: Rig, groups: tuple[str, ...] = kin.GROUPS, priors: Priors = Priors(),
                    settings: SamplerSettings = SamplerSettings(), seed: int = 0,
                    progress=None) -> Calibration:
    """NUTS posterior of a rig's identifiable parameters (the rest at the least-squares fit):
    a :class:`Calibration` whose x is the posterior mean, se the posterior sd."""
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
    if progress:
        progress(f"NUTS over {free.sum()} parameters")
    post = sample_posterior(robot, set_rows(rig, robot, "train"), np.where(
        free, robot.layout.nominal, ls.x), np.flatnonzero(free), ls.x, priors, settings, seed)
    draws = np.repeat(ls.x[None], len(post.draws), axis=0)
    draws[:, free] = post.draws
    x = np.where(free, draws.mean(axis=0), ls.x)
    se = np.where(free, draws.std(axis=0, ddof=1), np.nan)
    extra = {"posterior": {
        **post.diagnostics, "noise_sd_mm": float(post.noise_draws.mean()),
        "draws": len(draws), "chains": settings.num_chains,
        "least_squares_validation_mean_mm": ls.errors.get("validation", {}).get(
            "all", {}).get("mean_mm")}}
    return Calibration(robot, x, ls.groups, ls.ident, se, marker_errors(rig, robot, x),
                       ls.nfev, time.perf_counter() - t0, method="bayes", extra=extra,
                       draws=draws)
