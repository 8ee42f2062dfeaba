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

from bayesrob.robot import Robot, RobotStructure
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


@partial(jax.jit, static_argnames=("structure", "arm"))
def _torques(structure: RobotStructure, arm: str, values: dict, x: jax.Array, q: jax.Array,
             masses_kg: jax.Array, gravity: jax.Array) -> jax.Array:
    # gravity_torques' arithmetic, one program per robot structure
    robot = structure.robot(values)
    chain = robot.chains[arm]
    n = chain.n_joints
    half = jnp.concatenate([0.5 * chain.origins[1:, :3], jnp.ones((n, 1))], axis=1)  # (n, 4)
    joints, links = robot.element_frames(x, arm, q)
    centres = jnp.einsum("enij,ej->eni", links[:n], half)[..., :3]  # (n, N, 3)
    forces = masses_kg[:, None, None] * (gravity * G_N_PER_KG)  # (n, 1, 3)
    columns = []
    for i in range(n):
        axis = joints[i, :, :3, :3] @ chain.axes[i]
        origin = joints[i, :, :3, 3]
        moment = jnp.cross(centres[i:] - origin[None], jnp.broadcast_to(
            forces[i:], centres[i:].shape)).sum(axis=0)
        columns.append(jnp.sum(moment * axis, axis=1))
    return jnp.stack(columns, axis=1)


def gravity_torques(robot: Robot, x: np.ndarray, arm: str, q: np.ndarray,
                    masses_kg: np.ndarray, gravity: np.ndarray) -> np.ndarray:
    """The gravity torque (N, n) about each joint's axis at joint values q (N mm), each link's
    mass halfway along the next origin's translation."""
    return np.asarray(_torques(robot.structure, arm, robot.nominal_values, jnp.asarray(x),
                               jnp.asarray(q), jnp.asarray(masses_kg, float),
                               jnp.asarray(gravity, float)))


def gravity_deflection(robot: Robot, x: np.ndarray, arm: str, q: np.ndarray,
                       masses_kg: np.ndarray, stiffness: np.ndarray,
                       gravity: np.ndarray, iterations: int = 4) -> np.ndarray:
    """Joint deflections (N, n) at equilibrium, dq = tau(q + dq) / k, by fixed-point steps:
    at arm6's masses four leave about 1e-6 rad, eight about 1e-12 rad."""
    dq = np.zeros_like(q)
    for _ in range(iterations):
        dq = gravity_torques(robot, x, arm, q + dq, masses_kg, gravity) / stiffness
    return dq


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
