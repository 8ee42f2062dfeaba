"""Draws of where an assembly's end point lands: one arm, or any number linked, 2-D or 3-D.

Each arm is calibrated on its own ``train`` rows and its joint-error model fitted to their
residuals: a Parzen density of the joint errors J^-1 r where the rows observe them, else the
latent population (:mod:`bayesrob.errors.latent_errors`). Aimed at a target (:mod:`.aiming`),
an arm's *free* end point is the push-forward of its joint errors through the calibrated
robot. Linked arms share one point (:mod:`.fusion`): ``equilibrium`` (default), where their
elastic forces balance, by forward draws; ``product`` (the paper's rule), the product of the
arms' densities, sampled with NUTS with every arm's joint errors latent.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import numpyro
import numpyro.distributions as dist
from numpyro.infer import MCMC, NUTS

from bayesrob import robot as kin
from bayesrob.calibrate.arms import calibrate_arms
from bayesrob.calibrate.least_squares import Calibration, calibrate, parameter_covariance
from bayesrob.data.rig import Rig, RigError
from bayesrob.errors.distributions import joint_error_distribution
from bayesrob.errors.latent_errors import (
    LatentJointErrors,
    check_latent_model,
    fit_latent_errors,
    joint_jacobian,
    sharing_arms,
)
from bayesrob.errors.noise_models import (
    FittedNoiseModel,
    discover_models,
    fit_noise_models,
    joint_errors_observed,
    observed_joint_errors,
)
from bayesrob.predict.aiming import aim, check_reach
from bayesrob.predict.fusion import DRAWS, FUSIONS, equilibrium, fused_draws
from bayesrob.predict.stiffness import StiffnessPrior, stiffness_draws, stiffness_priors

__all__ = ["CalibratedModules", "PaperModules", "KernelJointErrors", "fit_modules",
           "fit_paper_modules", "fit_joint_errors", "check_module_arms", "assembly_draws",
           "free_draws", "parameter_draws", "product_draws_nuts"]

# Draws x rows pushed through a chain in one compiled call, at most: Justin's 4000 draws at 200
# poses with six sag steps took the process to 23 GB in one call; 16-24 targets stay one.
POINTS_PER_CALL = 100_000


@dataclass
class KernelJointErrors:
    """An arm's Parzen joint-error density fitted to the joint errors its rows observe, drawn
    as :class:`LatentJointErrors` draws."""

    arm: str
    fitted: FittedNoiseModel

    @property
    def noise_sd(self) -> np.ndarray:
        # each row's J^-1 r carried the tracker's noise into the density: none is left over
        return np.zeros(1)

    def draw(self, key: jax.Array, shape: tuple[int, int], u: np.ndarray
             ) -> tuple[jax.Array, jax.Array]:
        """Joint errors (S, T, n) at commands u (T, c) and the noise sds (S,), all zero."""
        d = joint_error_distribution(self.fitted, jnp.atleast_2d(jnp.asarray(u)))
        if d.batch_shape != (shape[1],):
            d = d.expand((shape[1],))
        return d.sample(key, (shape[0],)), jnp.zeros(shape[0])


@dataclass
class CalibratedModules:
    """Calibrated arms, their fitted joint-error models and their stiffness priors."""

    calibration: Calibration
    errors: dict[str, LatentJointErrors | KernelJointErrors]
    stiffness: dict[str, StiffnessPrior]
    # (P, P) the fitted parameters' covariance (zero where fixed), or None: held at their values
    param_cov: np.ndarray | None
    # arm -> (T, c): the columns aiming it at the targets it was fitted for, if any
    commands: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def robot(self) -> kin.Robot:
        return self.calibration.robot

    @property
    def x(self) -> np.ndarray:
        return self.calibration.x

    def draws(self, arms: Sequence[str], commands: Sequence[np.ndarray], targets: np.ndarray,
              fusion: str, num_samples: int = DRAWS, seed: int = 0) -> np.ndarray:
        return assembly_draws(self, arms, commands, fusion, num_samples, seed)


@dataclass
class PaperModules:
    """The paper's planar arms, calibrated by their eight parameters, with kernel joint-error
    models; ``stiffness`` per arm from the rig (N mm / rad), or None (the prior)."""

    arms: dict[str, kin.Arm]
    fitted: dict[str, FittedNoiseModel]
    stiffness: list[np.ndarray | None]
    commands: dict[str, np.ndarray] = field(default_factory=dict)

    def draws(self, arms: Sequence[str], commands: Sequence[np.ndarray], targets: np.ndarray,
              fusion: str, num_samples: int = DRAWS, seed: int = 0) -> np.ndarray:
        given = [self.stiffness[list(self.arms).index(a)] for a in arms]
        return fused_draws([self.fitted[a] for a in arms], [self.arms[a] for a in arms],
                           commands, targets, fusion,
                           given if any(k is not None for k in given) else None, seed,
                           num_samples)


def fit_paper_modules(rig: Rig, arms: Sequence[str], model: str, models_dir: Any = None,
                      targets: np.ndarray | None = None) -> PaperModules:
    """Calibrate the rig's planar arms, aim ``arms`` at ``targets`` by the closed-form inverse
    (refusing, before any model fit, a target out of reach) and fit ``model`` to each."""
    spec = discover_models(models_dir, [model])
    cal = calibrate_arms(rig)
    fitted_arms = {a: cal[a].arm for a in arms}
    commands = {} if targets is None else {a: _aim_arm(fitted_arms[a], targets) for a in arms}
    fitted = fit_noise_models(rig, fitted_arms, spec)[model]
    return PaperModules(fitted_arms, {a: fitted[a] for a in arms},
                        [rig.arms[a].stiffness for a in arms], commands)


def _aim_arm(arm: kin.Arm, targets: np.ndarray) -> np.ndarray:
    u = np.asarray(arm.command(jnp.asarray(targets)))
    for t, ut in zip(targets, u, strict=True):
        check_reach(arm, t, ut)
    return u


def check_module_arms(rig: Rig, arms: Sequence[str], model: str, models_dir: Any = None,
                      latent: bool = False) -> None:
    """Refuse in one line a model or an arm :func:`fit_modules` cannot fit."""
    if not latent and joint_errors_observed(rig.robot, arms):
        discover_models(models_dir, [model])
    else:
        check_latent_model(model)
    measured = rig.robot.measured_arms()
    for a in arms:
        if a not in measured:
            raise RigError(f"{rig.path}: {a!r} is not a measured arm of the rig (measured: "
                           f"{', '.join(measured)})")
        if not rig.measurements.mask(a, "train").any():
            raise RigError(f"{rig.path}: arm {a!r} has no train rows of its own to calibrate "
                           "and fit its joint-error model on")


def fit_joint_errors(rig: Rig, cal: Calibration, arm: str, model: str, seed: int = 0,
                     models_dir: Any = None, latent: bool = False,
                     populations: dict | None = None) -> LatentJointErrors | KernelJointErrors:
    """``arm``'s joint-error model fitted to its train residuals under ``cal``: a Parzen
    density where the rows observe its joint errors, else (or ``latent``) the population
    (one for the arms of a tree, kept in ``populations``: :func:`fit_latent_errors`)."""
    if latent or not joint_errors_observed(cal.robot, [arm]):
        return fit_latent_errors(rig, cal.robot, cal.x, arm, model, int(cal.ident.free.sum()),
                                 seed=seed, populations=populations)
    spec = discover_models(models_dir, [model])[0]
    u, errors = observed_joint_errors(rig, cal.robot, cal.x, arm)
    return KernelJointErrors(arm, spec.fit(errors, u))


def fit_modules(rig: Rig, arms: Sequence[str], model: str = "ind",
                groups: tuple[str, ...] = kin.GROUPS, seed: int = 0,
                calibration: Calibration | None = None,
                parameter_uncertainty: bool = False, masses: str = "fitted",
                sag_steps: int = 1, targets: np.ndarray | None = None,
                models_dir: Any = None, latent: bool = False,
                linked: bool = False) -> CalibratedModules:
    """Calibrate the rig on single-arm train rows and fit each of ``arms``' joint errors
    (``linked``: the arms are one assembly, so those sharing joints take one population).

    ``parameter_uncertainty``: also draw the parameters from their covariance
    (:func:`parameter_covariance`). Off by default: on the tuning rigs (arm6 seeds 11, 12) it
    once made the regions too wide (error ratio 1.17 and 1.03 with it, 1.07 and 0.96
    without); since the covariance is checked against the rows it changes them little (0.965
    and 1.031 with it, 0.964 and 1.030 without, linked within q50 0.27 against 0.23) and
    costs the check's 3-5 s. ``masses``, ``sag_steps``: :func:`calibrate`'s.
    ``targets``: aimed at (kept in ``commands``) before the joint-error fits, so a target out
    of reach is refused after the calibration alone.
    """
    check_module_arms(rig, arms, model, models_dir, latent)
    cal = (calibration if calibration is not None
           else calibrate(rig, groups, masses=masses, sag_steps=sag_steps))
    commands = ({} if targets is None
                else {a: aim(rig, cal.robot, cal.x, a, targets) for a in arms})
    # Linked hands of one tree take one population of all their joints, so the torso errs
    # alike for both (docs/fusion.md); an arm alone keeps its own rows' population.
    shared = linked and any(len(set(sharing_arms(cal.robot, a)) & set(arms)) > 1
                            for a in arms)
    populations: dict | None = {} if shared else None
    errors = {a: fit_joint_errors(rig, cal, a, model, seed + i, models_dir, latent,
                                  populations)
              for i, a in enumerate(arms)}
    stiffness = stiffness_priors(rig, arms, cal)
    cov = parameter_covariance(rig, cal) if parameter_uncertainty else None
    return CalibratedModules(cal, errors, stiffness, cov, commands)


def parameter_draws(mods: CalibratedModules, key: jax.Array, n: int) -> jax.Array:
    """Parameter vectors (S, P) from the calibration's Gaussian approximation, one per draw
    shared by every arm (the arms of a tree share links and the instrument)."""
    if mods.param_cov is None:
        return jnp.broadcast_to(jnp.asarray(mods.x), (n, len(mods.x)))
    w, v = np.linalg.eigh(mods.param_cov)
    # An eigenvector's sign is arbitrary and LAPACK builds and thread counts pick differently:
    # each is turned so its largest entry is positive, so a key gives the same draws in every
    # process (a Dask worker and the client alike).
    v = v * np.sign(v[np.argmax(np.abs(v), axis=0), np.arange(v.shape[1])])
    root = v * np.sqrt(np.clip(w, 0.0, None))
    z = jax.random.normal(key, (n, len(w)))
    return jnp.asarray(mods.x) + z @ jnp.asarray(root).T


def free_draws(mods: CalibratedModules, arm: str, u: np.ndarray, xs: jax.Array, key: jax.Array,
                side: dict[str, np.ndarray] | None = None, measured: bool = True,
                drawn: tuple[jax.Array, jax.Array] | None = None) -> np.ndarray:
    """Draws (S, T, dim) of the arm's free end point at columns u (T, c), a parameter vector
    of xs (S, P) per draw (``side``: the rest of each pose), with the tracker's noise if
    ``measured``; ``drawn``: its joint errors and noise sds, where drawn already."""
    n = xs.shape[0]
    e, noise = drawn if drawn is not None else mods.errors[arm].draw(key, (n, len(u)), u)
    # the rest of the pose weighs only where the model has gravity in it
    rest = (None if side is None or mods.robot.gravity is None
            else {b: jnp.asarray(v) for b, v in side.items()})
    push = _points_with_errors(mods.robot, arm)
    rows = jnp.asarray(u)
    per_call = max(1, POINTS_PER_CALL // max(1, len(u)))
    calls = max(1, -(-n // per_call))
    size = -(-n // calls)  # equal slices: one compiled shape (one more for a short last one)
    if calls == 1:
        pts = push(xs, rows, e, rest)
    else:
        # sliced on the host and each slice finished before the next starts: slicing device
        # arrays compiles a program per offset while earlier slices still run, and under the
        # persistent compilation cache one such run ended in a crash inside XLA's serialiser
        xs, e = np.asarray(xs), np.asarray(e)
        pts = np.concatenate([np.asarray(push(xs[i:i + size], rows, e[i:i + size], rest))
                              for i in range(0, n, size)])
    if not measured:
        return np.asarray(pts)
    eps = jax.random.normal(jax.random.fold_in(key, 1), pts.shape) * noise[:, None, None]
    return np.asarray(pts + eps)


@partial(jax.jit, static_argnames=("structure", "arm"))
def _points_with_errors_program(structure: kin.RobotStructure, arm: str, values: dict,
                                xs: jax.Array, u: jax.Array, e: jax.Array,
                                side: dict[str, jax.Array] | None) -> jax.Array:
    robot = structure.robot(values)
    return jax.vmap(lambda x, u, e, side: robot.marker_points(x, arm, u, e, side),
                    in_axes=(0, None, 0, None))(xs, u, e, side)


def _points_with_errors(robot: kin.Robot, arm: str) -> Callable:
    """(xs (S, P), u (T, c), e (S, T, n), side) -> points (S, T, dim), one program per structure."""
    return partial(_points_with_errors_program, robot.structure, arm, robot.nominal_values)


def assembly_draws(mods: CalibratedModules, arms: Sequence[str], commands: Sequence[np.ndarray],
                fusion: str = "equilibrium", num_samples: int = DRAWS, seed: int = 0,
                side: dict[str, np.ndarray] | None = None) -> np.ndarray:
    """Draws (S, T, dim) of one arm's end point or linked arms' shared point. ``side`` (one
    arm only): the other arms' columns in the same rows, whose weight bends shared chains."""
    if fusion not in FUSIONS:
        raise ValueError(f"unknown fusion {fusion!r}; choose from {', '.join(FUSIONS)}")
    key = jax.random.PRNGKey(seed)
    commands = [np.atleast_2d(np.asarray(u, float)) for u in commands]
    if fusion == "product" and len(arms) > 1:
        if any(isinstance(mods.errors[a], KernelJointErrors) for a in arms):
            raise ValueError("the product rule samples linked chain arms under latent joint-"
                             "error populations; kernel densities take the equilibrium rule")
        return product_draws_nuts(mods, arms, commands, seed=seed, num_samples=num_samples)
    xs = parameter_draws(mods, jax.random.fold_in(key, 99), num_samples)
    linked = len(arms) > 1
    # Linked, the free points are drawn without the tracker's noise and the balance is
    # measured once, with all of it (below): the balance would average the noise each free
    # point carried.
    if not linked:
        return free_draws(mods, arms[0], commands[0], xs, jax.random.fold_in(key, 1), side)
    drawn = _linked_joint_errors(mods, arms, commands, key, num_samples)
    free = [free_draws(mods, a, u, xs, jax.random.fold_in(key, i + 1), measured=False,
                       drawn=d)
            for i, (a, u, d) in enumerate(zip(arms, commands, drawn, strict=True))]
    jacs = [joint_jacobian(mods.robot, jnp.asarray(mods.x), a, jnp.asarray(u))
            for a, u in zip(arms, commands, strict=True)]
    # The joint Jacobian at the commanded pose serves every draw: joint errors of a few mrad
    # change it by parts in a thousand.
    log_k = stiffness_draws([mods.stiffness[a] for a in arms], jax.random.fold_in(key, 0),
                            num_samples)
    d = equilibrium(free, jacs, log_k)
    # each arm's population has its own fitted estimate of the one tracker's noise: their mean
    noise = float(np.mean([np.mean(mods.errors[a].noise_sd) for a in arms]))
    # a key of the parameters' branch: the arms' own keys are 1, 2, ... for any number of arms
    eps = jax.random.normal(jax.random.fold_in(jax.random.fold_in(key, 99), 1), d.shape)
    return np.asarray(d + noise * eps)


def _linked_joint_errors(mods: CalibratedModules, arms: Sequence[str],
                         commands: Sequence[np.ndarray], key: jax.Array, n: int
                         ) -> list[tuple[jax.Array, jax.Array] | None]:
    """Linked arms' joint errors where they share joints (a tree's hands on one torso: one
    population, drawn once, each arm its columns of it, so the torso errs alike for both), else
    None (each arm draws its own with its own key, as alone)."""
    pops = [getattr(mods.errors[a], "population", None) for a in arms]
    if pops[0] is None or any(p is not pops[0] for p in pops):
        return [None] * len(arms)
    t = len(commands[0])
    e, noise = pops[0].draw(jax.random.fold_in(key, 1), (n, t))
    return [(e[..., mods.errors[a].columns], noise) for a in arms]


def _product_model(commands, robot, x, arms, covs, noises, start) -> None:
    t, dim = start.shape
    p = numpyro.sample("p", dist.ImproperUniform(dist.constraints.real_vector, (t,), (dim,)))
    for i, (a, u, cov, s) in enumerate(zip(arms, commands, covs, noises, strict=True)):
        n = cov.shape[0]
        chol = jnp.linalg.cholesky(cov + 1e-18 * jnp.eye(n))
        z = numpyro.sample(f"z_{i}", dist.Normal(0.0, 1.0).expand([t, n]).to_event(2))
        e = z @ chol.T
        f = robot.marker_points(x, a, u, e)
        numpyro.sample(f"link_{i}", dist.Normal(f, s).to_event(2), obs=p)


@partial(jax.jit, static_argnames=("structure", "arms", "warmup", "per_chain", "chains"))
def _product_nuts(key: jax.Array, structure: kin.RobotStructure, values: dict, x: jax.Array,
                  arms: tuple[str, ...], commands: list, covs: list, noises: jax.Array,
                  start: jax.Array, warmup: int, per_chain: int, chains: int) -> jax.Array:
    # The robot's numbers are arguments: an MCMC built per call with them baked in compiled
    # anew for every rig and kept its code mapped.
    from numpyro.infer import init_to_value

    init = {"p": start, **{f"z_{i}": jnp.zeros((start.shape[0], c.shape[0]))
                           for i, c in enumerate(covs)}}
    kernel = NUTS(_product_model, init_strategy=init_to_value(values=init), dense_mass=False,
                  target_accept_prob=0.85)
    mcmc = MCMC(kernel, num_warmup=warmup, num_samples=per_chain, num_chains=chains,
                chain_method="sequential", progress_bar=False)
    mcmc.run(key, commands, structure.robot(values), x, arms, covs, list(noises), start)
    return mcmc.get_samples()["p"]


def product_draws_nuts(mods: CalibratedModules, arms: Sequence[str], commands: Sequence[np.ndarray],
                       seed: int = 0, num_samples: int = DRAWS, warmup: int = 500,
                       chains: int = 2) -> np.ndarray:
    """NUTS draws (S, T, dim) of the shared point under the product of the arms' densities,
    the populations at their posterior means (a mixture over them would make the target
    multimodal in Sigma for nothing the draws could resolve)."""
    commands = [jnp.asarray(np.atleast_2d(np.asarray(u, float))) for u in commands]
    covs = [jnp.asarray(mods.errors[a].covariance.mean(0)) for a in arms]
    noises = jnp.asarray([float(mods.errors[a].noise_sd.mean()) for a in arms])
    x = jnp.asarray(mods.x)
    start = jnp.mean(jnp.stack([mods.robot.compiled_points(a)(x, u)
                                for a, u in zip(arms, commands, strict=True)]), axis=0)
    p = _product_nuts(jax.random.PRNGKey(seed), mods.robot.structure, mods.robot.nominal_values,
                      x, tuple(arms), commands, covs, noises, start, warmup,
                      -(-num_samples // chains), chains)
    return np.asarray(p)[:num_samples]
