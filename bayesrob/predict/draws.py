"""Accuracy predictions for chain robots (URDF / DH arms, 2-D or 3-D), alone or linked.

Each arm is calibrated on its own ``train`` rows and its joint-error population fitted to their
residuals (:mod:`bayesrob.latent_errors`). At a target, each arm is aimed through its calibrated
model (position-only inverse kinematics, the minimum-norm solution nearest the train pose that
came closest, or the next closest where that one leaves the train commands' range), and its
*free* end point is the push-forward of the population: draws of
(Sigma, s), then of the joint errors e ~ N(0, Sigma), through the calibrated chain, plus
N(0, s^2) for what no joint explains.

Linked arms share one point:

- ``equilibrium`` (default): the point where the arms' elastic forces balance, linearised about
  the free points as in :mod:`bayesrob.fusion`. A redundant arm's Cartesian compliance is
  C_a = J_a diag(1 / k_a) J_a^T (J_a: 3 x n, k_a its joint stiffnesses), its stiffness
  K_a = C_a^-1, and d = (sum_a K_a)^-1 sum_a K_a d_a; for a square J this is the planar
  J^-T diag(k) J^-1. Stiffnesses: the rig's ``stiffness`` when given, else a log-normal prior
  centred on the joints' URDF torque limits, with a term per arm and one per joint
  (CHAIN_STIFFNESS_*); where every linked arm takes the prior, each arm's term is centred on
  its fitted sag against the others' (:func:`sag_scaled_priors`).
  Forward draws (``numpyro.infer.Predictive``), no sampler needed.
- ``product`` (the paper's rule): the density of the shared point is the product of the arms'
  end-point densities. Every arm's joint errors and the shared point are latent and sampled
  together with NUTS: p ~ flat, e_a ~ N(0, Sigma_a), p ~ N(f_a(e_a), s_a^2) for each arm a.

Densities of draws are Gaussian KDEs (Scott's rule, :func:`bayesrob.kde.kde_log_density`);
region sizes are the volumes (areas in 2-D) of the 50% / 90% highest-density regions, by
Monte Carlo: vol{p > c} = E_p[1{p > c} / p].
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import numpyro
import numpyro.distributions as dist
from numpyro.infer import MCMC, NUTS, Predictive

from bayesrob import kinematics as kin
from bayesrob.aiming import aim_chain
from bayesrob.calibration import ChainCalibration, calibrate_chain, chain_parameter_covariance
from bayesrob.fusion import DRAWS, FUSIONS
from bayesrob.kde import kde_bandwidth, kde_log_density
from bayesrob.latent_errors import (
    LatentJointErrors,
    check_latent_model,
    fit_latent_errors,
    joint_jacobian,
)
from bayesrob.rig import Rig, RigError

__all__ = ["ChainModules", "StiffnessPrior", "fit_chain_modules", "aim_chain", "chain_draws",
           "chain_equilibrium", "free_draws", "parameter_draws", "stiffness_draws",
           "arm_sags", "sag_scaled_priors", "stiffness_priors",
           "hdr_levels", "hdr_sizes", "product_draws_nuts", "predict_chain_points"]

VOLUME_POINTS = 800  # draws at which the region-volume estimator is evaluated
# Draws x rows pushed through a chain in one compiled call, at most (one draw at least). A
# call holds every draw's frames at once: Justin's 4000 draws at 200 validation poses, with
# the sag's torques taken six times, took the process to 23 GB in one call; a rig's 16-24
# targets stay one call.
POINTS_PER_CALL = 100_000
# The joint stiffness prior when the rig does not give them. Chosen on two sets of linked
# tuning rigs (arm6 --linked, each seed drawing its own arms' stiffnesses; 201-206, 24 points
# each, and 271-282, 8 each: 240 points; `bench_predict_3d.py --coverage tuning [--many-rigs]
# --variants`) as the prior whose pooled 50% / 90% coverage came closest to nominal: 0.47 /
# 0.96 (arm sd 0.5, chosen on 201-206 alone before: 0.64 / 0.98). Tried: per-joint sd 0.25 /
# 0.5 / 0.75, arm sd 0 / 0.25 / 0.5, centred on equal joints or on the torque limits. No prior
# moves the mean error's ratio by much (1.14-1.27 over all 18 on 271-282).
CHAIN_STIFFNESS_LOG_SD = 0.5  # each joint's own
CHAIN_STIFFNESS_ARM_LOG_SD = 0.25  # shared by an arm's joints: an arm stiffer or softer as a whole
# Where the prior is centred: "effort", each joint's stiffness in proportion to its URDF torque
# limit (a bigger drive is a stiffer one; equal joints where the file gives no limit), or
# "equal" joints
CHAIN_STIFFNESS_CENTRE = "effort"
# Where the arm term is centred when every linked arm takes the prior: "sags", each arm's log
# stiffness scale set against the others' by its fitted sag at the poses they were all trained
# on (:func:`sag_scaled_priors`), or "equal" arms (the two sds above).
CHAIN_STIFFNESS_ARM_CENTRE = "sags"
# The sag-centred prior's own per-joint and arm-term log sds: chosen on the tuning rigs
# 271-282 and 201-206 (`bench_predict_3d.py --coverage tuning [--many-rigs] --sag-variants`,
# 240 points) by a rule written before the sweep, the smallest largest miss relative to each
# target's half-width: 0.512 / 0.892, error ratio 0.929, against 0.471 / 0.958, 1.081 for the
# equal-arms prior (docs/fusion.md)
SAG_SCALED_LOG_SD = 0.4
SAG_SCALED_ARM_LOG_SD = 0.5
# How far a robot description's link masses are trusted (log sd): a compliance fitted under
# them carries their error into the stiffness read from it.
DESCRIBED_MASS_LOG_SD = 0.1


@dataclass
class ChainModules:
    """Calibrated chain arms and their fitted joint-error populations."""

    calibration: ChainCalibration
    errors: dict[str, LatentJointErrors]
    # per arm: the log joint stiffnesses' prior
    stiffness: dict[str, StiffnessPrior]
    # (P, P) the fitted parameters' covariance (zero where fixed), or None: held at their values
    param_cov: np.ndarray | None

    @property
    def robot(self) -> kin.Robot:
        return self.calibration.robot

    @property
    def x(self) -> np.ndarray:
        return self.calibration.x


def check_module_arms(rig: Rig, arms: Sequence[str], model: str) -> None:
    """Refuse, in one line, a joint-error model or an arm :func:`fit_chain_modules` cannot fit
    (not measured, or without train rows of its own)."""
    check_latent_model(model)
    measured = rig.robot.measured_arms()
    for a in arms:
        if a not in measured:
            raise RigError(f"{rig.path}: {a!r} is not a measured arm of the rig (measured: "
                           f"{', '.join(measured)})")
        if not rig.measurements.mask(a, "train").any():
            raise RigError(f"{rig.path}: arm {a!r} has no train rows of its own to calibrate "
                           "and fit its joint-error model on")


def fit_chain_modules(rig: Rig, arms: Sequence[str], model: str = "ind",
                      groups: tuple[str, ...] = kin.GROUPS, seed: int = 0,
                      calibration: ChainCalibration | None = None,
                      parameter_uncertainty: bool = False,
                      masses: str = "fitted", sag_steps: int = 1) -> ChainModules:
    """Calibrate the rig on single-arm train rows and fit each of ``arms``' joint errors.

    ``parameter_uncertainty``: also draw the calibrated parameters from their Gauss-Newton
    covariance. Off by default: on the tuning rigs (arm6 seeds 11 and 12) it made the regions
    too wide (predicted / observed error 1.17 and 1.03 with it, 1.07 and 0.96 without), the
    residual scaling for the fit's degrees of freedom having already widened them.
    ``masses`` ("fitted" or "description"): as :func:`calibrate_chain`'s, for the calibration
    made here (a ``calibration`` given carries its own); with the description's masses and a
    compliance group, the arms' stiffnesses come from the fitted compliances instead of the
    prior. ``sag_steps``: as :func:`calibrate_chain`'s (the joint-error fits and predictions
    use the calibration's robot, so its sag model too).
    """
    check_module_arms(rig, arms, model)  # before the calibration, which takes the time
    cal = (calibration if calibration is not None
           else calibrate_chain(rig, groups, masses=masses, sag_steps=sag_steps))
    n_free = int(cal.ident.free.sum())
    errors = {a: fit_latent_errors(rig, cal.robot, cal.x, a, model, n_free, seed=seed + i)
              for i, a in enumerate(arms)}
    stiffness = stiffness_priors(rig, arms, cal)
    cov = chain_parameter_covariance(rig, cal) if parameter_uncertainty else None
    return ChainModules(cal, errors, stiffness, cov)


class StiffnessPrior(NamedTuple):
    """An arm's log joint stiffnesses along its path (mounts first): Normal(centre, sd) per
    joint (sd 0: known), plus the prior's arm term where ``shared`` (an arm stiffer or softer
    as a whole, where nothing fixes its scale). ``source`` says where it came from, in words
    a report can print: one of ``STIFFNESS_SOURCES``."""

    centre: np.ndarray
    sd: np.ndarray
    shared: np.ndarray
    source: str
    # the arm term's mean (the arm's log stiffness scale against the other linked arms') and
    # sd (None: CHAIN_STIFFNESS_ARM_LOG_SD)
    arm_centre: float = 0.0
    arm_sd: float | None = None

    def arm_term_sd(self) -> float:
        """The arm term's log sd: its own, else CHAIN_STIFFNESS_ARM_LOG_SD as it stands now
        (a sweep of priors sets it between draws)."""
        return CHAIN_STIFFNESS_ARM_LOG_SD if self.arm_sd is None else self.arm_sd

    def record(self) -> dict[str, Any]:
        """What the balance draws this arm's joint stiffnesses from, for a report (``predict``'s
        JSON ``stiffness.<arm>``, ``design.json``'s ``stiffness[]``): ``from``, medians (N mm/rad;
        ``relative`` to the arm's first joint under the prior, whose scale is arbitrary), log
        sds, and ``arm_log_centre`` (the arm's log scale against the other linked arms', 0
        unless their fitted sags set it); under the prior also the arm term's sd."""
        k = np.exp(self.centre)
        out: dict[str, Any] = {"from": self.source}
        if np.any(self.shared):
            out |= {"relative": [float(v) for v in k / k[0]],
                    "log_sd": [float(v) for v in self.sd], "arm_log_sd": self.arm_term_sd()}
        else:
            out |= {"nmm_per_rad": [float(v) for v in k], "log_sd": [float(v) for v in self.sd]}
        return out | {"arm_log_centre": float(self.arm_centre)}


STIFFNESS_SOURCES = ("the rig", "compliances fitted under the URDF's masses", "the prior",
                     "the prior, the arms scaled by their fitted sags")


def _stiffness_prior(rig: Rig, arm: str, cal: ChainCalibration | None = None
                     ) -> StiffnessPrior:
    """The log joint stiffnesses along the path to ``arm``: the rig's ``stiffness`` when it
    gives them; else, from a calibration whose compliances were fitted under the description's
    masses (``masses="description"``), each seen joint's own and the rest scaled to them; else
    the prior."""
    parts = [getattr(rig.arms[c.name], "stiffness", None) for c in rig.robot.path(arm)]
    if all(p is not None for p in parts):
        k = np.concatenate(parts)
        return StiffnessPrior(np.log(k), np.zeros_like(k), np.zeros(k.shape, bool),
                              STIFFNESS_SOURCES[0])
    n = rig.robot.n_path_joints(arm)
    efforts = [c.source.get("efforts") for c in rig.robot.path(arm)]
    centre = (np.log(np.concatenate(efforts))
              if CHAIN_STIFFNESS_CENTRE == "effort" and all(e is not None for e in efforts)
              else np.zeros(n))
    sd = np.full(n, CHAIN_STIFFNESS_LOG_SD)
    if cal is None or cal.masses != "description" or "compliance" not in cal.groups:
        # Not from compliances fitted with the masses: then only compliance x first moment is
        # identified, so each arm's compliances carry its own unknown mass scale. Read as
        # stiffnesses they put the arms' ratio 4.5 times off on a report rig (seed 2) and
        # overflowed on another (seed 1), though they helped on the tuning rigs.
        return StiffnessPrior(centre, sd, np.ones(n, bool), STIFFNESS_SOURCES[2])
    layout = cal.robot.layout
    every = np.arange(layout.nominal.size)
    idx = np.concatenate([every[layout.slices[c.name, "compliance"]]
                          for c in rig.robot.path(arm)])
    c, se, free = cal.x[idx], cal.se[idx], cal.ident.free[idx]
    seen = free & (c > 0) & np.isfinite(se)
    if not seen.any():
        return StiffnessPrior(centre, sd, np.ones(n, bool), STIFFNESS_SOURCES[2])
    # The prior, log k_j = scale + profile_j + N(0, sd), updated by the fitted compliances
    # (each log k_j measured with its standard error and the masses' accuracy): the arm's
    # scale is their precision-weighted mean about the profile, so a poorly seen joint (a
    # wrist that gravity hardly turns) neither sets it nor leaves the profile by much; a joint
    # gravity never turns (a vertical axis) keeps the profile at that scale.
    y = -np.log(np.where(seen, c, 1.0))
    var_fit = (se / np.where(seen, c, 1.0)) ** 2 + DESCRIBED_MASS_LOG_SD**2
    w = np.where(seen, 1.0 / (sd**2 + var_fit), 0.0)
    scale = np.sum(w * (y - centre)) / w.sum()
    prior_mean, prior_var = centre + scale, sd**2 + 1.0 / w.sum()
    post_var = np.where(seen, 1.0 / (1.0 / prior_var + 1.0 / np.where(seen, var_fit, 1.0)),
                        prior_var)
    centre = np.where(seen, post_var * (prior_mean / prior_var + y / var_fit), prior_mean)
    sd = np.sqrt(post_var)
    return StiffnessPrior(centre, sd, np.zeros(n, bool), STIFFNESS_SOURCES[1])


def arm_sags(rig: Rig, cal: ChainCalibration, arms: Sequence[str]) -> dict[str, float] | None:
    """Each arm's mean fitted sag (mm): how far its marker moves when its own chains'
    compliances are set to zero, over the train poses of all ``arms`` pooled, so every arm is
    weighed at the same poses. None where that cannot be read: the arms' paths differ in
    joints (no common poses), the calibration fitted no compliance or has no gravity, or an
    arm shows no sag."""
    robot = cal.robot
    if ("compliance" not in cal.groups or robot.gravity is None or len(arms) < 2
            or len({robot.n_path_joints(a) for a in arms}) > 1):
        return None
    shared = set.intersection(*({c.name for c in robot.path(a)} for a in arms))
    u = jnp.asarray(np.concatenate([rig.rows(a, "train")[0] for a in arms]))
    sags = {}
    for a in arms:
        rigid = np.array(cal.x, float)
        for c in robot.path(a):
            if c.name not in shared:
                rigid[robot.layout.slices[c.name, "compliance"]] = 0.0
        points = robot.compiled_points(a)
        moved = np.asarray(points(jnp.asarray(cal.x), u) - points(jnp.asarray(rigid), u))
        sags[a] = float(np.linalg.norm(moved, axis=1).mean())
    if not all(np.isfinite(v) and v > 0 for v in sags.values()):
        return None
    return sags


def sag_scaled_priors(rig: Rig, cal: ChainCalibration, priors: dict[str, StiffnessPrior]
                      ) -> dict[str, StiffnessPrior]:
    """``priors`` with each arm's term centred on its fitted sag against the others' (log k_a
    = -log sag_a + the mean of log sag over the arms), where every arm took the prior and
    CHAIN_STIFFNESS_ARM_CENTRE is "sags"; else as given.

    Only the ratios of the arms' stiffnesses move the balance, and the prior alone treats
    the arms alike. A calibration that fits compliance without the masses identifies each
    joint's compliance times the first moment it carries, not the stiffness; but arms of one
    model carry alike moments, so an arm that sags further is the softer one. On the tuning
    rigs (271-282, 201-206) the log ratio of two arms' sags followed their true log stiffness
    ratio with slope -0.98 / -0.94 (Spearman -0.91 / -0.94), scattered by about 0.25
    (docs/fusion.md). Its sds are SAG_SCALED_LOG_SD per joint and SAG_SCALED_ARM_LOG_SD per
    arm.
    """
    if (CHAIN_STIFFNESS_ARM_CENTRE != "sags"
            or any(p.source != STIFFNESS_SOURCES[2] for p in priors.values())):
        return priors
    sags = arm_sags(rig, cal, list(priors))
    if sags is None:
        return priors
    log_sag = {a: np.log(v) for a, v in sags.items()}
    mean = float(np.mean(list(log_sag.values())))
    return {a: p._replace(sd=np.full_like(p.sd, SAG_SCALED_LOG_SD), arm_centre=mean - log_sag[a],
                          arm_sd=SAG_SCALED_ARM_LOG_SD, source=STIFFNESS_SOURCES[3])
            for a, p in priors.items()}


def stiffness_priors(rig: Rig, arms: Sequence[str], cal: ChainCalibration
                     ) -> dict[str, StiffnessPrior]:
    """The log joint stiffnesses' prior of each of ``arms``, linked: each arm's own
    (:func:`_stiffness_prior`), their arm terms then centred on their fitted sags
    (:func:`sag_scaled_priors`)."""
    return sag_scaled_priors(rig, cal, {a: _stiffness_prior(rig, a, cal) for a in arms})


def _log_stiffness_prior(priors: Sequence[StiffnessPrior]) -> None:
    """Each arm's joint log stiffnesses: Normal(centre, sd) per joint (sd 0: known), plus,
    where the prior marks them ``shared``, a Normal(arm_centre, arm_term_sd()) term the arm's
    joints share: an arm as a whole is stiffer or softer than another."""
    for i, p in enumerate(priors):
        z = numpyro.sample(f"log_stiffness_z_{i}",
                           dist.Normal(0.0, 1.0).expand([len(p.centre)]).to_event(1))
        whole = numpyro.sample(f"log_stiffness_arm_{i}", dist.Normal(0.0, 1.0))
        shared = jnp.where(jnp.asarray(p.shared), p.arm_centre + p.arm_term_sd() * whole, 0.0)
        numpyro.deterministic(f"log_stiffness_{i}",
                              jnp.asarray(p.centre) + jnp.asarray(p.sd) * z + shared)


def stiffness_draws(priors: Sequence[StiffnessPrior], key: jax.Array,
                    num_samples: int) -> list[jax.Array]:
    """Draws (S, n_a) of each arm's joint log stiffnesses from their prior (centre, sd)."""
    sites = Predictive(_log_stiffness_prior, num_samples=num_samples)(key, priors)
    return [jnp.broadcast_to(sites[f"log_stiffness_{i}"], (num_samples, len(p.centre)))
            for i, p in enumerate(priors)]


def chain_equilibrium(free: Sequence[jax.Array], jacs: Sequence[jax.Array],
                      log_k: Sequence[jax.Array], tracker_noise_mm: float = 0.0,
                      key: jax.Array | None = None) -> jax.Array:
    """The balance (S, T, dim) of free points (each (S, T, dim)) held by arms with joint
    Jacobians (T, dim, n_a) and log joint stiffnesses (S, n_a).

    ``tracker_noise_mm`` (with ``key``): the tracker's noise, sd per axis. Each free point
    carries it (the joint-error populations were fitted to measured points) and the balance
    averages it down to sum_a W_a W_a^T sigma^2 (W_a = (sum K)^-1 K_a), but the linked point
    is measured once, with all of it: sigma^2 (I - sum_a W_a W_a^T) is added back, as
    :func:`bayesrob.fusion.equilibrium_program` does in the plane.
    """
    springs = [jnp.linalg.inv(jnp.einsum("tik,sk,tjk->stij", j, jnp.exp(-lk), j))
               for j, lk in zip(jacs, log_k, strict=True)]
    k = jnp.stack(springs)
    total = k.sum(0)
    pull = jnp.einsum("astij,astj->sti", k, jnp.stack([jnp.asarray(f) for f in free]))
    d = jnp.linalg.solve(total, pull[..., None])[..., 0]
    if tracker_noise_mm <= 0:
        return d
    if key is None:
        raise ValueError("tracker noise needs a random key")
    w = jnp.linalg.solve(total[None], k)  # (A, S, T, dim, dim)
    dim = d.shape[-1]
    cov = tracker_noise_mm**2 * (jnp.eye(dim) - jnp.einsum("astij,astkj->stik", w, w))
    vals, vecs = jnp.linalg.eigh(0.5 * (cov + jnp.swapaxes(cov, -1, -2)))
    # a sum of W W^T can poke past I by rounding: its negative eigenvalues are clipped
    root = jnp.einsum("...ij,...j,...kj->...ik", vecs, jnp.sqrt(jnp.clip(vals, 0.0)), vecs)
    return d + jnp.einsum("stij,stj->sti", root, jax.random.normal(key, d.shape))


def parameter_draws(mods: ChainModules, key: jax.Array, n: int) -> jax.Array:
    """Parameter vectors (S, P) from the calibration's Gaussian approximation: one per draw,
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


def free_draws(mods: ChainModules, arm: str, u: np.ndarray, xs: jax.Array, key: jax.Array,
                side: dict[str, np.ndarray] | None = None, measured: bool = True
                ) -> np.ndarray:
    """Draws (S, T, dim) of the arm's free end point at columns u (T, c), one parameter
    vector of xs (S, P) per draw (``side``: the rest of each pose, where it weighs), as the
    tracker measures it (``measured``: with its noise) or as it is."""
    n = xs.shape[0]
    e, noise = mods.errors[arm].draw(key, (n, len(u)))
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
    """A jitted (xs (S, P), u (T, c), e (S, T, n), side or None) -> points (S, T, dim),
    compiled once per process for all robots of ``robot``'s structure."""
    return partial(_points_with_errors_program, robot.structure, arm, robot.nominal_values)


def chain_draws(mods: ChainModules, arms: Sequence[str], commands: Sequence[np.ndarray],
                fusion: str = "equilibrium", num_samples: int = DRAWS, seed: int = 0,
                side: dict[str, np.ndarray] | None = None) -> np.ndarray:
    """Draws (S, T, dim) of one arm's end point or of linked arms' shared point. ``side``
    (one arm only): the other arms' path columns in the same rows, whose weight bends the
    chains they share when the model has gravity in it."""
    if fusion not in FUSIONS:
        raise ValueError(f"unknown fusion {fusion!r}; choose from {', '.join(FUSIONS)}")
    key = jax.random.PRNGKey(seed)
    commands = [np.atleast_2d(np.asarray(u, float)) for u in commands]
    if fusion == "product" and len(arms) > 1:
        return product_draws_nuts(mods, arms, commands, seed=seed, num_samples=num_samples)
    xs = parameter_draws(mods, jax.random.fold_in(key, 99), num_samples)
    linked = len(arms) > 1
    # Linked, the free points are drawn without the tracker's noise and the balance is
    # measured once, with all of it (below): the balance would average the noise each free
    # point carried.
    free = [free_draws(mods, a, u, xs, jax.random.fold_in(key, i + 1),
                        None if linked else side, measured=not linked)
            for i, (a, u) in enumerate(zip(arms, commands, strict=True))]
    if not linked:
        return free[0]
    jacs = [joint_jacobian(mods.robot, jnp.asarray(mods.x), a, jnp.asarray(u))
            for a, u in zip(arms, commands, strict=True)]
    # The joint Jacobian at the commanded pose serves every draw: joint errors of a few mrad
    # change it by parts in a thousand.
    log_k = stiffness_draws([mods.stiffness[a] for a in arms], jax.random.fold_in(key, 0),
                            num_samples)
    d = chain_equilibrium(free, jacs, log_k)
    # each arm's population has its own fitted estimate of the one tracker's noise: their mean
    noise = float(np.mean([np.mean(mods.errors[a].noise_sd) for a in arms]))
    # a key of the parameters' branch: the arms' own keys are 1, 2, ... for any number of arms
    eps = jax.random.normal(jax.random.fold_in(jax.random.fold_in(key, 99), 1), d.shape)
    return np.asarray(d + noise * eps)


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


def product_draws_nuts(mods: ChainModules, arms: Sequence[str], commands: Sequence[np.ndarray],
                       seed: int = 0, num_samples: int = DRAWS, warmup: int = 500,
                       chains: int = 2) -> np.ndarray:
    """NUTS draws (S, T, dim) of the shared point under the product of the arms' densities.

    The population parameters are held at their posterior means (a mixture over them would
    make the target multimodal in Sigma for nothing the draws could resolve).
    """
    from numpyro.infer import init_to_value

    commands = [jnp.asarray(np.atleast_2d(np.asarray(u, float))) for u in commands]
    covs = [jnp.asarray(mods.errors[a].covariance.mean(0)) for a in arms]
    noises = [float(mods.errors[a].noise_sd.mean()) for a in arms]
    x = jnp.asarray(mods.x)
    start = jnp.mean(jnp.stack([mods.robot.compiled_points(a)(x, u)
                                for a, u in zip(arms, commands, strict=True)]), axis=0)
    init = {"p": start, **{f"z_{i}": jnp.zeros((start.shape[0], c.shape[0]))
                           for i, c in enumerate(covs)}}
    kernel = NUTS(_product_model, init_strategy=init_to_value(values=init), dense_mass=False,
                  target_accept_prob=0.85)
    per_chain = -(-num_samples // chains)
    mcmc = MCMC(kernel, num_warmup=warmup, num_samples=per_chain, num_chains=chains,
                chain_method="sequential", progress_bar=False)
    mcmc.run(jax.random.PRNGKey(seed), commands, mods.robot, x, list(arms), covs, noises,
             start)
    return np.asarray(mcmc.get_samples()["p"])[:num_samples]


def _kde_draws(draws: np.ndarray) -> np.ndarray:
    """VOLUME_POINTS draws (K, T, dim) from the KDE itself (a draw plus kernel noise): the
    region estimators below are expectations under the KDE, not under the draws it smooths."""
    sub = draws[:VOLUME_POINTS]
    chol = np.linalg.cholesky(kde_bandwidth(draws))  # (T, dim, dim)
    z = np.random.default_rng(0).standard_normal(sub.shape)
    return sub + np.einsum("tij,ktj->kti", chol, z)


def hdr_levels(draws: np.ndarray, points: np.ndarray) -> np.ndarray:
    """The HDR level of each point, (T,) for points (T, dim) or (K, T) for (K, T, dim): the
    share of the KDE's mass denser than the point (inside the 50% region: level < 0.5)."""
    log_at = kde_log_density(draws, points)
    ref = kde_log_density(draws, _kde_draws(draws))  # (K0, T)
    if log_at.ndim == 1:
        return np.mean(ref > log_at[None], axis=0)
    return np.mean(ref[None] > log_at[:, None], axis=1)


def hdr_sizes(draws: np.ndarray, masses: Sequence[float] = (0.5, 0.9)) -> np.ndarray:
    """Volumes (areas in 2-D) (len(masses), T) of the KDE's highest-density regions."""
    log_p = kde_log_density(draws, _kde_draws(draws))  # (K, T)
    out = []
    for m in masses:
        level = np.quantile(log_p, 1.0 - m, axis=0)
        inside = log_p >= level[None]
        out.append(np.mean(np.where(inside, np.exp(-log_p), 0.0), axis=0))
    return np.asarray(out)


def predict_chain_points(mods: ChainModules, rig: Rig, arms: Sequence[str], targets: np.ndarray,
                         fusion: str, seed: int = 0, num_samples: int = DRAWS
                         ) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Aim ``arms`` at targets and draw the (shared) end point: (commands, draws)."""
    commands = {a: aim_chain(rig, mods.robot, mods.x, a, targets) for a in arms}
    return commands, chain_draws(mods, arms, [commands[a] for a in arms], fusion, num_samples,
                                 seed)
