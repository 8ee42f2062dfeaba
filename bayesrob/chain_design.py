"""The configuration designer's chain modules: URDF / DH arms, placed in 3-D (or in the plane).

A chain module is a root arm of a chain rig (its path is one chain, no torso under it),
calibrated on the rig's single-arm ``train`` rows with the calibration groups its design entry
names, with its joint-error population fitted as ``bayesrob predict`` does
(:mod:`bayesrob.predict.draws`). Mounting it moves its robot base (the root's instrument
position) to the mount point and keeps its orientation, so gravity acts on it as it did while
it was calibrated. A world target t is then the point t - mount + base of the module's own
frame: it is aimed (position-only inverse kinematics from its nearest train pose, as
``predict.aiming.aim`` aims) and drawn there, and the draws are moved back.

A candidate's draws are builds, as in the plane: each carries one set of calibration errors
(the rig's parameter covariance; modules of one rig share a set) and one set of joint
stiffnesses (the rig's ``stiffness`` or the log-normal prior, linked arms of one rig centred on
their fitted sags as ``bayesrob predict`` centres them), the same at every target.
A placement's free-point draws do not depend on the other arms of the candidate, so each
worker draws them once per (module, mount) and every candidate that uses the placement reuses
them (common random numbers also make the ranking less noisy); linked arms then balance
(:func:`bayesrob.predict.draws.equilibrium`, with the tracker's noise put back).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from bayesrob import kinematics as kin
from bayesrob.design_file import DesignError, DesignSpec, ModuleSpec
from bayesrob.latent_errors import joint_jacobian
from bayesrob.predict.aiming import aim
from bayesrob.predict.draws import CalibratedModules, free_draws, parameter_draws
from bayesrob.predict.fusion import equilibrium
from bayesrob.predict.stiffness import StiffnessPrior, sag_scaled_priors, stiffness_draws
from bayesrob.rig import Rig, RigError

__all__ = ["ChainModule", "load_chain_modules", "chain_reach_table", "linked_priors",
           "chain_stiffness_record", "chain_candidate_draws", "write_chain_candidate_rig"]


@dataclass
class ChainModule:
    """A calibrated chain module, ready to be mounted anywhere."""

    name: str
    arm: str  # the arm of its rig
    rig: Rig  # its rig: the train poses aiming starts from
    mods: CalibratedModules  # its rig's calibration and this module's joint-error population
    base: np.ndarray  # (dim,) its robot base in its rig's instrument frame (calibrated)
    rig_index: int  # modules of one rig share its calibration errors in every draw
    model: str

    @property
    def dim(self) -> int:
        return self.mods.robot.dim

    def local(self, points: np.ndarray, mount: Sequence[float]) -> np.ndarray:
        """World points as seen from the module's own frame when its base is at ``mount``."""
        return np.asarray(points, float) - np.asarray(mount, float) + self.base


def load_chain_modules(design: DesignSpec, rigs: dict[Path, Rig],
                       by_rig: dict[Path, list[ModuleSpec]]) -> dict[str, ChainModule]:
    """Calibrate each chain rig once (the groups its modules name) and fit each module's
    joint-error population on its own train rows (``by_rig``: the modules of each rig)."""
    from bayesrob.calibration import calibrate_chain, chain_parameter_covariance
    from bayesrob.latent_errors import check_latent_model, fit_latent_errors
    from bayesrob.predict.stiffness import stiffness_prior

    out: dict[str, ChainModule] = {}
    for index, (rig_dir, specs) in enumerate(by_rig.items()):
        rig = rigs[rig_dir]
        groups = {m.params for m in specs}
        masses = {m.masses for m in specs}
        if len(groups) > 1 or len(masses) > 1:
            raise DesignError(f"{design.path}: modules {', '.join(m.name for m in specs)} "
                              f"share rig {rig_dir} but name different "
                              f"{'params' if len(groups) > 1 else 'masses'}; a rig is "
                              "calibrated once")
        for m in specs:
            where = f"{design.path}: [modules.{m.name}]"
            if m.arm not in rig.robot.measured_arms():
                raise DesignError(f"{where}: unknown module arm {m.arm!r} in {rig_dir} "
                                  f"(measured arms: {', '.join(rig.robot.measured_arms())})")
            path = rig.robot.path(m.arm)
            if len(path) > 1:
                raise DesignError(f"{where}: arm {m.arm!r} hangs on {path[-2].name!r}; the "
                                  "designer mounts whole root arms (no arm under them) so far")
            try:
                check_latent_model(m.model)
            except (RigError, ValueError) as e:
                raise DesignError(f"{where}: {e}") from None
            if rig.robot.dim != design.dim:
                raise DesignError(f"{where}: {rig_dir} measures {rig.robot.dim}-D points but "
                                  f"the mounts and the task are {design.dim}-D")
        try:
            cal = calibrate_chain(rig, groups.pop() or kin.GROUPS, masses=masses.pop())
        except ValueError as e:
            raise DesignError(f"{design.path}: {rig_dir}: {e}") from None
        n_free = int(cal.ident.free.sum())
        cov = chain_parameter_covariance(rig, cal)
        for i, m in enumerate(specs):
            errors = fit_latent_errors(rig, cal.robot, cal.x, m.arm, m.model, n_free,
                                       seed=design.seed + i)
            mods = CalibratedModules(cal, {m.arm: errors},
                                     {m.arm: stiffness_prior(rig, m.arm, cal)}, cov)
            base = np.asarray(cal.robot.instrument_pose(jnp.asarray(cal.x), m.arm))[:3, 3]
            out[m.name] = ChainModule(m.name, m.arm, rig, mods, base[: rig.robot.dim],
                                      index, m.model)
    return out


def chain_reach_table(modules: dict[str, ChainModule], mounts: np.ndarray, targets: np.ndarray
                      ) -> dict[tuple[str, int], np.ndarray]:
    """{(module, mount index): joint columns (T, c)} for every placement whose calibrated
    model reaches every target (within the inverse kinematics' tolerance)."""
    out = {}
    for name, m in modules.items():
        for j, mount in enumerate(mounts):
            try:
                out[name, j] = aim(m.rig, m.mods.robot, m.mods.x, m.arm,
                                         m.local(targets, mount))
            except RigError:
                continue
    return out


def _order(job: Any, name: str) -> int:
    """A module's place in the inventory: its seeds derive from it, so a module draws the
    same numbers in every candidate it is in (common random numbers)."""
    return list(job.modules).index(name)


def _placement(job: Any, name: str, mount: int) -> tuple[np.ndarray, jax.Array]:
    """A placement's free-point draws (S, T, dim) in the world and its joint Jacobian
    (T, dim, n), drawn once per worker (``job.cache``) from seeds of its own."""
    key = ("placement", name, mount)
    if key not in job.cache:
        m: ChainModule = job.modules[name]
        u = job.reach[name, mount]
        xs = _rig_parameters(job, m)
        k = jax.random.fold_in(jax.random.PRNGKey(job.seed), 1000 * _order(job, name) + mount)
        local = free_draws(m.mods, m.arm, u, xs, k)
        jac = joint_jacobian(m.mods.robot, jnp.asarray(m.mods.x), m.arm, jnp.asarray(u))
        world = local - m.base + np.asarray(job.mounts[mount], float)
        job.cache[key] = (world, jac)
    return job.cache[key]


def _rig_parameters(job: Any, m: ChainModule) -> jax.Array:
    """Parameter draws (S, P) of a module's rig, once per worker: every placement of every
    module of that rig builds on the same calibration errors."""
    key = ("parameters", m.rig_index)
    if key not in job.cache:
        job.cache[key] = parameter_draws(
            m.mods, jax.random.PRNGKey(job.seed * 7919 + m.rig_index), job.draws)
    return job.cache[key]


def linked_priors(modules: Sequence[ChainModule]) -> list[StiffnessPrior]:
    """The linked modules' log joint stiffness priors, as ``bayesrob predict`` links arms of
    one rig: where the modules are distinct arms of one rig and each took the prior, their arm
    terms are centred on their fitted sags
    (:func:`bayesrob.predict.draws.sag_scaled_priors`); else each module's own. Modules
    of different rigs keep their own, as their sags come from different calibrations. Like
    ``predict``, it takes arms with paths of equal joint counts to be of one model (alike
    first moments): that is what lets a sag stand for a stiffness."""
    own = [m.mods.stiffness[m.arm] for m in modules]
    arms = {m.arm for m in modules}
    if len({m.rig_index for m in modules}) > 1 or len(arms) < len(modules):
        return own
    first = modules[0]
    # the rig's arm order, not the candidate's: the sags pool the arms' poses, and a sum in
    # another order could move a centre in its last bit between (a, b) and (b, a)
    ordered = [a for a in first.rig.robot.measured_arms() if a in arms]
    by_arm = {m.arm: m for m in modules}
    scaled = sag_scaled_priors(first.rig, first.mods.calibration,
                               {a: by_arm[a].mods.stiffness[a] for a in ordered})
    return [scaled[m.arm] for m in modules]


def _candidate_priors(job: Any, names: Sequence[str]) -> list[StiffnessPrior]:
    """:func:`linked_priors` of a candidate's modules, once per worker."""
    key = ("priors", tuple(names))
    if key not in job.cache:
        job.cache[key] = linked_priors([job.modules[n] for n in names])
    return job.cache[key]


def chain_stiffness_record(job: Any, names: Sequence[str]) -> list[dict[str, Any]]:
    """What a linked candidate's balance drew each module's joint stiffnesses from, in
    ``names``' order, for ``design.json``: the record ``predict``'s JSON gives per arm
    (:meth:`predict.stiffness.StiffnessPrior.record`)."""
    return [p.record() for p in _candidate_priors(job, names)]


def _log_stiffness(job: Any, names: Sequence[str]) -> list[jax.Array]:
    """Linked modules' joint log stiffnesses, each (S, n). Each module draws its standard
    normals from its own seed, the same in every candidate it is in (common random numbers);
    the candidate's arms then set their centres and sds (:func:`linked_priors`)."""
    key = ("stiffness", tuple(names))
    if key not in job.cache:
        priors = _candidate_priors(job, names)
        job.cache[key] = [
            stiffness_draws([p], jax.random.PRNGKey(job.seed * 104729 + _order(job, n)),
                            job.draws)[0]
            for n, p in zip(names, priors, strict=True)]
    return job.cache[key]


def chain_candidate_draws(job: Any, arms: Sequence[str], mounts: Sequence[int],
                          index: int) -> np.ndarray:
    """Draws (S, T, dim) of a chain candidate's end point: one arm's free point, or linked
    arms' balance with the tracker's noise put back."""
    parts = [_placement(job, a, j) for a, j in zip(arms, mounts, strict=True)]
    if len(parts) == 1:
        return parts[0][0]
    d = equilibrium([p[0] for p in parts], [p[1] for p in parts],
                          _log_stiffness(job, arms),
                          tracker_noise_mm=job.tracker_noise_mm,
                          key=jax.random.fold_in(jax.random.PRNGKey(job.seed + 1), index))
    return np.asarray(d)


def write_chain_candidate_rig(candidate: dict, targets: np.ndarray,
                              modules: dict[str, ChainModule], mounts: np.ndarray,
                              reach: dict[tuple[str, int], np.ndarray], out: Path) -> None:
    """The candidate as a chain rig directory: each module's calibrated URDF
    (``<module>.urdf``), rig.toml with its instrument pose at the mount (orientation kept),
    and measurements.csv with the planned linked rows (targets and joint columns, x, y, z
    empty) for ``bayesrob collect`` or a simulator to fill."""
    import csv

    from bayesrob.calibration import chain_arm_table
    from bayesrob.rig import MEASUREMENTS_FILE, RIG_FILE, dump_toml

    names = candidate["arms"]
    first = modules[names[0]]
    gravity = first.rig.gravity
    arms_doc = {}
    for a, j in zip(names, candidate["mounts"], strict=True):
        m = modules[a]
        calibrated = m.mods.robot.with_values(m.mods.x)
        chain = calibrated.chains[m.arm]
        alone = kin.Robot({m.arm: chain}, calibrated.dim, calibrated.gravity,
                           calibrated.sag_steps)
        urdf = out / f"{a}.urdf"
        kin.write_urdf(alone, alone.layout.nominal, urdf, name=a)
        table = chain_arm_table(chain, urdf.name, kin.urdf.generated_arm_keys(alone)[m.arm],
                                measured=True)
        pose = np.asarray(table["instrument"], float)
        pose[: m.dim] = np.asarray(mounts[j], float)
        table["instrument"] = [float(v) for v in pose]
        arms_doc[a] = table
    doc = {"name": f"design-{candidate['config']}", "gravity": [float(v) for v in gravity],
           "arms": arms_doc}
    (out / RIG_FILE).write_text(dump_toml(doc))
    axes = "xyz"[: first.dim]
    cols = [f"{a}_u{k + 1}" for a in names
            for k in range(modules[a].mods.robot.chains[modules[a].arm].n_columns)]
    with (out / MEASUREMENTS_FILE).open("w", newline="") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(["config", "set", *(f"target_{c}" for c in axes), *cols, *axes])
        for i, t in enumerate(targets):
            u = [f"{v:.10g}" for a, j in zip(names, candidate["mounts"], strict=True)
                 for v in reach[a, j][i]]
            w.writerow(["+".join(names), "test", *(f"{v:.4f}" for v in t), *u,
                        *([""] * len(axes))])
