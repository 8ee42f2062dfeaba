"""The paper's eight parameters of each planar arm, calibrated from its measured end points,
and the observed accuracy of the calibrated arms.

A planar arm is a 2-joint chain: base the shoulder's origin, links the elbow's and tool's
origins along x, servo map the gains and offsets. ``least-squares`` is the group fit of
:mod:`.least_squares` restricted to those eight columns in the arm's own base frame;
``hill-climb`` the paper's procedure; ``bayes`` (:mod:`.bayes`) samples the same eight.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import jax.numpy as jnp
import numpy as np
import scipy.stats

from bayesrob import robot as kin
from bayesrob.calibrate.hill_climb import hill_climb
from bayesrob.calibrate.least_squares import Calibration, covariance, fit, residual_function
from bayesrob.data.rig import N_ARM_PARAMS, SETS, ArmSpec, Rig

Method = Literal["least-squares", "hill-climb"]
# The Bayesian method lives one layer up (bayesrob.calibrate.bayes builds on this module);
# bayesrob.report.outputs.calibrate_rig dispatches to all three.
METHODS: tuple[str, ...] = ("least-squares", "hill-climb")

# The chain's name for an arm fitted on its own: one name for every planar arm, so that all of
# them share one structure and so the fit's compiled programs.
ARM = "arm"
# The eight (PARAM_NAMES order: bx, by, l1, l2, a1, a2, b1, b2) as columns of the arm's chain.
ARM_PARAMETERS = tuple(f"{ARM}.{p}" for p in (
    "shoulder.origin.x", "shoulder.origin.y", "elbow.origin.x", "tool.origin.x", "u1.gain",
    "u2.gain", "shoulder.offset", "elbow.offset"))
ARM_GROUPS = ("offsets", "servo", "geometric")
ARM_TOL = 1e-12  # the solver's tolerances: the eight to 1e-9 of the paper's own 8-vector fit


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
        """This arm's entry of ``bayesrob calibrate --json``."""
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

    to_json = to_dict


def mean_error_mm(params: kin.ArmParams, u: np.ndarray, d: np.ndarray) -> float:
    pred = np.asarray(kin.forward_u(params, jnp.asarray(u)))
    return float(np.mean(np.linalg.norm(pred - d, axis=-1)))


def arm_robot(v: np.ndarray) -> tuple[kin.Robot, np.ndarray]:
    """The arm of eight parameters ``v`` as a one-chain robot, and the eight's indices (8,)."""
    robot = kin.Robot({ARM: kin.planar_chain(ARM, kin.ArmParams.from_vector(
        jnp.asarray(v, float)))}, 2)
    names = [p.name for p in robot.layout.params]
    return robot, np.array([names.index(n) for n in ARM_PARAMETERS])


def arm_covariance(v: np.ndarray, u: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Gauss-Newton covariance (8, 8) of an arm's fitted parameters ``v`` on its train rows."""
    robot, idx = arm_robot(v)
    res, jac, *_ = residual_function(robot, {ARM: (np.asarray(u, float),
                                                   np.asarray(d, float), None)})
    free = np.zeros(robot.layout.nominal.size, bool)
    free[idx] = True
    return covariance(res, jac, robot.layout.nominal, free)[np.ix_(idx, idx)]


def arm_fit(robot: kin.Robot, idx: np.ndarray, u: np.ndarray, d: np.ndarray) -> Calibration:
    """The least squares of an arm's eight, the columns ``idx`` of its chain, on its rows."""
    eight = np.zeros(robot.layout.nominal.size, bool)
    eight[idx] = True
    return fit(robot, {ARM: (u, d, None)}, ARM_GROUPS, candidates=eight, tol=ARM_TOL,
               max_nfev=2000)


def calibrate_arm(spec: ArmSpec, u: np.ndarray, d: np.ndarray, method: Method = "least-squares",
                  u_val: np.ndarray | None = None, d_val: np.ndarray | None = None
                  ) -> ArmCalibration:
    """Fit one arm's parameters to its training rows (u: pulses (N, 2), d: end points (N, 2))."""
    if method not in METHODS:
        raise ValueError(f"unknown calibration method {method!r}; use one of {METHODS}")
    u = np.asarray(u, float)
    d = np.asarray(d, float)
    # four rows fix the eight exactly (standard errors NaN): `simulate --grid 2` rigs have four
    if len(u) * 2 < N_ARM_PARAMS:
        raise ValueError(f"arm {spec.name!r}: {len(u)} train rows cannot fix {N_ARM_PARAMS} "
                         "parameters")
    v0 = np.asarray(kin.ArmParams.from_spec(spec).to_vector())
    if method == "least-squares":
        robot, idx = arm_robot(v0)
        cal = arm_fit(robot, idx, u, d)
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


def calibrate_arms(rig: Rig, method: Method = "least-squares", fit_arm=None
                   ) -> dict[str, ArmCalibration]:
    """Calibrate every arm of a rig on its single-arm ``train`` rows (``fit_arm``: called as
    :func:`calibrate_arm`, the method aside)."""
    out = {}
    for name, spec in rig.arms.items():
        u, d = rig.rows(name, "train")
        uv, dv = rig.rows(name, "validation")
        out[name] = (fit_arm(spec, u, d, uv, dv) if fit_arm
                     else calibrate_arm(spec, u, d, method, uv, dv))
    return out


def mean_ci95(errors: np.ndarray) -> dict:
    e = np.asarray(errors, float)
    n = len(e)
    mean = float(np.mean(e)) if n else float("nan")
    if n < 2:
        return {"mean_mm": mean, "ci95_mm": [float("nan"), float("nan")], "n": n}
    half = float(scipy.stats.t.ppf(0.975, n - 1) * np.std(e, ddof=1) / np.sqrt(n))
    return {"mean_mm": mean, "ci95_mm": [mean - half, mean + half], "n": n}


def predicted_points(rig: Rig, arms: dict[str, kin.Arm], config: str, set: str) -> np.ndarray:
    """Where the model says a config's rows ended up: one arm's f(g(u)); linked arms' target,
    as the paper did (their commands came from the arms' own inverse models)."""
    rows = rig.config_rows(config, set)
    members = config.split("+")
    if len(members) == 1:
        return np.asarray(arms[config].forward_u(jnp.asarray(rows["commands"][config])))
    target = rows["target"]
    if np.isnan(target).any():
        # No target recorded: fall back to the mean of the arms' forward predictions.
        return np.mean([np.asarray(arms[a].forward_u(jnp.asarray(rows["commands"][a])))
                        for a in members], axis=0)
    return target


def observed_errors(rig: Rig, arms: dict[str, kin.Arm], config: str, set: str) -> np.ndarray:
    rows = rig.config_rows(config, set)
    pred = predicted_points(rig, arms, config, set)
    return np.linalg.norm(pred - rows["observed"], axis=-1)


def observed_accuracy(rig: Rig, arms: dict[str, kin.Arm]) -> dict[str, dict[str, dict]]:
    out: dict[str, dict[str, dict]] = {}
    for config in rig.configs:
        for s in SETS:
            if rig.measurements.mask(config, s).any():
                out.setdefault(config, {})[s] = mean_ci95(observed_errors(rig, arms, config, s))
    return out
