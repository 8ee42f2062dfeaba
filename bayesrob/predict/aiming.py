"""Aiming arms at targets: :func:`aim`, position-only damped Gauss-Newton through any arm's
calibrated model from the nearest train poses (the planar closed form,
:meth:`bayesrob.robot.Arm.command`, is its specialisation), and the one-line refusals.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from bayesrob import robot as kin
from bayesrob.data.rig import Rig, RigError

__all__ = ["aim", "check_reach", "check_pulse_limits", "IK_TOL_MM"]

IK_TOL_MM = 1e-3
IK_ITERATIONS = 60
# Train poses (nearest first) an aim may start from while its solution leaves the train range:
# enough for a target near the edge to find the calibrated branch, few for one beyond it
AIM_SEEDS = 8

@partial(jax.jit, static_argnames=("structure", "arm"))
def _column_jacobian_program(structure: kin.RobotStructure, arm: str, values: dict,
                             x: jax.Array, u: jax.Array) -> tuple[jax.Array, jax.Array]:
    robot = structure.robot(values)

    def point(x, row):
        return robot.marker_points(x, arm, row[None])[0]

    return jax.vmap(lambda r: point(x, r))(u), jax.vmap(
        lambda r: jax.jacfwd(lambda v: point(x, v))(r))(u)


def _column_jacobian(robot: kin.Robot, arm: str) -> Callable:
    """(x, u) -> (points (T, dim), d points / d columns (T, dim, c)), one program per
    structure and row bucket."""
    program = partial(_column_jacobian_program, robot.structure, arm, robot.nominal_values)
    return partial(kin.on_row_buckets, lambda x, u, side: program(x, u))


def aim(rig: Rig, robot: kin.Robot, x: np.ndarray, arm: str, targets: np.ndarray
              ) -> np.ndarray:
    """Columns (T, c) putting ``arm``'s marker on each target under the calibrated model.

    Damped minimum-norm Gauss-Newton from the train pose observed nearest, so a redundant arm
    stays on its calibrated branch; where that leaves the train commands' range, the next
    nearest (up to AIM_SEEDS) are tried and the first solution inside (else the least beyond)
    taken. A target missed by over IK_TOL_MM, or off a planar arm's pulse limits, is refused.
    """
    targets = np.atleast_2d(np.asarray(targets, float))
    u_train, d_train = rig.rows(arm, "train")
    lo, hi = u_train.min(axis=0), u_train.max(axis=0)
    order = np.argsort(np.linalg.norm(d_train[None] - targets[:, None], axis=-1), axis=1)
    f = _column_jacobian(robot, arm)
    xj = jnp.asarray(x)
    per_rad = _radians_per_unit(robot, arm)
    best = np.zeros((len(targets), u_train.shape[1]))
    best_beyond = np.full(len(targets), np.inf)
    best_miss = np.full(len(targets), np.inf)
    for k in range(min(AIM_SEEDS, order.shape[1])):
        # targets already aimed inside the range start from their solution, where Gauss-Newton
        # stops at once, so a later seed costs the steps of the targets still outside only
        # (and every call keeps the shape its program was compiled for)
        settled = (best_beyond == 0.0)[:, None]
        u, miss = _aim_from(f, xj, targets, np.where(settled, best, u_train[order[:, k]]),
                            per_rad)
        beyond = np.where(miss < IK_TOL_MM, (np.maximum(lo - u, 0.0)
                                             + np.maximum(u - hi, 0.0)).sum(axis=1), np.inf)
        # a later seed replaces a solution only where it is strictly further inside the range
        # (or the first to reach the target): where the nearest seed's is inside, it stays
        better = (beyond < best_beyond) | (np.isinf(best_beyond) & (miss < best_miss))
        best[better], best_beyond[better], best_miss[better] = u[better], beyond[better], \
            miss[better]
        if np.all(best_beyond == 0.0):
            break
    for t, m in zip(targets, best_miss, strict=True):
        if not m < IK_TOL_MM:
            where = (f"its calibrated model gets no closer than {m:.1f} mm" if np.isfinite(m)
                     else "its calibrated model's inverse kinematics did not converge")
            raise RigError(f"target ({', '.join(f'{v:g}' for v in t)}) is out of reach of arm "
                           f"{arm!r}: {where}")
    limits = getattr(rig.arms[arm], "pulse_limits", None)  # planar arms: servo pulse limits
    if limits is not None:
        for t, ut in zip(targets, best, strict=True):
            check_pulse_limits(arm, t, ut, limits)
    return best


def _radians_per_unit(robot: kin.Robot, arm: str) -> np.ndarray:
    """Radians per command unit of ``arm``'s columns, from the nominal gains (so steps do not
    depend on the fit): a planar arm's pulse columns are limited in radians, not read as
    0.3 us a step, which never reaches a target. Couplings (usually +-1) are left out. A column
    that turns no revolute joint counts 0: the marker moves linearly with a slide, so its step
    needs no limit, and 0.3 mm a step left a gantry 30 mm short of targets 100 mm away."""
    return np.concatenate([
        np.abs(robot.layout.nominal[robot.layout.slices[(c.name, "gain")]])
        * ((np.abs(c.coupling) > 0).T @ (np.asarray(c.kinds) == "revolute") > 0)
        for c in robot.path(arm)])


def _aim_from(f, xj: jax.Array, targets: np.ndarray, u: np.ndarray, per_rad: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`aim`'s Gauss-Newton from seeds ``u`` (T, c): the columns and the misses (mm)."""
    for _ in range(IK_ITERATIONS):
        p, jac = (np.asarray(v) for v in f(xj, jnp.asarray(u)))
        r = targets - p
        err = np.linalg.norm(r, axis=1)
        if np.all(err < IK_TOL_MM):
            break
        # the step is limited to 0.3 rad per revolute column, so far targets are approached,
        # not jumped
        jjt = np.einsum("tic,tjc->tij", jac, jac) + 1e-6 * np.eye(jac.shape[1])
        step = np.einsum("tic,ti->tc", jac, np.linalg.solve(jjt, r[..., None])[..., 0])
        big = np.abs(step * per_rad).max(axis=1, keepdims=True)
        u = u + step * np.minimum(1.0, 0.3 / np.maximum(big, 1e-12))
    p = np.asarray(f(xj, jnp.asarray(u))[0])
    return u, np.linalg.norm(targets - p, axis=1)


def check_reach(arm: kin.Arm, target: np.ndarray, u: np.ndarray) -> None:
    """Refuse a target the arm cannot be aimed at: one line naming target, arm and reach."""
    l1, l2 = (float(x) for x in np.asarray(arm.params.links))
    base = np.asarray(arm.params.base, float)
    r = float(np.linalg.norm(target - base))
    lo, hi = abs(l1 - l2), l1 + l2
    where = f"target ({target[0]:g}, {target[1]:g})"
    if not lo <= r <= hi:
        raise ValueError(f"{where} is out of reach of arm {arm.name!r}: it is {r:.1f} mm from "
                         f"the arm's base ({base[0]:.1f}, {base[1]:.1f}), which reaches "
                         f"{lo:.1f} to {hi:.1f} mm")
    check_pulse_limits(arm.name, target, u, arm.pulse_limits,
                       f" (reach {lo:.1f} to {hi:.1f} mm from its base)")


def check_pulse_limits(name: str, target: np.ndarray, u: np.ndarray,
                       limits: Sequence[tuple[float, float]], note: str = "") -> None:
    """Refuse pulses ``u`` aimed at ``target`` beyond an arm's pulse limits, in one line."""
    for j, (p, (a, b)) in enumerate(zip(u, limits, strict=True)):
        if not a <= p <= b:
            raise ValueError(f"target ({', '.join(f'{v:g}' for v in target)}) is outside the "
                             f"workspace of arm {name!r}: aiming at it needs pulse {j + 1} = "
                             f"{p:.1f} us, outside its pulse_limits [{a:g}, {b:g}]{note}")
