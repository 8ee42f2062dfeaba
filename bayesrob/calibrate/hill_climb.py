"""The paper's calibration, a selectable baseline (``calibrate --method hill-climb``)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from bayesrob import robot as kin


@jax.jit
def _summed_errors(vs: jax.Array, u: jax.Array, d: jax.Array) -> jax.Array:
    """The paper's cost sum_i ||f(g(u_i)) - d_i|| for each parameter vector in vs (K, 8)."""
    pred = jax.vmap(lambda v: kin.forward_u(kin.ArmParams.from_vector(v), u))(vs)
    return jnp.sum(jnp.linalg.norm(pred - d, axis=-1), axis=-1)


def hill_climb(v0: np.ndarray, u: np.ndarray, d: np.ndarray, u_val: np.ndarray | None,
               d_val: np.ndarray | None, max_iter: int = 20000) -> tuple[np.ndarray, int]:
    """The paper's hill climb on J = sum ||f(g(u_i)) - d_i||: the best +-step move of any of
    the eight parameters, the steps halving when none helps; returns the eight and the
    iterations. Validation is checked at each halving: after every step it would stop on the
    first wobble of measurement noise, long before the fit is any good.
    """
    uj, dj = jnp.asarray(u), jnp.asarray(d)
    costs = _summed_errors
    has_val = u_val is not None and len(u_val) > 0
    v = v0.copy()
    # the eight's typical sizes, so a step means the same in each
    scale = np.array([10.0, 10.0, 10.0, 10.0, 0.05 * abs(v0[4]), 0.05 * abs(v0[5]), 0.05, 0.05])
    step = scale * 0.1
    best = float(costs(jnp.asarray(v[None]), uj, dj)[0])
    val = float(costs(jnp.asarray(v[None]), jnp.asarray(u_val), jnp.asarray(d_val))[0]) \
        if has_val else None
    kept = v.copy()
    it = 0
    moves = np.concatenate([np.eye(v.size), -np.eye(v.size)])
    while it < max_iter and np.any(step > scale * 1e-7):
        it += 1
        trials = v[None] + moves * step[None]
        c = np.asarray(costs(jnp.asarray(trials), uj, dj))
        k = int(np.argmin(c))
        if c[k] < best:
            v, best = trials[k], float(c[k])
            continue
        step = step / 2
        if has_val:
            new_val = float(costs(jnp.asarray(v[None]), jnp.asarray(u_val),
                                  jnp.asarray(d_val))[0])
            if new_val > val:
                return kept, it  # the paper's early stop: validation error rose
            val, kept = new_val, v.copy()
    return v, it
