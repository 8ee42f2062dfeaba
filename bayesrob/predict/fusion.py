"""How arms linked at their end points share it: two fusion rules.

- ``product`` (the paper's rule, the baseline): the product of the arms' likelihoods
  (:func:`bayesrob.predict.grid.grid_posterior`).
- ``equilibrium``: linked arms are springs. Arm a alone would hold its end point at its *free*
  point d_a (its single-arm prediction); linked, the point settles where the elastic forces
  balance. Linearised about the free points, arm a resists a displacement x with K_a x,
  K_a = J_a^-T diag(k_a) J_a^-1 (k_a its joint stiffnesses, N mm / rad), so
  d = (sum_a K_a)^-1 sum_a K_a d_a. On simulated rigs with sag and backlash this lands within
  0.1 mm of the simulator's exact minimum of the summed energies (tests/test_fusion.py), a
  tenth of the linked error. The product instead weights arms by how *sure* each model is,
  which is not what decides where the metal settles.

Stiffness: the rig's when given, else drawn from the planar servo prior (only ratios matter;
one value per arm and joint, shared by every target of a draw). :func:`equilibrium_program` is
the generative program; its draws' density is the KDE of :mod:`.regions`, binned on a zoomed
grid (:func:`draws_posterior`) where a grid posterior is asked for. The paper's histogram COND
has no sampler: its free points are drawn from its single-arm grid prediction instead.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import numpyro
import numpyro.distributions as dist
import scipy.signal
from numpyro.infer import Predictive

from bayesrob import robot as kin
from bayesrob.data.vocabulary import DEFAULT_FUSION, FUSIONS  # noqa: F401 (re-exported)
from bayesrob.errors.distributions import (
    error_arrays,
    error_distribution,
    error_kind,
    is_sampleable,
)
from bayesrob.errors.noise_models import FittedNoiseModel
from bayesrob.predict.grid import COARSE_GRID, GridPosterior, grid_posterior
from bayesrob.predict.regions import kernels
from bayesrob.predict.stiffness import given_or_servo_prior

__all__ = ["FUSIONS", "DEFAULT_FUSION", "springs", "balance", "tracker_remainder", "equilibrium",
           "equilibrium_program", "equilibrium_draws", "draws_posterior", "fused_draws",
           "fused_posterior"]

# Draws per target: the KDE's bandwidth is n^(-1/6) of the spread (0.25 at 4000), and the
# HDR level of a point moves by about sqrt(p (1 - p) / n) < 0.008.
DRAWS = 4000


def _inverse(m: jax.Array) -> jax.Array:
    """Inverse of small matrices (..., d, d), in closed form for 2 x 2: XLA's batched LAPACK
    costs a call per matrix, and draws hold tens of thousands."""
    if m.shape[-1] != 2:
        return jnp.linalg.inv(m)
    a, b, c, d = m[..., 0, 0], m[..., 0, 1], m[..., 1, 0], m[..., 1, 1]
    det = a * d - b * c
    return jnp.stack([jnp.stack([d, -b], -1), jnp.stack([-c, a], -1)], -2) / det[..., None, None]


def springs(jac: jax.Array, log_k: jax.Array) -> jax.Array:
    """K = (J diag(1 / k) J^T)^-1 (..., dim, dim), N per mm, from the joint Jacobian
    (..., dim, n) and log joint stiffnesses (..., n)."""
    return _inverse(jnp.einsum("...ik,...k,...jk->...ij", jac, jnp.exp(-log_k), jac))


def balance(free: jax.Array, stiffness: jax.Array) -> jax.Array:
    """Where springs K_a (A, ..., dim, dim) holding points d_a (A, ..., dim) balance (..., dim)."""
    pull = jnp.einsum("a...ik,a...k->...i", stiffness, free)
    return jnp.einsum("...ik,...k->...i", _inverse(stiffness.sum(axis=0)), pull)


def tracker_remainder(stiffness: jax.Array, tracker_noise_mm: float, z: jax.Array
                      ) -> jax.Array:
    """The tracker's noise the balance averaged away (..., dim), from standard normal ``z``:
    each free point carries it and the balance averages it to sum_a W_a W_a^T sigma^2
    (W_a = (sum K)^-1 K_a), but the linked point is measured once, with all of it."""
    w = jnp.einsum("...ij,a...jk->a...ik", _inverse(stiffness.sum(axis=0)), stiffness)
    dim = z.shape[-1]
    cov = tracker_noise_mm**2 * (jnp.eye(dim) - jnp.einsum("a...ij,a...kj->...ik", w, w))
    return jnp.einsum("...ij,...j->...i", _psd_sqrt(cov), z)


def _psd_sqrt(m: jax.Array) -> jax.Array:
    """Symmetric square root of symmetric matrices (..., d, d) whose least eigenvalue may poke
    below zero by rounding: closed form for 2 x 2 (shifted up to zero), else eigh (clipped)."""
    m = 0.5 * (m + jnp.swapaxes(m, -1, -2))
    if m.shape[-1] != 2:
        vals, vecs = jnp.linalg.eigh(m)
        return jnp.einsum("...ij,...j,...kj->...ik", vecs, jnp.sqrt(jnp.clip(vals, 0.0)), vecs)
    a, b, d = m[..., 0, 0], m[..., 0, 1], m[..., 1, 1]
    least = 0.5 * (a + d) - jnp.sqrt(0.25 * (a - d) ** 2 + b**2)
    m = m + jnp.clip(-least, 0.0)[..., None, None] * jnp.eye(2)
    s = jnp.sqrt(jnp.clip(m[..., 0, 0] * m[..., 1, 1] - m[..., 0, 1] ** 2, 0.0))
    t = jnp.sqrt(jnp.clip(m[..., 0, 0] + m[..., 1, 1] + 2 * s, 1e-300))
    return (m + s[..., None, None] * jnp.eye(2)) / t[..., None, None]


def equilibrium(free: Sequence[jax.Array], jacs: Sequence[jax.Array],
                log_k: Sequence[jax.Array], tracker_noise_mm: float = 0.0,
                key: jax.Array | None = None) -> jax.Array:
    """The balance (S, T, dim) of free points (S, T, dim) held by arms with joint Jacobians
    (T, dim, n_a) and log stiffnesses (S, n_a), plus :func:`tracker_remainder` if asked."""
    k = jnp.stack([springs(jnp.asarray(j)[None], jnp.asarray(lk)[:, None, :])
                   for j, lk in zip(jacs, log_k, strict=True)])
    d = balance(jnp.stack([jnp.asarray(f) for f in free]), k)
    if tracker_noise_mm <= 0:
        return d
    if key is None:
        raise ValueError("tracker noise needs a random key")
    return d + tracker_remainder(k, tracker_noise_mm, jax.random.normal(key, d.shape))


def _log_stiffness(n_arms: int, stiffness: Sequence[Any] | None) -> jax.Array:
    """log k (A, 2): given, or drawn from the prior in one site, a known arm's kept."""
    priors = [given_or_servo_prior(s) for s in (stiffness or [None] * n_arms)]
    loc = jnp.asarray(np.stack([p.centre for p in priors]))
    known = np.stack([p.sd == 0 for p in priors])
    if known.all():
        return loc
    # the servo prior gives every joint it draws one width
    (sd,) = {float(v) for p in priors for v in p.sd[p.sd > 0]}
    drawn = numpyro.sample("log_stiffness", dist.Normal(loc, sd).to_event(2))
    return jnp.where(known, loc, drawn)


def equilibrium_program(commands: Sequence[jax.Array], *, kinds: tuple[str, ...],
                        arrays: Sequence[dict[str, jax.Array]],
                        params: Sequence[kin.ArmParams], names: tuple[str, ...],
                        stiffness: Sequence[Any] | None = None,
                        param_cov: Sequence[jax.Array] | None = None,
                        tracker_noise_mm: float = 0.0,
                        densities_hold_tracker: bool = True) -> None:
    """Arms linked at their end point, settling where their stiffnesses balance.

    Per arm k at commands (T, 2): theta_err_k ~ its joint-error model (``kinds``, ``arrays``:
    traced, so a compiled caller does not bake them in), free point f(g(u) + theta_err_k);
    log stiffnesses from ``stiffness`` (N mm/rad per arm, None unknown) or the prior; ``d`` =
    :func:`balance` of the free points. ``param_cov``: each arm's parameter covariance (8, 8),
    the executing arm a draw from it (what calibration error does at unseen poses).
    ``tracker_noise_mm``: :func:`tracker_remainder` added back to a linked point; all of it,
    to any point, when not ``densities_hold_tracker`` (densities fitted without it).
    """
    frees, held = [], []
    log_k = _log_stiffness(len(kinds), stiffness)
    for i, (kind, arr, p, u) in enumerate(zip(kinds, arrays, params, commands, strict=True)):
        u = jnp.atleast_2d(jnp.asarray(u, dtype=jnp.float64))
        if param_cov is not None:
            v = p.to_vector()
            delta = numpyro.sample(f"param_err_{names[i]}", dist.MultivariateNormal(
                jnp.zeros_like(v), covariance_matrix=param_cov[i]))
            p = kin.ArmParams.from_vector(v + delta)
        with numpyro.plate("targets", u.shape[0]):
            err = numpyro.sample(f"theta_err_{names[i]}", error_distribution(kind, arr, u))
        theta = kin.servo(p, u) + err
        frees.append(numpyro.deterministic(f"free_{names[i]}", kin.forward(p, theta)))
        held.append(springs(kin.jacobian(p, theta), log_k[i]))
    k = jnp.stack(held)
    d = balance(jnp.stack(frees), k)
    if tracker_noise_mm > 0 and (len(kinds) > 1 or not densities_hold_tracker):
        with numpyro.plate("targets", d.shape[-2]):
            z = numpyro.sample("tracker", dist.Normal(0.0, 1.0).expand([2]).to_event(1))
        d = d + (tracker_remainder(k, tracker_noise_mm, z) if densities_hold_tracker
                 else tracker_noise_mm * z)
    numpyro.deterministic("d", d)


def static_stiffness(stiffness: Sequence[Any] | None) -> tuple | None:
    """Known stiffnesses as a static argument: a tuple per arm (None unknown), or None."""
    if stiffness is None or all(s is None for s in stiffness):
        return None
    return tuple(tuple(float(v) for v in s) if s is not None else None for s in stiffness)


@partial(jax.jit, static_argnames=("kinds", "names", "stiffness", "num_samples",
                                   "tracker_noise_mm", "densities_hold_tracker"))
def equilibrium_program_draws(key: jax.Array, commands: Sequence[jax.Array],
                              arrays: Sequence[dict], params: Sequence[kin.ArmParams],
                              param_cov: Sequence[jax.Array] | None = None, *,
                              kinds: tuple[str, ...], names: tuple[str, ...] | None = None,
                              stiffness: tuple | None = None, num_samples: int = DRAWS,
                              tracker_noise_mm: float = 0.0,
                              densities_hold_tracker: bool = True) -> jax.Array:
    """Draws (S, T, 2) of :func:`equilibrium_program`'s ``d``, one compiled program per kind
    of assembly (called eagerly, ``Predictive`` compiled its loop anew on every call)."""
    names = names or tuple(f"arm{i}" for i in range(len(kinds)))
    out = Predictive(equilibrium_program, num_samples=num_samples, return_sites=["d"])(
        key, commands, kinds=kinds, arrays=arrays, params=params, names=names,
        stiffness=stiffness, param_cov=param_cov, tracker_noise_mm=tracker_noise_mm,
        densities_hold_tracker=densities_hold_tracker)
    return out["d"]


@partial(jax.jit, static_argnames=("n_arms", "stiffness", "num_samples"))
def _log_stiffness_draws(key: jax.Array, *, n_arms: int, stiffness: tuple | None,
                         num_samples: int) -> jax.Array:
    # compiled once per kind, as equilibrium_program_draws
    return Predictive(lambda: numpyro.deterministic("log_k", _log_stiffness(n_arms, stiffness)),
                      num_samples=num_samples)(key)["log_k"]


def equilibrium_draws(models: Sequence[FittedNoiseModel], arms: Sequence[kin.Arm],
                      commands: Sequence[np.ndarray], targets: np.ndarray,
                      stiffness: Sequence[Any] | None = None, num_samples: int = DRAWS,
                      seed: int = 0) -> np.ndarray:
    """Draws (S, T, 2) of the linked end point under equilibrium fusion: of
    :func:`equilibrium_program` when every model can draw joint errors, else each arm's free
    points from its single-arm grid prediction, balanced alike."""
    commands = [np.atleast_2d(np.asarray(u, float)) for u in commands]
    key = jax.random.PRNGKey(seed)
    if all(is_sampleable(m) for m in models):
        return np.asarray(equilibrium_program_draws(
            key, [jnp.asarray(u) for u in commands], [error_arrays(m) for m in models],
            [a.params for a in arms], kinds=tuple(error_kind(m) for m in models),
            names=tuple(a.name for a in arms), stiffness=static_stiffness(stiffness),
            num_samples=num_samples))
    targets = np.atleast_2d(np.asarray(targets, float))
    frees, thetas = [], []
    for i, (m, a, u) in enumerate(zip(models, arms, commands, strict=True)):
        free = grid_posterior([m], [a], [u], targets).sample(seed + 7919 * (i + 1), num_samples)
        theta, _ = kin.inverse(a.params, jnp.asarray(free), a.elbow)
        frees.append(free)
        thetas.append(theta)
    log_k = _log_stiffness_draws(key, n_arms=len(arms), stiffness=static_stiffness(stiffness),
                                 num_samples=num_samples)
    k = jnp.stack([springs(kin.jacobian(a.params, th), log_k[:, i, None, :])
                   for i, (a, th) in enumerate(zip(arms, thetas, strict=True))])
    return np.asarray(balance(jnp.asarray(np.stack(frees)), k))


def draws_posterior(draws: np.ndarray, targets: np.ndarray, n: int = 150) -> GridPosterior:
    """The KDE of draws (S, T, 2) on a zoomed n x n grid per target, as a normalised
    :class:`GridPosterior`: binned draws convolved with the kernel."""
    t0 = time.perf_counter()
    draws = np.asarray(draws, float)
    targets = np.atleast_2d(np.asarray(targets, float))
    h = np.stack([k.covariance for k in kernels(draws)])  # (T, 2, 2)
    sd = np.sqrt(np.einsum("tii->ti", h))
    lo = draws.min(axis=0) - 4 * sd
    hi = draws.max(axis=0) + 4 * sd
    cell = (hi - lo) / n
    prob = np.empty((len(targets), n * n))
    for t in range(len(targets)):
        hist, _, _ = np.histogram2d(draws[:, t, 1], draws[:, t, 0], bins=n,
                                    range=[[lo[t, 1], hi[t, 1]], [lo[t, 0], hi[t, 0]]])
        # the kernel on the grid's own offsets, out to 4 bandwidths in each direction
        half = np.ceil(4 * sd[t] / cell[t]).astype(int)
        oy, ox = np.meshgrid(np.arange(-half[1], half[1] + 1) * cell[t, 1],
                             np.arange(-half[0], half[0] + 1) * cell[t, 0], indexing="ij")
        off = np.stack([ox, oy], -1)
        kern = np.exp(-0.5 * np.einsum("...i,ij,...j->...", off, np.linalg.inv(h[t]), off))
        smooth = np.clip(scipy.signal.fftconvolve(hist, kern, mode="same"), 0.0, None)
        prob[t] = (smooth / smooth.sum()).ravel()  # rows along y, x fastest
    half_box = COARSE_GRID.half_width_mm
    outside = np.any(np.abs(draws - targets[None]) > half_box - 2 * half_box / COARSE_GRID.n,
                     axis=-1).mean(axis=0)
    mean = draws.mean(axis=0)
    dev = draws - mean
    cov = np.einsum("sti,stj->tij", dev, dev) / (draws.shape[0] - 1) + h
    return GridPosterior(targets, lo, cell, n, prob, mean, cov, np.zeros(len(targets)),
                         outside, COARSE_GRID, time.perf_counter() - t0)


def fused_draws(models: Sequence[FittedNoiseModel], arms: Sequence[kin.Arm],
                commands: Sequence[np.ndarray], targets: np.ndarray,
                fusion: str = DEFAULT_FUSION, stiffness: Sequence[Any] | None = None,
                seed: int = 0, num_samples: int = DRAWS) -> np.ndarray:
    """Draws (S, T, 2) of planar arms' end point fused by ``fusion``: the equilibrium's
    forward draws, or the product's exact grid (one arm is its own prediction)."""
    if _on_grid(fusion, arms):
        return grid_posterior(models, arms, commands, targets).sample(seed, num_samples)
    return equilibrium_draws(models, arms, commands, targets, stiffness, num_samples, seed)


def fused_posterior(models: Sequence[FittedNoiseModel], arms: Sequence[kin.Arm],
                    commands: Sequence[np.ndarray], targets: np.ndarray,
                    fusion: str = DEFAULT_FUSION, stiffness: Sequence[Any] | None = None,
                    seed: int = 0, num_samples: int = DRAWS
                    ) -> tuple[GridPosterior, np.ndarray | None]:
    """The grid posterior of planar arms' end point fused by ``fusion`` and, for the
    equilibrium, the draws it was built from (their KDE is the exact density at a point)."""
    if _on_grid(fusion, arms):
        return grid_posterior(models, arms, commands, targets), None
    draws = equilibrium_draws(models, arms, commands, targets, stiffness, num_samples, seed)
    return draws_posterior(draws, targets), draws


def _on_grid(fusion: str, arms: Sequence[kin.Arm]) -> bool:
    """Whether the product's exact grid is the prediction (one arm is its own, either rule)."""
    if fusion not in FUSIONS:
        raise ValueError(f"unknown fusion {fusion!r}; choose from {', '.join(FUSIONS)}")
    return fusion == "product" or len(arms) == 1
