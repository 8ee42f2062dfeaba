"""The simulator's physical terms for any chain: gravity, compliance, backlash (dead band or
play), servo ripple, eccentric encoders, stiffness spread. Each random draw has a stream of its
own (``*_STREAM``), so switching one effect on leaves every other draw as it was.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from bayesrob.robot import Robot, RobotStructure, on_row_buckets, wrap_angle
from bayesrob.robot.chain import G_N_PER_KG

# Without gravity_sag a planar arm's servos are this much stiffer: gravity still decides which
# side of a dead band a joint rests on, but no longer deflects it measurably.
STIFF_FACTOR = 1000.0
ENCODER_STREAM = 7  # the encoder phases' own random stream
PLAY_STREAM = 8  # the approach sides' own random stream
STIFFNESS_STREAM = 17  # the drawn stiffnesses' own random stream


def dead_band(x: jax.Array, b: jax.Array) -> jax.Array:
    """What a spring with a dead band of half-width ``b`` sees of a deflection ``x``."""
    return jnp.sign(x) * jnp.maximum(jnp.abs(x) - b, 0.0)


def servo_ripple(u: jax.Array, u_mid: jax.Array, amplitude_rad: jax.Array,
                 period_us: jax.Array) -> jax.Array:
    """The servo map's departure from its line at pulse widths ``u`` (rad), as a feedback
    potentiometer's track and the gear train give."""
    phase = 2 * jnp.pi * (u - u_mid) / jnp.asarray(period_us)
    return jnp.asarray(amplitude_rad) * jnp.sin(phase)


def encoder_error(q_read: np.ndarray, eccentricity: float, phase: np.ndarray) -> np.ndarray:
    """How far each joint really is from the angle its eccentric encoder reads (rad): a unit
    disk ``eccentricity`` off the axis at ``phase``, read by a fixed head."""
    d = np.asarray(q_read) - np.asarray(phase)
    return -np.arctan2(eccentricity * np.sin(d), 1.0 + eccentricity * np.cos(d))


def play_offsets(tau: np.ndarray, play: float, stick_nmm: float,
                 rng: np.random.Generator, approach: np.ndarray | None = None) -> np.ndarray:
    """Where each joint rests in its play (N, n) rad: towards its gravity torque ``tau``
    (N mm), or, where that is weaker than ``stick_nmm``, towards the side it was approached
    from (``approach`` where non-zero, else drawn)."""
    drawn = rng.choice([-1.0, 1.0], size=tau.shape)
    if approach is not None:
        drawn = np.where(approach != 0, np.sign(approach), drawn)
    side = np.where(np.abs(tau) > stick_nmm, np.sign(tau), drawn)
    return 0.5 * play * side


@partial(jax.jit, static_argnames=("structure", "arm", "periodic"))
def arm_energy(structure: RobotStructure, arm: str, values: dict, x: jax.Array,
               u: jax.Array, u0: jax.Array, k: jax.Array, weight: jax.Array,
               centre: jax.Array, backlash: jax.Array, periodic: bool = False
               ) -> dict[str, jax.Array]:
    """Spring and weight energy of an arm of revolute joints standing on its own, over rows of
    joint columns u (N, n) held by springs k at u0 (a dead band of half-width ``backlash``
    each; ``periodic``: angles wrapped), its links' ``weight`` (n, 3) N acting ``centre`` of
    the way along each link: the energy, its gradient and Hessian in u, the marker and its
    two derivatives, in closed form on one forward pass (autodiff through the scan took
    seconds to compile): d r / du_j = a_j x (r - o_j), d2 r / du_i du_j = a_i x (a_j x (r - o_j)).
    Every equilibrium of the simulator and its gravity torques are this one program's."""
    robot = structure.robot(values)
    chain = robot.chains[arm]
    n = chain.n_joints
    half = jnp.concatenate([centre[:, None] * chain.origins[1:, :3], jnp.ones((n, 1))],
                           axis=1)
    axes = jnp.asarray(chain.axes)
    marker = robot.layout.slices[(arm, "marker")]
    upper = np.triu(np.ones((n, n), bool))  # [i, j]: i <= j
    ordered = jnp.asarray(upper[:, :, None] & upper[None, :, :])  # [i, j, k]: i <= j <= k
    joints, links = robot.element_frames(x, arm, u)  # (E, N, 4, 4)
    a = jnp.einsum("enij,ej->nei", joints[:n, :, :3, :3], axes)  # (N, n, 3)
    o = jnp.swapaxes(joints[:n, :, :3, 3], 0, 1)  # (N, n, 3)
    centres = jnp.swapaxes(jnp.einsum("enij,ej->eni", links[:n], half)[..., :3], 0, 1)
    tip = links[-1]
    p = jnp.einsum("nij,j->ni", tip[:, :3, :3], x[marker]) + tip[:, :3, 3]
    jp = jnp.cross(a, p[:, None] - o)  # (N, n, 3): row j = dp/du_j
    hp = jnp.cross(a[:, :, None], jp[:, None, :])  # [i, j] = a_i x dp/du_j
    hp = jnp.where(upper[None, :, :, None], hp, jnp.swapaxes(hp, 1, 2))
    # s[:, j, k] = d centre_k / du_j where j <= k (joint j carries link k)
    s = jnp.cross(a[:, :, None], centres[:, None, :] - o[:, :, None])
    torque = jnp.einsum("njkd,kd,jk->nj", s, weight, upper)  # of the weights beyond j
    t = jnp.einsum("nijkd,kd,ijk->nij", jnp.cross(a[:, :, None, None], s[:, None]),
                   weight, ordered)
    hv = -jnp.where(upper[None], t, jnp.swapaxes(t, 1, 2))  # Hessian of the potential
    d = wrap_angle(u - u0) if periodic else u - u0
    spring = jnp.where(jnp.abs(d) >= backlash, k, 0.0)  # no spring inside the dead band
    d = dead_band(d, backlash)
    return {"energy": 0.5 * jnp.sum(k * d * d, axis=1)
            - jnp.einsum("nkd,kd->n", centres, weight),
            "grad": k * d - torque, "hess": jax.vmap(jnp.diag)(spring) + hv,
            "point": p, "jac": jnp.swapaxes(jp, 1, 2), "point_hess": hp}


def gravity_torques(robot: Robot, x: np.ndarray, arm: str, q: np.ndarray,
                    masses_kg: np.ndarray, gravity: np.ndarray) -> np.ndarray:
    """The gravity torque (N, n) about each joint's axis at joint values q (N mm), each link's
    mass halfway along the next origin's translation, ``gravity`` in the instrument frame (the
    frames' own): minus :func:`arm_energy`'s gradient with no spring."""
    n = robot.chains[arm].n_joints
    weight = np.asarray(masses_kg, float)[:, None] * (np.asarray(gravity, float) * G_N_PER_KG)
    structure, values = robot.structure, robot.nominal_values
    springs, centre = np.zeros(n), np.full(n, 0.5)

    def gradient(x: jax.Array, q: jax.Array, side: None) -> jax.Array:
        return arm_energy(structure, arm, values, x, q, q, springs, weight, centre,
                          springs)["grad"]
    return -np.asarray(on_row_buckets(gradient, jnp.asarray(x), np.atleast_2d(
        np.asarray(q, float))))


def link_weights(masses_kg: np.ndarray | None, gravity: Sequence[float] | None,
                 n: int) -> np.ndarray:
    """Weights (n, 3) in N of the links' point masses; zero without gravity."""
    if masses_kg is None or gravity is None:
        return np.zeros((n, 3))
    g = np.asarray(gravity, float)
    return np.asarray(masses_kg, float)[:, None] * (G_N_PER_KG * g / np.linalg.norm(g))[None]


def draw_stiffnesses(seed: int, profiles: Mapping[str, Sequence[float]], log_sd: float
                     ) -> dict[str, np.ndarray]:
    """Each arm's joint stiffnesses for a seed: its profile times exp(N(0, sd) per arm +
    N(0, sd) per joint), arms in the order given."""
    rng = np.random.default_rng([seed, STIFFNESS_STREAM])
    out = {}
    for name, profile in profiles.items():
        k = np.asarray(profile, float)
        out[name] = k * np.exp(log_sd * rng.normal() + log_sd * rng.normal(size=k.shape))
    return out
