"""Parzen (Gaussian-kernel) density estimation in JAX, with the paper's and improved selectors.

The paper (Larkworthy & Hayes 2009, section III) divides the data by their componentwise
(population) standard deviation, puts a spherical Gaussian of width ``h`` on each point and
picks ``h`` by the leave-one-out criterion printed as
``J_LOO(h) = sum_i sum_j (pdf(x_i | D, h) - pdf(x_i | D_-j, h))^2``. That criterion decreases
monotonically in ``h``, so the "paper" selector searches an explicit range and reports landing
on its bound: it is kept as the faithful baseline. The improved selectors maximise the
leave-one-out log-likelihood (statsmodels' ``cv_ml``), with one width (``"loo-ml"``) or one
per dimension (``"loo-ml-diag"``). Densities are normalised in the data's original units
(NOTES item 3). Conditional densities p(x | z) are the paper's histogram of the joint KDE or
the kernel conditional ``sum_i w_i(z) K_x(x - x_i)``, ``w_i ∝ K_z(z - z_i)``
(:class:`ConditionalKDE`).

Kernel matrices are evaluated in blocks of rows (``jax.lax.map``) so memory stays bounded;
the pure functions take and return ``jnp`` arrays, usable under ``jax.grad`` / jit / NUTS.
"""

from __future__ import annotations

import contextlib
import functools
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
from scipy.spatial import cKDTree
from threadpoolctl import ThreadpoolController

__all__ = ["KDE", "ConditionalKDE", "KDEError", "BandwidthOnBoundWarning", "kde_logpdf",
           "conditional_kde_logpdf", "kernel_conditional_weights", "command_spacing",
           "histogram_lookup", "histogram_guide", "guided_histogram_lookup", "j_loo",
           "loo_loglik", "SELECTORS"]

SELECTORS = ("paper", "loo-ml", "loo-ml-diag")

_LOG_2PI = math.log(2.0 * math.pi)

# Elements of one block of the kernel matrix (rows x data points): 32 MB per float64
# intermediate, so a block stays well under 1 GB whatever M and N are.
_BLOCK_ELEMENTS = 2**22

# Per-dimension bandwidth bounds of the gradient-based selectors, in data standard deviations:
# they keep L-BFGS-B away from bw -> 0 (duplicate points make the LOO likelihood unbounded)
# and bw -> inf (an uninformative conditioning variable).
_DIAG_RANGE = (1e-3, 1e3)


class KDEError(ValueError):
    """Raised for data a kernel density estimate cannot be fitted to (degenerate, non-finite)."""


class BandwidthOnBoundWarning(UserWarning):
    """The selected bandwidth lies on the bound of its search range (for the paper's J_LOO,
    monotone in h, the expected outcome: the estimate over-smooths as far as the range allows)."""


def _as_data(data: Any, name: str = "data") -> np.ndarray:
    """``data`` as a float64 (N, d) array, rejecting data no KDE can be fitted to."""
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
    bad = np.flatnonzero(~(arr.std(axis=0) > 0))
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
    """(M, d) view of ``points``; the flag says the caller passed one point as a (d,) vector
    (a 1-D array is M points when d == 1, one point when d > 1)."""
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


# --------------------------------------------------------------------------------------------
# Core kernels (pure, jit-compiled, differentiable)
# --------------------------------------------------------------------------------------------


def _map_blocks(fn, m: int, n: int, *row_arrays: jnp.ndarray) -> jnp.ndarray:
    """``fn`` over blocks of rows of ``row_arrays`` (each (m, ...)), results concatenated.

    ``jax.checkpoint`` makes reverse-mode store each block's inputs rather than its
    (rows x N) kernel matrix, which keeps jax.grad over many points bounded.
    """
    rows = max(1, min(m, _BLOCK_ELEMENTS // max(n, 1)))
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

    The |a|^2 + |b|^2 - 2 a.b form is one matrix product; callers centre the data first so
    its cancellation error stays ~1e-16 of the data's spread, and tiny negatives are clipped.
    """
    if a.shape[1] == 1:
        return (a - b.T) ** 2
    sq = jnp.sum(a * a, axis=1)[:, None] + jnp.sum(b * b, axis=1)[None, :] - 2.0 * (a @ b.T)
    return jnp.maximum(sq, 0.0)


def _centred(data: jnp.ndarray, bw: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """The data's mean (no gradient) and the data centred on it, in bandwidths."""
    centre = jax.lax.stop_gradient(jnp.mean(data, axis=0))
    return centre, (data - centre) / bw


@jax.jit
def kde_logpdf(points: jnp.ndarray, data: jnp.ndarray, bandwidth: jnp.ndarray) -> jnp.ndarray:
    """``log (1/N) sum_i prod_k N(x_k; data_ik, bandwidth_k)`` at each row of ``points``
    (M, d), for ``data`` (N, d) and ``bandwidth`` (d,) in the same units."""
    points, data, bandwidth = (jnp.asarray(a, jnp.float64) for a in (points, data, bandwidth))
    m, d = points.shape
    n = data.shape[0]
    centre, y = _centred(data, bandwidth)
    const = -jnp.log(n) - jnp.sum(jnp.log(bandwidth)) - 0.5 * d * _LOG_2PI

    def block(p):
        return logsumexp(-0.5 * _sq_dist((p - centre) / bandwidth, y), axis=1)

    return _map_blocks(block, m, n, points) + const


@jax.jit
def kernel_conditional_weights(
    z: jnp.ndarray, z_data: jnp.ndarray, bw_z: jnp.ndarray
) -> jnp.ndarray:
    """Mixture weights ``w_i(z) ∝ prod_k N(z_k; z_data_ik, bw_z_k)`` of the kernel conditional,
    shape (..., N) for ``z`` (..., dz); a softmax of log-kernels, so far-away z do not give 0/0."""
    z, z_data, bw_z = (jnp.asarray(a, jnp.float64) for a in (z, z_data, bw_z))
    batch = z.shape[:-1]
    zz = z.reshape(-1, z.shape[-1])
    centre, y = _centred(z_data, bw_z)
    n = z_data.shape[0]

    def block(p):
        return jax.nn.softmax(-0.5 * _sq_dist((p - centre) / bw_z, y), axis=1)

    return _map_blocks(block, zz.shape[0], n, zz).reshape(batch + (n,))


@jax.jit
def conditional_kde_logpdf(
    x: jnp.ndarray,
    z: jnp.ndarray,
    x_data: jnp.ndarray,
    z_data: jnp.ndarray,
    bw_x: jnp.ndarray,
    bw_z: jnp.ndarray,
) -> jnp.ndarray:
    """``log p(x | z) = log sum_i w_i(z) K_x(x - x_i)`` for row-wise pairs ``x`` (M, dx), ``z``
    (M, dz): statsmodels' ``KDEMultivariateConditional.pdf`` at the same bandwidths."""
    x, z, bw_x, bw_z = (jnp.asarray(a, jnp.float64) for a in (x, z, bw_x, bw_z))
    m, dx = x.shape
    n = x_data.shape[0]
    cx, yx = _centred(x_data, bw_x)
    cz, yz = _centred(z_data, bw_z)
    const = -jnp.sum(jnp.log(bw_x)) - 0.5 * dx * _LOG_2PI

    def block(xb, zb):
        lz = -0.5 * _sq_dist((zb - cz) / bw_z, yz)
        lx = -0.5 * _sq_dist((xb - cx) / bw_x, yx)
        return logsumexp(lx + lz, axis=1) - logsumexp(lz, axis=1)

    return _map_blocks(block, m, n, x, z) + const


# --------------------------------------------------------------------------------------------
# The leave-one-out log-likelihood: one compiled objective for every selector
# --------------------------------------------------------------------------------------------


# Rows per tile of the objective (128: timed best at N = 700-1300), and the smallest data
# buffer it is compiled for: the loops over tiles run to the data's true size, a traced
# number, so one program serves every N up to the buffer, which doubles past it.
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
    """Fold one column tile into each row's running max and ``sum_j e_ij [1, v_j, v_j^2]``,
    e_ij = exp(logk_ij - max_i) (a streaming row softmax; masked -inf entries add zero)."""
    m, acc = state
    m_new = jnp.maximum(m, jnp.max(logk, axis=1))
    e = jnp.exp(logk - m_new[:, None])
    return m_new, acc * jnp.exp(m - m_new)[:, None] + e @ ext


@partial(jax.jit, static_argnames=("dx", "conditional"))
def _loo_value_and_grad_padded(
    log_bw: jnp.ndarray, y: jnp.ndarray, n: jnp.ndarray, dx: int, conditional: bool
) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Negative LOO (conditional, or with all columns "x") log-likelihood of the first ``n``
    rows of ``y`` (a buffer, :func:`_padded`) and its gradient w.r.t. log-bandwidths,
    hand-derived: one exponential per kernel pair, half the cost of autodiff. With s = y / bw,
    W the row-softmax of the (x, z) log-kernels without the diagonal and V that of the z
    log-kernels alone, d(-L)/d log bw_x,k = N - sum_ij W_ij (s_ik - s_jk)^2 and
    d(-L)/d log bw_z,k = - sum_ij (W_ij - V_ij) (s_ik - s_jk)^2, where
    ``sum_j W_ij (s_ik - s_jk)^2 = s_ik^2 - 2 s_ik m1_ik + m2_ik`` from the moments under W.
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
    """Where the executable for ``key`` is stored (None: caching off); the name hashes all the
    program depends on (this source, JAX/XLA versions, device, shapes), so none is stale."""
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
    """The executable in ``blob``, or None if it does not load or run (one evaluation on two
    rows proves it runs: a file can load and still lack kernels)."""
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
    """Compilations inside the block are fresh, past any cache (JAX decides once per process
    whether the cache is used: ``reset_cache`` on both sides makes it see the flag)."""
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

    Stored across processes with JAX's executable serialisation, because a persistent-cache
    hit still traces and lowers the function (0.3 s per process, more than a fit at N = 1000).
    A file that fails to load or run is compiled again and replaced.
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


def _loo_objective(y: np.ndarray, dx: int, conditional: bool) -> Any:
    """theta -> (value, gradient) of the negative LOO log-likelihood of the rows ``y`` at
    log-bandwidths theta, by the compiled objective."""
    buf = _padded(y)
    n = jax.device_put(np.int32(y.shape[0]))
    fn = _objective(y.shape[1], dx, conditional, int(buf.shape[0]))
    return lambda theta: fn(np.asarray(theta, dtype=np.float64), buf, n)


@jax.jit
def _j_loo_normalised(h: jnp.ndarray, y: jnp.ndarray, log_scale: jnp.ndarray) -> jnp.ndarray:
    """The paper's J_LOO for normalised data ``y`` and width ``h`` (pdfs in original units).

    With K_il = SGF(y_i | y_l, h) and S_i = sum_l K_il, the density at x_i is S_i / N, and
    (S_i - K_ij) / (N - 1) with point j removed (j = i included, as printed); their difference
    is (K_ij - S_i / N) / (N - 1), so J_LOO = sum_i sum_j (K_ij - mean_l K_il)^2 /
    ((N - 1)^2 prod sigma^2): the spread of each point's kernel values, which falls
    monotonically as h grows. Computed around the row mean, free of cancellation.
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
    value, _ = _loo_objective(arr - arr.mean(axis=0), arr.shape[1], False)(np.log(bw))
    return -float(value)


# --------------------------------------------------------------------------------------------
# Optimisers
# --------------------------------------------------------------------------------------------


def _scalar_search(objective_grid, objective_one, lo: float, hi: float, n_grid: int) -> float:
    """Minimise a 1-D objective of h on [lo, hi]: a log grid (against the local minima a
    bounded Brent search alone could settle in), then Brent in log h between the best grid
    point's neighbours."""
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


@functools.cache
def _threadpools() -> ThreadpoolController:
    return ThreadpoolController()


def _lbfgs_log_bw(vg, x0: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, float]:
    """Minimise a value-and-grad objective of log-bandwidths with bounded L-BFGS-B."""

    def fun(theta):
        v, g = vg(theta)
        return float(v), np.asarray(g, dtype=np.float64)

    # ftol 1e-11 / gtol 1e-7: bandwidths to 1e-6 relative or better (statsmodels stops at
    # 1e-3 absolute); tighter, the last iterations only chase rounding.
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
    """Deterministic starts around the normal reference ``x0`` for a multi-start search:
    shrinking / widening each width by 4, all by 3, and the z block by 3 found the best
    optimum in every case of a 60-problem survey, where ``x0`` alone missed it in 4."""
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


# Multi-start costs ~2q+5 optimisations: cheap below this N, where local maxima are most
# common; above it the surface is smoother and one start keeps large fits fast.
_MULTISTART_MAX_N = 500


def _select_log_bw(
    joint: np.ndarray, dx: int, conditional: bool, floor: np.ndarray | None = None
) -> tuple[np.ndarray, bool]:
    """Bandwidths (original units) maximising the (conditional) LOO log-likelihood, and
    whether one ended on its bound.

    Works in each column's standard deviations, from statsmodels' normal-reference start
    1.06 sigma N^(-1/(4+q)) over all q columns. ``floor``: least bandwidth per column
    (original units); a width ending on it is the caller's choice, not on the bound.
    """
    n, q = joint.shape
    sigma = joint.std(axis=0)
    objective = _loo_objective((joint - joint.mean(axis=0)) / sigma, dx, conditional)
    x0 = np.full(q, math.log(1.06 * n ** (-1.0 / (4 + q))))
    lo = np.full(q, math.log(_DIAG_RANGE[0]))
    hi = np.full(q, math.log(_DIAG_RANGE[1]))
    search_lo = lo
    if floor is not None:
        with np.errstate(divide="ignore"):
            search_lo = np.clip(np.log(np.asarray(floor, float) / sigma), lo, hi)
    # A survey of skewed, bimodal, clustered and heavy-tailed data never found a second
    # local maximum of the unconditional objective; the conditional one often has several.
    starts = _start_points(x0, dx) if conditional and n <= _MULTISTART_MAX_N else [x0]
    best_theta, best_val = None, np.inf
    # scipy's L-BFGS-B makes tiny BLAS calls that multi-threaded OpenBLAS slows tenfold
    with _threadpools().limit(limits=1, user_api="blas"):
        for x_start in starts:
            theta, val = _lbfgs_log_bw(objective, np.clip(x_start, search_lo, hi), search_lo, hi)
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
    """A fitted Gaussian-kernel density estimate with a diagonal bandwidth (:meth:`fit`).

    ``bandwidth`` is in the data's units, one value per dimension; ``h`` is the single
    normalised width of the ``"paper"`` and ``"loo-ml"`` selectors (``bandwidth = h * sigma``).
    """

    data: np.ndarray
    bandwidth: np.ndarray
    selector: str
    h: float | None = None
    on_bound: bool = False
    search_range: tuple[float, float] | None = None
    sigma: np.ndarray = field(default=None, repr=False)  # type: ignore[assignment]

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
    ) -> KDE:
        """Fit a KDE to ``data`` ((N, d), or (N,) for d = 1).

        ``bandwidth``: ``"paper"`` (J_LOO as printed) or ``"loo-ml"`` (one normalised width
        maximising the LOO log-likelihood), each on a log grid of ``n_grid`` widths over
        ``h_range`` refined by Brent; ``"loo-ml-diag"`` (one width per dimension, L-BFGS-B);
        or fixed widths in the data's units. A width on its bound sets ``on_bound`` and, if
        ``warn_on_bound``, warns.
        """
        arr = _as_data(data)
        n, d = arr.shape
        sigma = arr.std(axis=0)
        if not isinstance(bandwidth, str):
            return cls(arr, _fixed_bandwidth(bandwidth, d), "fixed", sigma=sigma)
        if bandwidth == "loo-ml-diag":
            bw, on = _select_log_bw(arr, d, False)
            if on and warn_on_bound:
                _warn_bound("'loo-ml-diag'", np.round(bw / sigma, 6).tolist(), _DIAG_RANGE)
            return cls(arr, bw, bandwidth, None, on, _DIAG_RANGE, sigma)
        if bandwidth not in ("paper", "loo-ml"):
            raise ValueError(
                f"unknown bandwidth selector {bandwidth!r}; use one of {SELECTORS} or a number"
            )
        lo, hi = (float(v) for v in h_range)
        if not (0 < lo < hi < np.inf):
            raise ValueError(f"h_range must satisfy 0 < lo < hi < inf, got {h_range}")
        # The paper divides by sigma without centring; the kernel only sees differences.
        y = (arr - arr.mean(axis=0)) / sigma
        if bandwidth == "paper":
            y = jnp.asarray(y)
            log_scale = jnp.float64(np.sum(np.log(sigma)))
            h = _scalar_search(
                lambda g: _j_loo_grid(g, y, log_scale),
                lambda v: _j_loo_normalised(jnp.float64(v), y, log_scale),
                lo,
                hi,
                n_grid,
            )
        else:
            objective = _loo_objective(y, d, False)

            def one(v):
                return objective(np.full(d, math.log(v)))[0]

            h = _scalar_search(lambda g: [one(float(v)) for v in g], one, lo, hi, n_grid)
        on = bool(abs(math.log(h / lo)) < 1e-3 or abs(math.log(hi / h)) < 1e-3)
        if on and warn_on_bound:
            extra = (" (J_LOO decreases monotonically in h, so the paper's criterion has no "
                     "interior minimum)") if bandwidth == "paper" else ""
            _warn_bound(f"{bandwidth!r}", f"h={h:.4g}", (lo, hi), extra)
        return cls(arr, h * sigma, bandwidth, h, on, (lo, hi), sigma)

    def logpdf(self, points: Any) -> jnp.ndarray:
        """Log density at (M, d) points (a (d,) vector is one point and gives a scalar);
        traceable under jax.grad / jit."""
        p, single = _points_2d(points, self.d)
        out = kde_logpdf(p, jnp.asarray(self.data), jnp.asarray(self.bandwidth))
        return out[0] if single else out

    def pdf(self, points: Any) -> jnp.ndarray:
        """Density at (M, d) points, in the data's original units."""
        return jnp.exp(self.logpdf(points))


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
    return jnp.broadcast_to(xp, (m, dx)), jnp.broadcast_to(zp, (m, dz)), xs and zs


def command_spacing(z: Any) -> float:
    """The median distance from each distinct row of ``z`` to its nearest other row: how far
    apart the conditioning values were sampled (0 with fewer than two distinct rows)."""
    u = np.unique(np.asarray(z, float), axis=0)
    if len(u) < 2:
        return 0.0
    return float(np.median(cKDTree(u).query(u, k=2)[0][:, 1]))


@dataclass(frozen=True, eq=False)
class ConditionalKDE:
    """A conditional density p(x | z) from paired samples, by kernels or the paper's histogram.

    ``method="kernel"``: ``p(x|z) = sum_i w_i(z) N(x; x_i, diag(bw_x^2))`` with
    ``w_i ∝ N(z; z_i, diag(bw_z^2))``.

    ``method="histogram"`` (the paper's COND): the joint KDE of (x, z) at the centres of a
    regular grid of bins, normalised over the x-bins of each z-bin and divided by the x-bin
    volume. The grid spans the data range (top edge closed), or with ``bin_widths`` is centred
    on the data mean. Points outside it get ``log(floor)``, which keeps log-densities finite.
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
        z_spacing_floor: float = 0.0,
    ) -> ConditionalKDE:
        """Fit p(x | z) to paired samples ``x`` (N, dx) and ``z`` (N, dz).

        Kernel method: ``bandwidth`` is ``"loo-ml-diag"`` (default; statsmodels'
        ``KDEMultivariateConditional(bw="cv_ml")`` objective, x widths then z) or fixed widths
        (dx + dz values, or one); for N <= 500 L-BFGS-B also runs from 2(dx + dz) + 4 perturbed
        starts, as local maxima are common there (statsmodels' single Nelder-Mead can stop in
        a worse one). ``z_spacing_floor``: every z width is at least this multiple of
        :func:`command_spacing`, as on a regular grid of z a width far below the spacing can
        still win leave-one-out (it conditions each point on its own grid line alone).

        Histogram method: ``bandwidth`` selects the joint KDE's (default ``"paper"``); the grid
        has ``bins`` bins per dimension (x, then z), over the data range or with ``bin_widths``
        (e.g. the paper's .01 rad, .1 rad, 50 us, 50 us) about the data mean; ``floor`` is the
        density outside it.
        """
        xa = _as_data(x, "x")
        za = _as_data(z, "z")
        if xa.shape[0] != za.shape[0]:
            raise KDEError(f"x has {xa.shape[0]} rows but z has {za.shape[0]}")
        dx, dz = xa.shape[1], za.shape[1]
        if method == "histogram":
            joint = KDE.fit(np.hstack([xa, za]), "paper" if bandwidth is None else bandwidth,
                            h_range=h_range, n_grid=n_grid, warn_on_bound=warn_on_bound)
            nb, widths, lo, table = _histogram_table(joint, dx, bins, bin_widths)
            return cls("histogram", xa, za, None, None, joint.selector, joint.on_bound,
                       joint.search_range, joint, nb, widths, lo, table, floor)
        if method != "kernel":
            raise ValueError(f"method must be 'kernel' or 'histogram', got {method!r}")
        if bandwidth is not None and not isinstance(bandwidth, str):
            bw = _fixed_bandwidth(bandwidth, dx + dz)
            return cls("kernel", xa, za, bw[:dx], bw[dx:], "fixed", floor=floor)
        if bandwidth not in (None, "loo-ml-diag"):
            raise ValueError(
                f"kernel conditional bandwidth must be 'loo-ml-diag' or fixed, got {bandwidth!r}"
            )
        least = None
        if z_spacing_floor > 0:
            least = np.r_[np.zeros(dx), np.full(dz, z_spacing_floor * command_spacing(za))]
        bw, on = _select_log_bw(np.hstack([xa, za]), dx, True, least)
        if on and warn_on_bound:
            _warn_bound("kernel-conditional", bw.tolist(), _DIAG_RANGE)
        return cls("kernel", xa, za, bw[:dx], bw[dx:], "loo-ml-diag", on, _DIAG_RANGE)

    def logpdf(self, x_points: Any, z_points: Any) -> jnp.ndarray:
        """log p(x | z) for row-wise pairs; either side may be a single point (broadcast)."""
        xp, zp, single = _broadcast_pairs(x_points, z_points, self.dx, self.dz)
        if self.method == "kernel":
            out = conditional_kde_logpdf(xp, zp, *(jnp.asarray(a) for a in (
                self.x_data, self.z_data, self.bw_x, self.bw_z)))
        else:
            out = histogram_lookup(xp, zp, *(jnp.asarray(a) for a in (
                self.log_table, self.grid_lo, self.bin_widths)),
                tuple(int(b) for b in self.bins), math.log(self.floor))
        return out[0] if single else out

    def pdf(self, x_points: Any, z_points: Any) -> jnp.ndarray:
        """p(x | z) for row-wise pairs, a density in x."""
        return jnp.exp(self.logpdf(x_points, z_points))

    def weights(self, z: Any) -> jnp.ndarray:
        """Kernel-conditional mixture weights over the N data points, shape (M, N) or (N,)."""
        if self.method != "kernel":
            raise NotImplementedError("weights is only available for method='kernel'")
        zp, single = _points_2d(z, self.dz)
        w = kernel_conditional_weights(zp, jnp.asarray(self.z_data), jnp.asarray(self.bw_z))
        return w[0] if single else w


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
    # The top edge is closed: the data maximum falls in the last bin of a data-range grid.
    rel = (p - lo) / widths
    inside = jnp.all((rel >= 0) & (rel <= nb), axis=1)
    idx = jnp.clip(jnp.floor(rel).astype(jnp.int32), 0, nb - 1)
    flat = jnp.zeros(p.shape[0], dtype=jnp.int32)
    for k, s in enumerate(bins):
        flat = flat * s + idx[:, k]
    return flat, inside


@partial(jax.jit, static_argnames=("bins", "log_floor"))
def histogram_lookup(x: jnp.ndarray, z: jnp.ndarray, table: jnp.ndarray, lo: jnp.ndarray,
                     widths: jnp.ndarray, bins: tuple[int, ...], log_floor: float
                     ) -> jnp.ndarray:
    """log p(x | z) from a histogram table (the paper's COND): ``table`` the log density per
    bin, ``lo`` the grid's lower corner, ``widths`` the bin widths (x dimensions, then z);
    points outside get ``log_floor``."""
    dx = x.shape[1]
    ix, xin = _bin_index(x, lo[:dx], widths[:dx], bins[:dx])
    iz, zin = _bin_index(z, lo[dx:], widths[dx:], bins[dx:])
    return jnp.where(xin & zin, table[ix, iz], log_floor)


def histogram_guide(x: jnp.ndarray, z: jnp.ndarray, table: jnp.ndarray, lo: jnp.ndarray,
                    widths: jnp.ndarray, bins: tuple[int, ...], wall: float) -> jnp.ndarray:
    """A smooth stand-in for :func:`histogram_lookup` in x, whose gradient steers NUTS: the
    log table of z's bin interpolated multilinearly between x-bin centres, and outside the grid
    its edge value minus ``0.5 * (distance / (wall * bin width))^2``, a wall turning
    trajectories back. Zero where z is outside its grid (the table says nothing about x)."""
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
def guided_histogram_lookup(x: jnp.ndarray, z: jnp.ndarray, table: jnp.ndarray,
                            lo: jnp.ndarray, widths: jnp.ndarray, bins: tuple[int, ...],
                            log_floor: float, wall: float) -> jnp.ndarray:
    """:func:`histogram_lookup`'s exact value, with :func:`histogram_guide`'s gradient in x.

    The table's true gradient is zero almost everywhere, so HMC would fly off the support.
    NUTS stays exact with any gradient field that is itself a gradient (leapfrog stays
    reversible and volume-preserving) as it accepts states by the exact density; the guide
    only steers. Derivatives in z, the table and the grid come out as zero.
    """
    return histogram_lookup(x, z, table, lo, widths, bins, log_floor)


@guided_histogram_lookup.defjvp
def _guided_histogram_lookup_jvp(bins, log_floor, wall, primals, tangents):
    x, z, table, lo, widths = primals
    value = histogram_lookup(x, z, table, lo, widths, bins, log_floor)
    grad = jax.grad(lambda xx: histogram_guide(xx, z, table, lo, widths, bins, wall).sum())(x)
    return value, jnp.sum(grad * tangents[0], axis=1)
