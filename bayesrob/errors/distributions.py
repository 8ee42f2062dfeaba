"""The joint-error models as numpyro distributions, and an arm's density of its end point.

Every kernel model is a numpyro distribution whose density *is* the KDE. The paper's histogram
COND has a density but no sampler, so it enters programs as a ``numpyro.factor`` whose gradient
is a smooth guide's (:func:`bayesrob.errors.kde.guided_histogram_lookup`). A model's learned
state is a dict of arrays (:func:`error_arrays`) and its kind a static string
(:func:`error_kind`), so one compiled program serves every fit of one kind and shape.
:func:`arm_log_density` is a planar arm's log-likelihood of an end point, shared by the exact
grid (:mod:`bayesrob.predict.grid`) and the samplers (:mod:`bayesrob.inference.sampling`).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpyro.distributions as dist

from bayesrob import robot as kin
from bayesrob.errors.kde import guided_histogram_lookup, kernel_conditional_weights
from bayesrob.errors.noise_models import FittedNoiseModel

__all__ = ["HISTOGRAM_WALL", "ArmStatic", "error_kind", "is_sampleable",
           "error_arrays", "error_distribution", "joint_error_distribution",
           "joint_error_log_prob", "arm_structures", "arm_log_density"]

# Width, in bins, of the guide's wall around a histogram table (kde.histogram_guide). Stiffer
# walls turn NUTS trajectories back sooner; on the default rig's 16 targets 0.25 bin took
# 2.6 s against 14 s at 0.5 and 77 s at 1 bin (all passing the cross-check), while 0.1 bin
# began to cost ESS. It shapes trajectories only: the density sampled is the table's.
HISTOGRAM_WALL = 0.25


def error_kind(model: FittedNoiseModel) -> str:
    if model.conditional is None:
        return model.spec.family
    return "COND" if model.conditional.method == "kernel" else "HIST"


def is_sampleable(model: FittedNoiseModel) -> bool:
    """Whether the model can draw joint errors (everything but the histogram COND)."""
    return error_kind(model) != "HIST"


def error_arrays(model: FittedNoiseModel) -> dict[str, jax.Array]:
    """The model's learned state as arrays: traced, not baked in, by the compiled samplers."""
    kind = error_kind(model)
    if kind in ("IND", "CORR"):
        out = {"x": model.theta_err, "bw_x": model.bandwidth}
    elif kind == "COND":
        c = model.conditional
        out = {"x": c.x_data, "bw_x": c.bw_x, "z": c.z_data, "bw_z": c.bw_z}
    else:
        c = model.conditional
        out = {"table": c.log_table, "lo": c.grid_lo, "widths": c.bin_widths}
    return {k: jnp.asarray(v, dtype=jnp.float64) for k, v in out.items()}


def error_distribution(kind: str, arrays: dict[str, jax.Array], u: jax.Array | None
                  ) -> dist.Distribution:
    """A kernel model's density over joint-error vectors: a Gaussian KDE is
    ``MixtureSameFamily(Categorical(w), Independent(Normal(data, bw), 1))``, with uniform w,
    or COND's kernel-conditional weights at u (batch shape u's leading dimensions)."""
    x, bw = arrays["x"], arrays["bw_x"]
    if kind == "IND":
        # 1-D mixtures side by side (a batch of n joints) made into one n-vector event: the
        # product density p1(e1) p2(e2) ... that IND is, and exactly sampleable.
        loc = x.T  # (n, N)
        scale = jnp.broadcast_to(bw[:, None], loc.shape)
        mix = dist.Categorical(probs=jnp.full(loc.shape, 1.0 / loc.shape[1]))
        return dist.MixtureSameFamily(mix, dist.Normal(loc, scale)).to_event(1)
    if kind == "CORR":
        w = jnp.full((x.shape[0],), 1.0 / x.shape[0])
    elif u is None:
        raise ValueError("COND needs the command u to condition on")
    else:
        w = kernel_conditional_weights(jnp.asarray(u, dtype=jnp.float64), arrays["z"],
                                       arrays["bw_z"])
    # Components carry the mixing batch in front of their own mixture axis.
    loc = jnp.broadcast_to(x, w.shape[:-1] + x.shape)
    comp = dist.Normal(loc, jnp.broadcast_to(bw, loc.shape)).to_event(1)
    return dist.MixtureSameFamily(dist.Categorical(probs=w), comp)


def joint_error_distribution(model: FittedNoiseModel, u: Any | None = None) -> dist.Distribution:
    """A fitted model's joint-error density as a numpyro distribution (COND at the commands
    ``u``, (2,) or (T, 2)); the histogram COND raises ``NotImplementedError`` (no sampler)."""
    kind = error_kind(model)
    if kind == "HIST":
        raise NotImplementedError(
            f"model {model.spec.name!r} (histogram COND) is a scored density only; "
            "use joint_error_log_prob inside numpyro.factor")
    return error_distribution(kind, error_arrays(model), u)


@dataclass(frozen=True)
class ArmStatic:
    """What a compiled program bakes in about one arm; everything else is traced arrays."""

    name: str
    kind: str
    jacobian: bool
    elbow: int
    bins: tuple[int, ...] = ()  # histogram COND: bins per dimension (x dims, then z)
    log_floor: float = 0.0  # histogram COND: log density outside the bins


def _error_log_prob(static: ArmStatic, arrays: dict[str, jax.Array], theta_err: jax.Array,
                    u: jax.Array) -> jax.Array:
    u = jnp.broadcast_to(jnp.asarray(u, dtype=jnp.float64), theta_err.shape)
    if static.kind != "HIST":
        return error_distribution(static.kind, arrays, u).log_prob(theta_err)
    # The paper's COND: the fitted table itself (grid and emcee see exactly it), with a
    # gradient from a smooth guide so that NUTS can move on a piecewise-constant density.
    shape = theta_err.shape[:-1]
    out = guided_histogram_lookup(theta_err.reshape(-1, 2), u.reshape(-1, 2), arrays["table"],
                                  arrays["lo"], arrays["widths"], static.bins, static.log_floor,
                                  HISTOGRAM_WALL)
    return out.reshape(shape)


def _static(model: FittedNoiseModel, arm: kin.Arm | None) -> ArmStatic:
    kind = error_kind(model)
    hist = {}
    if kind == "HIST":
        c = model.conditional
        hist = {"bins": tuple(int(b) for b in c.bins), "log_floor": math.log(c.floor)}
    return ArmStatic(arm.name if arm else "", kind, bool(model.spec.jacobian),
                      int(arm.elbow) if arm else 1, **hist)


def arm_structures(models: Sequence[FittedNoiseModel], arms: Sequence[kin.Arm]
               ) -> tuple[tuple[ArmStatic, ...], tuple[tuple[kin.ArmParams, dict], ...]]:
    """Split linked arms into the static part (compile key) and a pytree of arrays."""
    if len(models) != len(arms) or not arms:
        raise ValueError("need one fitted model per arm, and at least one arm")
    statics = tuple(_static(m, a) for m, a in zip(models, arms, strict=True))
    params = tuple((kin.ArmParams(*(jnp.asarray(x, dtype=jnp.float64) for x in a.params)),
                    error_arrays(m)) for m, a in zip(models, arms, strict=True))
    return statics, params


def joint_error_log_prob(model: FittedNoiseModel, theta_err: jax.Array, u: jax.Array
                         ) -> jax.Array:
    """log p(theta_err | u) for errors (..., 2) and commands (..., 2) broadcast together."""
    return _error_log_prob_jit(_static(model, None), error_arrays(model), jnp.asarray(theta_err),
                               jnp.asarray(u, dtype=jnp.float64))


# Compiled once per model structure and shapes, instead of op by op.
_error_log_prob_jit = jax.jit(_error_log_prob, static_argnums=0)


@functools.partial(jax.jit, static_argnums=0)
def compiled_arm_log_density(static: ArmStatic, arm_params: kin.ArmParams, arrays: dict,
                     u: jax.Array, d: jax.Array) -> jax.Array:
    theta, ok = kin.inverse(arm_params, d, static.elbow)
    err = kin.wrap_angle(theta - kin.servo(arm_params, u))
    lp = _error_log_prob(static, arrays, err, u)
    if static.jacobian:
        lp = lp + kin.log_abs_det_inverse_jacobian(arm_params, theta)
    return jnp.where(ok, lp, -jnp.inf)


def arm_log_density(model: FittedNoiseModel, arm: kin.Arm, u: jax.Array, d: jax.Array
                    ) -> jax.Array:
    """log-likelihood of end points d (..., T, 2) for one arm commanded with u (T, 2):
    log p(theta_err(d) | u) (+ log|det df^-1/dd| if the model says), -inf out of reach."""
    (static,), ((arm_params, arrays),) = arm_structures([model], [arm])
    return compiled_arm_log_density(static, arm_params, arrays, jnp.asarray(u, dtype=jnp.float64),
                            jnp.asarray(d, dtype=jnp.float64))
