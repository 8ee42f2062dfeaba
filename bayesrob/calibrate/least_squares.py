"""Least squares over named parameter groups: one calibration for every robot.

scipy's trust-region least squares with the JAX Jacobian on the ``train`` rows, over the groups
asked for (frames always), after a rank analysis that holds at nominal whatever the rows cannot
tell apart. A planar arm's eight parameters are one instance (:mod:`.arms`). The Gauss-Newton
:func:`covariance` is the one every consumer uses.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import scipy.optimize

from bayesrob import robot as kin
from bayesrob.calibrate.identifiability import Identifiability, identifiability
from bayesrob.data.rig import SETS, Rig

# arm -> (commands (N, c), observed markers (N, dim), the rest of the pose or None)
Rows = dict[str, tuple[np.ndarray, np.ndarray, "dict[str, jax.Array] | None"]]


def _error_stats(dist: np.ndarray) -> dict:
    d = np.asarray(dist, float)
    if d.size == 0:
        return {"mean_mm": None, "sd_mm": None, "max_mm": None, "n": 0}
    return {"mean_mm": float(d.mean()), "sd_mm": float(d.std(ddof=1)) if d.size > 1 else 0.0,
            "max_mm": float(d.max()), "n": int(d.size)}


@dataclass
class Calibration:
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
        """``bayesrob calibrate RIG --params ... --json``'s document but the rig's name."""
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

    to_json = to_dict


def side_rows(rig: Rig, robot: kin.Robot, arm: str, set: str) -> dict[str, jax.Array] | None:
    """The rest of the pose in ``arm``'s rows of a set where gravity weighs it, else None."""
    if robot.gravity is None:
        return None
    side = rig.side_rows(arm, set)
    return None if side is None else {b: jnp.asarray(v) for b, v in side.items()}


def set_rows(rig: Rig, robot: kin.Robot, set: str) -> Rows:
    out = {}
    for arm in robot.measured_arms():
        u, d = rig.rows(arm, set)
        if len(u):
            out[arm] = (np.asarray(u), np.asarray(d), side_rows(rig, robot, arm, set))
    return out


def marker_residuals(rig: Rig, robot: kin.Robot, x: np.ndarray, set: str
                     ) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per measured arm with rows in ``set``: observed markers and residuals (n, dim) each."""
    return {arm: (d, d - np.asarray(robot.compiled_points(arm)(jnp.asarray(x), jnp.asarray(u),
                                                                side)))
            for arm, (u, d, side) in set_rows(rig, robot, set).items()}


def marker_distances(rig: Rig, robot: kin.Robot, x: np.ndarray, set: str
                     ) -> dict[str, np.ndarray]:
    return {a: np.linalg.norm(r, axis=1)
            for a, (_, r) in marker_residuals(rig, robot, x, set).items()}


# The fit's programs are specialised on the robot's structure alone; its nominal values are
# an argument (``values``), so the fits of every robot of one design (simulated rigs of other
# seeds, a calibrated robot refitted, another rig's copy of the URDF) share them.
@partial(jax.jit, static_argnames=("structure", "arms"))
def _fit_residuals(structure: kin.RobotStructure, arms: tuple[str, ...], values: dict,
                   x: jax.Array, data: tuple) -> jax.Array:
    return _residuals(structure.robot(values), arms, x, data)


def _residuals(robot: kin.Robot, arms: tuple[str, ...], x: jax.Array, data: tuple
               ) -> jax.Array:
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


def residual_function(robot: kin.Robot, rows: Rows):
    """(residuals, Jacobian, number of residuals, exact columns) as functions of the
    parameters, compiled once per structure and row buckets (rows and nominal values are
    arguments; the rows padded as :func:`bayesrob.robot.on_row_buckets` pads them, the
    padding's residuals cut off)."""
    structure, values = robot.structure, robot.nominal_values
    arms, (data, keep) = tuple(rows), _device_rows(rows)

    def exact_columns(x, idx):
        # the columns picked on the host: indexing the device array would compile a gather
        # for every count of fitted columns
        return np.asarray(_fit_exact_jacobian(structure, arms, values, x, data))[
            np.ix_(keep, np.asarray(idx))]
    return (lambda x: _kept(_fit_residuals(structure, arms, values, x, data), keep)), (
        lambda x: _kept(_fit_jacobian(structure, arms, values, x, data), keep)), keep.size, \
        exact_columns


def misfit_function(robot: kin.Robot, rows: Rows, penalty: np.ndarray
                    ) -> Callable[[np.ndarray], np.ndarray]:
    """xs (K, P) -> the rows' sum of squares at each parameter vector, with the penalty rows
    :func:`fit` adds; one compiled program per structure, row buckets and batch size."""
    structure, values = robot.structure, robot.nominal_values
    arms, (data, keep) = tuple(rows), _device_rows(rows)
    real = np.zeros(sum(d.size for _, d, _ in data))
    real[keep] = 1.0
    weights, nominal = jnp.asarray(penalty), jnp.asarray(robot.layout.nominal)
    return lambda xs: np.asarray(_misfits(structure, arms, values, jnp.asarray(xs), data,
                                          jnp.asarray(real), weights, nominal))


def _device_rows(rows: Rows) -> tuple[tuple, np.ndarray]:
    """Each arm's rows padded to their bucket, on the device, and where the real rows'
    residuals stand in the padded residual vector."""
    data, keep, start = [], [], 0
    for u, d, side in rows.values():
        size = kin.row_bucket(len(u))
        data.append(jax.tree_util.tree_map(jnp.asarray, kin.pad_rows((u, d, side), size)))
        keep.append(start + np.arange(np.asarray(d).size))
        start += size * np.asarray(d).shape[1]
    return tuple(data), np.concatenate(keep)


def _kept(a: jax.Array, keep: np.ndarray) -> jax.Array | np.ndarray:
    # on the host, unless traced (a derivative taken through the residuals)
    return a[keep] if isinstance(a, jax.core.Tracer) else np.asarray(a)[keep]


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
    """Per parameter, the weight (mm per unit) of its zero-centred penalty row: the lateral
    compliances' prior when ``lateral`` is fitted, else zero."""
    lateral = layout.group_mask(("lateral",)) if "lateral" in groups else np.zeros(
        len(layout.params), bool)
    return np.where(lateral, LATERAL_PRIOR_MM / layout.scales, 0.0)


POLISH_NFEV = 20  # exact-Jacobian steps after a fit with joints giving way under gravity


def with_gravity(rig: Rig, sag_steps: int = 1) -> kin.Robot:
    """The rig's robot with its gravity model on (equal each call, so the compiled programs,
    keyed by structure, are reused)."""
    gravity = np.zeros(3)
    gravity[: len(rig.gravity)] = rig.gravity  # a planar rig's gravity lies in its plane
    return replace(rig.robot, gravity=gravity, sag_steps=sag_steps)


def base_groups(robot: kin.Robot) -> tuple[str, ...]:
    """The geometric calibration a diagnosis and a plan start from: frames and geometry, and
    the command map's gains where a chain is commanded through one (its columns are not its
    joint values, as the planar arms' pulse widths): a servo's gain is as uncertain as a
    link's length (the paper's eight parameters), where an encoder reads the joint value.
    Without it a planar arm's geometric fit is 3x off (default rig: 3.6 mm at its train rows
    against 1.2) and every effect is scored against that error."""
    if robot.servo_mapped:
        return ("frames", "geometric", "servo")
    return ("frames", "geometric")


def calibrate(rig: Rig, groups: tuple[str, ...] = kin.GROUPS, progress=None,
              polish: bool = True, max_nfev: int = 300, start: np.ndarray | None = None,
              sag_steps: int = 1, masses: str = "fitted") -> Calibration:
    """Least squares over the parameter ``groups`` (frames always) on the rig's ``train`` rows.
    ``polish``: finish a sagging fit with the exact Jacobian (off: faster, a little short).
    ``max_nfev``: per stage. ``start``: a fit of fewer groups to start from. ``sag_steps``:
    times the sag's torques are taken (:attr:`Robot.sag_steps`). ``masses``: "fitted", or
    "description" (held at the URDF's ``<inertial>``, so each compliance is the joint's own
    and not its product with an unknown mass scale)."""
    t0 = time.perf_counter()
    unknown = [g for g in groups if g not in kin.ALL_GROUPS]
    if unknown:
        raise ValueError(f"unknown parameter group {unknown[0]!r}; choose from "
                         f"{', '.join(kin.ALL_GROUPS)}")
    groups = tuple(g for g in kin.ALL_GROUPS if g in set(groups) | {"frames"})
    sags = bool(set(kin.SAG_GROUPS) & set(groups))
    if sag_steps < 1:
        raise ValueError(f"sag_steps must be at least 1, not {sag_steps}")
    robot = with_gravity(rig, sag_steps) if sags else rig.robot
    cal = fit(robot, set_rows(rig, robot, "train"), groups, progress=progress, polish=polish,
              max_nfev=max_nfev, start=start, masses=masses)
    cal.errors = marker_errors(rig, robot, cal.x)
    if sags and polish:
        cal.extra = sag_convergence(rig, cal.x, sag_steps)
    cal.seconds = time.perf_counter() - t0
    return cal


def fit(robot: kin.Robot, rows: Rows, groups: tuple[str, ...],
        candidates: np.ndarray | None = None, progress=None, polish: bool = True,
        max_nfev: int = 300, start: np.ndarray | None = None, masses: str = "fitted",
        tol: float = 1e-10) -> Calibration:
    """:func:`calibrate`'s least squares on given rows (``errors`` left empty) of the
    parameters of ``groups`` (or the mask ``candidates``) the rank analysis keeps; without a
    ``start``, the frames first."""
    t0 = time.perf_counter()
    layout = robot.layout
    sags = robot.gravity is not None and bool(set(kin.SAG_GROUPS) & set(groups))
    full_res, full_jac, n_res, exact_jac = residual_function(robot, rows)
    x = layout.nominal.copy() if start is None else np.array(start, float)
    if x.shape != layout.nominal.shape:
        raise ValueError(f"start has {x.size} parameters; the robot has {layout.nominal.size}")
    if masses not in kin.MASS_SOURCES:
        raise ValueError(f"masses must be one of {kin.MASS_SOURCES}, not {masses!r}")
    if candidates is None:
        candidates = layout.group_mask(groups)
    if sags and masses == "fitted":
        # the links' masses and first moments sit in the compliance group's columns, but the
        # lateral compliances bend the joints under the same unknown torques: fitted without
        # joint compliance they would otherwise weigh the links at the layout's guess
        candidates = candidates | link_mask(layout)
    if masses == "description":
        if not sags:
            raise ValueError("masses 'description' holds the link masses of a fit in which "
                             "joints give way under gravity; add compliance, lateral or "
                             f"backlash to the groups ({', '.join(groups)})")
        candidates = candidates & ~described_links(robot, x)
    nfev = 0
    penalty = prior_penalty(layout, groups)

    def solve(mask: np.ndarray, x0: np.ndarray, exact: bool = False, max_nfev: int = max_nfev
              ) -> tuple[np.ndarray, int]:
        idx = np.flatnonzero(mask)

        def put(v):  # on the host: a scatter on the device cost a dispatch per evaluation
            x = np.array(x0, float)
            x[idx] = v
            return x

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
            res, x0[idx], jac=jac, x_scale=layout.scales[idx], method="trf", xtol=tol,
            ftol=tol, gtol=tol, max_nfev=max_nfev)
        return np.asarray(put(out.x)), int(out.nfev)

    # The frames first (a rough instrument pose is a large, nonlinear correction), then the
    # rank analysis at that point and the fit of everything it keeps.
    if start is None and "frames" in groups:
        frames = layout.group_mask(("frames",))
        frames_ident = identifiability(np.asarray(full_jac(jnp.asarray(x))), layout, frames)
        x, n = solve(frames_ident.free, x)
        nfev += n
        if progress:
            progress("frames fitted")
    ident = identifiability(np.asarray(full_jac(jnp.asarray(x))), layout, candidates)
    if int(ident.free.sum()) > n_res:
        raise ValueError(f"{ident.free.sum()} identifiable parameters but only {n_res} "
                         "measured coordinates in the train rows")
    # a start with compliances fitted already shows the masses: the second round alone
    seen = start is not None and any(np.any(x[sl] != 0) for key, sl in layout.slices.items()
                                     if key[1] in ("compliance", "lateral"))
    if groups != ("frames",) and not (sags and seen):
        x, n = solve(ident.free, x)
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
        x, n = solve(ident.free, x)
        nfev += n
        if "backlash" in groups and any(s and kin.APPROACH in s for *_, s in rows.values()):
            # the stick deflection shows only once a play is fitted: a third round frees it
            ident = identifiability(np.asarray(full_jac(jnp.asarray(x))), layout, candidates)
            x, n = solve(ident.free, x)
            nfev += n
        # The analytic Jacobian leaves out how the geometry moves the sag, so its fit stops a
        # little short (on the linked arm6 rig, train error 0.168 against 0.163 mm): a few
        # steps with the exact, slower Jacobian finish it.
        if polish:
            if progress:
                progress("polishing with the exact Jacobian")
            x, n = solve(ident.free, x, exact=True, max_nfev=POLISH_NFEV)
            nfev += n
    se = standard_errors(covariance(full_res, full_jac, x, ident.free, penalty), ident.free)
    return Calibration(robot, x, groups, ident, se, {}, nfev, time.perf_counter() - t0,
                       masses=masses)


def link_mask(layout: kin.ParamLayout) -> np.ndarray:
    mask = np.zeros(len(layout.params), bool)
    for key, sl in layout.slices.items():
        if key[1] == "links":
            mask[sl] = True
    return mask


def described_links(robot: kin.Robot, x: np.ndarray) -> np.ndarray:
    """Put every chain's described link masses and first moments into ``x`` (in place) and
    return their mask (P,); a chain whose description does not weigh every link is an error."""
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
    """``sag_next_step_mm``: how far one more step of the sag's torques moves a train marker
    at most, with a note when more than one step was asked for and the last still moves one
    by over SAG_CONVERGED_MM (one step is a first-order model: docs/robots.md)."""
    # the rig's gravity robots: equal to the fit's, so its compiled residuals serve here
    robot = with_gravity(rig, sag_steps)
    further = with_gravity(rig, sag_steps + 1)
    now, *_ = residual_function(robot, set_rows(rig, robot, "train"))
    nxt, *_ = residual_function(further, set_rows(rig, further, "train"))
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


def covariance(full_res, full_jac, x: np.ndarray, free: np.ndarray,
               penalty: np.ndarray | None = None) -> np.ndarray:
    """Gauss-Newton covariance (P, P), s^2 (J^T J)^-1 with the penalty rows' information
    added; zero where fixed, NaN on the free block when no degree of freedom is left."""
    r = np.asarray(full_res(jnp.asarray(x)))
    dof = r.size - int(free.sum())
    cov = np.zeros((len(x), len(x)))
    if dof <= 0:
        cov[np.ix_(free, free)] = np.nan
        return cov
    a = np.asarray(full_jac(jnp.asarray(x)))[:, free]
    if penalty is not None and penalty[free].any():
        a = np.vstack([a, np.diag(penalty[free])])
    # From the SVD of the column-scaled Jacobian, not by inverting J^T J: a planar arm's gain
    # columns are 1e5 times its length columns, and the inverse of J^T J (condition 5e14)
    # kept only three or four digits of the standard errors (2.5e-4 off on the default rig).
    norms = np.linalg.norm(a, axis=0)
    norms[norms == 0] = 1.0
    _, sv, vt = np.linalg.svd(a / norms, full_matrices=False)
    keep = sv > np.finfo(float).eps * max(a.shape) * (sv.max() if sv.size else 0.0)
    inv = (vt[keep].T / sv[keep] ** 2) @ vt[keep]
    cov[np.ix_(free, free)] = float(r @ r) / dof * inv / np.outer(norms, norms)
    return cov


def standard_errors(cov: np.ndarray, free: np.ndarray) -> np.ndarray:
    se = np.full(len(free), np.nan)
    se[free] = np.sqrt(np.clip(np.diag(cov)[free], 0, None))
    return se


@partial(jax.jit, static_argnames=("structure", "arms"))
def _misfits(structure: kin.RobotStructure, arms: tuple[str, ...], values: dict,
             xs: jax.Array, data: tuple, real: jax.Array, penalty: jax.Array,
             nominal: jax.Array) -> jax.Array:
    """The train rows' sum of squares at each parameter vector of xs (K, P), with the penalty
    rows :func:`fit` adds (``penalty`` times the distance from ``nominal``); ``real``: 1 at
    the real rows' residuals, 0 at their padding's."""
    robot = structure.robot(values)

    def one(x: jax.Array) -> jax.Array:
        r = _residuals(robot, arms, x, data) * real
        return r @ r + jnp.sum((penalty * (x - nominal)) ** 2)
    return jax.vmap(one)(xs)


CHECK_STEPS = 24  # bisection steps on log(width) in (1e-9, 1]: a width to 1.2e-6 of itself
CHECK_SLACK = 1.01  # 1% over s2 is kept: a width within half a percent of the linearised one


def parameter_covariance(rig: Rig, cal: Calibration) -> np.ndarray:
    """The calibrated parameters' :func:`covariance` on the train rows, checked against the
    rows along each of its axes (:func:`checked_covariance`). Prediction and design draws use
    it; the standard errors a calibration reports are :func:`covariance`'s."""
    robot, x, free = cal.robot, np.asarray(cal.x, float), cal.ident.free
    rows = set_rows(rig, robot, "train")
    full_res, full_jac, *_ = residual_function(robot, rows)
    penalty = prior_penalty(robot.layout, cal.groups)
    cov = covariance(full_res, full_jac, x, free, penalty)
    if not free.any() or not np.all(np.isfinite(cov)):
        return cov
    r = np.asarray(full_res(jnp.asarray(x)))
    s2 = float(r @ r) / (r.size - int(free.sum()))
    return checked_covariance(cov, free, x, np.asarray(robot.layout.scales, float), s2,
                              misfit_function(robot, rows, penalty))


def checked_covariance(cov: np.ndarray, free: np.ndarray, x: np.ndarray, scales: np.ndarray,
                       s2: float, misfit: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """``cov`` with each axis narrowed where the rows say it is too wide, never widened.

    The axes are its eigenvectors in units of the parameters' ``scales``, each a standard
    deviation's move m_k with sum m_k m_k^T = cov, so by the linearisation each m_k misfits
    the rows by s2 (``misfit``: sums of squares at parameter vectors (K, P), the first of
    which is ``x``). Where the rows' own misfit of +-m_k (mean of the two) exceeds s2, or is
    not finite, the axis is narrowed by bisection to a move that misfits by s2: the one-sigma
    point of the likelihood along the axis, the other axes held (a slice, not a profile,
    which would refit them). A weak combination of columns (an elbow offset against the next
    origin's z; a link's mass against its joint's compliance, whose product alone is seen)
    keeps a linearised width whose move misfits the rows by thousands of s2: draws along it
    landed metres away. The linearisation is the covariance's Jacobian, which for a sagging
    fit leaves out how the geometry moves the sag; the check is made with the exact rows."""
    f = np.flatnonzero(free)
    s = scales[f]
    w, u = np.linalg.eigh(cov[np.ix_(f, f)] / np.outer(s, s))
    moves = np.zeros((len(w), len(x)))
    moves[:, f] = (u * np.sqrt(np.clip(w, 0.0, None))).T * s

    def excess(alpha: np.ndarray, k: np.ndarray) -> np.ndarray:
        # padded to a power of two, so few batch shapes are ever compiled per structure
        pad = 1 << (len(k) - 1).bit_length()
        kk = np.concatenate([k, np.full(pad - len(k), k[0])])
        aa = np.concatenate([alpha, np.full(pad - len(k), alpha[0])])
        m = aa[:, None] * moves[kk]
        got = misfit(np.concatenate([x[None], x + m, x - m]))
        e = (got[1:].reshape(2, -1).mean(axis=0) - got[0])[: len(k)] / s2
        return np.where(np.isfinite(e), e, np.inf)  # a move the model cannot evaluate: too far

    alpha = np.ones(len(w))
    k = np.flatnonzero(excess(alpha, np.arange(len(w))) > CHECK_SLACK)
    if not k.size:
        return cov
    # the bisection keeps lo where the misfit is within s2 (at 1e-9 sd it is, to rounding)
    lo, hi = np.full(k.size, np.log(1e-9)), np.zeros(k.size)
    for _ in range(CHECK_STEPS):
        mid = (lo + hi) / 2
        over = excess(np.exp(mid), k) > 1.0
        hi = np.where(over, mid, hi)
        lo = np.where(over, lo, mid)
    alpha[k] = np.exp(lo)
    out = np.zeros_like(cov)
    narrowed = moves[:, f] * alpha[:, None]
    out[np.ix_(f, f)] = narrowed.T @ narrowed
    return out


def marker_errors(rig: Rig, robot: kin.Robot, x: np.ndarray) -> dict:
    errors = {}
    for s in SETS:
        dist = marker_distances(rig, robot, x, s)
        if dist:
            errors[s] = {a: _error_stats(d) for a, d in dist.items()}
            errors[s]["all"] = _error_stats(np.concatenate(list(dist.values())))
    return errors


def calibrated_rig_document(rig: Rig, cal: Calibration, urdf_name: str) -> dict:
    """rig.toml of the calibrated robot read from the URDF ``urdf_name`` (origins, offsets)
    plus the markers and instrument poses a URDF has no place for."""
    calibrated = cal.robot.with_values(cal.x)
    keys = kin.urdf.generated_arm_keys(calibrated)
    measured = calibrated.measured_arms()
    arms = {name: arm_table(c, urdf_name, keys[name], name in measured)
            for name, c in calibrated.chains.items()}
    return {"name": f"{rig.name}-calibrated", "gravity": list(rig.gravity), "arms": arms}


def arm_table(c: kin.Chain, urdf_name: str, keys: dict, measured: bool) -> dict:
    """One calibrated chain as a rig.toml arm read from ``urdf_name`` (``keys``: root, tip)."""
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
