"""The paper's eight parameters of each planar arm, calibrated from its measured end points.

A planar arm is a 2-joint chain of the general robot model (:func:`kinematics.planar_chain`):
its base is the shoulder's origin, its links the elbow's and the tool's origins along x, its
servo map the chain's gains and offsets. So the ``least-squares`` fit is the group calibration
of :mod:`bayesrob.calibrate.least_squares` over the chain's offsets, servo and geometric
groups, restricted to those eight columns, with the measuring frame the arm's base frame
(the paper's setup; a rig's ``calibrate --params`` frees the frames instead, to the same
predictions), and the standard errors come from its one covariance routine. ``hill-climb``
is the paper's procedure (:mod:`bayesrob.calibrate.hill_climb`). The Bayesian calibration
(``bayes``) is :mod:`bayesrob.calibrate.bayes`; :func:`bayesrob.outputs.calibrate_rig`
chooses among the three.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import jax.numpy as jnp
import numpy as np

from bayesrob import kinematics as kin
from bayesrob.calibrate.hill_climb import hill_climb
from bayesrob.calibrate.least_squares import covariance, fit, residual_function
from bayesrob.rig import N_ARM_PARAMS, ArmSpec, Rig

Method = Literal["least-squares", "hill-climb"]
# The Bayesian method lives one layer up (bayesrob.calibrate.bayes builds on this module);
# bayesrob.outputs.calibrate_rig dispatches to all three.
METHODS: tuple[str, ...] = ("least-squares", "hill-climb")

# The chain's name for an arm fitted on its own: one name for every planar arm, so that all of
# them share one structure and so the fit's compiled programs.
ARM = "arm"
# The eight parameters (kinematics.PARAM_NAMES order: bx, by, l1, l2, a1, a2, b1, b2) as
# columns of the arm's chain, and the groups they belong to.
ARM_PARAMETERS = tuple(f"{ARM}.{p}" for p in (
    "shoulder.origin.x", "shoulder.origin.y", "elbow.origin.x", "tool.origin.x", "u1.gain",
    "u2.gain", "shoulder.offset", "elbow.offset"))
ARM_GROUPS = ("offsets", "servo", "geometric")
# The fit's tolerances: tight enough that the eight agree with an independent solver to far
# below the reported digits.
ARM_TOL = 1e-12


@dataclass
class ArmCalibration:
    """A calibrated arm and how well it fits."""

    arm: kin.Arm
    method: str
    params_se: np.ndarray  # (8,) in PARAM_NAMES order; NaN where not estimable
    train_error_mm: float
    validation_error_mm: float | None
    n_train: int
    iterations: int = 0
    extra: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        """This arm's entry of ``bayesrob calibrate --json`` (as :meth:`to_json`)."""
        return self.to_json()

    def to_json(self) -> dict:
        se = kin.ArmParams.from_vector(jnp.asarray(self.params_se))
        out = {
            "params": self.arm.params.as_dict(),
            "params_se": se.as_dict(),
            "elbow": self.arm.elbow,
            "train_error_mm": self.train_error_mm,
            "validation_error_mm": self.validation_error_mm,
            "n_train": self.n_train,
            "iterations": self.iterations,
        }
        out.update(self.extra)
        return out


def mean_error_mm(params: kin.ArmParams, u: np.ndarray, d: np.ndarray) -> float:
    """Mean Euclidean distance between f(g(u)) and the observed end points."""
    pred = np.asarray(kin.forward_u(params, jnp.asarray(u)))
    return float(np.mean(np.linalg.norm(pred - d, axis=-1)))


def arm_robot(v: np.ndarray) -> tuple[kin.Robot, np.ndarray]:
    """The arm of eight parameters ``v`` as a one-chain robot, and the indices (8,) of the
    eight among the robot's parameters."""
    robot = kin.Robot({ARM: kin.planar_chain(ARM, kin.ArmParams.from_vector(
        jnp.asarray(v, float)))}, 2)
    names = [p.name for p in robot.layout.params]
    return robot, np.array([names.index(n) for n in ARM_PARAMETERS])


def arm_covariance(v: np.ndarray, u: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Gauss-Newton covariance (8, 8) of an arm's fitted parameters ``v``
    (``ArmParams.to_vector`` order) on its train rows; NaN when the rows cannot fix them."""
    robot, idx = arm_robot(v)
    res, jac, *_ = residual_function(robot, {ARM: (np.asarray(u, float),
                                                   np.asarray(d, float), None)})
    free = np.zeros(robot.layout.nominal.size, bool)
    free[idx] = True
    return covariance(res, jac, robot.layout.nominal, free)[np.ix_(idx, idx)]


def calibrate_arm(spec: ArmSpec, u: np.ndarray, d: np.ndarray, method: Method = "least-squares",
                  u_val: np.ndarray | None = None, d_val: np.ndarray | None = None
                  ) -> ArmCalibration:
    """Fit one arm's parameters to its training rows (u: pulses (N, 2), d: end points (N, 2))."""
    if method not in METHODS:
        raise ValueError(f"unknown calibration method {method!r}; use one of {METHODS}")
    u = np.asarray(u, float)
    d = np.asarray(d, float)
    if len(u) * 2 < N_ARM_PARAMS:
        raise ValueError(f"arm {spec.name!r}: {len(u)} train rows cannot fix {N_ARM_PARAMS} "
                         "parameters")
    v0 = np.asarray(kin.ArmParams.from_spec(spec).to_vector())
    if method == "least-squares":
        robot, idx = arm_robot(v0)
        eight = np.zeros(robot.layout.nominal.size, bool)
        eight[idx] = True
        cal = fit(robot, {ARM: (u, d, None)}, ARM_GROUPS, candidates=eight, tol=ARM_TOL,
                  max_nfev=2000)
        # the chain's origins and offsets are corrections to the nominal ones, its gains whole
        v = v0 + cal.x[idx] - robot.layout.nominal[idx]
        iters, se = cal.nfev, cal.se[idx]
    else:
        v, iters = hill_climb(v0, u, d, u_val, d_val)
        se = np.sqrt(np.clip(np.diag(arm_covariance(v, u, d)), 0, None))
    params = kin.ArmParams.from_vector(jnp.asarray(v))
    elbow = kin.choose_elbow(params, u, d, spec.elbow)
    arm = kin.Arm(spec.name, params, elbow, spec.pulse_limits)
    return ArmCalibration(
        arm=arm,
        method=method,
        params_se=se,
        train_error_mm=mean_error_mm(params, u, d),
        validation_error_mm=(mean_error_mm(params, u_val, d_val)
                             if u_val is not None and len(u_val) else None),
        n_train=len(u),
        iterations=iters,
    )


def calibrate_arms(rig: Rig, method: Method = "least-squares") -> dict[str, ArmCalibration]:
    """Calibrate every arm of a rig on its single-arm ``train`` rows."""
    out = {}
    for name, spec in rig.arms.items():
        u, d = rig.rows(name, "train")
        uv, dv = rig.rows(name, "validation")
        out[name] = calibrate_arm(spec, u, d, method, uv, dv)
    return out
