"""Rigid transforms in 3-D. Poses are ``[x, y, z, roll, pitch, yaw]`` (mm, rad), meaning
``Trans(x, y, z) @ Rz(yaw) @ Ry(pitch) @ Rx(roll)`` as URDF's ``<origin xyz rpy>``; the NumPy
functions build the constant (nominal) transforms once.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def rot_x(a: jax.Array) -> jax.Array:
    c, s = jnp.cos(a), jnp.sin(a)
    o, z = jnp.ones_like(a), jnp.zeros_like(a)
    return jnp.stack([jnp.stack([o, z, z], -1), jnp.stack([z, c, -s], -1),
                      jnp.stack([z, s, c], -1)], -2)


def rot_y(a: jax.Array) -> jax.Array:
    c, s = jnp.cos(a), jnp.sin(a)
    o, z = jnp.ones_like(a), jnp.zeros_like(a)
    return jnp.stack([jnp.stack([c, z, s], -1), jnp.stack([z, o, z], -1),
                      jnp.stack([-s, z, c], -1)], -2)


def rot_z(a: jax.Array) -> jax.Array:
    c, s = jnp.cos(a), jnp.sin(a)
    o, z = jnp.ones_like(a), jnp.zeros_like(a)
    return jnp.stack([jnp.stack([c, -s, z], -1), jnp.stack([s, c, z], -1),
                      jnp.stack([z, z, o], -1)], -2)


def rot_axis(axis: jax.Array, angle: jax.Array) -> jax.Array:
    """Rotation by ``angle`` (...,) about the unit vector ``axis`` (3,) (Rodrigues)."""
    k = jnp.asarray(axis, dtype=jnp.result_type(float))
    kx = jnp.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    a = jnp.asarray(angle)[..., None, None]
    return jnp.eye(3) + jnp.sin(a) * kx + (1 - jnp.cos(a)) * (kx @ kx)


def homogeneous(rot: jax.Array, trans: jax.Array) -> jax.Array:
    """4x4 matrices from rotations (..., 3, 3) and translations (..., 3)."""
    top = jnp.concatenate([rot, trans[..., :, None]], -1)
    bottom = jnp.broadcast_to(jnp.array([0.0, 0.0, 0.0, 1.0]), top.shape[:-2] + (1, 4))
    return jnp.concatenate([top, bottom], -2)


def perturbation(delta: jax.Array) -> jax.Array:
    """A small correction ``[dx, dy, dz, rx, ry, rz]`` as Trans(d) Rx Ry Rz: at zero its
    derivatives are the frame's own translations and rotations, singular in no direction."""
    delta = jnp.asarray(delta)
    rot = rot_x(delta[..., 3]) @ rot_y(delta[..., 4]) @ rot_z(delta[..., 5])
    return homogeneous(rot, delta[..., :3])


def np_pose_matrix(pose: np.ndarray) -> np.ndarray:
    """A pose's 4x4 matrix in NumPy: a constant, also when called while JAX traces."""
    x, y, z, r, p, w = np.asarray(pose, float)
    cr, sr, cp, sp, cw, sw = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(w), np.sin(w)
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rz = np.array([[cw, -sw, 0], [sw, cw, 0], [0, 0, 1]])
    t = np.eye(4)
    t[:3, :3] = rz @ ry @ rx
    t[:3, 3] = x, y, z
    return t


def matrix_to_pose(t: np.ndarray) -> np.ndarray:
    """``[x, y, z, roll, pitch, yaw]`` of a 4x4 matrix, the inverse of :func:`np_pose_matrix`
    (at gimbal lock roll is 0 and yaw carries the rotation)."""
    t = np.asarray(t, float)
    r = t[:3, :3]
    pitch = float(np.arcsin(np.clip(-r[2, 0], -1.0, 1.0)))
    if abs(r[2, 0]) < 1 - 1e-10:
        roll = float(np.arctan2(r[2, 1], r[2, 2]))
        yaw = float(np.arctan2(r[1, 0], r[0, 0]))
    else:
        roll = 0.0
        yaw = float(np.arctan2(-r[0, 1], r[1, 1]))
    return np.array([t[0, 3], t[1, 3], t[2, 3], roll, pitch, yaw])

