"""The predictive density of an arm's measured marker at given commands, for IND, CORR and COND
on any robot: a Gaussian mixture per row, scored, sampled and multiplied the same way for all.

IND and CORR (joint errors not observed: more joints than measured coordinates): the latent
population of :mod:`bayesrob.errors.latent_errors`, e ~ N(0, Sigma), r = J e + eps, integrated
over e: row t's residual is the equal-weight mixture over posterior draws s of
N(0, J_t Sigma_s J_t^T + s_s^2 I).

COND conditions on the commands through a Parzen kernel in command space, as the paper's does;
on a chain the rows observe the marker residual (not the joint errors), so COND is the kernel
conditional of the train residuals given the path's commands (:class:`ConditionalKDE`, the
command widths at least ``command_bandwidth_floor`` spacings): sum_i w_i(u_t) N(r_i, diag(bw^2)).

Both are fitted on train residuals scaled by sqrt(N / (N - p)) for the calibration's p
parameters, so a row no fit has seen is scored against the spread such rows have. Leave-one-out
keeps the calibration: exact for COND (row i's own component dropped, the widths kept),
Pareto-smoothed importance sampling (arviz ``loo``) over the population's draws for IND and CORR.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import numpyro.distributions as dist
import scipy.special
from jax.scipy.special import logsumexp

from bayesrob.calibrate.least_squares import Calibration, side_rows
from bayesrob.data.rig import Rig, RigError
from bayesrob.errors.kde import ConditionalKDE
from bayesrob.errors.latent_errors import (
    LatentJointErrors,
    fit_latent_errors,
    joint_jacobian,
    scaled_train_residuals,
)
from bayesrob.errors.noise_models import ModelSpec

__all__ = ["MarkerDensity", "MarkerModel", "fit_marker_model", "marker_model_kind",
           "loo_marker_scores"]

# Posterior draws of the population a latent density mixes over: the mixture's spread
# settles within a few per cent by 100 draws; 200 keep the HDR levels' Monte Carlo error below
# the binomial error of 200 rows.
LATENT_COMPONENTS = 200
HDR_DRAWS = 4000  # draws of the mixture against which a point's HDR level is read


def marker_model_kind(spec: ModelSpec) -> str:
    """"ind", "corr" or "cond": the model a spec is on a chain arm; one-line error otherwise."""
    if spec.paper:
        raise RigError(f"model {spec.name!r}: the paper's estimators read joint errors off a "
                       "planar arm's residual; a URDF/DH arm takes ind, corr and cond")
    if spec.family == "COND" and spec.conditioning != "kernel":
        raise RigError(f"model {spec.name!r}: a URDF/DH arm's COND is the kernel conditional "
                       f"of its marker residuals, not conditioning = {spec.conditioning!r}")
    return spec.family.lower()


@dataclass(frozen=True)
class MarkerDensity:
    """p(marker | commands) at T rows: row t is sum_k exp(log_w[t, k]) N(centre[t] +
    means[t, k], chol[t, k] chol[t, k]^T). Arrays may broadcast over K (COND's shared kernel)."""

    centre: np.ndarray  # (T, dim)
    log_w: np.ndarray  # (T, K) normalised
    means: np.ndarray  # (T | 1, K, dim)
    chol: np.ndarray  # (T | 1, K | 1, dim, dim) lower triangular

    @property
    def dim(self) -> int:
        return int(self.centre.shape[-1])

    def arrays(self) -> tuple[jax.Array, ...]:
        """(centre, log weights with each component's normaliser, means, inverse Cholesky
        factors): what :func:`mixture_logpdf` takes. Inverted once here, the density is
        products and sums alone (XLA's CPU runtime stalled on batched triangular solves)."""
        dim = self.dim
        inv = np.linalg.inv(self.chol)
        log_det = np.sum(np.log(np.abs(np.diagonal(self.chol, axis1=-2, axis2=-1))), axis=-1)
        log_c = self.log_w - log_det - 0.5 * dim * math.log(2 * math.pi)
        return tuple(jnp.asarray(a) for a in (self.centre, log_c, self.means, inv))

    def logpdf(self, points: np.ndarray) -> np.ndarray:
        """Log density (per mm^dim) of points (T, dim) -> (T,), or (M, T, dim) -> (M, T)."""
        return np.asarray(_logpdf_blocks(jnp.asarray(points, float), *self.arrays()))

    def sample(self, seed: int, n: int) -> np.ndarray:
        """n draws (n, T, dim) of the marker at every row."""
        key = jax.random.PRNGKey(seed)
        return np.asarray(_sample(key, *(jnp.asarray(a) for a in (
            self.centre, self.log_w, self.means, self.chol)), n))

    def hdr_level(self, points: np.ndarray, seed: int = 0) -> np.ndarray:
        """Mass denser than each point (T,): a point lies in the m region when <= m."""
        ref = self.logpdf(self.sample(seed, HDR_DRAWS))  # (M, T)
        return np.mean(ref > self.logpdf(points)[None], axis=0)


def mixture_logpdf(points: jax.Array, centre: jax.Array, log_c: jax.Array, means: jax.Array,
                   inv_chol: jax.Array) -> jax.Array:
    """A MarkerDensity's log density as a JAX function of its :meth:`MarkerDensity.arrays`:
    points (..., T, dim) -> (..., T)."""
    dev = points[..., None, :] - centre[:, None, :] - means  # (..., T, K, dim)
    z = jnp.einsum("...ij,...j->...i", inv_chol, dev)
    return logsumexp(log_c - 0.5 * jnp.sum(z**2, -1), axis=-1)


@jax.jit
def _logpdf_blocks(points, centre, log_w, means, chol):
    if points.ndim == 2:
        return mixture_logpdf(points, centre, log_w, means, chol)
    # draws one at a time: (M, T, K, dim, dim) at once would not fit for a few thousand draws
    return jax.lax.map(lambda p: mixture_logpdf(p, centre, log_w, means, chol), points,
                       batch_size=64)


@partial(jax.jit, static_argnames=("n",))
def _sample(key, centre, log_w, means, chol, n):
    t, k = log_w.shape
    dim = centre.shape[-1]
    k1, k2 = jax.random.split(key)
    # inverse CDF, one uniform per draw: categorical's Gumbel trick draws n*T*K variates,
    # 240 million (17 s) for Justin's 4000 draws x 200 rows x 300 kernels
    cdf = jnp.cumsum(jnp.exp(log_w - logsumexp(log_w, axis=-1, keepdims=True)), axis=-1)
    u = jax.random.uniform(k1, (t, n)) * cdf[:, -1:]
    pick = jax.vmap(lambda c, v: jnp.searchsorted(c, v, side="right"))(cdf, u)
    pick = jnp.minimum(pick, k - 1).T  # (n, T)
    rows = jnp.arange(t)[None, :]
    mu = jnp.broadcast_to(means, (t, k, dim))[rows, pick]
    lower = jnp.broadcast_to(chol, (t, k, dim, dim))[rows, pick]
    z = jax.random.normal(k2, (n, t, dim))
    return centre[None] + mu + jnp.einsum("ntij,ntj->nti", lower, z)


def _cond_density(c: ConditionalKDE, u: np.ndarray, centre: np.ndarray) -> MarkerDensity:
    """The kernel conditional of the residuals at commands u (T, c), centred on ``centre``."""
    w = np.asarray(c.weights(u)).reshape(len(u), -1)
    with np.errstate(divide="ignore"):
        log_w = np.log(w)
    return MarkerDensity(centre, log_w, c.x_data[None], np.diag(c.bw_x)[None, None])


def _marker_covariances(jac: np.ndarray, cov_e: np.ndarray, noise: np.ndarray) -> np.ndarray:
    """J_t Sigma_s J_t^T + s_s^2 I, (T, S, dim, dim)."""
    dim = jac.shape[1]
    return (np.einsum("tij,sjk,tlk->tsil", jac, cov_e, jac)
            + noise[None, :, None, None] ** 2 * np.eye(dim))


# ---------------------------------------------------------------------------------- fitting


@dataclass
class MarkerModel:
    """One arm's fitted joint-error model on a chain, ready to give its marker density."""

    arm: str
    kind: str  # "ind", "corr" or "cond"
    calibration: Calibration
    train_residuals: np.ndarray  # (N, dim) scaled
    train_commands: np.ndarray  # (N, c)
    latent: LatentJointErrors | None = None
    conditional: ConditionalKDE | None = None

    def centre(self, u: np.ndarray, side: dict | None = None) -> np.ndarray:
        cal = self.calibration
        return np.asarray(cal.robot.compiled_points(self.arm)(
            jnp.asarray(cal.x), jnp.asarray(u), side))

    def jacobian(self, u: np.ndarray, side: dict | None = None) -> np.ndarray:
        """d marker / d joint errors at commands u, (T, dim, n)."""
        cal = self.calibration
        return np.asarray(joint_jacobian(cal.robot, jnp.asarray(cal.x), self.arm,
                                         jnp.asarray(u), side))

    def density(self, u: np.ndarray, side: dict | None = None) -> MarkerDensity:
        """The marker's density at commands u (T, c) (``side``: the rest of each pose)."""
        u = np.atleast_2d(np.asarray(u, float))
        centre = self.centre(u, side)
        if self.kind == "cond":
            return _cond_density(self.conditional, u, centre)
        cov_e, noise = _population(self.latent)
        chol = np.linalg.cholesky(_marker_covariances(self.jacobian(u, side), cov_e, noise))
        k = len(noise)
        return MarkerDensity(centre, np.full((len(u), k), -math.log(k)),
                             np.zeros((1, k, centre.shape[1])), chol)


def _population(latent: LatentJointErrors) -> tuple[np.ndarray, np.ndarray]:
    """LATENT_COMPONENTS evenly spaced posterior draws: (Sigma (K, n, n), s (K,))."""
    cov = latent.covariance
    pick = np.unique(np.linspace(0, len(cov) - 1, LATENT_COMPONENTS).round().astype(int))
    return cov[pick], latent.noise_sd[pick]


def fit_marker_model(rig: Rig, cal: Calibration, arm: str, spec: ModelSpec,
                     seed: int = 0) -> MarkerModel:
    """Fit ``spec`` (as :func:`marker_model_kind` reads it) to ``arm``'s train rows."""
    kind = marker_model_kind(spec)
    n_free = int(cal.ident.free.sum())
    u, res, _, _ = scaled_train_residuals(rig, cal.robot, cal.x, arm, n_free)
    model = MarkerModel(arm, kind, cal, res, u)
    if kind == "cond":
        model.conditional = ConditionalKDE.fit(
            res, u, "kernel", "loo-ml-diag", warn_on_bound=False,
            z_spacing_floor=spec.command_bandwidth_floor)
    else:
        model.latent = fit_latent_errors(rig, cal.robot, cal.x, arm, kind, n_free, seed=seed)
    return model


@jax.jit
def _gaussian_rows(cov: jax.Array, r: jax.Array) -> jax.Array:
    # one program: eagerly, numpyro's Cholesky and solves compiled a hundred small ones
    return dist.MultivariateNormal(covariance_matrix=cov).log_prob(
        jnp.broadcast_to(r, cov.shape[:-1]))


def loo_marker_scores(rig: Rig, model: MarkerModel) -> tuple[np.ndarray, np.ndarray]:
    """(leave-one-out, in-sample) log density (N,) of each train row's scaled residual,
    the calibration kept (see the module docstring)."""
    r, u = model.train_residuals, model.train_commands
    if model.kind == "cond":
        dens = _cond_density(model.conditional, u, np.zeros_like(r))
        loo_w = np.exp(dens.log_w)
        np.fill_diagonal(loo_w, 0.0)  # each row without its own kernel
        with np.errstate(divide="ignore"):
            loo_log_w = np.log(loo_w / loo_w.sum(1, keepdims=True))
        return replace(dens, log_w=loo_log_w).logpdf(r), dens.logpdf(r)
    import arviz as az

    lat = model.latent
    side = side_rows(rig, model.calibration.robot, model.arm, "train")
    cov = np.swapaxes(_marker_covariances(model.jacobian(u, side), lat.covariance,
                                          lat.noise_sd), 0, 1)  # (S, N, dim, dim)
    loglik = np.asarray(_gaussian_rows(jnp.asarray(cov), jnp.asarray(r)))  # (S, N)
    in_sample = scipy.special.logsumexp(loglik.T, axis=-1) - math.log(loglik.shape[0])
    chains = 2 if loglik.shape[0] % 2 == 0 else 1
    idata = az.from_dict(posterior={"noise_sd": lat.noise_sd.reshape(chains, -1)},
                         log_likelihood={"r": loglik.reshape(chains, -1, loglik.shape[1])})
    loo = az.loo(idata, pointwise=True)
    return np.asarray(loo.loo_i.values, float), in_sample
