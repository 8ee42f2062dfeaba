"""Chains from Denavit-Hartenberg tables, in the modified (Craig) or the standard convention.

Rows are ``[d, theta, a, alpha]`` (mm, rad). Modified: ``Rx(alpha) Tx(a) Rz(theta + q) Tz(d)``,
the fixed origin then the motion about z (``Rz(q)`` and ``Tz(d)`` commute); standard:
``Rz(theta + q) Tz(d) Tx(a) Rx(alpha)``, whose fixed part becomes the next joint's origin (the
last the tool). The calibration corrects every origin with six numbers, so the singularity of
near-parallel axes (Hayati's beta) does not arise.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

import bayesrob.robot.transforms as tf
from bayesrob.robot.chain import Chain, KinematicsError

CONVENTIONS = ("modified", "standard")


def _fixed(d: float, theta: float, a: float, alpha: float, convention: str) -> np.ndarray:
    rz = np.asarray(tf.rot_z(np.float64(theta)))
    rx = np.asarray(tf.rot_x(np.float64(alpha)))
    tz, tx = np.eye(4), np.eye(4)
    tz[2, 3], tx[0, 3] = d, a
    hz, hx = np.eye(4), np.eye(4)
    hz[:3, :3], hx[:3, :3] = rz, rx
    if convention == "modified":
        return hx @ tx @ hz @ tz
    return hz @ tz @ tx @ hx


def dh_chain(name: str, rows: Sequence[Sequence[float]], convention: str = "modified",
             kinds: Sequence[str] | None = None, origin: Sequence[float] | None = None,
             tool: Sequence[float] | None = None, **chain_kwargs) -> Chain:
    """A chain from DH rows ``[d, theta, a, alpha]``; ``origin``/``tool`` are extra fixed poses
    ``[x, y, z, roll, pitch, yaw]`` before the first row and after the last."""
    if convention not in CONVENTIONS:
        raise KinematicsError(f"DH convention must be one of {', '.join(CONVENTIONS)}, "
                              f"got {convention!r}")
    rows = [list(map(float, r)) for r in rows]
    for i, r in enumerate(rows):
        if len(r) != 4:
            raise KinematicsError(f"DH row {i} must be [d, theta, a, alpha], got {len(r)} values")
    n = len(rows)
    if n == 0:
        raise KinematicsError("a DH table needs at least one row")
    kinds = list(kinds) if kinds is not None else ["revolute"] * n
    before = tf.np_pose_matrix(np.asarray(origin if origin is not None else np.zeros(6), float))
    after = tf.np_pose_matrix(np.asarray(tool if tool is not None else np.zeros(6), float))
    fixed = [_fixed(*r, convention) for r in rows]
    if convention == "modified":
        mats = [before @ fixed[0], *fixed[1:], after]
    else:
        mats = [before, *fixed[:-1], fixed[-1] @ after]
    origins = np.array([tf.matrix_to_pose(m) for m in mats])
    axes = np.tile([0.0, 0.0, 1.0], (n, 1))
    names = [f"j{i + 1}" for i in range(n)]
    source = {"kind": "dh", "convention": convention, "rows": rows}
    return Chain.build(name, names, kinds, axes, origins, source=source, **chain_kwargs)
