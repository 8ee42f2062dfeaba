"""The planar two-link arm of the paper, as pure JAX functions broadcasting over leading
dimensions: ``f(theta)`` joint angles to end point, ``g(u) = gain * u + offset`` pulse widths
(us) to angles. It is also a 2-joint :class:`~bayesrob.robot.chain.Chain`
(:func:`planar_chain`); the closed forms here are kept for speed, tested equal to the chain.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from bayesrob.robot.chain import Chain


@dataclass(frozen=True)
class ArmGeometry:
    """What a planar arm is built from: the fields the rig's nominal ``ArmSpec`` and the
    simulator's ``ArmTruth`` share (defined here, below both, so kinematics imports neither)."""

    name: str
    base: tuple[float, float]
    links: tuple[float, float]
    gain: tuple[float, float]
    offset: tuple[float, float]
    elbow: int = 1
    pulse_limits: tuple[tuple[float, float], tuple[float, float]] = ((500.0, 2500.0),) * 2

PARAM_NAMES = ("bx", "by", "l1", "l2", "a1", "a2", "b1", "b2")


class ArmParams(NamedTuple):
    """The eight geometric and servo parameters of an arm (a JAX pytree)."""

    base: jax.Array  # (2,) mm
    links: jax.Array  # (2,) mm
    gain: jax.Array  # (2,) rad per microsecond
    offset: jax.Array  # (2,) rad

    @classmethod
    def from_vector(cls, v: jax.Array) -> ArmParams:
        v = jnp.asarray(v)
        return cls(v[..., 0:2], v[..., 2:4], v[..., 4:6], v[..., 6:8])

    def to_vector(self) -> jax.Array:
        return jnp.concatenate(
            [jnp.asarray(self.base), jnp.asarray(self.links), jnp.asarray(self.gain),
             jnp.asarray(self.offset)], axis=-1
        )

    @classmethod
    def from_spec(cls, spec: ArmGeometry) -> ArmParams:
        return cls(*(jnp.asarray(x, dtype=jnp.float64)
                     for x in (spec.base, spec.links, spec.gain, spec.offset)))

    def as_dict(self) -> dict[str, list[float]]:
        return {k: [float(x) for x in np.asarray(getattr(self, k))] for k in self._fields}


def wrap_angle(a: jax.Array) -> jax.Array:
    """Map angles to (-pi, pi]; joint-angle differences are only meaningful wrapped."""
    return jnp.pi - jnp.mod(jnp.pi - a, 2 * jnp.pi)


@jax.jit
def servo(params: ArmParams, u: jax.Array) -> jax.Array:
    """g(u): pulse widths (..., 2) in microseconds to joint angles (..., 2)."""
    return params.gain * u + params.offset


@jax.jit
def servo_inverse(params: ArmParams, theta: jax.Array) -> jax.Array:
    """g^-1(theta): the pulse widths that command the joint angles."""
    return (theta - params.offset) / params.gain


@jax.jit
def forward(params: ArmParams, theta: jax.Array) -> jax.Array:
    """f(theta): end point (..., 2) in mm."""
    t12 = theta[..., 0] + theta[..., 1]
    c12 = jnp.stack([jnp.cos(t12), jnp.sin(t12)], -1)
    return elbow_point(params, theta) + params.links[..., 1:2] * c12


@jax.jit
def elbow_point(params: ArmParams, theta: jax.Array) -> jax.Array:
    t1 = theta[..., 0]
    return params.base + params.links[..., 0:1] * jnp.stack([jnp.cos(t1), jnp.sin(t1)], -1)


def forward_u(params: ArmParams, u: jax.Array) -> jax.Array:
    """f(g(u)): the end point the model predicts for pulse widths u."""
    return forward(params, servo(params, u))


@jax.jit
def inverse(params: ArmParams, d: jax.Array, elbow: int | jax.Array) -> tuple[jax.Array, jax.Array]:
    """f^-1(d) by the law of cosines on the ``elbow`` branch (+1: theta2 >= 0): ``(theta,
    reachable)``, unreachable points clamped to the nearest reachable configuration."""
    l1, l2 = params.links[..., 0], params.links[..., 1]
    p = d - params.base
    r2 = jnp.sum(p**2, axis=-1)
    c2 = (r2 - l1**2 - l2**2) / (2 * l1 * l2)
    reachable = jnp.abs(c2) <= 1.0
    # Clamp just inside +-1: arccos has an infinite derivative at the boundary.
    c2c = jnp.clip(c2, -1.0 + 1e-12, 1.0 - 1e-12)
    t2 = elbow * jnp.arccos(c2c)
    t1 = jnp.arctan2(p[..., 1], p[..., 0]) - jnp.arctan2(l2 * jnp.sin(t2), l1 + l2 * jnp.cos(t2))
    return jnp.stack([wrap_angle(t1), t2], -1), reachable


@jax.jit
def jacobian(params: ArmParams, theta: jax.Array) -> jax.Array:
    """df/dtheta (..., 2, 2), analytic."""
    t1 = theta[..., 0]
    t12 = t1 + theta[..., 1]
    l1, l2 = params.links[..., 0], params.links[..., 1]
    s1, c1, s12, c12 = jnp.sin(t1), jnp.cos(t1), jnp.sin(t12), jnp.cos(t12)
    row_x = jnp.stack([-l1 * s1 - l2 * s12, -l2 * s12], -1)
    row_y = jnp.stack([l1 * c1 + l2 * c12, l2 * c12], -1)
    return jnp.stack([row_x, row_y], -2)


def log_abs_det_inverse_jacobian(params: ArmParams, theta: jax.Array) -> jax.Array:
    """log |det d f^-1 / d d| = -log |l1 l2 sin theta2|: the change of variables from joint
    errors to end points, which the paper omits."""
    l1, l2 = params.links[..., 0], params.links[..., 1]
    return -jnp.log(jnp.abs(l1 * l2 * jnp.sin(theta[..., 1])))


def choose_elbow(params: ArmParams, u: np.ndarray, d: np.ndarray, default: int = 1) -> int:
    """The elbow branch whose f^-1(d) lies closest to the commanded angles g(u), as the paper
    chose it (``default`` without data)."""
    if len(u) == 0:
        return default
    theta_cmd = servo(params, jnp.asarray(u))
    dist = []
    for e in (1, -1):
        theta, _ = inverse(params, jnp.asarray(d), e)
        dist.append(float(jnp.sum(wrap_angle(theta - theta_cmd) ** 2)))
    return 1 if dist[0] <= dist[1] else -1


@dataclass(frozen=True)
class Arm:
    """A (calibrated or nominal) arm: parameters plus the branch and limits it works with."""

    name: str
    params: ArmParams
    elbow: int
    pulse_limits: tuple[tuple[float, float], tuple[float, float]] = ((500.0, 2500.0),) * 2

    @classmethod
    def nominal(cls, spec: ArmGeometry) -> Arm:
        return cls(spec.name, ArmParams.from_spec(spec), spec.elbow, spec.pulse_limits)

    @property
    def mid_pulse(self) -> np.ndarray:
        return np.array([(lo + hi) / 2 for lo, hi in self.pulse_limits])

    def forward_u(self, u: jax.Array) -> jax.Array:
        return forward_u(self.params, jnp.asarray(u))

    def inverse(self, d: jax.Array) -> jax.Array:
        """Joint angles for end points d, on the turn nearest the servo's mid range."""
        return _nearest_turn(self.params, jnp.asarray(d), self.elbow, self.mid_pulse)

    def reachable(self, d: jax.Array) -> jax.Array:
        return inverse(self.params, jnp.asarray(d), self.elbow)[1]

    def command(self, d: jax.Array) -> jax.Array:
        """Pulse widths aiming at end points d (not rounded, not limit-checked)."""
        return servo_inverse(self.params, self.inverse(d))


# One compiled program: called eagerly, its small operations were compiled one by one (with
# the closed forms above, about 2 s of every simulated rig).
@jax.jit
def _nearest_turn(params: ArmParams, d: jax.Array, elbow: int, mid_pulse: jax.Array
                  ) -> jax.Array:
    theta, _ = inverse(params, d, elbow)
    ref = servo(params, mid_pulse)
    return ref + wrap_angle(theta - ref)


def planar_chain(name: str, params: ArmParams) -> Chain:
    """The planar arm as a 2-joint chain (z = 0) whose ``marker_points`` at its nominal vector
    equal :func:`forward_u`: base and links as origins, the servo map as the command map."""
    (bx, by), (l1, l2) = np.asarray(params.base, float), np.asarray(params.links, float)
    origins = np.zeros((3, 6))
    origins[0, :2] = bx, by
    origins[1, 0] = l1
    origins[2, 0] = l2
    return Chain.build(name, ("shoulder", "elbow"), ("revolute", "revolute"),
                       np.tile([0.0, 0.0, 1.0], (2, 1)), origins,
                       gain=np.asarray(params.gain, float), offset=np.asarray(params.offset, float),
                       source={"kind": "planar"})
