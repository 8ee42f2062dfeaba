"""Calibration of each arm's eight parameters from its measured end points, and observed accuracy.

Two point-estimate methods:
- ``least-squares`` (default): scipy's trust-region least squares on the x/y residuals, with
  the JAX Jacobian; parameter standard errors from s^2 (J^T J)^-1.
- ``hill-climb``: the paper's procedure, kept as the baseline: coordinate steps on the summed
  Euclidean error, halving the steps when none helps, stopped as soon as the error on the
  ``validation`` rows rises.
A third, ``bayes``, samples the posterior of the parameters by NUTS (params = posterior mean,
params_se = posterior sd); it lives in :mod:`bayesrob.bayes_calibration`, which builds on this
module, and :func:`bayesrob.outputs.calibrate_rig` chooses among the three.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import partial
from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np
import scipy.optimize
import scipy.stats

from bayesrob import kinematics as kin
from bayesrob import release_compiled_programs
from bayesrob.rig import N_ARM_PARAMS, SETS, ArmSpec, Rig

Method = Literal["least-squares", "hill-climb"]
# The Bayesian method lives one layer up (bayesrob.bayes_calibration builds on this module);
# bayesrob.outputs.calibrate_rig dispatches to all three.
METHODS: tuple[str, ...] = ("least-squares", "hill-climb")


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


@jax.jit
def _residuals(v: jax.Array, u: jax.Array, d: jax.Array) -> jax.Array:
    return (kin.forward_u(kin.ArmParams.from_vector(v), u) - d).ravel()


_residual_jac = jax.jit(jax.jacfwd(_residuals))


@jax.jit
def _summed_errors(vs: jax.Array, u: jax.Array, d: jax.Array) -> jax.Array:
    """The paper's cost sum_i ||f(g(u_i)) - d_i|| for each parameter vector in vs (K, 8)."""
    pred = jax.vmap(lambda v: kin.forward_u(kin.ArmParams.from_vector(v), u))(vs)
    return jnp.sum(jnp.linalg.norm(pred - d, axis=-1), axis=-1)


def mean_error_mm(params: kin.ArmParams, u: np.ndarray, d: np.ndarray) -> float:
    """Mean Euclidean distance between f(g(u)) and the observed end points."""
    pred = np.asarray(kin.forward_u(params, jnp.asarray(u)))
    return float(np.mean(np.linalg.norm(pred - d, axis=-1)))


def _scales(v0: np.ndarray) -> np.ndarray:
    """Typical sizes of the parameters, so steps and tolerances mean the same in each."""
    return np.array([10.0, 10.0, 10.0, 10.0, 0.05 * abs(v0[4]), 0.05 * abs(v0[5]), 0.05, 0.05])


def _least_squares(v0: np.ndarray, u: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, int]:
    uj, dj = jnp.asarray(u), jnp.asarray(d)
    res = scipy.optimize.least_squares(
        lambda v: np.asarray(_residuals(jnp.asarray(v), uj, dj)),
        v0,
        jac=lambda v: np.asarray(_residual_jac(jnp.asarray(v), uj, dj)),
        x_scale=_scales(v0),
        method="trf",
        xtol=1e-12,
        ftol=1e-12,
        gtol=1e-12,
        max_nfev=2000,
    )
    return res.x, int(res.nfev)


def parameter_covariance(v: np.ndarray, u: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Gauss-Newton covariance (8, 8) of a planar arm's fitted parameters ``v``
    (``ArmParams.to_vector`` order) on its train rows; NaN when the rows cannot fix them."""
    v = np.asarray(v, float)
    r = np.asarray(_residuals(jnp.asarray(v), jnp.asarray(u), jnp.asarray(d)))
    J = np.asarray(_residual_jac(jnp.asarray(v), jnp.asarray(u), jnp.asarray(d)))
    dof = r.size - v.size
    if dof <= 0:
        return np.full((v.size, v.size), np.nan)
    return float(r @ r) / dof * np.linalg.pinv(J.T @ J)


def _standard_errors(v: np.ndarray, u: np.ndarray, d: np.ndarray) -> np.ndarray:
    return np.sqrt(np.clip(np.diag(parameter_covariance(v, u, d)), 0, None))


def _hill_climb(v0: np.ndarray, u: np.ndarray, d: np.ndarray, u_val: np.ndarray | None,
                d_val: np.ndarray | None, max_iter: int = 20000) -> tuple[np.ndarray, int]:
    """The paper's hill climb on J = sum ||f(g(u_i)) - d_i||, halted when validation rises.

    Each iteration takes the best of the +-step moves of every parameter; when none improves
    the training cost the steps halve. The validation cost is checked at each halving (a
    finished climb at one step size): checking after every single step would stop on the
    first wobble of measurement noise, long before the fit is any good.
    """
    uj, dj = jnp.asarray(u), jnp.asarray(d)
    costs = _summed_errors
    has_val = u_val is not None and len(u_val) > 0
    v = v0.copy()
    scale = _scales(v0)
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
        v, iters = _least_squares(v0, u, d)
    else:
        v, iters = _hill_climb(v0, u, d, u_val, d_val)
    params = kin.ArmParams.from_vector(jnp.asarray(v))
    elbow = kin.choose_elbow(params, u, d, spec.elbow)
    arm = kin.Arm(spec.name, params, elbow, spec.pulse_limits)
    return ArmCalibration(
        arm=arm,
        method=method,
        params_se=_standard_errors(v, u, d),
        train_error_mm=mean_error_mm(params, u, d),
        validation_error_mm=(mean_error_mm(params, u_val, d_val)
                             if u_val is not None and len(u_val) else None),
        n_train=len(u),
        iterations=iters,
    )


def calibrate(rig: Rig, method: Method = "least-squares") -> dict[str, ArmCalibration]:
    """Calibrate every arm of a rig on its single-arm ``train`` rows."""
    out = {}
    for name, spec in rig.arms.items():
        u, d = rig.rows(name, "train")
        uv, dv = rig.rows(name, "validation")
        out[name] = calibrate_arm(spec, u, d, method, uv, dv)
    return out


def mean_ci95(errors: np.ndarray) -> dict:
    """Mean with the Student-t 95% confidence interval of the mean."""
    e = np.asarray(errors, float)
    n = len(e)
    mean = float(np.mean(e)) if n else float("nan")
    if n < 2:
        return {"mean_mm": mean, "ci95_mm": [float("nan"), float("nan")], "n": n}
    half = float(scipy.stats.t.ppf(0.975, n - 1) * np.std(e, ddof=1) / np.sqrt(n))
    return {"mean_mm": mean, "ci95_mm": [mean - half, mean + half], "n": n}


def predicted_points(rig: Rig, arms: dict[str, kin.Arm], config: str, set: str) -> np.ndarray:
    """Where the model says the rows of a config ended up.

    A single arm: f(g(u)) of the commands sent. Linked arms: the target the commands aimed at,
    as the paper did (the commands came from the arms' own inverse models).
    """
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
    """Euclidean distance (mm) between predicted and observed end point, row by row."""
    rows = rig.config_rows(config, set)
    pred = predicted_points(rig, arms, config, set)
    return np.linalg.norm(pred - rows["observed"], axis=-1)


def observed_accuracy(rig: Rig, arms: dict[str, kin.Arm]) -> dict[str, dict[str, dict]]:
    """Mean error with 95% CI per config and set, for every config and set present."""
    out: dict[str, dict[str, dict]] = {}
    for config in rig.configs:
        for s in SETS:
            if rig.measurements.mask(config, s).any():
                out.setdefault(config, {})[s] = mean_ci95(observed_errors(rig, arms, config, s))
    return out


# ----------------------------------------------------------------------------- any chain
# Calibration of a rig of URDF/DH chains (or of planar arms through the same general model):
# least squares over named parameter groups, after a rank analysis that fixes at nominal
# whatever the training rows cannot tell apart.

# Groups are tried in this order when the rank analysis decides which of two redundant
# parameters to keep: the simpler explanation (a frame, a joint offset, a gain) before a
# general correction of a joint's origin.
PRIORITY = ("frames", "offsets", "servo", "geometric", "compliance", "lateral", "encoder",
            "backlash")
# A column is identifiable when the part of it no earlier column explains is at least this
# fraction of its length (column-scaled to each parameter's typical size). Exact
# redundancies sit at 1e-10 and below; 1e-4 also drops directions whose standard error would
# be thousands of times the noise, which only fit noise.
RANK_TOL = 1e-4


@dataclass
class Identifiability:
    """Which parameters the rows can identify, and how the others depend on them."""

    free: np.ndarray  # (P,) bool: fitted
    not_observed: list[str]  # no measured point depends on these at all
    unidentifiable: list[dict]  # {"name", "group", "explained_by": {name: coefficient}}


def identifiability(jac: np.ndarray, layout: kin.ParamLayout, candidates: np.ndarray
                    ) -> Identifiability:
    """Rank analysis of the column-scaled Jacobian: a greedy, priority-ordered Gram-Schmidt
    (a rank-revealing QR whose pivots follow :data:`PRIORITY` rather than column norms, so
    the parameter kept of a redundant pair is the one with the plain name)."""
    js = np.asarray(jac) * layout.scales[None, :]
    norms = np.linalg.norm(js, axis=0)
    top = norms[candidates].max() if candidates.any() else 1.0
    order = [i for g in PRIORITY for i, p in enumerate(layout.params)
             if p.group == g and candidates[i]]
    basis = np.zeros((js.shape[0], 0))
    free = np.zeros(len(layout.params), bool)
    not_observed, dropped = [], []
    for i in order:
        c = js[:, i]
        if norms[i] <= 1e-12 * top:
            not_observed.append(layout.params[i].name)
            continue
        r = c - basis @ (basis.T @ c)
        r = r - basis @ (basis.T @ r)  # twice: classical Gram-Schmidt loses orthogonality
        if np.linalg.norm(r) > RANK_TOL * norms[i]:
            basis = np.column_stack([basis, r / np.linalg.norm(r)])
            free[i] = True
        else:
            dropped.append(i)
    kept = np.flatnonzero(free)
    unident = []
    # every dropped column at once: one factorisation of the kept columns (one solve per
    # column took 8.6 s of a compliance fit's 11 s on a linked 6-joint pair)
    coefs = (np.linalg.lstsq(js[:, kept], js[:, dropped], rcond=None)[0] if dropped
             else np.zeros((len(kept), 0)))
    for col, i in enumerate(dropped):
        # back to parameter units: J_i ~ sum_k coef_k (s_k / s_i) J_k
        coef = coefs[:, col] * layout.scales[kept] / layout.scales[i]
        big = np.argsort(-np.abs(coef))[:3]
        unident.append({
            "name": layout.params[i].name, "group": layout.params[i].group,
            "explained_by": {layout.params[kept[k]].name: float(coef[k]) for k in big
                             if abs(coef[k]) > 1e-3 * np.abs(coef).max()}})
    return Identifiability(free, not_observed, unident)


def _error_stats(dist: np.ndarray) -> dict:
    d = np.asarray(dist, float)
    if d.size == 0:
        return {"mean_mm": None, "sd_mm": None, "max_mm": None, "n": 0}
    return {"mean_mm": float(d.mean()), "sd_mm": float(d.std(ddof=1)) if d.size > 1 else 0.0,
            "max_mm": float(d.max()), "n": int(d.size)}


@dataclass
class ChainCalibration:
    """A calibrated robot: the parameter vector, what was fitted and how well it fits."""

    robot: kin.Robot
    x: np.ndarray  # (P,) every parameter, fixed ones at nominal
    groups: tuple[str, ...]
    ident: Identifiability
    se: np.ndarray  # (P,) standard errors, NaN where fixed
    errors: dict  # set -> arm | "all" -> {mean_mm, sd_mm, max_mm, n}
    nfev: int
    seconds: float
    method: str = "least-squares"
    extra: dict = field(default_factory=dict)  # e.g. the Bayesian posterior's diagnostics
    draws: np.ndarray | None = None  # (S, P) posterior draws of every parameter (bayes only)
    # "description": the links' masses and first moments held at the robot description's
    # (URDF <inertial>), so the compliances are the joints' own; "fitted": free, only their
    # products with the compliances seen
    masses: str = "fitted"

    def to_dict(self) -> dict:
        """``bayesrob calibrate RIG --params ... --json``'s document but the rig's name, which
        the command adds (as :meth:`to_json`)."""
        return self.to_json()

    def to_json(self) -> dict:
        layout = self.robot.layout
        return {
            "method": self.method,
            "params": list(self.groups),
            "n_free": int(self.ident.free.sum()),
            "n_parameters": len(layout.params),
            "parameters": {
                p.name: {"group": p.group, "value": float(self.x[i]),
                         "nominal": p.nominal, "free": bool(self.ident.free[i]),
                         "se": None if not self.ident.free[i] else float(self.se[i])}
                for i, p in enumerate(layout.params)},
            "unidentifiable": self.ident.unidentifiable,
            "not_observed": self.ident.not_observed,
            "errors": self.errors,
            "nfev": self.nfev,
            "seconds": self.seconds,
            **({"lateral_prior_mm": LATERAL_PRIOR_MM} if "lateral" in self.groups else {}),
            **({"masses": self.masses} if self.masses != "fitted" else {}),
            **self.extra,
        }


def side_rows(rig: Rig, robot: kin.Robot, arm: str, set: str) -> dict[str, jax.Array] | None:
    """The rest of the pose in ``arm``'s rows of a set, where it matters (joints that give
    way under gravity) and the rows carry it; else None."""
    if robot.gravity is None:
        return None
    side = rig.chain_side_rows(arm, set)
    return None if side is None else {b: jnp.asarray(v) for b, v in side.items()}


def chain_residuals(rig: Rig, robot: kin.Robot, x: np.ndarray, set: str
                    ) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per measured arm with rows in ``set``: the observed markers (n, 3) and the residuals
    observed - model (n, 3), row by row."""
    out = {}
    for arm in robot.measured_arms():
        u, d = rig.rows(arm, set)
        if len(u):
            p = np.asarray(robot.compiled_points(arm)(jnp.asarray(x), jnp.asarray(u),
                                                      side_rows(rig, robot, arm, set)))
            out[arm] = (np.asarray(d), np.asarray(d) - p)
    return out


def chain_distances(rig: Rig, robot: kin.Robot, x: np.ndarray, set: str
                    ) -> dict[str, np.ndarray]:
    """Per measured arm, the distance (mm) between model and observed marker, row by row."""
    return {a: np.linalg.norm(r, axis=1)
            for a, (_, r) in chain_residuals(rig, robot, x, set).items()}


# The fit's programs are specialised on the robot's structure alone; its nominal values are
# an argument (``values``), so the fits of every robot of one design (simulated rigs of other
# seeds, a calibrated robot refitted, another rig's copy of the URDF) share them.
@partial(jax.jit, static_argnames=("structure", "arms"))
def _fit_residuals(structure: kin.RobotStructure, arms: tuple[str, ...], values: dict,
                   x: jax.Array, data: tuple) -> jax.Array:
    robot = structure.robot(values)
    return jnp.concatenate([(robot.marker_points(x, a, u, side=side) - d).ravel()
                            for a, (u, d, side) in zip(arms, data, strict=True)])


@partial(jax.jit, static_argnames=("structure", "arms"))
def _fit_jacobian(structure: kin.RobotStructure, arms: tuple[str, ...], values: dict,
                  x: jax.Array, data: tuple) -> jax.Array:
    robot = structure.robot(values)
    return jnp.concatenate([robot.marker_jacobian(x, a, u, side).reshape(
        -1, x.shape[0]) for a, (u, _, side) in zip(arms, data, strict=True)])


@partial(jax.jit, static_argnames=("structure", "arms"))
def _fit_exact_jacobian(structure: kin.RobotStructure, arms: tuple[str, ...], values: dict,
                        x: jax.Array, data: tuple) -> jax.Array:
    # Reverse mode, row by row: a row's marker depends on the parameters through its own
    # pose alone, so each row costs a pull-back per measured coordinate (2-3), where forward
    # mode costs a push-forward per fitted column (Justin: 127-192) for every row at once (on
    # Justin about thirty times the cost: docs/diagnose.md); and one compiled program serves
    # every set of fitted columns.
    robot = structure.robot(values)

    def rows(a, u, side):
        def one(u1, side1):
            s1 = None if side1 is None else {b: v[None] for b, v in side1.items()}
            return jax.jacrev(lambda x: robot.marker_points(x, a, u1[None],
                                                             side=s1)[0])(x)
        return jax.vmap(one)(u, side).reshape(-1, x.shape[0])
    return jnp.concatenate([rows(a, u, side)
                            for a, (u, _, side) in zip(arms, data, strict=True)])


def _residual_function(rig: Rig, robot: kin.Robot, set: str):
    """Residuals and their Jacobian as functions of the parameters alone, compiled once per
    process for all robots of ``robot``'s structure (the rows and the nominal values are
    arguments, so a second calibration of the same rig, or of another rig of a robot of the
    same design, is warm)."""
    structure, values = robot.structure, robot.nominal_values
    arms = tuple(a for a in robot.measured_arms() if len(rig.rows(a, set)[0]))
    data = tuple((jnp.asarray(u), jnp.asarray(d), side_rows(rig, robot, a, set))
                 for a, (u, d) in ((a, rig.rows(a, set)) for a in arms))
    n_res = sum(int(d.size) for _, d, _ in data)

    def exact_columns(x, idx):
        # the columns picked on the host: indexing the device array would compile a gather
        # for every count of fitted columns
        return np.asarray(_fit_exact_jacobian(structure, arms, values, x, data))[
            :, np.asarray(idx)]
    return (lambda x: _fit_residuals(structure, arms, values, x, data)), (
        lambda x: _fit_jacobian(structure, arms, values, x, data)), n_res, exact_columns


# A lateral compliance of one typical size (1e-7 rad per N mm) costs as much as a marker
# residual of this many mm: a zero-centred Gaussian prior on bending across the axes
# (bearings are stiff unless the rows say otherwise). Without it, Justin's fit with lateral
# settles in a basin that fits the train poses no better and the held-out poses worse: on two
# inner splits of its train poses (225 fitted, 75 scored; validation rows never used), 3.17
# and 3.35 mm without, 3.06-3.08 and 3.19 with 3.2-32 mm here (weights 10-1000 in mm^2: flat),
# in half the evaluations. Its sd is in the markers' units: on a rig with tenfold finer
# markers it is a tenfold tighter prior (docs/robots.md).
LATERAL_PRIOR_MM = 10.0


def prior_penalty(layout: kin.ParamLayout, groups: tuple[str, ...]) -> np.ndarray:
    """Per parameter, the weight (mm per unit) of its zero-centred penalty row beside the
    residuals: the lateral compliances' prior when ``lateral`` is fitted, else zero."""
    lateral = layout.group_mask(("lateral",)) if "lateral" in groups else np.zeros(
        len(layout.params), bool)
    return np.where(lateral, LATERAL_PRIOR_MM / layout.scales, 0.0)


POLISH_NFEV = 20  # exact-Jacobian steps after a fit with joints giving way under gravity


def _with_gravity(rig: Rig, sag_steps: int = 1) -> kin.Robot:
    """The rig's robot with its gravity model on. A new object each call, equal to the last:
    the compiled residuals and Jacobians are keyed by the robot's structure, so every
    calibration of a diagnosis (and of any rig of a robot of the same design) reuses them."""
    gravity = np.zeros(3)
    gravity[: len(rig.gravity)] = rig.gravity  # a planar rig's gravity lies in its plane
    return replace(rig.robot, gravity=gravity, sag_steps=sag_steps)


def calibrate_chain(rig: Rig, groups: tuple[str, ...] = kin.GROUPS, progress=None,
                    polish: bool = True, max_nfev: int = 300,
                    start: np.ndarray | None = None, sag_steps: int = 1,
                    masses: str = "fitted") -> ChainCalibration:
    """Least squares (scipy's trust region, JAX Jacobian) over the parameter ``groups`` on the
    ``train`` rows, after the rank analysis; frames (instrument poses, markers) always.
    ``polish``: finish a fit with joints giving way under gravity with the exact Jacobian
    (off: faster, a little short of the optimum; the diagnosis's comparisons use that).
    ``max_nfev``: residual evaluations allowed to each of the fit's least-squares stages.
    ``start``: the parameter vector to start from (a fit of fewer groups on the same rig, its
    frames fitted), instead of the nominal one. ``sag_steps``: how many times the sag's
    torques are taken, the first at the commanded pose, each next at the pose the last one
    sagged into (:attr:`kinematics.Robot.sag_steps`). ``masses``: "fitted" (the links' masses
    and first moments are free, the rank analysis keeping what the compliances make visible),
    or "description": held at the robot description's (URDF ``<inertial>``), so that each
    compliance is the joint's own and not its product with an unknown mass scale."""
    import time

    t0 = time.perf_counter()
    # a fit compiles programs for its robot; sweeps fit robot after robot in one process
    release_compiled_programs()
    unknown = [g for g in groups if g not in kin.ALL_GROUPS]
    if unknown:
        raise ValueError(f"unknown parameter group {unknown[0]!r}; choose from "
                         f"{', '.join(kin.ALL_GROUPS)}")
    groups = tuple(g for g in kin.ALL_GROUPS if g in set(groups) | {"frames"})
    sags = bool(set(kin.SAG_GROUPS) & set(groups))
    if sag_steps < 1:
        raise ValueError(f"sag_steps must be at least 1, not {sag_steps}")
    robot = _with_gravity(rig, sag_steps) if sags else rig.robot
    layout = robot.layout
    full_res, full_jac, n_res, exact_jac = _residual_function(rig, robot, "train")
    x = layout.nominal.copy() if start is None else np.array(start, float)
    if x.shape != layout.nominal.shape:
        raise ValueError(f"start has {x.size} parameters; the robot has {layout.nominal.size}")
    if masses not in kin.MASS_SOURCES:
        raise ValueError(f"masses must be one of {kin.MASS_SOURCES}, not {masses!r}")
    candidates = layout.group_mask(groups)
    if sags and masses == "fitted":
        # the links' masses and first moments sit in the compliance group's columns, but the
        # lateral compliances bend the joints under the same unknown torques: fitted without
        # joint compliance they would otherwise weigh the links at the layout's guess
        candidates |= link_mask(layout)
    if masses == "description":
        if not sags:
            raise ValueError("masses 'description' holds the link masses of a fit in which "
                             "joints give way under gravity; add compliance, lateral or "
                             f"backlash to the groups ({', '.join(groups)})")
        candidates = candidates & ~described_links(robot, x)
    nfev = 0
    penalty = prior_penalty(layout, groups)

    def fit(mask: np.ndarray, x0: np.ndarray, exact: bool = False, max_nfev: int = max_nfev
            ) -> tuple[np.ndarray, int]:
        idx = np.flatnonzero(mask)

        def put(v):
            return jnp.asarray(x0).at[idx].set(jnp.asarray(v))

        # the prior's rows only in fits that free a penalised parameter: elsewhere they would
        # be zeros that every trust-region step still factorises
        pen = penalty[idx]
        prior = bool(pen.any())

        def jac(v):
            j = (np.asarray(exact_jac(put(v), idx)) if exact
                 else np.asarray(full_jac(put(v)))[:, idx])
            return np.vstack([j, np.diag(pen)]) if prior else j

        def res(v):
            r = np.asarray(full_res(put(v)))
            return np.concatenate([r, pen * (v - layout.nominal[idx])]) if prior else r
        out = scipy.optimize.least_squares(
            res, x0[idx], jac=jac,
            x_scale=layout.scales[idx], method="trf", xtol=1e-10, ftol=1e-10, gtol=1e-10,
            max_nfev=max_nfev)
        return np.asarray(put(out.x)), int(out.nfev)

    # The frames first (a rough instrument pose is a large, nonlinear correction), then the
    # rank analysis at that point and the fit of everything it keeps.
    if start is None:
        frames = layout.group_mask(("frames",))
        frames_ident = identifiability(np.asarray(full_jac(jnp.asarray(x))), layout, frames)
        x, n = fit(frames_ident.free, x)
        nfev += n
        if progress:
            progress("frames fitted")
    ident = identifiability(np.asarray(full_jac(jnp.asarray(x))), layout, candidates)
    if int(ident.free.sum()) >= n_res:
        raise ValueError(f"{ident.free.sum()} identifiable parameters but only {n_res} "
                         "measured coordinates in the train rows")
    # a start with compliances fitted already shows the masses: the second round alone
    seen = start is not None and any(np.any(x[sl] != 0) for key, sl in layout.slices.items()
                                     if key[1] in ("compliance", "lateral"))
    if groups != ("frames",) and not (sags and seen):
        x, n = fit(ident.free, x)
        nfev += n
    if sags:
        # Masses are seen only through non-zero compliances: at the start (compliance 0) the
        # rank analysis frees the compliances alone; a second round frees the masses and
        # first moments the fitted compliances make visible, and the play, whose side is the
        # fitted deflection's.
        if progress:
            progress("compliances fitted; freeing " + ("link masses" if masses == "fitted"
                                                      else "what they make visible"))
        ident = identifiability(np.asarray(full_jac(jnp.asarray(x))), layout, candidates)
        x, n = fit(ident.free, x)
        nfev += n
        # The analytic Jacobian leaves out how the geometry moves the sag, so its fit stops a
        # little short (on the linked arm6 rig, train error 0.168 against 0.163 mm): a few
        # steps with the exact, slower Jacobian finish it.
        if polish:
            if progress:
                progress("polishing with the exact Jacobian")
            x, n = fit(ident.free, x, exact=True, max_nfev=POLISH_NFEV)
            nfev += n
    se = _chain_standard_errors(full_res, full_jac, x, ident.free, penalty)
    extra = sag_convergence(rig, x, sag_steps) if sags and polish else {}
    return ChainCalibration(robot, x, groups, ident, se, chain_errors(rig, robot, x), nfev,
                            time.perf_counter() - t0, extra=extra,
                            masses=masses)


def link_mask(layout: kin.ParamLayout) -> np.ndarray:
    """The parameters (P,) that weigh the links: every chain's masses and first moments."""
    mask = np.zeros(len(layout.params), bool)
    for key, sl in layout.slices.items():
        if key[1] == "links":
            mask[sl] = True
    return mask


def described_links(robot: kin.Robot, x: np.ndarray) -> np.ndarray:
    """Put every chain's link masses and first moments from its description into ``x`` (in
    place) and return the mask (P,) of those parameters; a chain whose description does not
    weigh every moving link is an error."""
    layout = robot.layout
    held = np.zeros(layout.nominal.shape, bool)
    for c in robot.chains.values():
        if not c.weighed:
            why = c.source.get("unweighed") or f"a {c.source.get('kind', 'DH')} description"
            raise ValueError(f"chain {c.name!r}: its description does not give every moving "
                             f"link a mass ({why}), so the masses cannot be held at it; fit "
                             "them instead (masses 'fitted')")
        m, h = c.source["link_masses_kg"], c.source["link_moments_kg_mm"]
        sl = layout.slices[c.name, "links"]
        x[sl] = np.column_stack([np.asarray(m, float), np.asarray(h, float)]).ravel()
        held[sl] = True
    return held


SAG_CONVERGED_MM = 0.01  # a tenth of the markers' noise on the arms seen so far


def sag_convergence(rig: Rig, x: np.ndarray, sag_steps: int = 1) -> dict:
    """How far one more step of the sag's torques (taken at the pose the fitted sag leaves)
    moves the train markers, for the parameters ``x`` of the rig's gravity model with
    ``sag_steps`` steps: ``sag_next_step_mm`` (largest). One step is a first-order model
    whose free masses and compliances absorb the rest (docs/robots.md); when more steps were
    asked for and the last still moves a marker by more than SAG_CONVERGED_MM, a note says
    that the iteration did not reach the torque equilibrium."""
    # the rig's gravity robots: equal to the fit's, so its compiled residuals serve here
    robot = _with_gravity(rig, sag_steps)
    now, *_ = _residual_function(rig, robot, "train")
    nxt, *_ = _residual_function(rig, _with_gravity(rig, sag_steps + 1), "train")
    moved = np.asarray(nxt(jnp.asarray(x)) - now(jnp.asarray(x))).reshape(-1, robot.dim)
    change = float(np.linalg.norm(moved, axis=1).max())
    out: dict = {"sag_steps": robot.sag_steps, "sag_next_step_mm": change}
    if robot.sag_steps > 1 and change > SAG_CONVERGED_MM:
        out["notes"] = [
            f"the sag is not at equilibrium: its torques taken once more, at the pose the "
            f"fitted sag leaves (sag_steps {robot.sag_steps + 1}), move a train marker by up to "
            f"{change:.3g} mm; the fitted sag is a model with {robot.sag_steps} step(s) of "
            "the torques, whose masses and compliances are fitted for that model "
            "(docs/robots.md)"]
    return out


def _chain_covariance(full_res, full_jac, x: np.ndarray, free: np.ndarray,
                      penalty: np.ndarray) -> np.ndarray:
    """Gauss-Newton covariance (P, P) of the fitted parameters, zero where fixed; a prior's
    penalty rows (``prior_penalty``) add their information."""
    r = np.asarray(full_res(jnp.asarray(x)))
    jac = np.asarray(full_jac(jnp.asarray(x)))[:, free]
    dof = r.size - int(free.sum())
    cov = np.zeros((len(x), len(x)))
    if dof > 0:
        info = jac.T @ jac + np.diag(penalty[free] ** 2)
        cov[np.ix_(free, free)] = float(r @ r) / dof * np.linalg.pinv(info)
    return cov


def _chain_standard_errors(full_res, full_jac, x: np.ndarray, free: np.ndarray,
                           penalty: np.ndarray) -> np.ndarray:
    cov = _chain_covariance(full_res, full_jac, x, free, penalty)
    se = np.full(len(x), np.nan)
    if cov.any():
        se[free] = np.sqrt(np.clip(np.diag(cov)[free], 0, None))
    return se


def chain_parameter_covariance(rig: Rig, cal: ChainCalibration) -> np.ndarray:
    """The calibrated parameters' covariance (P, P) on the train rows (zero where fixed): what
    a prediction at a new pose inherits from the fit, beside the joint errors."""
    full_res, full_jac, *_ = _residual_function(rig, cal.robot, "train")
    return _chain_covariance(full_res, full_jac, cal.x, cal.ident.free,
                             prior_penalty(cal.robot.layout, cal.groups))


def chain_errors(rig: Rig, robot: kin.Robot, x: np.ndarray) -> dict:
    """Marker error statistics per set and arm (and over all arms) at parameters x."""
    errors = {}
    for s in SETS:
        dist = chain_distances(rig, robot, x, s)
        if dist:
            errors[s] = {a: _error_stats(d) for a, d in dist.items()}
            errors[s]["all"] = _error_stats(np.concatenate(list(dist.values())))
    return errors


def calibrated_rig_document(rig: Rig, cal: ChainCalibration, urdf_name: str) -> dict:
    """rig.toml of the calibrated robot, its arms read from the URDF ``urdf_name`` that
    :func:`bayesrob.kinematics.write_urdf` wrote: origins and offsets are in the URDF, marker
    positions and instrument poses (not part of a URDF) here."""
    calibrated = cal.robot.with_values(cal.x)
    keys = kin.urdf.generated_arm_keys(calibrated)
    measured = calibrated.measured_arms()
    arms = {name: chain_arm_table(c, urdf_name, keys[name], name in measured)
            for name, c in calibrated.chains.items()}
    return {"name": f"{rig.name}-calibrated", "gravity": list(rig.gravity), "arms": arms}


def chain_arm_table(c: kin.Chain, urdf_name: str, keys: dict, measured: bool) -> dict:
    """One calibrated chain as a rig.toml arm read from ``urdf_name`` (``keys``: its root and
    tip there): the instrument pose (or mount), the marker, coupling, gains and offsets."""
    table: dict = {"urdf": urdf_name, **keys}
    if c.mount is not None:
        table["mount"] = c.mount
    else:
        table["instrument"] = [float(v) for v in c.instrument]
    if measured:
        table["marker"] = [float(v) for v in c.marker]
    if c.coupling.shape[0] != c.coupling.shape[1] or not np.allclose(
            c.coupling, np.eye(c.coupling.shape[0])):
        table["coupling"] = [[float(v) for v in row] for row in c.coupling]
    table["gain"] = [float(v) for v in c.gain]
    table["offset"] = [float(v) for v in c.offset]
    return table
