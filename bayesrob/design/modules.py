"""The designer's modules: calibrated arms of any rig, mounted anywhere, aimed and drawn.

A module is a rig's arm calibrated once on its single-arm ``train`` rows, with its joint-error
model picked as ``bayesrob predict`` picks it. Mounting moves its calibrated base and keeps
its orientation, so gravity acts as it did in calibration. The search asks every module the
same: ``aim(targets, mount)`` (commands, or None out of reach), ``draws`` (S, T, dim) of a
candidate's end point, each draw **one build**, ``sketch`` and ``write_rig``. The paper's
planar arms are :class:`PaperModule` (closed forms, the exact grid); every other robot is a
:class:`CalibratedModule`. A design places one kind.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp
import numpy as np

from bayesrob import robot as kin
from bayesrob.data.rig import ArmSpec, Rig, RigError
from bayesrob.design.file import DesignError, DesignSpec, ModuleSpec
from bayesrob.errors.distributions import error_arrays, error_kind, is_sampleable
from bayesrob.errors.latent_errors import joint_jacobian
from bayesrob.errors.noise_models import FittedNoiseModel
from bayesrob.predict.aiming import aim
from bayesrob.predict.draws import (
    CalibratedModules,
    check_module_arms,
    fit_joint_errors,
    free_draws,
    parameter_draws,
)
from bayesrob.predict.fusion import (
    equilibrium,
    equilibrium_program_draws,
    fused_posterior,
    static_stiffness,
)
from bayesrob.predict.stiffness import StiffnessPrior, sag_scaled_priors, stiffness_draws

if TYPE_CHECKING:
    from bayesrob.sim.truth import ArmTruth, Truth

__all__ = ["Module", "PaperModule", "CalibratedModule", "load_modules", "linked_priors",
           "stiffness_record", "mounted_truth", "COV_JITTER"]

# Keeps a parameter covariance with an unidentified direction sampleable, relative to each
# parameter: an absolute 1e-12 added 1.5 mrad of gain noise at 1500 us and widened every
# prediction (tuning inventories 1-4: q95 ratios 1.43-1.76 with it, 1.28-1.44 without).
COV_JITTER = 1e-9


def load_modules(design: DesignSpec, models_dir: Any = None) -> dict[str, Module]:
    """Calibrate each module's arm on its rig's train rows and fit its joint-error model."""
    from bayesrob.data.rig import load_rig

    by_rig: dict[Path, list[ModuleSpec]] = {}
    for m in design.modules.values():
        by_rig.setdefault(m.rig, []).append(m)
    rigs = {}
    for rig_dir, mods in by_rig.items():
        try:
            rigs[rig_dir] = load_rig(rig_dir)
        except RigError as e:
            raise DesignError(f"{design.path}: [modules.{mods[0].name}]: {e}") from None
    # the paper's planar arms take their closed-form specialisation; the joint-error model is
    # the rule's in both (fit_joint_errors, and the paper's kernel models)
    kinds = {n: CalibratedModule if rigs[m.rig].is_chain else PaperModule
             for n, m in design.modules.items()}
    if len(set(kinds.values())) > 1:
        chain = next(n for n, k in kinds.items() if k is CalibratedModule)
        flat = next(n for n, k in kinds.items() if k is PaperModule)
        raise DesignError(f"{design.path}: module {chain!r} is a URDF/DH arm and {flat!r} a "
                          "planar arm; a design places one kind")
    return next(iter(kinds.values())).load(design, rigs, by_rig, models_dir)


def _fail(design: DesignSpec, m: ModuleSpec, message: str) -> DesignError:
    return DesignError(f"{design.path}: [modules.{m.name}]: {message}")


@dataclass
class PaperModule:
    """A planar arm of the paper: its model a density of the joint errors its rows observe
    (J^-1 r), calibrated by its eight parameters, drawn by the equilibrium program or grid."""

    name: str
    arm: kin.Arm  # calibrated, at the base it was calibrated at
    fitted: FittedNoiseModel
    spec: ArmSpec  # the calibrated values as a rig.toml arm (for the planned rig)
    gravity: tuple[float, float]
    param_cov: np.ndarray  # (8, 8) the calibration's parameter covariance
    truth_rig: Truth | None = None  # simulated modules: their rig's physics, for the proof
    # the joint-error model was fitted with the tracker's noise taken out of its rows
    tracker_removed: bool = False

    @property
    def model(self) -> str:
        return self.fitted.spec.name

    @property
    def truth(self) -> ArmTruth | None:
        return self.truth_rig.arms.get(self.arm.name) if self.truth_rig else None

    def at(self, base: Sequence[float]) -> kin.Arm:
        return replace(self.arm, name=self.name,
                       params=self.arm.params._replace(base=jnp.asarray(base, jnp.float64)))

    def aim(self, targets: np.ndarray, mount: Sequence[float]) -> np.ndarray | None:
        """Pulses (T, 2) aiming the module on ``mount`` at every target, or None when one is
        out of its reach, off its elbow branch or outside its pulse limits."""
        arm = self.at(mount)
        if not bool(np.all(np.asarray(arm.reachable(jnp.asarray(targets))))):
            return None
        u = np.asarray(arm.command(jnp.asarray(targets)))
        lim = np.asarray(arm.pulse_limits)
        if not np.all((u >= lim[:, 0]) & (u <= lim[:, 1])):
            return None
        return u

    def sketch(self, mount: Sequence[float], target: np.ndarray) -> np.ndarray:
        """Base, elbow and end point aimed at ``target``."""
        arm = self.at(mount)
        elbow = np.asarray(kin.elbow_point(arm.params, arm.inverse(jnp.asarray(target))))
        return np.array([np.asarray(mount, float), elbow, np.asarray(target, float)])

    @classmethod
    def load(cls, design: DesignSpec, rigs: dict[Path, Rig],
             by_rig: dict[Path, list[ModuleSpec]], models_dir: Any) -> dict[str, PaperModule]:
        from bayesrob.calibrate.arms import arm_covariance, calibrate_arms
        from bayesrob.errors.noise_models import (
            discover_models,
            joint_errors,
            without_tracker_noise,
        )
        from bayesrob.sim.truth import TRUTH_FILE, Truth

        if design.dim != 2:
            raise DesignError(f"{design.path}: the mounts are 3-D points but the modules are "
                              "planar arms; give [x, y] mounts and a box of the plane")
        for m in design.modules.values():
            if m.params is not None:  # a planar arm's eight parameters are always fitted
                raise _fail(design, m, "params names calibration groups of URDF/DH arms; a "
                            "planar arm fits its eight parameters")
            if m.masses != "fitted":
                raise _fail(design, m, "masses is for URDF arms calibrated with compliance; a "
                            "planar arm has no link masses")
        out: dict[str, PaperModule] = {}
        specs: dict[str, list] = {}  # model name -> its discovered file, read once
        for rig_dir, mods in by_rig.items():
            rig = rigs[rig_dir]
            for m in mods:
                if m.arm not in rig.arms:
                    raise _fail(design, m, f"unknown module arm {m.arm!r} in {rig_dir} "
                                f"(arms: {', '.join(rig.arms)})")
            cal = calibrate_arms(rig)
            truth = (Truth.from_toml(rig_dir / TRUTH_FILE) if (rig_dir / TRUTH_FILE).is_file()
                     else None)
            for m in mods:
                if m.model not in specs:
                    try:  # a name no file has is a ModelFileError, a ValueError
                        specs[m.model] = discover_models(models_dir, [m.model])
                    except ValueError as e:
                        raise _fail(design, m, str(e)) from None
                arm = cal[m.arm].arm
                u, d = rig.rows(m.arm, "train")
                errors = joint_errors(arm, u, d)
                spec = specs[m.model][0]
                # equilibrium draws add the tracker's noise to the measured point: the density
                # is then of the joints' own errors (the grid's product, and a model that
                # cannot draw, which goes to the grid, keep the paper's rows)
                removed = design.tracker_noise_mm > 0 and design.fusion == "equilibrium"
                fitted = spec.fit(without_tracker_noise(arm, u, errors, design.tracker_noise_mm)
                                  if removed else errors, u)
                if removed and not is_sampleable(fitted):
                    removed = False
                    fitted = spec.fit(errors, u)
                p = arm.params
                orig = rig.arms[m.arm]
                cspec = ArmSpec(m.name, *(tuple(float(v) for v in np.asarray(x))
                                          for x in (p.base, p.links, p.gain, p.offset)),
                                orig.elbow, orig.pulse_limits, orig.stiffness)
                cov = arm_covariance(np.asarray(arm.params.to_vector()), u, d)
                out[m.name] = cls(m.name, arm, fitted, cspec, tuple(rig.gravity),
                                  cov + COV_JITTER * np.diag(np.diag(cov)), truth, removed)
        return out

    @staticmethod
    def draws(job: Any, arms: Sequence[str], mounts: Sequence[int], index: int
              ) -> tuple[np.ndarray, dict]:
        """Builds (S, T, 2) of a candidate: the equilibrium program's draws (one compiled
        program per kind of assembly), or :func:`_grid_builds` where no program draws."""
        mods: list[PaperModule] = [job.modules[a] for a in arms]
        placed = [m.at(job.mounts[j]) for m, j in zip(mods, mounts, strict=True)]
        commands = [job.reach[a, j] for a, j in zip(arms, mounts, strict=True)]
        if not (all(is_sampleable(m.fitted) for m in mods)
                and (job.fusion == "equilibrium" or len(mods) == 1)):
            return _grid_builds(job, mods, placed, commands, index), {}
        stiff = [m.spec.stiffness for m in mods]
        stiffness = static_stiffness(stiff)
        d = equilibrium_program_draws(
            jax.random.PRNGKey(job.seed + index), tuple(jnp.asarray(u) for u in commands),
            tuple(error_arrays(m.fitted) for m in mods), tuple(a.params for a in placed),
            tuple(jnp.asarray(m.param_cov) for m in mods),
            kinds=tuple(error_kind(m.fitted) for m in mods), stiffness=stiffness,
            num_samples=job.draws, tracker_noise_mm=job.tracker_noise_mm,
            densities_hold_tracker=not all(m.tracker_removed for m in mods))
        return np.asarray(d), {}

    @staticmethod
    def write_rig(candidate: dict, targets: np.ndarray, modules: dict[str, PaperModule],
                  reach: dict[tuple[str, int], np.ndarray], region: np.ndarray, out: Path
                  ) -> None:
        """rig.toml (calibrated values at the new bases), measurements.csv (the planned rows, x
        and y empty) and, for simulated modules, truth.toml for ``simulate DIR --planned``."""
        import csv
        import math

        from bayesrob.data.rig import (
            MEASUREMENTS_FILE,
            RIG_FILE,
            dump_toml,
            format_row,
            measurement_header,
            rig_toml_dict,
        )
        from bayesrob.sim.rigs import round_pulse
        from bayesrob.sim.truth import TRUTH_FILE

        names = candidate["arms"]
        placed = list(zip(names, candidate["mounts"], candidate["bases"], strict=True))
        specs = {a: replace(modules[a].spec, base=tuple(b)) for a, _, b in placed}
        lo, hi = region.min(axis=0), region.max(axis=0)
        workspace = ((float(lo[0]), float(hi[0])), (float(lo[1]), float(hi[1])))
        doc = rig_toml_dict(f"design-{candidate['config']}", specs, modules[names[0]].gravity,
                            workspace)
        (out / RIG_FILE).write_text(dump_toml(doc))
        pulses = {a: round_pulse(reach[a, j]) for a, j, _ in placed}
        with (out / MEASUREMENTS_FILE).open("w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(measurement_header(names))
            for i, target in enumerate(targets):
                w.writerow(format_row(names, "+".join(names), "test", target,
                                      {a: u[i] for a, u in pulses.items()},
                                      (math.nan, math.nan)))
        mods = [modules[a] for a in names]
        if all(m.truth is not None for m in mods):
            truth = replace(mods[0].truth_rig, name=doc["name"], arms={
                a: mounted_truth(modules[a], b) for a, _, b in placed}, workspace=workspace)
            (out / TRUTH_FILE).write_text(truth.to_toml())


def _grid_builds(job: Any, mods: Sequence[PaperModule], arms: Sequence[kin.Arm],
                 commands: Sequence[np.ndarray], index: int) -> np.ndarray:
    """Builds (S, T, 2) where no program draws the whole assembly (the product rule, or the
    histogram COND): one draw per target of the fused grid density, plus one calibration
    error per module shared by the targets; linked arms' shifts are weighted by their end-point
    precisions (J C J^T)^-1, as the mean of a product of shifted Gaussian likelihoods.
    """
    post, _ = fused_posterior([m.fitted for m in mods], arms, commands, job.targets,
                              job.fusion, seed=job.seed + index, num_samples=job.draws)
    points = post.sample(job.seed + index, job.draws)
    rng = np.random.default_rng([job.seed, index])
    shifts, precisions = [], []
    for m, arm, u in zip(mods, arms, commands, strict=True):
        delta = rng.multivariate_normal(np.zeros(len(m.param_cov)), m.param_cov,
                                        size=job.draws, method="eigh")
        shifts.append(_calibration_shift(arm.params, jnp.asarray(u), jnp.asarray(delta)))
        if len(mods) > 1:
            err = np.asarray(m.fitted.theta_err, float)
            c = np.cov(err.T) + 1e-8 * np.eye(2)  # one point or collinear errors: not singular
            jac = np.asarray(kin.jacobian(arm.params, kin.servo(arm.params, jnp.asarray(u))))
            precisions.append(np.linalg.inv(np.einsum("tij,jk,tlk->til", jac, c, jac)))
    if len(mods) == 1:
        return points + shifts[0]
    total = np.linalg.inv(sum(precisions))
    return points + sum(np.einsum("tij,tjk,stk->sti", total, p, s)
                        for p, s in zip(precisions, shifts, strict=True))


@jax.jit
def _calibration_shift(params: kin.ArmParams, u: jax.Array, delta: jax.Array) -> jax.Array:
    """(S, T, 2): how far each parameter error delta (S, 8) moves the end point at u (T, 2)."""
    v = params.to_vector()

    def reached(d: jax.Array) -> jax.Array:
        p = kin.ArmParams.from_vector(v + d)
        return kin.forward(p, kin.servo(p, u))

    return jax.vmap(reached)(delta) - reached(jnp.zeros_like(v))[None]


def mounted_truth(module: PaperModule, base: Sequence[float]) -> ArmTruth:
    """A simulated module's true arm moved with its calibrated base to ``base`` (the base
    error moves with the module)."""
    shift = np.asarray(base, float) - np.asarray(module.arm.params.base, float)
    b = np.asarray(module.truth.base) + shift
    return replace(module.truth, name=module.name, base=(float(b[0]), float(b[1])))


@dataclass
class CalibratedModule:
    """A root arm of a URDF / DH robot, calibrated and fitted as ``bayesrob predict`` does; a
    world target t is aimed and drawn at t - mount + base. A placement's draws are made once
    per worker and reused by every candidate (common random numbers rank less noisily)."""

    name: str
    arm: str  # the arm of its rig
    rig: Rig  # its rig: the train poses aiming starts from
    mods: CalibratedModules  # its rig's calibration and this module's joint-error model
    base: np.ndarray  # (dim,) its robot base in its rig's instrument frame (calibrated)
    rig_index: int  # modules of one rig share its calibration errors in every draw
    model: str

    @property
    def dim(self) -> int:
        return self.mods.robot.dim

    def local(self, points: np.ndarray, mount: Sequence[float]) -> np.ndarray:
        return np.asarray(points, float) - np.asarray(mount, float) + self.base

    def aim(self, targets: np.ndarray, mount: Sequence[float]) -> np.ndarray | None:
        """Joint columns (T, c) whose calibrated model reaches every target, or None."""
        try:
            return aim(self.rig, self.mods.robot, self.mods.x, self.arm,
                             self.local(targets, mount))
        except RigError:
            return None

    def sketch(self, mount: Sequence[float], target: np.ndarray) -> np.ndarray:
        return np.array([np.asarray(mount, float), np.asarray(target, float)])

    @classmethod
    def load(cls, design: DesignSpec, rigs: dict[Path, Rig],
             by_rig: dict[Path, list[ModuleSpec]], models_dir: Any = None
             ) -> dict[str, CalibratedModule]:
        """Calibrate each rig once (the groups its modules name) and fit each module's
        joint-error model on its own train rows."""
        from bayesrob.calibrate.least_squares import calibrate, parameter_covariance
        from bayesrob.predict.stiffness import stiffness_prior

        if design.fusion != "equilibrium" and design.max_arms > 1 and design.linked:
            raise DesignError(f"{design.path}: fusion = {design.fusion!r} samples every "
                              "linked chain assembly with NUTS, minutes each; chain modules "
                              "are designed with fusion = \"equilibrium\"")
        out: dict[str, CalibratedModule] = {}
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
                if m.arm not in rig.robot.measured_arms():
                    raise _fail(design, m, f"unknown module arm {m.arm!r} in {rig_dir} "
                                f"(measured arms: {', '.join(rig.robot.measured_arms())})")
                path = rig.robot.path(m.arm)
                if len(path) > 1:
                    raise _fail(design, m, f"arm {m.arm!r} hangs on {path[-2].name!r}; the "
                                "designer mounts whole root arms (no arm under them) so far")
                try:
                    check_module_arms(rig, [m.arm], m.model, models_dir)
                except (RigError, ValueError) as e:
                    raise _fail(design, m, str(e)) from None
                if rig.robot.dim != design.dim:
                    raise _fail(design, m, f"{rig_dir} measures {rig.robot.dim}-D points but "
                                f"the mounts and the task are {design.dim}-D")
            try:
                cal = calibrate(rig, groups.pop() or kin.GROUPS, masses=masses.pop())
            except ValueError as e:
                raise DesignError(f"{design.path}: {rig_dir}: {e}") from None
            cov = parameter_covariance(rig, cal)
            for i, m in enumerate(specs):
                errors = fit_joint_errors(rig, cal, m.arm, m.model, design.seed + i, models_dir)
                mods = CalibratedModules(cal, {m.arm: errors},
                                    {m.arm: stiffness_prior(rig, m.arm, cal)}, cov)
                base = np.asarray(cal.robot.instrument_pose(jnp.asarray(cal.x), m.arm))[:3, 3]
                out[m.name] = cls(m.name, m.arm, rig, mods, base[: rig.robot.dim], index,
                                  m.model)
        return out

    @staticmethod
    def draws(job: Any, arms: Sequence[str], mounts: Sequence[int], index: int
              ) -> tuple[np.ndarray, dict]:
        """Builds (S, T, dim) of a candidate's end point: one arm's free point, or linked
        arms' balance with the tracker's noise put back (and their stiffness record)."""
        parts = [_placement(job, a, j) for a, j in zip(arms, mounts, strict=True)]
        if len(parts) == 1:
            return parts[0][0], {}
        d = equilibrium([p[0] for p in parts], [p[1] for p in parts],
                              _log_stiffness(job, arms),
                              tracker_noise_mm=job.tracker_noise_mm,
                              key=jax.random.fold_in(jax.random.PRNGKey(job.seed + 1), index))
        return np.asarray(d), {"stiffness": stiffness_record(job, arms)}

    @staticmethod
    def write_rig(candidate: dict, targets: np.ndarray, modules: dict[str, CalibratedModule],
                  reach: dict[tuple[str, int], np.ndarray], region: np.ndarray, out: Path
                  ) -> None:
        """Each module's calibrated URDF, rig.toml (instrument poses at the mounts, orientation
        kept) and measurements.csv with the planned linked rows, x, y, z empty."""
        import csv

        from bayesrob.calibrate.least_squares import arm_table
        from bayesrob.data.rig import MEASUREMENTS_FILE, RIG_FILE, dump_toml

        names = candidate["arms"]
        first = modules[names[0]]
        arms_doc = {}
        for a, b in zip(names, candidate["bases"], strict=True):
            m = modules[a]
            calibrated = m.mods.robot.with_values(m.mods.x)
            chain = calibrated.chains[m.arm]
            alone = kin.Robot({m.arm: chain}, calibrated.dim, calibrated.gravity,
                              calibrated.sag_steps)
            urdf = out / f"{a}.urdf"
            kin.write_urdf(alone, alone.layout.nominal, urdf, name=a)
            table = arm_table(chain, urdf.name, kin.urdf.generated_arm_keys(alone)[m.arm],
                                    measured=True)
            pose = np.asarray(table["instrument"], float)
            pose[: m.dim] = np.asarray(b, float)
            table["instrument"] = [float(v) for v in pose]
            arms_doc[a] = table
        doc = {"name": f"design-{candidate['config']}",
               "gravity": [float(v) for v in first.rig.gravity], "arms": arms_doc}
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


def _order(job: Any, name: str) -> int:
    """A module's place in the inventory: its seeds derive from it, so a module draws the
    same numbers in every candidate it is in (common random numbers)."""
    return list(job.modules).index(name)


def _placement(job: Any, name: str, mount: int) -> tuple[np.ndarray, jax.Array]:
    """A placement's free-point draws (S, T, dim) in the world and its joint Jacobian
    (T, dim, n), drawn once per worker (``job.cache``) from seeds of its own."""
    key = ("placement", name, mount)
    if key not in job.cache:
        m: CalibratedModule = job.modules[name]
        u = job.reach[name, mount]
        xs = _rig_parameters(job, m)
        k = jax.random.fold_in(jax.random.PRNGKey(job.seed), 1000 * _order(job, name) + mount)
        local = free_draws(m.mods, m.arm, u, xs, k)
        jac = joint_jacobian(m.mods.robot, jnp.asarray(m.mods.x), m.arm, jnp.asarray(u))
        world = local - m.base + np.asarray(job.mounts[mount], float)
        job.cache[key] = (world, jac)
    return job.cache[key]


def _rig_parameters(job: Any, m: CalibratedModule) -> jax.Array:
    """Parameter draws (S, P) of a module's rig, once per worker: every placement of every
    module of that rig builds on the same calibration errors."""
    key = ("parameters", m.rig_index)
    if key not in job.cache:
        job.cache[key] = parameter_draws(
            m.mods, jax.random.PRNGKey(job.seed * 7919 + m.rig_index), job.draws)
    return job.cache[key]


def linked_priors(modules: Sequence[CalibratedModule]) -> list[StiffnessPrior]:
    """The linked modules' log joint stiffness priors, as ``bayesrob predict`` links arms:
    distinct arms of one rig centred on their fitted sags
    (:func:`bayesrob.predict.stiffness.sag_scaled_priors`); modules of different rigs keep
    their own, as their sags come from different calibrations."""
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


def stiffness_record(job: Any, names: Sequence[str]) -> list[dict[str, Any]]:
    """What a linked candidate's balance drew each module's joint stiffnesses from, in
    ``names``' order, for ``design.json`` (as ``predict``'s JSON gives it per arm)."""
    return [p.record() for p in _candidate_priors(job, names)]


def _log_stiffness(job: Any, names: Sequence[str]) -> list[jax.Array]:
    """Linked modules' joint log stiffnesses, each (S, n): each module's standard normals from
    its own seed, the same in every candidate (common random numbers)."""
    key = ("stiffness", tuple(names))
    if key not in job.cache:
        priors = _candidate_priors(job, names)
        job.cache[key] = [
            stiffness_draws([p], jax.random.PRNGKey(job.seed * 104729 + _order(job, n)),
                            job.draws)[0]
            for n, p in zip(names, priors, strict=True)]
    return job.cache[key]


# what the search holds: one kind per design
Module = PaperModule | CalibratedModule
