"""Joint-error densities for chains with more joints than measured coordinates.

On the paper's planar arms a row's joint errors are read off its residual, theta_err = J^-1 r,
and a KDE over them is the density (:mod:`bayesrob.errors.noise_models`). A 6- or 11-joint
chain measured at a 3-D marker explains every residual by a family of joint errors, so they
are latent, and what is fitted is their population density:

    e_i ~ N(0, Sigma)                     (IND: Sigma diagonal; CORR: full, LKJ prior)
    r_i = J_i e_i + eps_i,  eps_i ~ N(0, s^2 I)

with r_i train row i's residual (scaled by sqrt(N / (N - p)) for the calibration's p
parameters), J_i = d marker / d joints there, and s what no joint explains. e_i is integrated
out exactly, r_i ~ N(0, J_i Sigma J_i^T + s^2 I), and NUTS samples Sigma and s; the mean is
zero as the calibration fitted every joint's zero offset. Predictions push draws of
(Sigma, s), then of e, through the calibrated chain (:mod:`bayesrob.predict.draws`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import numpyro
import numpyro.distributions as dist
from numpyro.infer import MCMC, NUTS

from bayesrob import robot as kin
from bayesrob.calibrate.least_squares import side_rows
from bayesrob.data.rig import Rig, RigError

__all__ = ["LATENT_MODELS", "LatentJointErrors", "check_latent_model", "fit_latent_errors",
           "joint_jacobian", "joint_names", "scaled_train_residuals", "sharing_arms"]

LATENT_MODELS = ("ind", "corr")
# Prior scale of a joint's error sd (rad, or mm for prismatic joints): weakly informative,
# ten times the errors of the arms this package has seen (about 1 mrad).
JOINT_SD_PRIOR = 0.01
NOISE_SD_PRIOR_MM = 2.0  # prior scale of what no joint explains (mm)
JOINT_SD_SPREAD = 1.0  # sd of a joint's log error sd about the arm's scale
LKJ_CONCENTRATION = 2.0  # mild pull of CORR's correlations towards zero
WARMUP, SAMPLES, CHAINS = 400, 400, 2


def check_latent_model(model: str) -> None:
    """Refuse a joint-error model chain arms do not have, in one line."""
    if model not in LATENT_MODELS:
        raise RigError(f"model {model!r}: chain arms take the latent joint-error models "
                       f"{', '.join(LATENT_MODELS)} (their joint errors are not read off a "
                       "residual, so there is no per-row density to condition)")


def joint_names(robot: kin.Robot, arm: str) -> list[str]:
    """The joints on the path to ``arm``'s tip, base first (each chain's joints)."""
    return [f"{c.name}.{j}" for c in robot.path(arm) for j in c.joint_names]


def joint_jacobian(robot: kin.Robot, x: jax.Array, arm: str, u: jax.Array,
                   side: dict[str, jax.Array] | None = None) -> jax.Array:
    """d marker / d joint errors at zero error, (N, dim, n) (``side``: the rest of each
    pose, as :meth:`Robot.tip_transforms`); one compiled program per structure and row bucket.

    Run eagerly, the vmapped forward-mode derivative dispatched and compiled each of its
    primitives alone: 5-6 s for a 6-joint arm's 80 rows in a fresh process, against 0.8 s
    compiled as one program (which the persistent cache then keeps)."""
    return jnp.asarray(kin.on_row_buckets(
        partial(_joint_jacobian_program, robot.structure, arm, robot.nominal_values),
        jnp.asarray(x), u, side))


@partial(jax.jit, static_argnames=("structure", "arm"))
def _joint_jacobian_program(structure: kin.RobotStructure, arm: str, values: dict,
                            x: jax.Array, u: jax.Array,
                            side: dict[str, jax.Array] | None) -> jax.Array:
    robot = structure.robot(values)
    n = robot.n_path_joints(arm)

    def per_row(row, srow):
        rest = None if srow is None else {b: v[None] for b, v in srow.items()}
        return jax.jacfwd(lambda e: robot.marker_points(x, arm, row[None], e[None],
                                                        side=rest)[0])(jnp.zeros(n))
    return jax.vmap(per_row)(u, side)


def _model(jac: jax.Array, res: jax.Array, structure: str) -> None:
    n = jac.shape[-1]
    # The joints of one arm share a scale: a joint the residuals hardly see (its lever to the
    # marker is short) is drawn towards its neighbours rather than left at the prior's width.
    scale = numpyro.sample("joint_sd_scale", dist.HalfNormal(JOINT_SD_PRIOR))
    log_sd = numpyro.sample("joint_log_sd_dev",
                            dist.Normal(0.0, JOINT_SD_SPREAD).expand([n]).to_event(1))
    sd = numpyro.deterministic("joint_sd", scale * jnp.exp(log_sd))
    noise = numpyro.sample("noise_sd", dist.HalfNormal(NOISE_SD_PRIOR_MM))
    # one joint has no correlation to fit (LKJ needs two): CORR is IND there
    if structure == "corr" and n > 1:
        chol = numpyro.sample("joint_corr_chol", dist.LKJCholesky(n, LKJ_CONCENTRATION))
        scale = sd[:, None] * chol
        cov = scale @ scale.T
    else:
        cov = jnp.diag(sd**2)
    dim = jac.shape[1]
    s = jnp.einsum("nij,jk,nlk->nil", jac, cov, jac) + noise**2 * jnp.eye(dim)
    numpyro.factor("residual", _gaussian_log_density(s, res).sum())


def _gaussian_log_density(cov: jax.Array, r: jax.Array) -> jax.Array:
    """log N(r_i; 0, cov_i) of rows r (N, d) with covariances (N, d, d), by the adjugate for
    the 2 or 3 coordinates a marker has (a 2 x 2 padded with a unit third axis): XLA's batched
    Cholesky takes a call per row, and a gradient of the population's density cost three
    times as much through it."""
    d = r.shape[-1]
    if d > 3:
        return dist.MultivariateNormal(jnp.zeros(d), cov).log_prob(r)
    s = jnp.pad(cov, ((0, 0), (0, 3 - d), (0, 3 - d))) + jnp.diag(jnp.arange(3) >= d)
    c0, c1, c2 = s[..., 0], s[..., 1], s[..., 2]
    adj = jnp.stack([jnp.cross(c1, c2), jnp.cross(c2, c0), jnp.cross(c0, c1)], axis=-2)
    det = jnp.sum(c0 * adj[..., 0, :], axis=-1)
    x = jnp.pad(r, ((0, 0), (0, 3 - d)))
    quad = jnp.einsum("ni,nij,nj->n", x, adj, x) / det
    return -0.5 * (quad + jnp.log(det) + d * jnp.log(2 * jnp.pi))


@dataclass
class LatentJointErrors:
    """A chain arm's fitted joint-error population: posterior draws of its parameters."""

    arm: str
    model: str  # "ind" or "corr"
    joints: list[str]
    joint_sd: np.ndarray  # (S, n) rad
    corr_chol: np.ndarray | None  # (S, n, n) for CORR
    noise_sd: np.ndarray  # (S,) mm
    n_rows: int
    dof_scale: float
    diagnostics: dict = field(default_factory=dict)  # arviz r_hat / ess of the parameters
    seconds: float = 0.0
    # Where the arm shares joints with other measured arms (a tree's hands share its torso):
    # the population of all their joints, fitted on all their rows, and the arm's joints'
    # columns in it; None where the arm shares none.
    population: LatentJointErrors | None = field(default=None, repr=False)
    columns: np.ndarray | None = None

    def view_of(self, robot: kin.Robot, arm: str) -> LatentJointErrors:
        """``arm``'s part of this population (of ``robot``'s arms sharing joints): its
        joints' sds and correlations."""
        joints = joint_names(robot, arm)
        columns = np.array([self.joints.index(j) for j in joints])
        chol = None
        if self.corr_chol is not None:
            corr = np.einsum("sik,sjk->sij", self.corr_chol, self.corr_chol)
            chol = np.linalg.cholesky(corr[:, columns][:, :, columns])
        return LatentJointErrors(arm, self.model, joints, self.joint_sd[:, columns], chol,
                                 self.noise_sd, self.n_rows, self.dof_scale, self.diagnostics,
                                 self.seconds, self, columns)

    @property
    def covariance(self) -> np.ndarray:
        """Joint-error covariance draws (S, n, n)."""
        if self.corr_chol is None:
            return np.einsum("si,ij->sij", self.joint_sd**2, np.eye(self.joint_sd.shape[1]))
        scale = self.joint_sd[:, :, None] * self.corr_chol
        return np.einsum("sik,sjk->sij", scale, scale)

    def draw(self, key: jax.Array, shape: tuple[int, ...], u: object = None
             ) -> tuple[jax.Array, jax.Array]:
        """Joint errors (*shape, n) and noise sds (shape[0],), one population draw per leading
        index: the predictive mixes over the fitted parameters' uncertainty (the commands
        ``u`` do not move it)."""
        k1, k2 = jax.random.split(key)
        s = jax.random.randint(k1, (shape[0],), 0, self.joint_sd.shape[0])
        chol = jnp.linalg.cholesky(jnp.asarray(self.covariance)[s]
                                   + 1e-18 * jnp.eye(len(self.joints)))
        z = jax.random.normal(k2, (*shape, len(self.joints)))
        extra = (1,) * (len(shape) - 1)
        e = jnp.einsum("s...ij,s...j->s...i", chol.reshape(shape[0], *extra, *chol.shape[1:]), z)
        return e, jnp.asarray(self.noise_sd)[s]


def scaled_train_residuals(rig: Rig, robot: kin.Robot, x: np.ndarray, arm: str, n_free: int
                           ) -> tuple[np.ndarray, np.ndarray, float, dict | None]:
    """``arm``'s train commands, residuals under x scaled by sqrt(n / (n - p)) (p = ``n_free``
    fitted on n train coordinates: the spread an unseen row has), the scale and the side rows."""
    u, d = rig.rows(arm, "train")
    side = side_rows(rig, robot, arm, "train")
    res = d - np.asarray(robot.compiled_points(arm)(jnp.asarray(x), jnp.asarray(u), side))
    n_coords = sum(rig.rows(a, "train")[1].size for a in robot.measured_arms())
    scale = float(np.sqrt(n_coords / max(n_coords - n_free, 1)))
    return u, res * scale, scale, side


@partial(jax.jit, static_argnames=("structure", "warmup", "samples", "chains"))
def _posterior(key: jax.Array, jac: jax.Array, res: jax.Array, structure: str, warmup: int,
               samples: int, chains: int) -> tuple[dict[str, jax.Array], jax.Array]:
    """NUTS draws of the population's parameters, by chain, and the divergences: the whole
    run one compiled program, shared by every arm of the same shapes (an MCMC object per fit
    traced its programs again: 4 s of a fit's 7 on the linked arm6 pair).

    A dense mass matrix: the arm's scale and a common shift of its joints' log sds trade off
    along a straight ridge, which a diagonal one crosses in 34 leapfrog steps per draw and a
    dense one in 10, at the same or larger ESS (arm6 linked pair, seed 0)."""
    mcmc = MCMC(NUTS(_model, target_accept_prob=0.9, dense_mass=True), num_warmup=warmup,
                num_samples=samples, num_chains=chains, chain_method="sequential",
                progress_bar=False)
    mcmc.run(key, jac, res, structure, extra_fields=("diverging",))
    return (mcmc.get_samples(group_by_chain=True),
            mcmc.get_extra_fields(group_by_chain=True)["diverging"])


def sharing_arms(robot: kin.Robot, arm: str) -> list[str]:
    """The measured arms whose paths share a chain with ``arm``'s (``arm`` among them, in the
    robot's order): their rows all see the shared joints' errors."""
    mine = {c.name for c in robot.path(arm) if c.n_joints}
    return [a for a in robot.measured_arms()
            if a == arm or mine & {c.name for c in robot.path(a) if c.n_joints}]


def fit_latent_errors(rig: Rig, robot: kin.Robot, x: np.ndarray, arm: str, model: str = "ind",
                      n_free: int = 0, seed: int = 0, warmup: int = WARMUP,
                      samples: int = SAMPLES, chains: int = CHAINS,
                      populations: dict | None = None) -> LatentJointErrors:
    """Fit ``arm``'s joint-error population to its train residuals under parameters x.

    ``n_free``: how many parameters the calibration fitted (over every arm's rows), for the
    degrees-of-freedom scaling of the residuals. Given ``populations`` (a dict the caller
    keeps), where other measured arms share joints with ``arm`` (:func:`sharing_arms`), the
    population is of all their joints, fitted once on all their rows (a torso's errors seen
    from both hands), and the arm's part of it is returned: linked hands of one tree. Without
    it each arm's population is its own rows' (what a single arm is predicted and compared
    with).
    """
    import arviz as az

    check_latent_model(model)
    arms = sharing_arms(robot, arm) if populations is not None else [arm]
    key = (tuple(arms), model)
    if populations is not None and key in populations:
        return populations[key].view_of(robot, arm)
    t0 = time.perf_counter()
    names = list(dict.fromkeys(j for a in arms for j in joint_names(robot, a)))
    jacs, residuals, n_rows = [], [], 0
    for a in arms:
        u, res, scale, side = scaled_train_residuals(rig, robot, x, a, n_free)
        jac = joint_jacobian(robot, jnp.asarray(x), a, jnp.asarray(u), side)
        if len(arms) > 1:  # the arm's joints at their columns of the shared population
            cols = [names.index(j) for j in joint_names(robot, a)]
            jac = jnp.zeros((*jac.shape[:2], len(names))).at[..., cols].set(jac)
        jacs.append(jac)
        residuals.append(jnp.asarray(res))
        n_rows += len(u)
    by_chain, diverging = _posterior(jax.random.PRNGKey(seed), jnp.concatenate(jacs),
                                     jnp.concatenate(residuals), model, warmup, samples,
                                     chains)
    by_chain = {k: np.asarray(v) for k, v in by_chain.items()}
    draws = {k: v.reshape(-1, *v.shape[2:]) for k, v in by_chain.items()}
    if model == "corr" and "joint_corr_chol" not in draws:  # one joint: its correlation is 1
        draws["joint_corr_chol"] = np.ones((len(draws["noise_sd"]), 1, 1))
    summ = az.summary(az.from_dict(posterior=by_chain), var_names=["joint_sd", "noise_sd"],
                      kind="diagnostics", round_to="none")
    diagnostics = {"max_r_hat": float(summ["r_hat"].max()),
                   "min_ess_bulk": float(summ["ess_bulk"].min()),
                   "divergences": int(np.asarray(diverging).sum())}
    whole = LatentJointErrors(
        arm if len(arms) == 1 else "+".join(arms), model, names,
        np.asarray(draws["joint_sd"]),
        np.asarray(draws["joint_corr_chol"]) if model == "corr" else None,
        np.asarray(draws["noise_sd"]), n_rows, scale, diagnostics, time.perf_counter() - t0)
    if len(arms) == 1:
        return whole
    populations[key] = whole  # more than one arm: asked for with populations
    return whole.view_of(robot, arm)
