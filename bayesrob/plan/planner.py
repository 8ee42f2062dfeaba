"""``bayesrob plan``: choose the poses to measure next, and write them as ``poses.csv``: the
calibration linearised at the nominal robot (compliances at one typical size, so gravity's
effects show their signature), candidates scored by :mod:`.criteria`, picked greedily.
"""

from __future__ import annotations

import csv
import io
import os
import time
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from bayesrob import robot as kin
from bayesrob.calibrate.least_squares import base_groups, link_mask, with_gravity
from bayesrob.data.rig import Measurements, Rig, RigError, parse_number
from bayesrob.data.vocabulary import CHAIN_EFFECTS, GROUPS
from bayesrob.plan.criteria import PRIOR_SD, Accuracy, Discriminate, Identify
from bayesrob.plan.greedy import Selection, greedy
from bayesrob.plan.pool import Pool, command_limits, read_pool, read_text, sample_pool
from bayesrob.predict.aiming import aim
from bayesrob.robot.effects import resolve_effects

DEFAULT_SAMPLES = 2000
DEFAULT_NOISE_MM = 0.1
SOFT_GROUPS = ("compliance", "lateral")  # linearised at one typical size, not at zero
# prior sd (typical sizes) of the sag groups a calibration leaves out, for ``accuracy``: none
# by default (on the simulated arm6 tuning seeds, which do not sag, any bias term cost accuracy)
OMITTED_SD = 0.0


@partial(jax.jit, static_argnames=("structure", "arm"))
def _jacobian_program(structure: kin.RobotStructure, arm: str, values: dict, x: jax.Array,
                      u: jax.Array, side: dict | None) -> jax.Array:
    return structure.robot(values).marker_jacobian(x, arm, u, side)


# rows per call of the compiled Jacobian: one program serves pools and rigs of any size
CHUNK = 512


def pose_jacobians(robot: kin.Robot, x: np.ndarray, pool: Pool) -> np.ndarray:
    """d marker / d parameters (N, dim, P) at every pose of ``pool``."""
    out = np.zeros((len(pool), robot.dim, len(x)))
    for arm in dict.fromkeys(pool.config.tolist()):
        rows = np.flatnonzero(pool.config == arm)
        side = pool.side(robot, arm, rows)
        u = pool.columns(robot, arm, rows)
        for start in range(0, len(rows), CHUNK):
            part = np.arange(start, min(start + CHUNK, len(rows)))
            pad = np.concatenate([part, np.full(CHUNK - len(part), part[-1])])
            jac = _jacobian_program(
                robot.structure, arm, robot.nominal_values, jnp.asarray(x),
                jnp.asarray(u[pad]),
                None if side is None else {b: jnp.asarray(v[pad]) for b, v in side.items()})
            out[rows[part]] = np.asarray(jac)[: len(part)]
    return out


def measured_pool(rig: Rig, set: str = "train") -> Pool:
    """A rig's rows of one set as a pool (the poses measured already, or a task region)."""
    meas = rig.measurements
    m = meas.set == set
    return Pool(meas.config[m], {c: u[m] for c, u in meas.commands.items()}, [], [], set)


@dataclass
class Plan:
    """The planned poses (pool rows, best first) and what the criterion predicts of them."""

    criterion: str
    groups: tuple[str, ...]
    pool: Pool
    selection: Selection
    unit: str
    noise_mm: float
    n_measured: int
    seconds: float
    effects: list[str] = field(default_factory=list)
    omitted: tuple[str, ...] = ()  # groups whose bias ``accuracy`` weighs, prior sd below
    omitted_sd: float = 0.0
    prior_sd: float = PRIOR_SD

    @property
    def before(self) -> float:
        return self.selection.before

    @property
    def after(self) -> float:
        return float(self.selection.values[-1])

    def to_dict(self) -> dict:
        return {"criterion": self.criterion, "params": list(self.groups),
                "effects": self.effects, "n": len(self.selection.order),
                "pool": self.pool.source, "pool_size": len(self.pool),
                "n_measured": self.n_measured, "noise_mm": self.noise_mm, "unit": self.unit,
                "before": self.before, "after": self.after,
                "values": self.selection.values.tolist(),
                "gains": self.selection.gains.tolist(), "seconds": self.seconds,
                "omitted": list(self.omitted), "omitted_sd": self.omitted_sd,
                "prior_sd": self.prior_sd}


def resolve_groups(rig: Rig, groups: tuple[str, ...] | None, criterion: str
                   ) -> tuple[tuple[str, ...], list[str]]:
    """The groups the planned calibration fits (frames always) and, for ``discriminate``,
    the candidate effects beside them (every chain effect the base does not fit)."""
    # without groups, discriminate separates the diagnosis's rivals beside its base model
    base = (tuple(groups) if groups else
            base_groups(rig.robot) if criterion == "discriminate" else GROUPS)
    effects = ([e for e in resolve_effects(None, chain=True, robot=rig.robot)
                if CHAIN_EFFECTS[e] not in base] if criterion == "discriminate" else [])
    fitted = {"frames", *base, *(CHAIN_EFFECTS[e] for e in effects)}
    return tuple(g for g in kin.ALL_GROUPS if g in fitted), effects


def _linearisation(rig: Rig, groups: tuple[str, ...], omitted: tuple[str, ...]
                   ) -> tuple[kin.Robot, np.ndarray, np.ndarray, np.ndarray]:
    sags = bool(set(kin.SAG_GROUPS) & set(groups))
    robot = with_gravity(rig) if sags or omitted else rig.robot
    layout = robot.layout
    x = layout.nominal.copy()
    soft = layout.group_mask(tuple(g for g in SOFT_GROUPS if g in groups + omitted))
    x[soft] += layout.scales[soft]
    free = layout.group_mask(groups)
    if sags:
        free |= link_mask(layout)
    return robot, x, free, layout.group_mask(omitted) & ~free


def _task_pool(path: str | Path, rig: Rig, pool: Pool, robot: kin.Robot, x: np.ndarray,
               limits: dict) -> Pool:
    """A task file: poses (command columns) or targets (``x,y[,z]``) aimed at from the pool's
    nearest poses (refused in one line where none reaches)."""
    path = Path(path)
    text = read_text(path, "task")
    header = [h.strip() for h in next(csv.reader(io.StringIO(text)), [])]
    axes = "xyz"[:robot.dim]
    if not all(a in header for a in axes):
        return read_pool(path, rig, limits, "task", text)
    measured = robot.measured_arms()
    rows = [r for r in csv.DictReader(io.StringIO(text)) if any((v or "").strip()
                                                                 for v in r.values())]
    if not rows:
        raise RigError(f"{path}: no rows in the task file")
    targets = np.array([[parse_number(r[a] or "", f"{path}: line {i + 2}", a) for a in axes]
                        for i, r in enumerate(rows)])
    config = np.array([(r.get("config") or measured[0]).strip() for r in rows])
    # the pool as a rig whose train rows are the pool's poses at their nominal end points:
    # the aim starts from the nearest and stays inside the pool's range of commands
    seen = np.concatenate([np.asarray(robot.compiled_points(a)(
        jnp.asarray(x), pool.columns(robot, a, pool.config == a)))
        if (pool.config == a).any() else np.zeros((0, robot.dim)) for a in measured])
    cfg = np.concatenate([pool.config[pool.config == a] for a in measured])
    cmds = {c: np.concatenate([pool.commands[c][pool.config == a] for a in measured])
            for c in pool.commands}
    pool_rig = Rig(rig.name, rig.arms, Measurements(cfg, np.full(len(cfg), "train"),
                                                    np.full_like(seen, np.nan), cmds, seen,
                                                    np.arange(len(cfg))), robot=robot)
    commands = {c: np.full((len(rows), ch.n_columns), np.nan) for c, ch in robot.chains.items()}
    for arm in dict.fromkeys(config.tolist()):
        if arm not in measured:
            raise RigError(f"{path}: column 'config' = {arm!r} is not a measured arm of the "
                           f"rig ({', '.join(measured)})")
        if not (pool.config == arm).any():
            raise RigError(f"{path}: arm {arm!r} has no pose in the pool to aim from")
        m = config == arm
        try:
            u = aim(pool_rig, robot, x, arm, targets[m])
        except (RigError, ValueError) as exc:
            raise RigError(f"{path}: {exc}") from None
        col = 0
        for c in robot.path(arm):
            commands[c.name][m] = u[:, col:col + c.n_columns]
            col += c.n_columns
        # the rest of the pose (what the other arms weigh) as the nearest pool pose has it
        near = np.flatnonzero(pool.config == arm)[np.argmin(np.linalg.norm(
            pool.columns(robot, arm, pool.config == arm)[None] - u[:, None], axis=-1), axis=1)]
        for c in pool.commands:
            if np.isnan(commands[c][m]).all():
                commands[c][m] = pool.commands[c][near]
    return Pool(config, commands, [], [], str(path))


def plan_poses(rig: Rig, n: int, *, criterion: str = "accuracy",
               groups: tuple[str, ...] | None = None, pool: str | Path | None = None,
               samples: int | None = None, task: str | Path | None = None, seed: int = 0,
               noise_mm: float = DEFAULT_NOISE_MM, omitted_sd: float = OMITTED_SD,
               prior_sd: float = PRIOR_SD) -> Plan:
    """Choose ``n`` poses for ``rig``; bad input is a one-line RigError. ``omitted_sd``, and
    ``prior_sd`` (about nominal): prior sds in typical sizes of the sag groups left out (whose
    bias ``accuracy`` adds; 0: none) and of the fitted parameters."""
    t0 = time.perf_counter()
    if criterion not in ("accuracy", "identify", "discriminate"):
        raise RigError(f"unknown criterion {criterion!r} (accuracy, identify, discriminate)")
    if n < 1:
        raise RigError(f"--n must be at least 1, not {n}")
    if prior_sd <= 0:
        raise RigError(f"--prior-sd must be positive, not {prior_sd:g}")
    groups, effects = resolve_groups(rig, groups, criterion)
    limits = command_limits(rig)
    cands = (read_pool(pool, rig, limits) if pool is not None else
             sample_pool(rig, limits, samples or DEFAULT_SAMPLES, np.random.default_rng(seed)))
    if n > len(cands):
        raise RigError(f"--n {n} is more poses than the pool's {len(cands)} ({cands.source})")
    omitted = (tuple(g for g in SOFT_GROUPS if g not in groups)
               if criterion == "accuracy" and omitted_sd > 0 else ())
    robot, x, free, nuisance = _linearisation(rig, groups, omitted)
    scale = robot.layout.scales
    cols = free | nuisance

    def jac(p: Pool) -> np.ndarray:
        return pose_jacobians(robot, x, p)[:, :, cols] * scale[cols]

    measured = measured_pool(rig)
    j_meas = jac(measured) if len(measured) else np.zeros((0, robot.dim, int(cols.sum())))
    j_cand = jac(cands)
    j_task = (jac(_task_pool(task, rig, cands, robot, x, limits))
              if task is not None and criterion == "accuracy" else j_cand)
    # parameters no row here moves (another arm's, a mass no compliance shows) keep their
    # prior whatever is measured: left out, they cost the greedy steps nothing
    seen = np.zeros(int(cols.sum()), bool)
    for j in (j_meas, j_cand, j_task):
        seen |= np.abs(j).max(axis=(0, 1), initial=0.0) > 0
    fit, omit = seen & free[cols], seen & nuisance[cols]
    (j_meas, k_meas), (j_cand, k_cand), (j_task, k_task) = (
        (j[:, :, fit], j[:, :, omit]) for j in (j_meas, j_cand, j_task))
    free[np.flatnonzero(cols)[~fit]] = False
    info = np.eye(int(free.sum())) / prior_sd**2
    if len(measured):
        j0 = j_meas.reshape(-1, int(free.sum())) / noise_mm
        info += j0.T @ j0
    if criterion == "accuracy":
        crit = Accuracy(np.einsum("ndp,ndq->pq", j_task, j_task) / len(j_task))
        if omit.any():
            crit.omitted, crit.sd = k_cand / noise_mm, omitted_sd
            crit.cross = np.einsum("ndp,ndq->pq", j_task, k_task) / len(j_task)
            crit.e0 = float(np.sum(k_task**2)) / len(j_task)
            crit.measured = np.einsum("ndp,ndq->pq", j_meas, k_meas) / noise_mm**2
    elif criterion == "identify":
        crit = Identify()
    else:
        names = np.array([p.group for p in robot.layout.params])[free]
        crit = Discriminate({e: np.flatnonzero(names == CHAIN_EFFECTS[e]) for e in effects
                             if (names == CHAIN_EFFECTS[e]).any()})
        if not crit.effects:
            raise RigError("discriminate: no candidate effect beside the groups "
                           f"{', '.join(groups)}")
    sel = greedy(j_cand / noise_mm, info, n, crit)
    return Plan(criterion, groups, cands, sel, crit.unit, noise_mm, len(measured),
                time.perf_counter() - t0, effects, omitted if omit.any() else (),
                omitted_sd if omit.any() else 0.0, prior_sd)


def write_poses(plan: Plan, path: str | Path) -> Path:
    """``poses.csv``: config, set (train), the command columns as the pool wrote them, the
    pool's other columns, and each pose's gain; written whole or not at all."""
    pool = plan.pool
    header = ["config", "set", *[h for h in pool.header if h not in ("config", "set", "gain")],
              "gain"]
    idx = {h: i for i, h in enumerate(pool.header)}
    lines = [header]
    for k, g in zip(plan.selection.order, plan.selection.gains, strict=True):
        row = pool.cells[k]
        lines.append([str(pool.config[k]), "train", *[row[idx[h]] for h in header[2:-1]],
                      f"{g:.6g}"])
    path = Path(path)
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerows(lines)
    path.parent.mkdir(parents=True, exist_ok=True)  # the output-path check allowed it
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(buf.getvalue())
    os.replace(tmp, path)
    return path
