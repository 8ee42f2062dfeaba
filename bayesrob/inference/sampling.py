"""The joint-error models as numpyro programs, sampled by NUTS and emcee and checked on the grid.

:func:`arm_model` is one arm as a generative program (its prior predictive is the push-forward
of the joint-error density); :func:`linked_model` is any number of arms linked at their end
point: a flat prior on the shared point d and one ``numpyro.factor`` per arm with the log
density of its joint error at d, the product of likelihoods written as a program. The grid
(:func:`bayesrob.predict.grid.grid_posterior`) is flat within its box; the two agree because
the mass outside that box is negligible (``edge_mass`` reports it). :func:`run_nuts` and
:func:`run_emcee` return arviz ``InferenceData``, :func:`cross_check` compares them with the
grid, and :func:`sample_linked` is the ``bayesrob sample`` command.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import arviz as az
import emcee
import jax
import jax.numpy as jnp
import numpy as np
import numpyro
import numpyro.distributions as dist
from numpyro.distributions import constraints
from numpyro.infer import Predictive
from numpyro.infer.hmc import hmc
from numpyro.infer.util import log_density
from threadpoolctl import threadpool_limits

from bayesrob import robot as kin
from bayesrob.data.rig import Rig
from bayesrob.errors.distributions import (
    ArmStatic,
    arm_structures,
    compiled_arm_log_density,
    is_sampleable,
    joint_error_distribution,
    joint_error_log_prob,
)
from bayesrob.errors.noise_models import FittedNoiseModel
from bayesrob.predict.aiming import check_pulse_limits, check_reach
from bayesrob.predict.grid import (
    Grid,
    GridPosterior,
    grid_posterior,
    points_log_likelihood,
    zoomed_grid,
)
from bayesrob.progress import FIRST_LINE_S, Progress

__all__ = ["SAMPLERS", "CheckTolerances", "NutsSampler", "SamplerResult",
           "SampleReport", "arm_model", "prior_predictive", "linked_model",
           "linked_log_density", "prior_spread", "initial_points", "check_pulse_limits",
           "check_reach", "run_nuts", "run_emcee", "cross_check", "cov_rel_error",
           "emcee_density", "sample_linked"]

SAMPLERS = ("nuts", "emcee", "grid")

# NUTS defaults, tuned on the default rig (1 target, cond, 5 seeds, median bulk ESS per second
# with warm-up in the wall time): 500 warm-up + 2000 draws at acceptance 0.8 gave 13k/s, 300 +
# 4000 draws the same bulk ESS in half the time. Acceptance 0.65 took 20% longer steps but
# diverged in the bulk of the posterior (lp percentiles 1-97, not its tails) in 7 of 12 runs
# (3 targets x 4 seeds, cond; up to 100 of 16,000 transitions): one chain's short warm-up
# ends on too long a step. At 0.8 no run of cond, ind or corr diverged (30 runs), bulk ESS
# unchanged, sampling 25% slower (0.35 s against 0.28 s, beside 4 s of compilation).
NUTS_WARMUP = 300
NUTS_SAMPLES = 4000
NUTS_TARGET_ACCEPT = 0.8
# cells per side of the coarse and the zoomed grid that check a marker point (3-D included)
MARKER_GRID_N = 41


def arm_model(model: FittedNoiseModel, arm: kin.Arm, u: jax.Array,
              measurement_noise_mm: float = 0.0) -> None:
    """One arm at commands ``u`` (T, 2): theta_err ~ the joint-error model, d = f(g(u) +
    theta_err), plus Normal measurement noise if ``measurement_noise_mm``. The histogram COND
    enters as a flat latent times a ``numpyro.factor``: conditioned and run by MCMC, never
    forward-sampled."""
    u = jnp.atleast_2d(jnp.asarray(u, dtype=jnp.float64))
    t = u.shape[0]
    with numpyro.plate("targets", t):
        if is_sampleable(model):
            theta_err = numpyro.sample("theta_err", joint_error_distribution(model, u))
        else:
            theta_err = numpyro.sample(
                "theta_err", dist.ImproperUniform(constraints.real, (), event_shape=(2,)))
            numpyro.factor("theta_err_density", joint_error_log_prob(model, theta_err, u))
        d_true = kin.forward(arm.params, kin.servo(arm.params, u) + theta_err)
        if measurement_noise_mm > 0:
            numpyro.deterministic("d_true", d_true)
            numpyro.sample("d", dist.Normal(d_true, measurement_noise_mm).to_event(1))
        else:
            numpyro.deterministic("d", d_true)


def prior_predictive(model: FittedNoiseModel, arm: kin.Arm, u: Any, num_samples: int,
                     seed: int = 0, measurement_noise_mm: float = 0.0) -> dict[str, np.ndarray]:
    """Draws of :func:`arm_model` by ``numpyro.infer.Predictive``: ``d`` is (S, T, 2)."""
    if not is_sampleable(model):
        raise NotImplementedError(f"model {model.spec.name!r} cannot be forward-sampled")
    pred = Predictive(arm_model, num_samples=num_samples)
    out = pred(jax.random.PRNGKey(seed), model, arm, jnp.asarray(u, dtype=jnp.float64),
               measurement_noise_mm)
    return {k: np.asarray(v) for k, v in out.items()}


def _linked_program(commands: Sequence[jax.Array], params: tuple, *,
                    statics: tuple[ArmStatic, ...]) -> None:
    t = commands[0].shape[0]
    d = numpyro.sample("d", dist.ImproperUniform(constraints.real, (t,), event_shape=(2,)))
    for static, (arm_params, arrays), u in zip(statics, params, commands, strict=True):
        numpyro.factor(f"loglik_{static.name}",
                       compiled_arm_log_density(static, arm_params, arrays, u, d))


def linked_model(commands: Sequence[jax.Array], *, models: Sequence[FittedNoiseModel],
                 arms: Sequence[kin.Arm]) -> None:
    """Arms linked at their end point: the shared point d (T, 2) flat on the plane, one
    ``numpyro.factor`` ``loglik_<arm>`` per arm at its pulses ``commands[k]`` (T, 2)."""
    statics, params = arm_structures(models, arms)
    _linked_program(tuple(jnp.asarray(u, dtype=jnp.float64) for u in commands), params,
                    statics=statics)


@functools.lru_cache(maxsize=64)
def _compiled_log_density(statics: tuple[ArmStatic, ...]) -> Callable:
    potential = _linked_potential(statics)

    def one(x, commands, params):
        lp = -potential(x.reshape(commands[0].shape[0], 2), commands, params)
        # emcee treats NaN as an error; the clamp in f^-1 keeps it finite, this is a guard.
        return jnp.where(jnp.isnan(lp), -jnp.inf, lp)

    return jax.jit(jax.vmap(one, in_axes=(0, None, None)))


def linked_log_density(models: Sequence[FittedNoiseModel], arms: Sequence[kin.Arm]
                       ) -> Callable[[jax.Array, tuple[jax.Array, ...]], jax.Array]:
    """``fn(d, commands)``: the (W,) log densities of :func:`linked_model` at ``d`` (W, T * 2,
    emcee's layout), by ``numpyro.infer.util.log_density``, so emcee and NUTS see the same
    density; compiled once per structure (family, Jacobian, branch per arm)."""
    statics, params = arm_structures(models, arms)
    fn = _compiled_log_density(statics)
    # No conversions here: emcee calls this thousands of times and jit takes numpy arrays.
    return lambda d, commands: fn(d, tuple(commands), params)


# Starting spread in units of the widest arm's own end-point sd: over-dispersed, as r_hat
# needs, yet a few posterior widths only, so warm-up and burn-in absorb it.
INIT_OVERDISPERSION = 2.0
# Starts lie where the log density is within this of the densest candidate: 9.21 is the
# 99.99% contour of a 2-D Gaussian, so a start is never where the posterior has no mass.
INIT_LOG_DENSITY_DROP = 9.21


def prior_spread(models: Sequence[FittedNoiseModel], arms: Sequence[kin.Arm],
                 targets: np.ndarray) -> np.ndarray:
    """Covariance (T, 2, 2) of the widest arm's own prediction at each target (its fitted
    joint errors through its Jacobian): wider than the linked posterior, so starts drawn from
    it over-disperse."""
    targets = np.atleast_2d(np.asarray(targets, float))
    out = np.zeros((len(targets), 2, 2))
    for model, arm in zip(models, arms, strict=True):
        err = np.asarray(model.theta_err, float)
        sigma = np.cov(err.T) if len(err) > 1 else np.zeros((2, 2))
        sigma = sigma + np.diag(np.full(2, 1e-8))  # one point or collinear errors: not singular
        theta = kin.inverse(arm.params, jnp.asarray(targets), arm.elbow)[0]
        jac = np.asarray(kin.jacobian(arm.params, theta))  # (T, 2, 2)
        cov = np.einsum("tij,jk,tlk->til", jac, sigma, jac)
        wider = np.trace(cov, axis1=1, axis2=2) > np.trace(out, axis1=1, axis2=2)
        out[wider] = cov[wider]
    return out


def initial_points(models: Sequence[FittedNoiseModel], arms: Sequence[kin.Arm],
                   commands: Sequence[np.ndarray], targets: np.ndarray, n: int, seed: int = 0,
                   overdispersion: float = INIT_OVERDISPERSION, max_rounds: int = 20
                   ) -> np.ndarray:
    """n starting end points (n, T, 2) per target, without the grid (the samplers must find
    the modes themselves): draws of N(target, overdispersion^2 * :func:`prior_spread`) whose
    density is within ``INIT_LOG_DENSITY_DROP`` of the densest seen, so no chain starts where
    the density is nil (beyond reach, or on the paper COND's flat floor, with no gradient)."""
    targets = np.atleast_2d(np.asarray(targets, float))
    t_count = len(targets)
    chol = np.linalg.cholesky(overdispersion ** 2 * prior_spread(models, arms, targets))
    rng = np.random.default_rng(seed)
    m = max(20 * n, 200)
    pool = np.zeros((t_count, 0, 2))
    pool_lp = np.zeros((t_count, 0))
    for _ in range(max_rounds):
        z = rng.standard_normal((t_count, m, 2))
        cand = targets[:, None, :] + np.einsum("tij,tmj->tmi", chol, z)
        lp = points_log_likelihood(models, arms, commands, cand)
        pool = np.concatenate([pool, cand], axis=1)
        pool_lp = np.concatenate([pool_lp, np.where(np.isnan(lp), -np.inf, lp)], axis=1)
        ok = pool_lp >= pool_lp.max(axis=1, keepdims=True) - INIT_LOG_DENSITY_DROP
        ok &= np.isfinite(pool_lp)
        if np.all(ok.sum(axis=1) >= n):
            out = np.empty((n, t_count, 2))
            for t in range(t_count):
                out[:, t] = pool[t, rng.choice(np.flatnonzero(ok[t]), n, replace=False)]
            return out
    bad = int(np.flatnonzero(ok.sum(axis=1) < n)[0])
    raise ValueError(f"target ({targets[bad, 0]:g}, {targets[bad, 1]:g}): fewer than {n} "
                     f"starting points with non-negligible density in {max_rounds * m} draws "
                     "around it")


@dataclass
class SamplerResult:
    """One sampler's draws of the linked end point: InferenceData plus the figures we check."""

    name: str
    idata: az.InferenceData
    seconds: float  # sampling wall time, compilation excluded
    summary: Any = field(repr=False)  # az.summary DataFrame
    compile_seconds: float = 0.0

    @property
    def draws(self) -> np.ndarray:
        """Pooled draws (S, T, 2)."""
        d = self.idata.posterior["d"].values  # (chain, draw, T, 2)
        return d.reshape(-1, *d.shape[2:])

    @property
    def mean(self) -> np.ndarray:
        return self.draws.mean(axis=0)

    @property
    def cov(self) -> np.ndarray:
        dev = self.draws - self.mean
        return np.einsum("sti,stj->tij", dev, dev) / (dev.shape[0] - 1)

    @property
    def ess_bulk(self) -> float:
        return float(self.summary["ess_bulk"].min())

    @property
    def ess_tail(self) -> float:
        return float(self.summary["ess_tail"].min())

    @property
    def r_hat(self) -> float:
        return float(self.summary["r_hat"].max())

    @property
    def ess_per_s(self) -> float:
        return self.ess_bulk / self.seconds if self.seconds > 0 else float("nan")


def _summary(idata: az.InferenceData) -> Any:
    return az.summary(idata, var_names=["d"], kind="diagnostics", round_to="none")


_DIMS = {"d": ["target", "xy"]}


class NutsSampler:
    """numpyro's NUTS kernel (``hmc(..., algo="NUTS")``, with its step-size and mass-matrix
    adaptation) on :func:`linked_model` (:meth:`run`) or any point's potential (:meth:`sample`),
    in a jitted ``lax.scan`` vmapped over (target, chain) lanes, each with its own adaptation.

    Not ``numpyro.infer.MCMC``: its ``run`` re-compiles the loop on every call. Here models and
    arm parameters are traced arguments, so the programs are compiled ahead of time (timed as
    ``compile_seconds``) once per potential and shapes, whatever the targets, rig or refit.
    """

    def __init__(self, *, num_chains: int = 4, num_warmup: int = NUTS_WARMUP,
                 num_samples: int = NUTS_SAMPLES, dense_mass: bool = True,
                 target_accept_prob: float = NUTS_TARGET_ACCEPT,
                 max_tree_depth: int = 10, progress_bar: bool = False, chunks: int = 10) -> None:
        self.num_chains, self.num_warmup, self.num_samples = num_chains, num_warmup, num_samples
        self.dense_mass, self.target_accept_prob = dense_mass, target_accept_prob
        self.max_tree_depth = max_tree_depth
        self.progress_bar = progress_bar
        total = num_warmup + num_samples
        # Progress is reported between chunks of the scan; the chunk length must divide the
        # run, so round the number of chunks down to a divisor.
        self.chunks = max(c for c in range(1, max(1, chunks) + 1) if total % c == 0)
        self._compiled: dict[Any, tuple[Any, Any, float]] = {}

    def _functions(self, potential: Callable, keys, z0, lane, shared):
        leaves, treedef = jax.tree.flatten((lane, shared))
        key = (potential, z0.shape, treedef, tuple(jnp.shape(x) for x in leaves))
        if key in self._compiled:
            return self._compiled[key]

        def potential_gen(lane, shared):
            return lambda z: potential(z, lane, shared)

        init_kernel, sample_kernel = hmc(potential_fn_gen=potential_gen, algo="NUTS")
        length = (self.num_warmup + self.num_samples) // self.chunks

        def init_one(key, z0, lane, shared):
            return init_kernel(z0, self.num_warmup, dense_mass=self.dense_mass,
                               target_accept_prob=self.target_accept_prob,
                               max_tree_depth=self.max_tree_depth,
                               model_args=(lane, shared), rng_key=key)

        def advance_one(state, lane, shared):
            def step(st, _):
                st = sample_kernel(st, model_args=(lane, shared))
                return st, (st.z, st.diverging, st.num_steps, st.potential_energy)
            return jax.lax.scan(step, state, None, length=length)

        init_v = jax.jit(jax.vmap(init_one, in_axes=(0, 0, 0, None)))
        advance_v = jax.jit(jax.vmap(advance_one, in_axes=(0, 0, None)))
        t0 = time.perf_counter()
        init_c = init_v.lower(keys, z0, lane, shared).compile()
        state = jax.eval_shape(init_v, keys, z0, lane, shared)
        advance_c = advance_v.lower(state, lane, shared).compile()
        self._compiled[key] = (init_c, advance_c, time.perf_counter() - t0)
        return self._compiled[key]

    def run(self, models: Sequence[FittedNoiseModel], arms: Sequence[kin.Arm],
            commands: Sequence[np.ndarray], init: np.ndarray, seed: int = 0) -> SamplerResult:
        """Sample every target; ``init`` (num_chains, T, 2) are the chains' starting points."""
        statics, params = arm_structures(models, arms)
        cmds = [np.atleast_2d(np.asarray(u, float)) for u in commands]
        c, t = self.num_chains, cmds[0].shape[0]
        if np.shape(init) != (c, t, 2):
            raise ValueError(f"init must have shape ({c}, {t}, 2), got {np.shape(init)}")
        lane_cmds = tuple(jnp.asarray(np.repeat(u, c, axis=0)[:, None, :]) for u in cmds)
        return self.sample(_linked_potential(statics), init, lane_cmds, params, seed)

    def sample(self, potential: Callable, init: np.ndarray, lane: Any = (), shared: Any = (),
               seed: int = 0) -> SamplerResult:
        """NUTS on ``potential(z, lane, shared)`` of one target's point z (1, dim) from ``init``
        (num_chains, T, dim), a lane per (target, chain), target-major; ``lane`` holds arrays
        with a row per lane, ``shared`` those every lane reads."""
        init = np.asarray(init, float)
        c, t, dim = init.shape
        z0 = jnp.asarray(init.transpose(1, 0, 2).reshape(t * c, 1, dim))
        keys = jax.random.split(jax.random.PRNGKey(seed), t * c)
        # A structure's first run compiles for seconds: the report starts before that.
        bar = Progress(self.chunks, "nuts", "chunks", enabled=self.progress_bar,
                       postfix="compiling")
        init_fn, advance_fn, compile_s = self._functions(potential, keys, z0, lane, shared)
        bar.set_postfix("sampling")
        t0 = time.perf_counter()
        state = init_fn(keys, z0, lane, shared)
        pieces = []
        for _ in range(self.chunks):
            state, out = advance_fn(state, lane, shared)
            pieces.append(out)
            bar.update()
        bar.close()
        out = jax.block_until_ready(jax.tree.map(lambda *a: jnp.concatenate(a, axis=1), *pieces))
        seconds = time.perf_counter() - t0
        z, div, steps, pe = (np.asarray(a)[:, self.num_warmup:] for a in out)

        def by_chain(a):  # (T*C, S, ...) -> (C, S, T, ...)
            a = a.reshape((t, c) + a.shape[1:])
            return np.moveaxis(a, 0, 2)

        idata = az.from_dict(
            posterior={"d": by_chain(z[:, :, 0, :])},
            sample_stats={"diverging": by_chain(div), "n_steps": by_chain(steps),
                          "lp": -by_chain(pe)},
            dims={**_DIMS, "diverging": ["target"], "n_steps": ["target"], "lp": ["target"]},
            coords={"xy": ["x", "y", "z"][:dim]},
        )
        return SamplerResult("nuts", idata, seconds, _summary(idata), compile_s)


@functools.lru_cache(maxsize=64)
def _linked_potential(statics: tuple[ArmStatic, ...]) -> Callable:
    """:func:`linked_model`'s potential energy at z given (commands, params), one function per
    structure: what NutsSampler caches its programs on."""
    program = functools.partial(_linked_program, statics=statics)
    return lambda z, commands, params: -log_density(program, (commands, params), {}, {"d": z})[0]


@functools.lru_cache(maxsize=8)
def _shared_nuts(num_chains: int, num_warmup: int, num_samples: int, dense_mass: bool,
                 target_accept_prob: float) -> NutsSampler:
    return NutsSampler(num_chains=num_chains, num_warmup=num_warmup, num_samples=num_samples,
                       dense_mass=dense_mass, target_accept_prob=target_accept_prob)


def run_nuts(models: Sequence[FittedNoiseModel], arms: Sequence[kin.Arm],
             commands: Sequence[np.ndarray], init: np.ndarray, *, seed: int = 0,
             num_warmup: int = NUTS_WARMUP, num_samples: int = NUTS_SAMPLES,
             dense_mass: bool = True, target_accept_prob: float = NUTS_TARGET_ACCEPT,
             progress_bar: bool = False) -> SamplerResult:
    """Sample the linked posterior of every target with NUTS (:class:`NutsSampler`, shared by
    calls with the same settings) from ``init`` (num_chains, T, 2), normally
    :func:`initial_points`: chains that start apart and find the modes themselves let r_hat
    and the grid check see a sampler that misses a mode backlash split off."""
    sampler = _shared_nuts(int(np.shape(init)[0]), num_warmup, num_samples, dense_mass,
                           target_accept_prob)
    sampler.progress_bar = progress_bar
    return sampler.run(models, arms, commands, init, seed)


def run_emcee(models: Sequence[FittedNoiseModel], arms: Sequence[kin.Arm],
              commands: Sequence[np.ndarray], init: np.ndarray, *, n_steps: int = 2500,
              burn: int = 500, seed: int = 0, progress: bool = False) -> SamplerResult:
    """Sample the linked posterior with emcee, one 2-D ensemble per target, walkers from
    ``init`` (W, T, 2), all evaluated in one call of :func:`linked_log_density`; the first
    ``burn`` steps (the contraction from the over-dispersed start) are dropped."""
    init = np.asarray(init, float)
    cmds = [np.atleast_2d(np.asarray(u, float)) for u in commands]
    lp = linked_log_density(models, arms)
    rng = np.random.default_rng(seed)
    per_target = [tuple(jnp.asarray(u[t:t + 1]) for u in cmds) for t in range(init.shape[1])]
    return _emcee([lambda x, c=c: np.asarray(lp(x, c)) for c in per_target], init,
                  [int(rng.integers(2**31)) for _ in per_target], n_steps, burn, progress)


def _emcee(log_probs: Sequence[Callable], init: np.ndarray, states: Sequence[int],
           n_steps: int, burn: int, progress: bool) -> SamplerResult:
    """One ensemble per target t on ``log_probs[t]``, walkers from ``init`` (W, T, dim), its
    random state seeded by ``states[t]``; the first target's compilation timed apart."""
    bar = Progress(len(log_probs) * n_steps, "emcee", "steps", enabled=progress,
                   postfix="compiling")
    compile_seconds = _compile_halves(log_probs[0], init[:, 0, :])
    bar.set_postfix("sampling")
    t0 = time.perf_counter()
    draws = [_ensemble(lp, init[:, t, :], state, n_steps, burn, bar)
             for t, (lp, state) in enumerate(zip(log_probs, states, strict=True))]
    seconds = time.perf_counter() - t0
    bar.close()
    idata = az.from_dict(posterior={"d": np.stack(draws, axis=2)}, dims=_DIMS,
                         coords={"xy": ["x", "y", "z"][:init.shape[2]]})
    return SamplerResult("emcee", idata, seconds, _summary(idata), compile_seconds)


def _compile_halves(log_prob: Callable, x: np.ndarray) -> float:
    """Seconds to compile ``log_prob`` outside the timed run, for both shapes emcee calls it
    with: the whole ensemble ``x`` (first step) and each half of it (the red-blue moves)."""
    t0 = time.perf_counter()
    for k in {len(x), len(x) // 2, len(x) - len(x) // 2}:
        jax.block_until_ready(log_prob(x[:k]))
    return time.perf_counter() - t0


def _ensemble(log_prob: Callable, init: np.ndarray, state: int, n_steps: int, burn: int, bar
              ) -> np.ndarray:
    """emcee's EnsembleSampler from ``init`` (W, dim), its random state seeded by ``state``:
    the draws (W, n_steps - burn, dim)."""
    # With walkers spread over the modes, differential evolution and KDE proposals jump
    # between the modes backlash splits: on a bimodal case the default stretch move left the
    # covariance 10-20% off, this mix within 2%.
    moves = [(emcee.moves.DEMove(), 0.7), (emcee.moves.KDEMove(), 0.3)]
    sampler = emcee.EnsembleSampler(*init.shape, log_prob, vectorize=True, moves=moves)
    sampler.random_state = np.random.RandomState(state).get_state()
    # KDEMove solves small triangular systems through scipy every step: multi-threaded BLAS
    # hands each one between threads, ~6 ms instead of ~0.05 ms on 2 busy cores.
    with threadpool_limits(limits=1, user_api="blas"):
        for _ in sampler.sample(init, iterations=n_steps):
            bar.update()
    return np.swapaxes(sampler.get_chain(), 0, 1)[:, burn:]


def _marker_potential(z: jax.Array, lane: Any, arrays: tuple) -> jax.Array:
    """Minus the log density of a point z (1, dim) under the product of the arms' marker
    densities (their :meth:`~bayesrob.errors.marker_density.MarkerDensity.arrays`)."""
    from bayesrob.errors.marker_density import mixture_logpdf

    return -sum(mixture_logpdf(z, *a)[0] for a in arrays)


def emcee_density(log_density: Callable, init: np.ndarray, *, n_steps: int = 2500,
                  burn: int = 500, seed: int = 0, progress: bool = False) -> SamplerResult:
    """:func:`run_emcee` on ``log_density`` of one point, walkers from ``init`` (W, dim)."""
    batch = jax.jit(jax.vmap(log_density))
    return _emcee([lambda x: np.asarray(batch(jnp.asarray(x)))],
                  np.asarray(init, float)[:, None, :], [seed], n_steps, burn, progress)


@dataclass(frozen=True)
class CheckTolerances:
    """What "agrees with the grid" means (per target): see :func:`cross_check`."""

    mean_mm: float = 0.1
    cov_rel: float = 0.10
    r_hat: float = 1.01
    ess_bulk: float = 400.0
    edge_mass: float = 1e-6  # grid mass on the box edge above which the box truncates


def cross_check(grid: GridPosterior, results: Sequence[SamplerResult],
                tol: CheckTolerances = CheckTolerances()) -> dict[str, Any]:
    """Compare each sampler with the grid: ``{"passed": bool, "failures": [str]}``, every
    failure with its figures. Per target, mean within ``tol.mean_mm`` and covariance within
    ``tol.cov_rel`` (relative Frobenius); per sampler, r_hat and bulk ESS; and the grid's
    own edge mass (above ``tol.edge_mass`` its box truncates the posterior)."""
    failures: list[str] = []
    for t in np.flatnonzero(grid.edge_mass > tol.edge_mass):
        failures.append(f"grid: {grid.edge_mass[t]:.1e} of the mass lies on the edge of the "
                        f"+-{grid.coarse.half_width_mm:g} mm box at target "
                        f"({grid.targets[t, 0]:.1f}, {grid.targets[t, 1]:.1f}): the box "
                        "truncates the posterior, so its flat prior differs from the programs'")
    for res in results:
        mean = res.mean
        dcs = cov_rel_error(res.cov, grid.cov)
        for t in range(len(grid.targets)):
            tgt = f"target ({grid.targets[t, 0]:.1f}, {grid.targets[t, 1]:.1f})"
            dm = float(np.linalg.norm(mean[t] - grid.mean[t]))
            if not dm <= tol.mean_mm:
                failures.append(f"{res.name}: mean {np.round(mean[t], 3).tolist()} is {dm:.3f} mm"
                                f" from the grid's {np.round(grid.mean[t], 3).tolist()} "
                                f"(> {tol.mean_mm} mm) at {tgt}")
            dc = float(dcs[t])
            if not dc <= tol.cov_rel:
                failures.append(f"{res.name}: covariance differs from the grid's by {dc:.1%} "
                                f"(Frobenius, > {tol.cov_rel:.0%}) at {tgt}")
        if not res.r_hat <= tol.r_hat:
            failures.append(f"{res.name}: r_hat {res.r_hat:.4f} > {tol.r_hat}")
        if not res.ess_bulk >= tol.ess_bulk:
            failures.append(f"{res.name}: bulk ESS {res.ess_bulk:.0f} < {tol.ess_bulk:.0f}")
    return {"passed": not failures, "failures": failures}


def cov_rel_error(cov: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """||cov - ref||_F / ||ref||_F per target, for (T, 2, 2) stacks."""
    return np.linalg.norm(cov - ref, axis=(-2, -1)) / np.linalg.norm(ref, axis=(-2, -1))


@dataclass
class SampleReport:
    """What :func:`sample_linked` computed: the ``sample --json`` document, live objects."""

    document: dict
    grid: GridPosterior
    results: dict[str, SamplerResult]

    @property
    def passed(self) -> bool:
        return bool(self.document["check"]["passed"])

    def to_dict(self) -> dict:
        return self.document


def _run_and_judge(doc: dict, grid: GridPosterior, runs: dict[str, Callable[[], SamplerResult]],
                   tol: CheckTolerances, burn: int, sampler: str, notes: Sequence[str] = ()
                   ) -> dict[str, SamplerResult]:
    """Run the samplers asked for, unless the grid truncates the posterior (nothing valid to
    check them against); then each one's entry of ``doc["samplers"]``, the ``check`` (always,
    ``--sampler grid`` included: a truncating grid is a wrong answer whoever asked) and
    ``notes``."""
    truncated = bool(np.any(grid.edge_mass > tol.edge_mass))
    results = {name: run() for name, run in runs.items()
               if sampler in (name, "all") and not truncated}
    for name, res in results.items():
        entry = {**_moments(res.mean[0], res.cov[0]), "ess_bulk": res.ess_bulk,
                 "ess_tail": res.ess_tail, "r_hat": res.r_hat, "seconds": res.seconds,
                 "compile_seconds": res.compile_seconds, "ess_per_s": res.ess_per_s,
                 "chains": int(res.idata.posterior.sizes["chain"]),
                 "draws": int(res.idata.posterior.sizes["draw"])}
        if name == "nuts":
            entry["divergences"] = int(res.idata.sample_stats["diverging"].values.sum())
        else:
            entry["burn"] = burn
        doc["samplers"][name] = entry
    check = cross_check(grid, list(results.values()), tol)
    check["tolerances"] = {"mean_mm": tol.mean_mm, "cov_rel": tol.cov_rel,
                           "r_hat": tol.r_hat, "ess_bulk": tol.ess_bulk,
                           "edge_mass": tol.edge_mass}
    check["compared"] = list(results)
    doc["check"] = check
    doc["notes"] = list(notes)
    if truncated and sampler != "grid":
        doc["notes"].append("no sampler was run: the grid reference truncates the posterior, "
                            "so there is nothing valid to check a sampler against")
    return results


def _moments(mean: np.ndarray, cov: np.ndarray) -> dict:
    return {"mean": [float(x) for x in mean], "cov": [[float(x) for x in r] for r in cov]}


def _grid_entry(grid: GridPosterior, **extra: float) -> dict:
    """The grid reference's entry of ``doc["samplers"]`` (its one target)."""
    return {**_moments(grid.mean[0], grid.cov[0]), "seconds": grid.seconds,
            "cell_mm": grid.cell_mm[0].tolist(), "n": grid.n, "box_lo": grid.lo[0].tolist(),
            **extra, "edge_mass": float(grid.edge_mass[0])}


def sample_linked(rig: Rig, config: str, target: Sequence[float], model: str = "cond",
                  sampler: str = "all", *, seed: int = 0, progress: bool = False,
                  num_chains: int = 4, num_warmup: int = NUTS_WARMUP,
                  num_samples: int = NUTS_SAMPLES,
                  walkers: int = 32, steps: int = 2500, burn: int = 500,
                  tol: CheckTolerances = CheckTolerances(), models_dir: Any = None,
                  groups: tuple[str, ...] | None = None) -> SampleReport:
    """Sample the end point of ``config`` (arms joined by '+') aimed at ``target`` with
    ``sampler`` ("nuts", "emcee", "grid" or "all") and check the samplers on the grid.

    Each planar arm is aimed by its calibrated inverse (a target out of reach or off its
    pulse limits is refused in one line before any fit); chains and walkers start from
    :func:`initial_points`, never the grid. A rig of URDF/DH arms, or a planar rig given
    ``groups``, is calibrated over ``groups`` and sampled under its arms' marker densities
    (:func:`_sample_markers`)."""
    from bayesrob.calibrate.arms import calibrate_arms
    from bayesrob.errors.noise_models import discover_models, fit_noise_models

    if sampler not in (*SAMPLERS, "all"):
        raise ValueError(f"sampler must be one of {SAMPLERS} or 'all', got {sampler!r}")
    if rig.is_chain or groups is not None:
        return _sample_markers(rig, config, target, model, sampler, seed=seed,
                               progress=progress, groups=groups, models_dir=models_dir,
                               num_chains=num_chains, walkers=walkers, steps=steps, burn=burn,
                               tol=tol)
    members = config.split("+")
    unknown = [a for a in members if a not in rig.arms]
    if unknown:
        raise ValueError(f"config {config!r}: no arm {unknown[0]!r} in the rig "
                         f"(arms: {', '.join(rig.arms)})")
    specs = discover_models(models_dir, [model])
    # The steps before the samplers, which report on their own bars. The first line waits a
    # second: a target out of reach, found after the calibration, is then the only line.
    with Progress(3, "sample", "steps", enabled=progress, postfix="calibrating",
                  first_after=FIRST_LINE_S) as bar:
        cal = calibrate_arms(rig)
        arms = {a: cal[a].arm for a in members}
        target = np.asarray(target, float).reshape(1, 2)
        commands = [np.asarray(arms[a].command(jnp.asarray(target))) for a in members]
        for a, u in zip(members, commands, strict=True):
            check_reach(arms[a], target[0], u[0])
        bar.update()
        bar.set_postfix(f"fitting {model}")
        fitted = fit_noise_models(rig, arms, specs)[model]
        models = [fitted[a] for a in members]
        arm_list = [arms[a] for a in members]
        bar.update()
        bar.set_postfix("grid posterior")
        grid = grid_posterior(models, arm_list, commands, target)
        bar.update()
    doc: dict[str, Any] = {
        "target": [float(x) for x in target[0]],
        "config": config,
        "model": model,
        "commands": {a: [float(x) for x in u[0]] for a, u in zip(members, commands,
                                                                 strict=True)},
        "prior": "flat on the plane (numpyro ImproperUniform); the grid's box holds all but "
                 "edge_mass of the posterior",
        "init": f"NUTS chains and emcee walkers start at the target plus draws of "
                f"{INIT_OVERDISPERSION:g} x the widest arm's prior spread (its joint errors "
                "through its Jacobian), not at the grid",
        "samplers": {"grid": _grid_entry(grid)},
    }

    def starts(n: int, s: int) -> np.ndarray:
        return initial_points(models, arm_list, commands, target, n, s)

    results = _run_and_judge(doc, grid, {
        "nuts": lambda: run_nuts(models, arm_list, commands, starts(num_chains, seed),
                                 seed=seed, num_warmup=num_warmup, num_samples=num_samples,
                                 progress_bar=progress),
        "emcee": lambda: run_emcee(models, arm_list, commands, starts(walkers, seed + 1),
                                   n_steps=steps, burn=burn, seed=seed, progress=progress)},
        tol, burn, sampler)
    if "nuts" in results and any(not is_sampleable(m) for m in models):
        doc["notes"].append(
            "the histogram COND is piecewise constant in the joint errors and zero outside its "
            "table: NUTS follows the gradient of a smooth guide (kde.histogram_guide) and "
            "weighs states by the exact table, so its divergences are trajectories that left "
            "the table's support, where there is no mass to miss")
    return SampleReport(doc, grid, results)


def _side(robot: kin.Robot, arm: str, commands: dict[str, np.ndarray]) -> dict | None:
    """The rest of a linked pose, where the robot's gravity model weighs it."""
    if robot.gravity is None:
        return None
    others = robot.side_arms(arm)
    if not others or any(b not in commands for b in others):
        return None
    return {b: jnp.asarray(commands[b]) for b in others}


def _sample_markers(rig: Rig, config: str, target: Sequence[float], model: str, sampler: str,
                    *, seed: int, progress: bool, groups: tuple[str, ...] | None,
                    models_dir: Any, num_chains: int, walkers: int, steps: int, burn: int,
                    tol: CheckTolerances) -> SampleReport:
    """:func:`sample_linked` on a rig of URDF/DH arms: the shared point of arms aimed at
    ``target`` has the density prod_a p_a(point | u_a) of the arms' marker densities (flat
    prior); NUTS and emcee sample it and a zoomed grid (2-D or 3-D) checks both."""
    from bayesrob.calibrate.least_squares import calibrate
    from bayesrob.data.rig import RigError
    from bayesrob.errors.marker_density import fit_marker_model, marker_model_kind
    from bayesrob.errors.noise_models import discover_models
    from bayesrob.predict.aiming import aim

    members = config.split("+")
    measured = rig.robot.measured_arms()
    unknown = [a for a in members if a not in measured]
    if unknown:
        raise RigError(f"config {config!r}: {unknown[0]!r} is not a measured arm of the rig "
                       f"(measured: {', '.join(measured)})")
    spec = discover_models(models_dir, [model])[0]
    kind = marker_model_kind(spec)
    dim = rig.robot.dim
    target = np.asarray(target, float).reshape(1, dim)
    with Progress(3, "sample", "steps", enabled=progress, postfix="calibrating") as bar:
        cal = calibrate(rig, groups if groups is not None else kin.GROUPS)
        commands = {a: aim(rig, cal.robot, cal.x, a, target) for a in members}
        bar.update()
        bar.set_postfix(f"fitting {model}")
        densities = [fit_marker_model(rig, cal, a, spec, seed=i).density(
            commands[a], _side(cal.robot, a, commands)) for i, a in enumerate(members)]
        arrays = [d.arrays() for d in densities]
        bar.update()
        bar.set_postfix("grid")

        def log_density(p):
            return -_marker_potential(p[None], (), arrays)

        # compiled whole: dispatched op by op, a mixture of a few hundred components in 3-D
        # stalled XLA's CPU runtime for minutes
        grid_ll = jax.jit(lambda p: jax.lax.map(log_density, p, batch_size=1024))
        draws = [d.sample(seed + 7 + i, 2000)[:, 0] for i, d in enumerate(densities)]
        spread = max(float(np.sqrt(np.linalg.eigvalsh(np.cov(x.T)).max())) for x in draws)
        centres = np.array([d.centre[0] for d in densities])
        half = 10.0 * spread + float(np.ptp(centres, axis=0).max())
        grid = zoomed_grid(lambda pts: np.asarray(grid_ll(jnp.asarray(pts[0])))[None],
                           centres.mean(0), Grid(half, MARKER_GRID_N), MARKER_GRID_N)
        bar.update()
    rng = np.random.default_rng(seed)

    def start(n: int) -> np.ndarray:
        # the target plus over-dispersed draws of the arms' own spread, never the grid's
        dev = np.concatenate([x - x.mean(0) for x in draws])
        return target[0] + INIT_OVERDISPERSION * dev[rng.choice(len(dev), n, replace=False)]

    def nuts() -> SamplerResult:
        sampler = _shared_nuts(num_chains, NUTS_WARMUP, NUTS_SAMPLES, True, NUTS_TARGET_ACCEPT)
        sampler.progress_bar = progress
        return sampler.sample(_marker_potential, start(num_chains)[:, None], (), tuple(arrays),
                              seed)

    doc = {
        "target": [float(v) for v in target[0]], "config": config, "model": model,
        "marker_model": kind,
        "commands": {a: [float(v) for v in u[0]] for a, u in commands.items()},
        "prior": f"flat in {dim}-D (numpyro potential of the arms' marker densities); the "
                 "grid's box holds all but edge_mass of the posterior",
        "init": f"NUTS chains and emcee walkers start at the target plus draws of "
                f"{INIT_OVERDISPERSION:g} x the arms' own spread about their centres, not at "
                "the grid",
        "params": list(cal.groups),
        "samplers": {"grid": _grid_entry(grid, box_half_width_mm=half)},
    }
    results = _run_and_judge(doc, grid, {
        "nuts": nuts,
        "emcee": lambda: emcee_density(log_density, start(walkers), n_steps=steps, burn=burn,
                                       seed=seed, progress=progress)},
        tol, burn, sampler, [f"calibrated with --params {','.join(cal.groups)}; each arm aimed "
                             "by its calibrated inverse kinematics"])
    return SampleReport(doc, grid, results)
