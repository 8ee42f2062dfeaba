"""Parzen (Gaussian-kernel) density estimation in JAX, with the paper's and improved selectors.

The paper (Larkworthy & Hayes 2009, section III) estimates every density with a Parzen window:
the data are divided by their componentwise (population) standard deviation, one spherical
Gaussian of width ``h`` sits on each normalised point, and ``h`` minimises the leave-one-out
criterion printed as

    J_LOO(h) = sum_i sum_j (pdf(x_i | D, h) - pdf(x_i | D_-j, h))^2.

That criterion decreases monotonically in ``h`` (see the reading notes on the paper), so the
"paper" selector searches an explicit range and reports when its answer lies on the bound; it is
kept as the faithful baseline. The improved selectors maximise the leave-one-out log-likelihood
(statsmodels' ``cv_ml``), with one width (``"loo-ml"``) or one width per dimension
(``"loo-ml-diag"``), optimised on log-bandwidths with exact gradients.

Densities are always normalised in the data's original units (NOTES item 3):

    pdf(x) = (1/N) sum_i prod_k N(x_k; x_ik, bw_k).

Conditional densities p(x | z) come two ways (:class:`ConditionalKDE`): the paper's histogram
of the joint KDE, and the kernel conditional ``sum_i w_i(z) K_x(x - x_i)`` with
``w_i ∝ K_z(z - z_i)``, whose bandwidths follow statsmodels'
``KDEMultivariateConditional(bw="cv_ml")`` objective.

Everything that touches an M x N kernel matrix is jit-compiled and evaluated in blocks of rows
(``jax.lax.map``), so memory stays bounded for e.g. 100,000 points against 10,000 data in 4-D.
The pure functions :func:`kde_logpdf`, :func:`conditional_kde_logpdf` and
:func:`kernel_conditional_weights` take and return ``jnp`` arrays so they can be used under
``jax.grad`` / ``jax.jit`` / NUTS.

Draws of a prediction are smoothed by scipy's ``gaussian_kde`` (Scott's rule), in
:mod:`bayesrob.predict.regions`.
"""

from __future__ import annotations

import contextlib
import hashlib
import math
import os
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import serialize_executable
from jax.experimental.compilation_cache import compilation_cache
from jax.scipy.special import logsumexp
from scipy import optimize

try:  # optional: only used to keep L-BFGS-B's tiny BLAS calls single-threaded
    from threadpoolctl import ThreadpoolController
except ImportError:  # pragma: no cover
    ThreadpoolController = None

__all__ = [
    "KDE",
    "ConditionalKDE",
    "KDEError",
    "BandwidthOnBoundWarning",
    "kde_logpdf",
    "conditional_kde_logpdf",
    "kernel_conditional_weights",
    "command_spacing",
    "histogram_lookup",
    "histogram_guide",
    "guided_histogram_lookup",
    "j_loo",
    "loo_loglik",
    "SELECTORS",
]

SELECTORS = ("paper", "loo-ml", "loo-ml-diag")

_LOG_2PI = math.log(2.0 * math.pi)

# Elements of one block of the kernel matrix (rows x data points). 2**22 float64 values are
# 32 MB per intermediate; XLA keeps a few of them alive, so a block stays well under 1 GB
# whatever M and N are.
_BLOCK_ELEMENTS = 2**22

# Per-dimension bandwidth bounds for the gradient-based selectors, in units of the data's
# standard deviation. They only exist to keep L-BFGS-B away from bw -> 0 (duplicate points make
# the leave-one-out likelihood unbounded there) and bw -> inf (an uninformative conditioning
# variable); hitting one is reported through ``on_bound``.
_DIAG_RANGE = (1e-3, 1e3)


class KDEError(ValueError):
    """Raised for data a kernel density estimate cannot be fitted to (degenerate, non-finite)."""


class BandwidthOnBoundWarning(UserWarning):
    """The selected bandwidth lies on the bound of its search range.

    For the paper's J_LOO criterion this is the expected outcome (the criterion is monotone in
    h), so the estimate over-smooths by as much as the range allows.
    """


# --------------------------------------------------------------------------------------------
# Validation helpers
# --------------------------------------------------------------------------------------------


def _as_data(data: Any, name: str = "data") -> np.ndarray:
    """Return ``data`` as a float64 (N, d) array, rejecting data no KDE can be fitted to."""
    arr = np.asarray(data, dtype=np.float64)
    if arr.ndim == 1:
        arr = arr[:, None]
    if arr.ndim != 2:
        raise KDEError(f"{name} must be an (N, d) or (N,) array, got shape {arr.shape}")
    if arr.shape[1] < 1:
        raise KDEError(f"{name} has no dimensions (shape {arr.shape})")
    if not np.all(np.isfinite(arr)):
        raise KDEError(f"{name} contains NaN or infinite values")
    if arr.shape[0] < 2:
        raise KDEError(f"{name} needs at least 2 points for a density estimate, got {arr.shape[0]}")
    if np.all(arr == arr[0]):
        raise KDEError(f"all {arr.shape[0]} points in {name} are identical")
    std = arr.std(axis=0)
    bad = np.flatnonzero(~(std > 0))
    if bad.size:
        raise KDEError(
            f"{name} has zero variance in dimension(s) {bad.tolist()}; a kernel width cannot "
            "be scaled to it (drop the dimension or add it as a fixed offset)"
        )
    return arr


def _fixed_bandwidth(bandwidth: Any, d: int, name: str = "bandwidth") -> np.ndarray:
    bw = np.asarray(bandwidth, dtype=np.float64)
    if bw.ndim == 0:
        bw = np.full(d, float(bw))
    bw = bw.reshape(-1)
    if bw.shape != (d,):
        raise KDEError(f"{name} needs 1 or {d} values, got {bw.size}")
    if not np.all(np.isfinite(bw)) or np.any(bw <= 0):
        raise KDEError(f"{name} must be positive and finite, got {bw.tolist()}")
    return bw


def _points_2d(points: Any, d: int) -> tuple[jnp.ndarray, bool]:
    """(M, d) view of ``points``; the flag says the caller passed one point as a (d,) vector.

    A 1-D array means M points when d == 1 and a single point when d > 1.
    """
    p = jnp.asarray(points, dtype=jnp.float64)
    if p.ndim == 0:
        if d != 1:
            raise KDEError(f"a scalar point needs d == 1, the estimate has d = {d}")
        return p.reshape(1, 1), True
    if p.ndim == 1:
        if d == 1:
            return p[:, None], False
        if p.shape[0] != d:
            raise KDEError(f"a point needs {d} coordinates, got {p.shape[0]}")
        return p[None, :], True
    if p.ndim != 2 or p.shape[1] != d:
        raise KDEError(f"points must have shape (M, {d}), got {p.shape}")
    return p, False


def _key(key_or_seed: Any) -> jax.Array:
    if isinstance(key_or_seed, (int, np.integer)):
        return jax.random.PRNGKey(int(key_or_seed))
    return key_or_seed


# --------------------------------------------------------------------------------------------
# Core kernels (pure, jit-compiled, differentiable)
# --------------------------------------------------------------------------------------------


def _block_rows(m: int, n: int) -> int:
    return max(1, min(m, _BLOCK_ELEMENTS // max(n, 1)))


def _map_blocks(fn, m: int, n: int, *row_arrays: jnp.ndarray) -> jnp.ndarray:
    """Apply ``fn`` to blocks of rows of ``row_arrays`` (each (m, ...)), concatenating results.

    Shapes are static under jit, so the block size is a Python int and the loop is a single
    ``lax.map``. ``jax.checkpoint`` makes reverse-mode store only each block's inputs rather
    than its (rows x N) kernel matrix, which is what keeps jax.grad over many points bounded.
    """
    rows = _block_rows(m, n)
    if rows >= m:
        return fn(*row_arrays)
    n_blocks = -(-m // rows)
    pad = n_blocks * rows - m
    blocked = [
        jnp.pad(a, [(0, pad)] + [(0, 0)] * (a.ndim - 1)).reshape((n_blocks, rows) + a.shape[1:])
        for a in row_arrays
    ]
    out = jax.lax.map(lambda args: jax.checkpoint(fn)(*args), tuple(blocked))
    return out.reshape((n_blocks * rows,) + out.shape[2:])[:m]


def _sq_dist(a: jnp.ndarray, b: jnp.ndarray) -> jnp.ndarray:
    """Pairwise squared distances between rows of already-scaled ``a`` (M, d) and ``b`` (N, d).

    The |a|^2 + |b|^2 - 2 a.b form turns the M x N x d difference tensor into one matrix
    product; callers centre the data first so the cancellation error stays ~1e-16 relative to
    the spread of the data, and tiny negative results are clipped.
    """
    if a.shape[1] == 1:
        # A 1-D "matrix product" wastes the BLAS call; the direct difference is exact and cheap.
        return (a - b.T) ** 2
    sq = jnp.sum(a * a, axis=1)[:, None] + jnp.sum(b * b, axis=1)[None, :] - 2.0 * (a @ b.T)
    return jnp.maximum(sq, 0.0)


@jax.jit
def kde_logpdf(points: jnp.ndarray, data: jnp.ndarray, bandwidth: jnp.ndarray) -> jnp.ndarray:
    """Log density of the diagonal-bandwidth Gaussian KDE at ``points``.

    ``log pdf(x) = log (1/N) sum_i prod_k N(x_k; data_ik, bandwidth_k)`` for each row of
    ``points`` (M, d), with ``data`` (N, d) and ``bandwidth`` (d,) in the same units. Pure JAX:
    differentiable w.r.t. all three arguments and usable inside jit / grad / NUTS. Points are
    processed in row blocks so an M x N problem never materialises more than a few tens of MB.
    """
    points = jnp.asarray(points, dtype=jnp.float64)
    data = jnp.asarray(data, dtype=jnp.float64)
    bandwidth = jnp.asarray(bandwidth, dtype=jnp.float64)
    m, d = points.shape
    n = data.shape[0]
    # Centring on the data mean keeps the matrix-product distance form accurate far from 0.
    centre = jax.lax.stop_gradient(jnp.mean(data, axis=0))
    y = (data - centre) / bandwidth
    const = -jnp.log(n) - jnp.sum(jnp.log(bandwidth)) - 0.5 * d * _LOG_2PI

    def block(p):
        z = (p - centre) / bandwidth
        return logsumexp(-0.5 * _sq_dist(z, y), axis=1)

    return _map_blocks(block, m, n, points) + const


@jax.jit
def kernel_conditional_weights(
    z: jnp.ndarray, z_data: jnp.ndarray, bw_z: jnp.ndarray
) -> jnp.ndarray:
    """Mixture weights ``w_i(z) ∝ prod_k N(z_k; z_data_ik, bw_z_k)`` of the kernel conditional.

    ``z`` has shape (..., dz) (or (dz,)); the result has shape (..., N) and sums to 1 over the
    last axis. Computed as a softmax of log-kernels, so far-away ``z`` do not underflow to 0/0.
    These weights plus per-component ``Normal(x_data_i, bw_x)`` form the conditional density as
    a ``MixtureSameFamily`` distribution.
    """
    z = jnp.asarray(z, dtype=jnp.float64)
    z_data = jnp.asarray(z_data, dtype=jnp.float64)
    bw_z = jnp.asarray(bw_z, dtype=jnp.float64)
    batch = z.shape[:-1]
    zz = z.reshape(-1, z.shape[-1])
    centre = jax.lax.stop_gradient(jnp.mean(z_data, axis=0))
    y = (z_data - centre) / bw_z
    n = z_data.shape[0]

    def block(p):
        return jax.nn.softmax(-0.5 * _sq_dist((p - centre) / bw_z, y), axis=1)

    w = _map_blocks(block, zz.shape[0], n, zz)
    return w.reshape(batch + (n,))


@jax.jit
def conditional_kde_logpdf(
    x: jnp.ndarray,
    z: jnp.ndarray,
    x_data: jnp.ndarray,
    z_data: jnp.ndarray,
    bw_x: jnp.ndarray,
    bw_z: jnp.ndarray,
) -> jnp.ndarray:
    """Log of the kernel conditional density ``p(x | z) = sum_i w_i(z) K_x(x - x_i)``.

    ``x`` (M, dx) and ``z`` (M, dz) are row-wise pairs (broadcast them first). Equals
    statsmodels' ``KDEMultivariateConditional.pdf`` ``f(x, z) / f(z)`` with the same bandwidths.
    """
    x = jnp.asarray(x, dtype=jnp.float64)
    z = jnp.asarray(z, dtype=jnp.float64)
    bw_x = jnp.asarray(bw_x, dtype=jnp.float64)
    bw_z = jnp.asarray(bw_z, dtype=jnp.float64)
    m, dx = x.shape
    n = x_data.shape[0]
    cx = jax.lax.stop_gradient(jnp.mean(x_data, axis=0))
    cz = jax.lax.stop_gradient(jnp.mean(z_data, axis=0))
    yx = (x_data - cx) / bw_x
    yz = (z_data - cz) / bw_z
    const = -jnp.sum(jnp.log(bw_x)) - 0.5 * dx * _LOG_2PI

    def block(xb, zb):
        lz = -0.5 * _sq_dist((zb - cz) / bw_z, yz)
        lx = -0.5 * _sq_dist((xb - cx) / bw_x, yx)
        return logsumexp(lx + lz, axis=1) - logsumexp(lz, axis=1)

    return _map_blocks(block, m, n, x, z) + const


@partial(jax.jit, static_argnames=("n",))
def _sample_kde(key: jax.Array, data: jnp.ndarray, bw: jnp.ndarray, n: int) -> jnp.ndarray:
    k1, k2 = jax.random.split(key)
    idx = jax.random.randint(k1, (n,), 0, data.shape[0])
    return data[idx] + jax.random.normal(k2, (n, data.shape[1]), dtype=jnp.float64) * bw


@partial(jax.jit, static_argnames=("n",))
def _sample_conditional(
    key: jax.Array,
    z: jnp.ndarray,
    x_data: jnp.ndarray,
    z_data: jnp.ndarray,
    bw_x: jnp.ndarray,
    bw_z: jnp.ndarray,
    n: int,
) -> jnp.ndarray:
    """(n, M, dx) draws: a component by inverse-CDF on the weights, then its kernel noise.

    Inverse-CDF (a binary search per draw) rather than ``random.categorical``, whose Gumbel
    trick draws n x M x N variates.
    """
    k1, k2 = jax.random.split(key)
    cw = jnp.cumsum(kernel_conditional_weights(z, z_data, bw_z), axis=1)  # (M, N)
    u = jax.random.uniform(k1, (n, z.shape[0]), dtype=jnp.float64) * cw[:, -1]
    # side="right": component i is drawn when cw[i-1] <= u < cw[i], so zero weights never are.
    idx = jax.vmap(partial(jnp.searchsorted, side="right"), in_axes=(0, 1), out_axes=1)(cw, u)
    idx = jnp.minimum(idx, x_data.shape[0] - 1)
    noise = jax.random.normal(k2, (n, z.shape[0], x_data.shape[1]), dtype=jnp.float64)
    return x_data[idx] + noise * bw_x


# --------------------------------------------------------------------------------------------
# Bandwidth-selection objectives
# --------------------------------------------------------------------------------------------


def _loo_lse(groups: Sequence[tuple[jnp.ndarray, jnp.ndarray]]) -> jnp.ndarray:
    """Row-wise ``logsumexp_{j != i} sum_g -0.5 |(y_gi - y_gj) * inv_bw_g|^2`` for each i.

    ``groups`` are (y (N, d_g), inv_bw (d_g,)) pairs whose log-kernels add (a product kernel
    over blocks of columns). The diagonal, the point itself, is excluded with -inf: that is
    what makes it leave-one-out. Rows are processed in blocks so memory stays bounded for
    large N.
    """
    scaled = [y * inv for y, inv in groups]
    n = scaled[0].shape[0]

    def block(rows, *row_blocks):
        logk = sum(-0.5 * _sq_dist(rb, s) for rb, s in zip(row_blocks, scaled, strict=True))
        logk = jnp.where(rows[:, None] == jnp.arange(n)[None, :], -jnp.inf, logk)
        return logsumexp(logk, axis=1)

    return _map_blocks(block, n, n, jnp.arange(n), *scaled)


@jax.jit
def _neg_loo_loglik_diag(log_bw: jnp.ndarray, y: jnp.ndarray) -> jnp.ndarray:
    """Negative leave-one-out log-likelihood, ``-sum_i log f_-i(y_i)``, for log-bandwidths.

    Same objective (up to an additive constant) as statsmodels ``KDEMultivariate.loo_likelihood``
    with ``func=np.log``, which drops the 1/(N-1) and 1/sqrt(2 pi) factors.
    """
    n, d = y.shape
    lse = _loo_lse([(y, jnp.exp(-log_bw))])
    return -(jnp.sum(lse) - n * jnp.sum(log_bw) - n * jnp.log(n - 1.0) - 0.5 * n * d * _LOG_2PI)


# Rows per tile of the size-independent objective below (128: the last, partly empty tile
# wastes less than with 256 and the loop overhead is still small; both timed at N = 700-1300),
# and the smallest data buffer it is compiled for. One compiled program serves every N up to
# the buffer (the loops over tiles run to the data's true size, a traced number), so fits at
# new sizes do not recompile; the buffer only costs memory (4096 x q floats). Past it the
# buffer doubles, one program each.
_TILE = 128
_MIN_CAPACITY = 4096


def _capacity(n: int) -> int:
    cap = _MIN_CAPACITY
    while cap < n:
        cap *= 2
    return cap


def _padded(y: np.ndarray) -> jnp.ndarray:
    """``y`` (N, q) followed by zero rows up to its capacity; the objective never reads them."""
    n = y.shape[0]
    # device_put, not jnp.asarray: a transfer, where asarray may compile a conversion.
    return jax.device_put(np.pad(np.asarray(y, np.float64), ((0, _capacity(n) - n), (0, 0))))


def _online_moments(state, logk: jnp.ndarray, ext: jnp.ndarray):
    """Fold one column tile into each row's running max and ``sum_j e_ij [1, v_j, v_j^2]``.

    e_ij = exp(logk_ij - max_i): the streaming form of a row softmax, rescaling what was
    summed so far whenever the row maximum grows. Masked entries (-inf) add exactly zero.
    ``ext`` holds the columns [1, v, v^2] of the tile's points, so the sum of weights and both
    moments come from one matrix product.
    """
    m, acc = state
    m_new = jnp.maximum(m, jnp.max(logk, axis=1))
    e = jnp.exp(logk - m_new[:, None])
    return m_new, acc * jnp.exp(m - m_new)[:, None] + e @ ext


@partial(jax.jit, static_argnames=("dx", "conditional"))
def _loo_value_and_grad_padded(
    log_bw: jnp.ndarray, y: jnp.ndarray, n: jnp.ndarray, dx: int, conditional: bool
) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Negative LOO (conditional, or with all columns "x") log-likelihood of the first ``n``
    rows of ``y`` (any traced ``n``) and its gradient w.r.t. log-bandwidths, hand-derived: one
    exponential per kernel pair, half the cost of autodiff (which the tests check it against)
    on a search that calls it tens of times. With s = y / bw, W the row-softmax of the (x, z)
    log-kernels without the diagonal and V that of the z log-kernels alone,
    d(-L)/d log bw_x,k = N - sum_ij W_ij (s_ik - s_jk)^2 and
    d(-L)/d log bw_z,k = - sum_ij (W_ij - V_ij) (s_ik - s_jk)^2.

    ``y`` is a buffer of at least ``n`` rows (see :func:`_padded`); rows from ``n`` on have
    zero weight: the loops over row and column tiles stop at ``n``, and the entries of the
    last tiles beyond it are masked to -inf, so they contribute exactly nothing and the
    result does not depend on the buffer's size. Each row's softmax is accumulated tile by
    tile (:func:`_online_moments`) together with the first and second moments of the scaled
    data under it, from which ``sum_j W_ij (s_ik - s_jk)^2 = s_ik^2 - 2 s_ik m1_ik + m2_ik``.
    """
    q = y.shape[1]
    t = _TILE
    s = y * jnp.exp(-log_bw)
    ones = jnp.ones((s.shape[0], 1))
    ext = jnp.concatenate([ones, s, s * s], axis=1)
    ext_z = jnp.concatenate([ones, s[:, dx:], s[:, dx:] ** 2], axis=1)
    n_tiles = (n + t - 1) // t
    # A finite "minus infinity" for the running maxima: a fully masked tile then rescales by
    # exp(0) = 1 and adds exp(-inf) = 0 instead of producing inf - inf.
    low = jnp.float64(-1e300)

    def start(width):
        return jnp.full(t, low), jnp.zeros((t, 1 + 2 * width))

    def row_tile(a, acc):
        val, gx, gz = acc
        rows = a * t + jnp.arange(t)
        s_r = jax.lax.dynamic_slice(s, (a * t, jnp.zeros_like(a)), (t, q))

        def col_tile(b, states):
            cols = b * t + jnp.arange(t)
            zero = jnp.zeros_like(b)
            s_c = jax.lax.dynamic_slice(s, (b * t, zero), (t, q))
            e_c = jax.lax.dynamic_slice(ext, (b * t, zero), (t, 1 + 2 * q))
            keep = (cols[None, :] < n) & (rows[:, None] != cols[None, :])
            logk = -0.5 * _sq_dist(s_r[:, :dx], s_c[:, :dx])
            if not conditional:
                return (_online_moments(states[0], jnp.where(keep, logk, -jnp.inf), e_c),)
            ez_c = jax.lax.dynamic_slice(ext_z, (b * t, zero), (t, 1 + 2 * (q - dx)))
            lz = jnp.where(keep, -0.5 * _sq_dist(s_r[:, dx:], s_c[:, dx:]), -jnp.inf)
            return (_online_moments(states[0], jnp.where(keep, logk + lz, -jnp.inf), e_c),
                    _online_moments(states[1], lz, ez_c))

        init = (start(q),) if not conditional else (start(q), start(q - dx))
        states = jax.lax.fori_loop(0, n_tiles, col_tile, init)
        valid = rows < n

        def finish(state):
            m, acc = state
            w = acc.shape[1] // 2
            tot = jnp.where(valid, acc[:, 0], 1.0)  # padded rows: no columns, no log(0)
            moments = acc[:, 1:] / tot[:, None]
            return jnp.where(valid, jnp.log(tot) + m, 0.0), moments[:, :w], moments[:, w:]

        lse, m1, m2 = finish(states[0])
        w = valid[:, None]
        sq = jnp.where(w, s_r * s_r - 2.0 * s_r * m1 + m2, 0.0)
        val = val + jnp.sum(lse)
        gx = gx + jnp.sum(sq[:, :dx], axis=0)
        if conditional:
            lse_z, v1, v2 = finish(states[1])
            sz = s_r[:, dx:]
            gz = gz + jnp.sum(jnp.where(w, -2.0 * sz * (m1[:, dx:] - v1) + m2[:, dx:] - v2,
                                        0.0), axis=0)
            val = val - jnp.sum(lse_z)
        return val, gx, gz

    acc = (jnp.float64(0.0), jnp.zeros(dx), jnp.zeros(q - dx))
    val, gx, gz = jax.lax.fori_loop(0, n_tiles, row_tile, acc)
    nf = n.astype(jnp.float64)
    if conditional:
        ll = val - nf * jnp.sum(log_bw[:dx]) - 0.5 * nf * dx * _LOG_2PI
        return -ll, jnp.concatenate([nf - gx, -gz])
    ll = val - nf * jnp.sum(log_bw) - nf * jnp.log(nf - 1.0) - 0.5 * nf * dx * _LOG_2PI
    return -ll, nf - gx


# The objective compiled ahead of time per (q, dx, conditional, buffer rows): called directly,
# a fit neither traces nor lowers it again in this process, and (see _objective) not in the
# next one either when the executable was stored on disk.
_OBJECTIVES: dict[tuple[int, int, bool, int], Any] = {}


def _executable_path(key: tuple[int, int, bool, int]) -> Path | None:
    """Where the executable for ``key`` is stored, or None when caching is off.

    The name hashes everything the program depends on (this module's source, the JAX and
    XLA versions, the device, the shapes), so a stale file is never loaded: it is simply
    not looked up again.
    """
    from bayesrob import cache_dir

    root = cache_dir()
    if root is None:
        return None
    dev = jax.devices()[0]
    parts = [Path(__file__).read_bytes(), jax.__version__.encode(),
             jax.lib.__version__.encode() if hasattr(jax.lib, "__version__") else b"",
             str((dev.platform, dev.device_kind, dev.client.platform_version, key, _TILE,
                  jax.config.jax_enable_x64)).encode()]
    digest = hashlib.sha256(b"\0".join(parts)).hexdigest()[:32]
    return root / "executables" / f"loo-{digest}.bin"


def _loaded(blob: bytes, in_tree: Any, out_tree: Any, capacity: int, q: int) -> Any:
    """The executable in ``blob``, or None if it does not load or cannot run.

    One evaluation on two rows (about a millisecond) proves it runs: a file can load and
    still lack kernels (see :func:`_objective`).
    """
    try:
        fn = serialize_executable.deserialize_and_load(blob, in_tree, out_tree)
        two = np.zeros((capacity, q))
        two[1] = 1.0
        jax.block_until_ready(fn(np.zeros(q), jax.device_put(two), np.int32(2)))
        return fn
    except Exception:
        return None


def _serialised(fn: Any, in_tree: Any, out_tree: Any, capacity: int, q: int) -> bytes | None:
    """``fn`` serialised, if what it serialises to loads and runs again."""
    blob, _, _ = serialize_executable.serialize(fn)
    return blob if _loaded(blob, in_tree, out_tree, capacity, q) is not None else None


@contextlib.contextmanager
def _persistent_cache_off():
    """Compilations inside the block are fresh: not read from (nor written to) any cache.

    JAX decides once per process whether the cache is used; resetting that decision on both
    sides (public ``reset_cache``) makes it take the flag into account, and then the
    configured directory again.
    """
    enabled = jax.config.jax_enable_compilation_cache
    compilation_cache.reset_cache()
    jax.config.update("jax_enable_compilation_cache", False)
    jax.clear_caches()  # or the in-memory cache hands back the same executable
    try:
        yield
    finally:
        jax.config.update("jax_enable_compilation_cache", enabled)
        compilation_cache.reset_cache()


def _objective(q: int, dx: int, conditional: bool, capacity: int) -> Any:
    """The compiled (value, gradient) of the LOO objective for a buffer of ``capacity`` rows.

    In-process it is compiled once; across processes it is stored with JAX's executable
    serialisation next to JAX's compilation cache, because a persistent-cache hit still
    traces and lowers the function (about 0.3 s of Python per new process), more than a
    whole fit at N = 1000 takes. A file that fails to load or run is compiled again and
    replaced; failing to write one only costs the next process the compilation.
    """
    key = (q, dx, bool(conditional), capacity)
    fn = _OBJECTIVES.get(key)
    if fn is not None:
        return fn
    f64 = jnp.float64
    args = (jax.ShapeDtypeStruct((q,), f64), jax.ShapeDtypeStruct((capacity, q), f64),
            jax.ShapeDtypeStruct((), jnp.int32))
    in_tree = jax.tree_util.tree_structure((args, {}))
    out_tree = jax.tree_util.tree_structure((args[2], args[0]))
    path = _executable_path(key)
    if path is not None and path.is_file():
        fn = _loaded(path.read_bytes(), in_tree, out_tree, capacity, q)
    if fn is None:
        fn = _loo_value_and_grad_padded.lower(*args, dx=dx, conditional=conditional).compile()
        if path is not None:
            with contextlib.suppress(Exception):
                blob = _serialised(fn, in_tree, out_tree, capacity, q)
                if blob is None:
                    # That executable came from JAX's persistent cache, and XLA:CPU cannot
                    # serialise a deserialised executable again in full (it loses its fused
                    # kernels); compile it afresh, past that cache, to store it.
                    with _persistent_cache_off():
                        fresh = _loo_value_and_grad_padded.lower(
                            *args, dx=dx, conditional=conditional).compile()
                    blob = _serialised(fresh, in_tree, out_tree, capacity, q)
                if blob is not None:
                    path.parent.mkdir(parents=True, exist_ok=True)
                    tmp = path.with_suffix(f".{os.getpid()}.tmp")
                    tmp.write_bytes(blob)
                    os.replace(tmp, path)  # atomic: a concurrent reader never sees half a file
    _OBJECTIVES[key] = fn
    return fn


@jax.jit
def _j_loo_normalised(h: jnp.ndarray, y: jnp.ndarray, log_scale: jnp.ndarray) -> jnp.ndarray:
    """The paper's J_LOO for normalised data ``y`` and width ``h`` (pdfs in original units).

    With K_il = SGF(y_i | y_l, h) and S_i = sum_l K_il, the full-data density at x_i is
    S_i / N and the density with point j removed is (S_i - K_ij) / (N - 1); both carry the
    1/prod(sigma) change of variables (NOTES item 3). Every (i, j) pair is summed, including
    j = i, exactly as the formula is printed. Their difference simplifies to
    (K_ij - S_i / N) / (N - 1), so

        J_LOO = sum_i sum_j (K_ij - mean_l K_il)^2 / ((N - 1)^2 prod sigma^2):

    the spread of each point's kernel values. That is why it falls monotonically as h grows
    (all kernel values flatten towards the same small number) and has no interior minimum.
    The spread is computed around the row mean (two passes), which is exact and, unlike
    the expanded sum of squares, free of cancellation; rows are processed in blocks.
    """
    n, d = y.shape
    s = y / h
    const = -d * jnp.log(h) - 0.5 * d * _LOG_2PI

    def block(rows):
        k = jnp.exp(-0.5 * _sq_dist(rows, s) + const)
        return jnp.sum((k - jnp.mean(k, axis=1, keepdims=True)) ** 2, axis=1)

    spread = _map_blocks(block, n, n, s)
    return jnp.sum(spread) / (n - 1.0) ** 2 * jnp.exp(-2.0 * log_scale)


_j_loo_grid = jax.jit(jax.vmap(_j_loo_normalised, in_axes=(0, None, None)))


@jax.jit
def _loo_loglik_single(h: jnp.ndarray, y: jnp.ndarray) -> jnp.ndarray:
    d = y.shape[1]
    return -_neg_loo_loglik_diag(jnp.full(d, jnp.log(h)), y)


_loo_loglik_grid = jax.jit(jax.vmap(_loo_loglik_single, in_axes=(0, None)))


def j_loo(data: Any, h: float) -> float:
    """The paper's J_LOO(h) for ``data`` normalised by its componentwise population std."""
    arr = _as_data(data)
    sigma = arr.std(axis=0)
    y = jnp.asarray(arr / sigma)
    return float(_j_loo_normalised(jnp.float64(h), y, jnp.float64(np.sum(np.log(sigma)))))


def loo_loglik(data: Any, bandwidth: Any) -> float:
    """Leave-one-out log-likelihood ``sum_i log pdf(x_i | D_-i)`` for a bandwidth in data units."""
    arr = _as_data(data)
    bw = _fixed_bandwidth(bandwidth, arr.shape[1])
    return float(-_neg_loo_loglik_diag(jnp.log(jnp.asarray(bw)), jnp.asarray(arr)))


# --------------------------------------------------------------------------------------------
# Optimisers
# --------------------------------------------------------------------------------------------


def _check_range(h_range: Sequence[float]) -> tuple[float, float]:
    lo, hi = (float(v) for v in h_range)
    if not (0 < lo < hi < np.inf):
        raise ValueError(f"h_range must satisfy 0 < lo < hi < inf, got {h_range}")
    return lo, hi


def _scalar_search(objective_grid, objective_one, lo: float, hi: float, n_grid: int) -> float:
    """Minimise a 1-D objective of h on [lo, hi]: log grid, then bounded refinement.

    The grid guards against the local minima a bounded Brent search alone could settle in; the
    refinement runs in log h between the grid neighbours of the best grid point.
    """
    if n_grid < 3:
        raise ValueError(f"n_grid must be >= 3, got {n_grid}")
    grid = np.geomspace(lo, hi, n_grid)
    vals = np.asarray(objective_grid(jnp.asarray(grid)))
    vals = np.where(np.isfinite(vals), vals, np.inf)
    k = int(np.argmin(vals))
    a = math.log(grid[max(k - 1, 0)])
    b = math.log(grid[min(k + 1, n_grid - 1)])
    res = optimize.minimize_scalar(
        lambda t: float(objective_one(math.exp(t))),
        bounds=(a, b),
        method="bounded",
        options={"xatol": 1e-6},
    )
    # Brent's bounded search never evaluates the bracket ends, so a best grid point on the
    # range's bound (the paper criterion's usual answer) is kept exactly rather than 1e-6 in.
    best_t = res.x if res.fun < vals[k] else math.log(grid[k])
    return float(min(max(math.exp(best_t), lo), hi))


def _on_bound(value: float, lo: float, hi: float, rtol: float = 1e-3) -> bool:
    return bool(abs(math.log(value / lo)) < rtol or abs(math.log(hi / value)) < rtol)


_BLAS_CONTROLLER: Any = None


def _single_threaded_blas() -> contextlib.AbstractContextManager:
    """Limit BLAS to one thread while L-BFGS-B runs.

    scipy's L-BFGS-B makes a few BLAS/LAPACK calls on (2m x 2m) matrices per iteration;
    with multi-threaded OpenBLAS each costs ~1 ms of thread hand-off instead of ~0.1 ms (10x
    measured on 2 busy cores), which at N <= 1000 is as much as the objective itself.
    Without threadpoolctl installed this is a no-op.
    """
    global _BLAS_CONTROLLER
    if ThreadpoolController is None:
        return contextlib.nullcontext()
    if _BLAS_CONTROLLER is None:
        _BLAS_CONTROLLER = ThreadpoolController()
    return _BLAS_CONTROLLER.limit(limits=1, user_api="blas")


def _lbfgs_log_bw(vg, x0: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, float]:
    """Minimise a jitted value-and-grad objective of log-bandwidths with bounded L-BFGS-B."""

    def fun(theta):
        v, g = vg(np.asarray(theta, dtype=np.float64))
        return float(v), np.asarray(g, dtype=np.float64)

    # ftol 1e-11 / gtol 1e-7: bandwidths to 1e-6 relative or better (statsmodels stops at
    # 1e-3 absolute). Tighter, the last iterations only chase rounding: at N = 700 a 2-D | 2-D
    # conditional fit took 34 evaluations instead of 21 for the same widths to 8 digits.
    res = optimize.minimize(
        fun,
        x0,
        jac=True,
        method="L-BFGS-B",
        bounds=list(zip(lo, hi, strict=True)),
        options={"ftol": 1e-11, "gtol": 1e-7, "maxiter": 1000, "maxcor": 20},
    )
    if not (np.all(np.isfinite(res.x)) and np.isfinite(res.fun)):
        raise KDEError("bandwidth optimisation diverged (non-finite objective or bandwidth)")
    return np.asarray(res.x), float(res.fun)


def _start_points(x0: np.ndarray, dx: int) -> list[np.ndarray]:
    """Deterministic starts around the normal reference ``x0`` for a multi-start search.

    The conditional likelihood often has several local maxima at small N (which z dimensions
    get narrow kernels); shrinking / widening each width by 4, all by 3, and the z block by 3
    found the best one in every case of a 60-problem survey, where the single normal-reference
    start missed it in 4 of 60.
    """
    q = x0.size
    pts = [x0, x0 - math.log(3.0), x0 + math.log(3.0)]
    if dx < q:
        zs = np.r_[np.zeros(dx), np.ones(q - dx)] * math.log(3.0)
        pts += [x0 - zs, x0 + zs]
    for k in range(q):
        for f in (-math.log(4.0), math.log(4.0)):
            p = x0.copy()
            p[k] += f
            pts.append(p)
    return pts


# Multi-start costs ~2q+5 optimisations; below this N it is cheap (the N x N objective is small)
# and local maxima are most common, above it the likelihood surface is smoother and one start
# from the normal reference keeps large fits fast.
_MULTISTART_MAX_N = 500


def _select_log_bw(
    joint: np.ndarray, dx: int, conditional: bool, multistart: bool | None,
    floor: np.ndarray | None = None,
) -> tuple[np.ndarray, bool]:
    """Bandwidths (original units) maximising the (conditional) LOO log-likelihood.

    Works in units of each column's standard deviation so one set of bounds and starts fits
    every data set. The first start is statsmodels': the normal reference 1.06 sigma
    N^(-1/(4+q)) over all q columns (for the conditional, q counts x and z, as statsmodels
    computes it on the joint data).

    ``floor``: least bandwidth per column (original units; 0 for none). A width that ends on
    it is a choice the caller made, not a search that ran out of range, so it does not count
    as ``on`` the bound.
    """
    n, q = joint.shape
    sigma = joint.std(axis=0)
    y = _padded((joint - joint.mean(axis=0)) / sigma)
    n_traced = jax.device_put(np.int32(n))
    objective = _objective(q, dx, conditional, int(y.shape[0]))
    x0 = np.full(q, math.log(1.06 * n ** (-1.0 / (4 + q))))
    lo = np.full(q, math.log(_DIAG_RANGE[0]))
    hi = np.full(q, math.log(_DIAG_RANGE[1]))
    search_lo = lo
    if floor is not None:
        with np.errstate(divide="ignore"):
            search_lo = np.clip(np.log(np.asarray(floor, float) / sigma), lo, hi)
    if multistart is None:
        multistart = conditional and n <= _MULTISTART_MAX_N
    starts = _start_points(x0, dx if conditional else q) if multistart else [x0]
    best_theta, best_val = None, np.inf
    with _single_threaded_blas():
        for x_start in starts:
            theta, val = _lbfgs_log_bw(
                lambda t: objective(t, y, n_traced),
                np.clip(x_start, search_lo, hi),
                search_lo,
                hi,
            )
            # Later starts must beat the first clearly, so ties keep statsmodels' start.
            if best_theta is None or val < best_val - 1e-9 * max(1.0, abs(best_val)):
                best_theta, best_val = theta, val
    on = bool(np.any(np.minimum(best_theta - lo, hi - best_theta) < 1e-3))
    return np.exp(best_theta) * sigma, on


def _warn_bound(what: str, value: Any, rng: tuple[float, float], extra: str = "") -> None:
    warnings.warn(
        f"{what} bandwidth {value} lies on the bound of its search range {rng} "
        f"(normalised units){extra}; widen the range or treat the estimate with care",
        BandwidthOnBoundWarning,
        stacklevel=3,
    )


# --------------------------------------------------------------------------------------------
# KDE
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class KDE:
    """A fitted Gaussian-kernel density estimate with a diagonal bandwidth.

    Build it with :meth:`KDE.fit`. ``bandwidth`` is in the data's original units (one value per
    dimension); ``h`` is the single normalised width of the ``"paper"`` and ``"loo-ml"``
    selectors (``bandwidth = h * sigma``), None otherwise.
    """

    data: np.ndarray
    bandwidth: np.ndarray
    selector: str
    h: float | None = None
    on_bound: bool = False
    search_range: tuple[float, float] | None = None
    sigma: np.ndarray = field(default=None, repr=False)  # type: ignore[assignment]

    @property
    def n(self) -> int:
        return int(self.data.shape[0])

    @property
    def d(self) -> int:
        return int(self.data.shape[1])

    @classmethod
    def fit(
        cls,
        data: Any,
        bandwidth: str | float | Sequence[float] | np.ndarray = "loo-ml-diag",
        *,
        h_range: Sequence[float] = (0.05, 2.0),
        n_grid: int = 41,
        warn_on_bound: bool = True,
        multistart: bool | None = None,
    ) -> KDE:
        """Fit a KDE to ``data`` ((N, d), or (N,) for d = 1).

        ``bandwidth`` is one of ``"paper"`` (J_LOO as printed, on a log grid of ``n_grid``
        widths over ``h_range`` refined by a bounded scalar search), ``"loo-ml"`` (one
        normalised width maximising the leave-one-out log-likelihood, same search),
        ``"loo-ml-diag"`` (one width per dimension, statsmodels' cv_ml objective, L-BFGS-B on
        log-bandwidths with exact gradients), or a fixed width: a number or one value per
        dimension, in the data's units. A width on its search bound sets ``on_bound`` and, if
        ``warn_on_bound``, emits :class:`BandwidthOnBoundWarning`.

        ``multistart`` (``"loo-ml-diag"`` only): also start L-BFGS-B from 2d + 2 perturbed
        widths and keep the best optimum. Off by default (None) because in a survey of skewed,
        bimodal, clustered and heavy-tailed data the unconditional objective never had more
        than one local maximum.
        """
        arr = _as_data(data)
        n, d = arr.shape
        sigma = arr.std(axis=0)
        if isinstance(bandwidth, str):
            if bandwidth in ("paper", "loo-ml"):
                lo, hi = _check_range(h_range)
                # Dividing by sigma without centring is the paper's normalisation; the kernel
                # only sees differences, so centring (done for accuracy) changes nothing.
                y = jnp.asarray((arr - arr.mean(axis=0)) / sigma)
                if bandwidth == "paper":
                    log_scale = jnp.float64(np.sum(np.log(sigma)))
                    h = _scalar_search(
                        lambda g: _j_loo_grid(g, y, log_scale),
                        lambda v: _j_loo_normalised(jnp.float64(v), y, log_scale),
                        lo,
                        hi,
                        n_grid,
                    )
                else:
                    h = _scalar_search(
                        lambda g: -_loo_loglik_grid(g, y),
                        lambda v: -_loo_loglik_single(jnp.float64(v), y),
                        lo,
                        hi,
                        n_grid,
                    )
                on = _on_bound(h, lo, hi)
                if on and warn_on_bound:
                    extra = (
                        " (J_LOO decreases monotonically in h, so the paper's criterion "
                        "has no interior minimum)"
                        if bandwidth == "paper"
                        else ""
                    )
                    _warn_bound(f"{bandwidth!r}", f"h={h:.4g}", (lo, hi), extra)
                return cls(arr, h * sigma, bandwidth, h, on, (lo, hi), sigma)
            if bandwidth == "loo-ml-diag":
                bw, on = _select_log_bw(arr, d, False, multistart)
                if on and warn_on_bound:
                    _warn_bound("'loo-ml-diag'", np.round(bw / sigma, 6).tolist(), _DIAG_RANGE)
                return cls(arr, bw, bandwidth, None, on, _DIAG_RANGE, sigma)
            raise ValueError(
                f"unknown bandwidth selector {bandwidth!r}; use one of {SELECTORS} or a number"
            )
        bw = _fixed_bandwidth(bandwidth, d)
        return cls(arr, bw, "fixed", None, False, None, sigma)

    def logpdf(self, points: Any) -> jnp.ndarray:
        """Log density at (M, d) points (a (d,) vector is one point and gives a scalar).

        Traceable: it wraps :func:`kde_logpdf`, so it works under jax.grad / jit.
        """
        p, single = _points_2d(points, self.d)
        out = kde_logpdf(p, jnp.asarray(self.data), jnp.asarray(self.bandwidth))
        return out[0] if single else out

    def pdf(self, points: Any) -> jnp.ndarray:
        """Density at (M, d) points, in the data's original units."""
        return jnp.exp(self.logpdf(points))

    def sample(self, key_or_seed: Any, n: int) -> jnp.ndarray:
        """Draw ``n`` points, shape (n, d): a uniformly chosen data point plus kernel noise."""
        return _sample_kde(
            _key(key_or_seed), jnp.asarray(self.data), jnp.asarray(self.bandwidth), int(n)
        )

    def mean(self) -> np.ndarray:
        """Mean of the KDE (the data mean)."""
        return self.data.mean(axis=0)

    def cov(self) -> np.ndarray:
        """Covariance of the KDE: the population covariance of the data plus diag(bw^2)."""
        c = np.atleast_2d(np.cov(self.data, rowvar=False, bias=True))
        return c + np.diag(self.bandwidth**2)


# --------------------------------------------------------------------------------------------
# Conditional densities
# --------------------------------------------------------------------------------------------


def _broadcast_pairs(x: Any, z: Any, dx: int, dz: int) -> tuple[jnp.ndarray, jnp.ndarray, bool]:
    xp, xs = _points_2d(x, dx)
    zp, zs = _points_2d(z, dz)
    m = max(xp.shape[0], zp.shape[0])
    for name, a in (("x", xp), ("z", zp)):
        if a.shape[0] not in (1, m):
            raise KDEError(f"{name} has {a.shape[0]} rows, cannot pair with {m}")
    xp = jnp.broadcast_to(xp, (m, dx))
    zp = jnp.broadcast_to(zp, (m, dz))
    return xp, zp, xs and zs


def command_spacing(z: Any) -> float:
    """The median distance from each distinct row of ``z`` to its nearest other row: how far
    apart the conditioning values were sampled (0 with fewer than two distinct rows)."""
    u = np.unique(np.asarray(z, float), axis=0)
    if len(u) < 2:
        return 0.0
    d = np.linalg.norm(u[:, None, :] - u[None, :, :], axis=-1)
    np.fill_diagonal(d, np.inf)
    return float(np.median(d.min(axis=1)))


@dataclass(frozen=True, eq=False)
class ConditionalKDE:
    """A conditional density p(x | z) from paired samples, by the paper's histogram or kernels.

    ``method="kernel"``: ``p(x|z) = sum_i w_i(z) N(x; x_i, diag(bw_x^2))`` with
    ``w_i ∝ N(z; z_i, diag(bw_z^2))`` — a proper, smooth mixture that can be sampled directly.

    ``method="histogram"`` (the paper's COND): the joint KDE of (x, z) is evaluated at the
    centres of a regular grid of bins and normalised over the x-bins of each z-bin, then divided
    by the x-bin volume so the result is a (piecewise-constant) density in x. By default the
    grid spans the data range [min, max] of every dimension (its top edge closed so the maxima
    fall inside); with ``bin_widths`` it is centred on the data mean. Points outside the grid
    (in x or z) get ``log(floor)``, a stand-in for "no support here" that keeps log-densities
    finite (default floor 1e-300, i.e. about -690.8).
    """

    method: str
    x_data: np.ndarray
    z_data: np.ndarray
    bw_x: np.ndarray | None = None
    bw_z: np.ndarray | None = None
    selector: str = "fixed"
    on_bound: bool = False
    search_range: tuple[float, float] | None = None
    joint: KDE | None = None
    bins: np.ndarray | None = None
    bin_widths: np.ndarray | None = None
    grid_lo: np.ndarray | None = None
    log_table: np.ndarray | None = field(default=None, repr=False)
    floor: float = 1e-300

    @property
    def dx(self) -> int:
        return int(self.x_data.shape[1])

    @property
    def dz(self) -> int:
        return int(self.z_data.shape[1])

    @property
    def bandwidth(self) -> np.ndarray:
        """Kernel bandwidths [bw_x, bw_z] (kernel method) or the joint KDE's (histogram)."""
        if self.method == "kernel":
            return np.concatenate([self.bw_x, self.bw_z])
        return self.joint.bandwidth

    @classmethod
    def fit(
        cls,
        x: Any,
        z: Any,
        method: str = "kernel",
        bandwidth: str | float | Sequence[float] | np.ndarray | None = None,
        *,
        bins: int | Sequence[int] = 10,
        bin_widths: Sequence[float] | np.ndarray | None = None,
        floor: float = 1e-300,
        h_range: Sequence[float] = (0.05, 2.0),
        n_grid: int = 41,
        warn_on_bound: bool = True,
        multistart: bool | None = None,
        z_spacing_floor: float = 0.0,
    ) -> ConditionalKDE:
        """Fit p(x | z) to paired samples ``x`` (N, dx) and ``z`` (N, dz).

        Kernel method: ``bandwidth`` is ``"loo-ml-diag"`` (default; statsmodels'
        ``KDEMultivariateConditional(bw="cv_ml")`` objective, one width per dimension of x then
        z, optimised on log-bandwidths with L-BFGS-B and exact gradients from the normal
        reference start) or fixed widths (a number, or dx + dz values: x dims first).
        The conditional likelihood can have several local maxima, so with ``multistart``
        L-BFGS-B also runs from 2(dx + dz) + 4 perturbed starts and the best optimum wins;
        None (default) does so for N <= 500, where it is cheap and local maxima are common,
        and uses the normal-reference start alone above that. Statsmodels' Nelder-Mead is a
        single local search, so where it stops in a worse local maximum the widths differ
        and ours have the higher likelihood.
        ``z_spacing_floor``: every z width is at least this multiple of
        :func:`command_spacing` (0: no floor). Leave-one-out scores each point by the others,
        and on a regular grid of z a width far below the spacing can still win it: the
        points of a grid line share a coordinate, so a tiny width along it conditions each
        point on its line's neighbours alone, which do not exist at a z between the lines.

        Histogram method: ``bandwidth`` selects the joint KDE's bandwidth (default
        ``"paper"``). The grid has ``bins`` bins per dimension (x dims first, then z). Without
        ``bin_widths`` it spans the data range [min, max] of each dimension; with
        ``bin_widths`` (e.g. the paper's .01 rad, .1 rad, 50 us, 50 us) it is centred on the
        data mean with those widths. ``floor`` is the density given to points outside it.
        """
        xa = _as_data(x, "x")
        za = _as_data(z, "z")
        if xa.shape[0] != za.shape[0]:
            raise KDEError(f"x has {xa.shape[0]} rows but z has {za.shape[0]}")
        dx, dz = xa.shape[1], za.shape[1]
        if method == "kernel":
            if bandwidth is None or (isinstance(bandwidth, str) and bandwidth == "loo-ml-diag"):
                floor = None
                if z_spacing_floor > 0:
                    floor = np.r_[np.zeros(dx),
                                  np.full(dz, z_spacing_floor * command_spacing(za))]
                bw, on = _select_log_bw(np.hstack([xa, za]), dx, True, multistart, floor)
                if on and warn_on_bound:
                    _warn_bound("kernel-conditional", bw.tolist(), _DIAG_RANGE)
                return cls(
                    "kernel",
                    xa,
                    za,
                    bw[:dx],
                    bw[dx:],
                    "loo-ml-diag",
                    on,
                    _DIAG_RANGE,
                    floor=floor,
                )
            if isinstance(bandwidth, str):
                raise ValueError(
                    "kernel conditional bandwidth must be 'loo-ml-diag' or fixed, "
                    f"got {bandwidth!r}"
                )
            bw = _fixed_bandwidth(bandwidth, dx + dz)
            return cls("kernel", xa, za, bw[:dx], bw[dx:], "fixed", floor=floor)
        if method == "histogram":
            joint = KDE.fit(
                np.hstack([xa, za]),
                "paper" if bandwidth is None else bandwidth,
                h_range=h_range,
                n_grid=n_grid,
                warn_on_bound=warn_on_bound,
                multistart=multistart,
            )
            nb, widths, lo, table = _histogram_table(joint, dx, bins, bin_widths)
            return cls(
                "histogram",
                xa,
                za,
                None,
                None,
                joint.selector,
                joint.on_bound,
                joint.search_range,
                joint,
                nb,
                widths,
                lo,
                table,
                floor,
            )
        raise ValueError(f"method must be 'kernel' or 'histogram', got {method!r}")

    def logpdf(self, x_points: Any, z_points: Any) -> jnp.ndarray:
        """log p(x | z) for row-wise pairs; either side may be a single point (broadcast)."""
        xp, zp, single = _broadcast_pairs(x_points, z_points, self.dx, self.dz)
        if self.method == "kernel":
            out = conditional_kde_logpdf(
                xp,
                zp,
                jnp.asarray(self.x_data),
                jnp.asarray(self.z_data),
                jnp.asarray(self.bw_x),
                jnp.asarray(self.bw_z),
            )
        else:
            out = histogram_lookup(
                xp,
                zp,
                jnp.asarray(self.log_table),
                jnp.asarray(self.grid_lo),
                jnp.asarray(self.bin_widths),
                tuple(int(b) for b in self.bins),
                math.log(self.floor),
            )
        return out[0] if single else out

    def pdf(self, x_points: Any, z_points: Any) -> jnp.ndarray:
        """p(x | z) for row-wise pairs, a density in x."""
        return jnp.exp(self.logpdf(x_points, z_points))

    def weights(self, z: Any) -> jnp.ndarray:
        """Kernel-conditional mixture weights over the N data points, shape (M, N) or (N,)."""
        self._need_kernel("weights")
        zp, single = _points_2d(z, self.dz)
        w = kernel_conditional_weights(zp, jnp.asarray(self.z_data), jnp.asarray(self.bw_z))
        return w[0] if single else w

    def sample(self, key_or_seed: Any, z: Any, n: int) -> jnp.ndarray:
        """Draw ``n`` x's from p(x | z): shape (n, dx) for one z, (n, M, dx) for M z's."""
        self._need_kernel("sample")
        zp, single = _points_2d(z, self.dz)
        out = _sample_conditional(
            _key(key_or_seed),
            zp,
            jnp.asarray(self.x_data),
            jnp.asarray(self.z_data),
            jnp.asarray(self.bw_x),
            jnp.asarray(self.bw_z),
            int(n),
        )
        return out[:, 0] if single else out

    def _need_kernel(self, what: str) -> None:
        if self.method != "kernel":
            raise NotImplementedError(f"{what} is only available for method='kernel'")


def _histogram_table(
    joint: KDE, dx: int, bins: int | Sequence[int], bin_widths: Any
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Log p(x-bin | z-bin) / x-bin volume on the grid, shape (prod x-bins, prod z-bins)."""
    data = joint.data
    q = data.shape[1]
    nb = np.asarray(bins, dtype=int)
    nb = np.full(q, int(nb)) if nb.ndim == 0 else nb.reshape(-1)
    if nb.shape != (q,) or np.any(nb < 1):
        raise KDEError(f"bins needs 1 or {q} positive integers, got {bins}")
    if bin_widths is None:
        lo = data.min(axis=0)
        widths = (data.max(axis=0) - lo) / nb
    else:
        widths = _fixed_bandwidth(bin_widths, q, "bin_widths")
        lo = data.mean(axis=0) - 0.5 * nb * widths
    centres = [lo[k] + (np.arange(nb[k]) + 0.5) * widths[k] for k in range(q)]
    mesh = np.stack(np.meshgrid(*centres, indexing="ij"), axis=-1).reshape(-1, q)
    logv = np.asarray(joint.logpdf(mesh)).reshape(int(np.prod(nb[:dx])), int(np.prod(nb[dx:])))
    # Normalising in log space: a z-bin whose joint values all underflow in linear space still
    # gets a proper conditional instead of 0/0.
    log_vol_x = float(np.sum(np.log(widths[:dx])))
    table = logv - np.asarray(logsumexp(jnp.asarray(logv), axis=0))[None, :] - log_vol_x
    return nb, widths, lo, table


def _bin_index(p: jnp.ndarray, lo: jnp.ndarray, widths: jnp.ndarray, bins: tuple[int, ...]
               ) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Row-major flat bin index of points (M, q) and whether each lies inside the grid."""
    nb = jnp.asarray(bins)
    # The top edge is closed so that the data maximum (when the grid spans the data range)
    # falls in the last bin rather than outside.
    rel = (p - lo) / widths
    inside = jnp.all((rel >= 0) & (rel <= nb), axis=1)
    idx = jnp.clip(jnp.floor(rel).astype(jnp.int32), 0, nb - 1)
    flat = jnp.zeros(p.shape[0], dtype=jnp.int32)
    for k, s in enumerate(bins):
        flat = flat * s + idx[:, k]
    return flat, inside


@partial(jax.jit, static_argnames=("bins", "log_floor"))
def histogram_lookup(
    x: jnp.ndarray,
    z: jnp.ndarray,
    table: jnp.ndarray,
    lo: jnp.ndarray,
    widths: jnp.ndarray,
    bins: tuple[int, ...],
    log_floor: float,
) -> jnp.ndarray:
    """log p(x | z) from a histogram table (the paper's COND), pure so it can be traced.

    ``table`` holds the log conditional density per bin, ``lo`` the grid's lower corner and
    ``widths`` the bin widths (x dimensions first, then z); points outside get ``log_floor``.
    """
    dx = x.shape[1]
    ix, xin = _bin_index(x, lo[:dx], widths[:dx], bins[:dx])
    iz, zin = _bin_index(z, lo[dx:], widths[dx:], bins[dx:])
    return jnp.where(xin & zin, table[ix, iz], log_floor)


def histogram_guide(
    x: jnp.ndarray,
    z: jnp.ndarray,
    table: jnp.ndarray,
    lo: jnp.ndarray,
    widths: jnp.ndarray,
    bins: tuple[int, ...],
    wall: float,
) -> jnp.ndarray:
    """A smooth stand-in for :func:`histogram_lookup` in x, whose gradient steers NUTS.

    Inside the grid: the log table of z's bin, interpolated multilinearly between x-bin
    centres (it departs from the table by at most half the jump between neighbouring bins).
    Outside: that value at the nearest edge minus ``0.5 * (distance / (wall * bin width))^2``,
    a wall that turns trajectories back into the support. Zero where z is outside its grid
    (the table then says nothing about x).
    """
    dx = x.shape[1]
    bx = bins[:dx]
    iz, zin = _bin_index(z, lo[dx:], widths[dx:], bins[dx:])
    rows = table[:, iz].T  # (M, x-bins): the conditional table of each point's z-bin
    nb = jnp.asarray(bx)
    rel = (x - lo[:dx]) / widths[:dx]
    centre = jnp.clip(rel - 0.5, 0.0, nb - 1.0)
    i0 = jnp.clip(jnp.floor(centre).astype(jnp.int32), 0, jnp.maximum(nb - 2, 0))
    frac = centre - i0
    value = jnp.zeros(x.shape[0])
    for corner in np.ndindex(*(2,) * dx):
        weight = jnp.ones(x.shape[0])
        flat = jnp.zeros(x.shape[0], dtype=jnp.int32)
        for k, s in enumerate(bx):
            weight = weight * (frac[:, k] if corner[k] else 1.0 - frac[:, k])
            flat = flat * s + jnp.minimum(i0[:, k] + corner[k], s - 1)
        value = value + weight * jnp.take_along_axis(rows, flat[:, None], axis=1)[:, 0]
    beyond = rel - jnp.clip(rel, 0.0, nb)
    value = value - 0.5 * jnp.sum(beyond**2, axis=1) / wall**2
    return jnp.where(zin, value, 0.0)


@partial(jax.custom_jvp, nondiff_argnums=(5, 6, 7))
def guided_histogram_lookup(
    x: jnp.ndarray,
    z: jnp.ndarray,
    table: jnp.ndarray,
    lo: jnp.ndarray,
    widths: jnp.ndarray,
    bins: tuple[int, ...],
    log_floor: float,
    wall: float,
) -> jnp.ndarray:
    """:func:`histogram_lookup`'s exact value, with :func:`histogram_guide`'s gradient in x.

    The table is piecewise constant, so its true gradient is zero almost everywhere: HMC would
    fly straight through the support and off its edge, where the density is the floor. NUTS
    stays exact with any gradient field that is itself a gradient (leapfrog is then still
    reversible and volume-preserving) because it weighs and accepts states by the exact
    density; the guide only chooses where trajectories go. Derivatives with respect to z, the
    table and the grid are not defined (they are data) and come out as zero.
    """
    return histogram_lookup(x, z, table, lo, widths, bins, log_floor)


@guided_histogram_lookup.defjvp
def _guided_histogram_lookup_jvp(bins, log_floor, wall, primals, tangents):
    x, z, table, lo, widths = primals
    value = histogram_lookup(x, z, table, lo, widths, bins, log_floor)
    grad = jax.grad(lambda xx: histogram_guide(xx, z, table, lo, widths, bins, wall).sum())(x)
    return value, jnp.sum(grad * tangents[0], axis=1)
