"""The configuration designer (``bayesrob design``): which calibrated modules, mounted where and
linked how, reach a required accuracy over a task region.

A design file (TOML) names the inventory and the task::

    fusion = "equilibrium"          # how linked arms share their end point (predict.fusion)
    seed = 0
    tracker_noise_mm = 0.35         # the tracker's noise, sd per axis (default 0: not known)

    [modules.top]                   # a calibrated module: an arm of a rig directory
    rig = "modules"                 # relative to the design file
    arm = "top"                     # default: the module's name
    model = "ind"                   # its joint-error model (default ind)

    [mounts]                        # where module bases may go: a list ...
    points = [[20.0, 440.0], [20.0, -20.0]]
    # ... or a grid: grid = { x = [lo, hi, n], y = [lo, hi, n] }

    [task]                          # the region the end point must serve
    box = [[80.0, 260.0], [100.0, 280.0]]   # or polygon = [[x, y], ...]
    targets = 16                    # sampled inside it (scrambled Halton, seeded)

    [requirement]
    error_mm = 1.0                  # the end point within error_mm of the target ...
    quantile = 0.95                 # ... this often, over the region ...
    confidence = 0.9                # ... in this share of the assemblies one might build

    [limits]
    max_arms = 3                    # arms per assembly (min_arms = 2: linked ones only)
    linked = true                   # false: single arms only

A module keeps its calibrated geometry and joint-error model wherever it is mounted: mounting
translates its base (its orientation, hence its servo offsets, is kept). Every assembly of one
to ``max_arms`` modules on distinct mount points is a candidate; those where some arm cannot
reach some target on its configured elbow branch within its pulse limits are dropped before
anything is predicted. The others are predicted a priori, from the modules' single-arm data
only (as ``bayesrob predict`` does), and ranked: requirement met first, then fewest modules,
then the smaller predicted error quantile over the region.

The error of a candidate is the distance from the target of the predicted end point as the
tracker would measure it. The joint-error models are fitted to measured end points; with
``tracker_noise_mm`` known (and equilibrium fusion) the tracker's noise is first taken out of
each train row's joint errors (:func:`bayesrob.noise_models.without_tracker_noise`), so a
module's density is of its joints' own errors at any mount, and each predicted point gets the
tracker's noise once. Its
quantile "over the region" pools every target's predicted distribution, one target as likely
as another: the accuracy at a target drawn at random from the task.

A built assembly is one draw of its calibration errors: its modules' parameters are off by
fixed amounts, the same at every target (each prediction draw carries one such set, from the
calibration's covariance). So an assembly whose pooled quantile just meets the requirement
misses it about half the time once built. The requirement is therefore met when the share of
draws whose own quantile over the targets is within ``error_mm`` reaches ``confidence``.

Modules may instead be URDF/DH arms placed in space (``[x, y, z]`` mounts, a 3-D task box):
:mod:`bayesrob.chain_design` loads, aims and draws them; ranking and outputs are shared.

Candidates are evaluated as Dask tasks (``dask.distributed``): batches of candidates per task,
so each worker compiles its JAX program once per kind of assembly and reuses it (the
modules' arrays and the bases are traced arguments, not constants). The modules are
scattered to every worker once; each task carries only its candidates' names and bases.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import math
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp
import numpy as np
from distributed import WorkerPlugin

from bayesrob import kinematics as kin
from bayesrob import release_compiled_programs
from bayesrob.chain_design import (
    ChainModule,
    chain_candidate_draws,
    chain_reach_table,
    chain_stiffness_record,
)
from bayesrob.design_file import (
    DesignError,
    DesignSpec,
    ModuleSpec,
    load_design,
)
from bayesrob.inference import error_arrays, error_kind, is_sampleable
from bayesrob.noise_models import FittedNoiseModel
from bayesrob.predict.fusion import equilibrium_program, fused_posterior
from bayesrob.rig import ArmSpec, RigError

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from bayesrob.simulator import ArmTruth, Truth

__all__ = ["DesignError", "DesignSpec", "ModuleSpec", "Module", "Candidate", "DesignResult",
           "load_design", "load_modules", "task_targets", "reach_table", "enumerate_candidates",
           "evaluate_batch", "run_design", "design_figure", "write_candidate_rig",
           "mounted_truth"]

BATCH = 25  # candidates per Dask task: enough to hide a task's overhead, small to spread well
MAX_CANDIDATES = 200_000
# Keeps a parameter covariance with an unidentified direction sampleable, in each parameter's
# own scale: an absolute 1e-12 added gain noise of 1e-6 rad/us (1.5 mrad at 1500 us) to arms
# whose gains are fitted to far better, and widened every prediction (tuning inventories 1-4:
# single arms predicted at 1.43-1.76 of the observed q95 with it, 1.28-1.44 without).
COV_JITTER = 1e-9
# Worker processes run one XLA thread each: two workers on two cores then share nothing, and a
# single worker is not secretly using both cores (the speed-up benchmark would lie).
WORKER_ENV = {"XLA_FLAGS": "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1",
              "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


# ------------------------------------------------------------------------------ modules


@dataclass
class Module:
    """A calibrated module, ready to be mounted anywhere."""

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
    def truth(self) -> ArmTruth | None:
        """The module's own true arm, when its rig was simulated."""
        return self.truth_rig.arms.get(self.arm.name) if self.truth_rig else None

    def at(self, base: Sequence[float]) -> kin.Arm:
        """The module with its base moved to ``base``."""
        return replace(self.arm, name=self.name,
                       params=self.arm.params._replace(base=jnp.asarray(base, jnp.float64)))


def load_modules(design: DesignSpec, models_dir: Any = None
                 ) -> dict[str, Module] | dict[str, ChainModule]:
    """Calibrate each module's arm on its rig's train rows and fit its joint-error model:
    planar arms (:class:`Module`) or URDF/DH arms (:class:`~bayesrob.chain_design.ChainModule`),
    one kind per design."""
    from bayesrob.chain_design import load_chain_modules
    from bayesrob.rig import load_rig

    by_rig: dict[Path, list[ModuleSpec]] = {}
    for m in design.modules.values():
        by_rig.setdefault(m.rig, []).append(m)
    rigs = {}
    for rig_dir, mods in by_rig.items():
        try:
            rigs[rig_dir] = load_rig(rig_dir)
        except RigError as e:
            raise DesignError(f"{design.path}: [modules.{mods[0].name}]: {e}") from None
    kinds = {n: rigs[m.rig].is_chain for n, m in design.modules.items()}
    if len(set(kinds.values())) > 1:
        chain = next(n for n, c in kinds.items() if c)
        flat = next(n for n, c in kinds.items() if not c)
        raise DesignError(f"{design.path}: module {chain!r} is a URDF/DH arm and {flat!r} a "
                          "planar arm; a design places one kind")
    if any(kinds.values()):
        return load_chain_modules(design, rigs, by_rig)
    if design.dim != 2:
        raise DesignError(f"{design.path}: the mounts are 3-D points but the modules are "
                          "planar arms; give [x, y] mounts and a box of the plane")
    for m in design.modules.values():
        if m.params is not None:  # a planar arm's eight parameters are always fitted
            raise DesignError(f"{design.path}: [modules.{m.name}]: params names calibration "
                              "groups of URDF/DH arms; a planar arm fits its eight parameters")
        if m.masses != "fitted":
            raise DesignError(f"{design.path}: [modules.{m.name}]: masses is for URDF arms "
                              "calibrated with compliance; a planar arm has no link masses")
    return _load_planar_modules(design, rigs, by_rig, models_dir)


def _load_planar_modules(design: DesignSpec, rigs: dict, by_rig: dict[Path, list[ModuleSpec]],
                         models_dir: Any) -> dict[str, Module]:
    from bayesrob.calibration import calibrate, parameter_covariance
    from bayesrob.noise_models import (
        ModelFileError,
        discover_models,
        joint_errors,
        without_tracker_noise,
    )
    from bayesrob.simulator import TRUTH_FILE, Truth

    out: dict[str, Module] = {}
    specs: dict[str, list] = {}  # model name -> its discovered file, read once
    for rig_dir, mods in by_rig.items():
        rig = rigs[rig_dir]
        for m in mods:
            if m.arm not in rig.arms:
                raise DesignError(f"{design.path}: [modules.{m.name}]: unknown module arm "
                                  f"{m.arm!r} in {rig_dir} (arms: {', '.join(rig.arms)})")
        cal = calibrate(rig)
        truth = (Truth.from_toml(rig_dir / TRUTH_FILE) if (rig_dir / TRUTH_FILE).is_file()
                 else None)
        for m in mods:
            if m.model not in specs:
                try:
                    specs[m.model] = discover_models(models_dir, [m.model])
                except (ModelFileError, KeyError, ValueError) as e:
                    raise DesignError(f"{design.path}: [modules.{m.name}]: {e}") from None
            if not specs[m.model]:
                raise DesignError(f"{design.path}: [modules.{m.name}]: unknown model "
                                  f"{m.model!r}")
            arm = cal[m.arm].arm
            u, d = rig.rows(m.arm, "train")
            errors = joint_errors(arm, u, d)
            spec = specs[m.model][0]
            # equilibrium draws add the tracker's noise to the measured point: the density
            # is then of the joints' own errors (the grid's product, and a model that cannot
            # draw, which goes to the grid, keep the paper's rows)
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
            cov = parameter_covariance(np.asarray(arm.params.to_vector()), u, d)
            out[m.name] = Module(m.name, arm, fitted, cspec, tuple(rig.gravity),
                                 cov + COV_JITTER * np.diag(np.diag(cov)), truth, removed)
    return out


def task_targets(region: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """``n`` targets inside the polygon ``region``: a scrambled Halton sequence over its
    bounding box, keeping the points inside (even spread, reproducible from ``seed``). A 3-D
    region is a box: the sequence fills it."""
    from matplotlib.path import Path as Polygon
    from scipy.stats import qmc

    lo, hi = region.min(axis=0), region.max(axis=0)
    if region.shape[1] == 3:
        return qmc.scale(qmc.Halton(3, scramble=True, seed=seed).random(n), lo, hi)
    poly = Polygon(region)
    sampler = qmc.Halton(2, scramble=True, seed=seed)
    out = np.zeros((0, 2))
    for _ in range(50):
        pts = qmc.scale(sampler.random(4 * n), lo, hi)
        out = np.vstack([out, pts[poly.contains_points(pts)]])
        if len(out) >= n:
            return out[:n]
    raise DesignError(f"the task region {region.tolist()} has no area to place {n} targets in")


# ------------------------------------------------------------------------------ candidates


@dataclass(frozen=True)
class Candidate:
    """One assembly: modules ``arms`` with their bases at ``mounts`` (indices) = ``bases``."""

    arms: tuple[str, ...]
    mounts: tuple[int, ...]
    bases: tuple[tuple[float, ...], ...]

    @property
    def linking(self) -> str:
        return "alone" if len(self.arms) == 1 else "linked at the end point"

    @property
    def config(self) -> str:
        return "+".join(self.arms)


def _aims(arm: kin.Arm, targets: np.ndarray) -> np.ndarray | None:
    """Pulses aiming ``arm`` at every target, or None when one is out of its reach, off its
    elbow branch or outside its pulse limits."""
    if not bool(np.all(np.asarray(arm.reachable(jnp.asarray(targets))))):
        return None
    u = np.asarray(arm.command(jnp.asarray(targets)))
    lim = np.asarray(arm.pulse_limits)
    if not np.all((u >= lim[:, 0]) & (u <= lim[:, 1])):
        return None
    return u


def reach_table(modules: dict[str, Module] | dict[str, ChainModule], mounts: np.ndarray,
                targets: np.ndarray) -> dict[tuple[str, int], np.ndarray]:
    """{(module, mount index): commands (T, c)} for every placement that reaches every
    target: planar pulses, or a chain module's joint columns."""
    if _is_chain(modules):
        return chain_reach_table(modules, mounts, targets)
    out = {}
    for name, m in modules.items():
        for j, base in enumerate(mounts):
            u = _aims(m.at(base), targets)
            if u is not None:
                out[name, j] = u
    return out


def enumerate_candidates(design: DesignSpec, reach: dict[tuple[str, int], np.ndarray]
                         ) -> list[Candidate]:
    """Every assembly of 1..max_arms modules on distinct mounts that reaches every target
    (single arms only when ``linked`` is false)."""
    names = list(design.modules)
    sizes = range(design.min_arms, (design.max_arms if design.linked else 1) + 1)
    out = []
    for k in sizes:
        for group in itertools.combinations(names, k):
            options = [[j for j in range(len(design.mounts)) if (a, j) in reach] for a in group]
            for mounts in itertools.product(*options):
                if len(set(mounts)) < k:
                    continue
                out.append(Candidate(group, mounts, tuple(
                    tuple(float(v) for v in design.mounts[j]) for j in mounts)))
                if len(out) > MAX_CANDIDATES:
                    raise DesignError(f"{design.path}: more than {MAX_CANDIDATES} candidate "
                                      "assemblies; use fewer mounts, modules or max_arms")
    return out


# ------------------------------------------------------------------------------ evaluation


@dataclass(frozen=True)
class _Job:
    """What every task shares (scattered to the workers once)."""

    modules: dict[str, Module]
    targets: np.ndarray
    reach: dict[tuple[str, int], np.ndarray]
    fusion: str
    quantile: float
    error_mm: float
    confidence: float
    draws: int
    seed: int
    tracker_noise_mm: float = 0.0
    mounts: np.ndarray | None = None  # (P, dim): where chain placements' draws are moved to
    # each worker's chain draws (per placement, per rig's parameters, per linked module
    # set's priors and stiffnesses), reused by every candidate that shares them
    cache: dict = field(default_factory=dict, compare=False)


@partial(jax.jit, static_argnames=("kinds", "stiffness", "num_samples", "tracker_noise_mm",
                                   "densities_hold_tracker"))
def _draws(key: jax.Array, commands: tuple, arrays: tuple, params: tuple, param_cov: tuple, *,
           kinds: tuple[str, ...], stiffness: tuple | None, num_samples: int,
           tracker_noise_mm: float, densities_hold_tracker: bool) -> jax.Array:
    # One compiled program per kind of assembly (model kinds, stiffness knowledge, shapes):
    # which modules and where they stand are traced arguments.
    from numpyro.infer import Predictive

    names = tuple(f"arm{i}" for i in range(len(kinds)))
    out = Predictive(equilibrium_program, num_samples=num_samples, return_sites=["d"])(
        key, commands, kinds=kinds, arrays=arrays, params=params, names=names,
        stiffness=stiffness, param_cov=param_cov, tracker_noise_mm=tracker_noise_mm,
        densities_hold_tracker=densities_hold_tracker)
    return out["d"]


def _quantiles(dist: np.ndarray, weights: np.ndarray | None, q: float) -> np.ndarray:
    """Per-target quantile of distances (T, M) (weights (T, M) summing to 1 per target)."""
    if weights is None:
        return np.quantile(dist, q, axis=1)
    order = np.argsort(dist, axis=1)
    d = np.take_along_axis(dist, order, 1)
    c = np.cumsum(np.take_along_axis(weights, order, 1), axis=1)
    idx = np.minimum((c < q).sum(axis=1), d.shape[1] - 1)
    return d[np.arange(len(d)), idx]


def _is_chain(modules: dict) -> bool:
    return any(isinstance(m, ChainModule) for m in modules.values())


def _draw_scores(job: _Job, d: np.ndarray) -> tuple:
    """Distances (T, S), mean point, and the build statistics of draws (S, T, dim), each draw
    one possible built assembly."""
    dist = np.linalg.norm(d - job.targets[None], axis=-1).T  # (T, S)
    # each draw is one possible built assembly: its own quantile over the targets
    own = np.quantile(dist, job.quantile, axis=0)
    confidence = float(np.mean(own <= job.error_mm))
    # the error this assembly keeps within in `confidence` of the builds: any requirement
    # can be checked against it without predicting again
    # (the inverted CDF makes "meets" exactly "assured <= error_mm")
    assured = float(np.quantile(own, job.confidence, method="inverted_cdf"))
    # ... and the error it exceeds in `confidence` of them: beyond error_mm, a sure miss
    optimistic = float(np.quantile(own, 1.0 - job.confidence, method="inverted_cdf"))
    return dist, d.mean(axis=0), confidence, assured, optimistic


def _evaluate(job: _Job, cand: Candidate, index: int) -> dict:
    if _is_chain(job.modules):
        d = chain_candidate_draws(job, cand.arms, cand.mounts, index)
        dist, mean, confidence, assured, optimistic = _draw_scores(job, d)
        out = _result(job, cand, [job.modules[a].model for a in cand.arms], dist, None, mean,
                      confidence, assured, optimistic)
        if len(cand.arms) > 1:
            out["stiffness"] = chain_stiffness_record(job, cand.arms)
        return out
    mods = [job.modules[a] for a in cand.arms]
    arms = [m.at(b) for m, b in zip(mods, cand.bases, strict=True)]
    commands = [job.reach[a, j] for a, j in zip(cand.arms, cand.mounts, strict=True)]
    t = job.targets
    sampleable = all(is_sampleable(m.fitted) for m in mods)
    if sampleable and (job.fusion == "equilibrium" or len(arms) == 1):
        stiff = [m.spec.stiffness for m in mods]
        stiffness = (tuple(tuple(s) if s is not None else None for s in stiff)
                     if any(s is not None for s in stiff) else None)
        d = np.asarray(_draws(
            jax.random.PRNGKey(job.seed + index), tuple(jnp.asarray(u) for u in commands),
            tuple(error_arrays(m.fitted) for m in mods), tuple(a.params for a in arms),
            tuple(jnp.asarray(m.param_cov) for m in mods),
            kinds=tuple(error_kind(m.fitted) for m in mods), stiffness=stiffness,
            num_samples=job.draws, tracker_noise_mm=job.tracker_noise_mm,
            densities_hold_tracker=not all(m.tracker_removed for m in mods)))
        weights = None
        dist, mean, confidence, assured, optimistic = _draw_scores(job, d)
    else:  # the product of likelihoods (or the paper's histogram COND): the grid
        post, _ = fused_posterior([m.fitted for m in mods], arms, commands, t, job.fusion,
                                  seed=job.seed + index)
        dist = np.linalg.norm(post.points() - t[:, None, :], axis=-1)
        weights = post.prob
        mean = post.mean
        confidence = None
        assured = optimistic = None
    return _result(job, cand, [m.fitted.spec.name for m in mods], dist, weights, mean,
                   confidence, assured, optimistic)


def _result(job: _Job, cand: Candidate, models: list[str], dist: np.ndarray,
            weights: np.ndarray | None, mean: np.ndarray, confidence: float | None,
            assured: float | None, optimistic: float | None) -> dict:
    t = job.targets
    per = _quantiles(dist, weights, job.quantile)
    pooled = _quantiles(dist.reshape(1, -1), None if weights is None
                        else weights.reshape(1, -1) / len(t), job.quantile)[0]
    expected = (dist.mean(axis=1) if weights is None else (dist * weights).sum(axis=1))
    return {
        "arms": list(cand.arms), "bases": [list(b) for b in cand.bases],
        "mounts": list(cand.mounts), "linking": cand.linking,
        "models": models, "fusion": job.fusion,
        "error_quantile_mm": [float(v) for v in per],
        "expected_error_mm": [float(v) for v in expected],
        "expected_point": [[float(v) for v in p] for p in mean],
        "overall": {"error_quantile_mm": float(pooled),
                    "worst_target_quantile_mm": float(per.max()),
                    "expected_error_mm": float(expected.mean()),
                    "assured_error_mm": float(pooled) if assured is None else assured,
                    "optimistic_error_mm": float(pooled) if optimistic is None else optimistic},
        # the grid has no draws of a whole assembly: its pooled quantile decides alone
        "confidence": confidence,
        "meets": bool(pooled <= job.error_mm if confidence is None
                      else confidence >= job.confidence),
    }


def evaluate_batch(job: _Job, batch: Sequence[tuple[int, Candidate]]) -> list[tuple[int, dict]]:
    """Predict every candidate of a batch (one Dask task): (index, result) pairs."""
    release_compiled_programs()  # a worker lives through many batches
    return [(i, _evaluate(job, c, i)) for i, c in batch]


# ------------------------------------------------------------------------------ the run


@dataclass
class DesignResult:
    """The ranked candidates of one design run."""

    design: DesignSpec
    targets: np.ndarray
    candidates: list[dict]  # ranked, best first
    n_placements: int  # (module, mount) pairs considered
    n_reachable: int
    workers: int
    scheduler: str
    seconds: float
    notes: list[str] = field(default_factory=list)
    # {(module, mount index): commands (T, c)}: how each placement aims at the targets
    reach: dict = field(default_factory=dict)

    @property
    def best(self) -> dict | None:
        return self.candidates[0] if self.candidates else None

    @property
    def met(self) -> bool:
        return bool(self.candidates) and self.candidates[0]["meets"]

    @property
    def document(self) -> dict:
        d = self.design
        return {
            "design": str(d.path), "requirement": d.requirement, "fusion": d.fusion,
            "region": d.region.tolist(), "targets": self.targets.tolist(),
            "modules": {n: {"rig": str(m.rig), "arm": m.arm, "model": m.model}
                        for n, m in d.modules.items()},
            "mounts": d.mounts.tolist(),
            "n_candidates": len(self.candidates),
            "n_meeting": sum(c["meets"] for c in self.candidates),
            "workers": self.workers, "scheduler": self.scheduler, "seconds": self.seconds,
            "rows_used": "train rows of each module's rig (no assembly was measured)",
            "candidates": self.candidates,
        }

    def format(self, top: int = 10) -> str:
        from bayesrob.report import format_table

        d = self.design
        q = f"q{round(100 * d.quantile)}"
        rows = [[str(c["rank"]), c["config"],
                 _bases_text(c["bases"]),
                 f"{c['overall']['error_quantile_mm']:.3f}",
                 f"{c['overall']['worst_target_quantile_mm']:.3f}",
                 f"{c['overall']['expected_error_mm']:.3f}",
                 f"{c['overall']['assured_error_mm']:.3f}", "yes" if c["meets"] else "no"]
                for c in self.candidates[:top]]
        head = (f"{len(self.candidates)} candidate assemblies ({self.n_reachable} of "
                f"{self.n_placements} module placements reach all {len(self.targets)} "
                f"targets), requirement {d.error_mm:g} mm at {d.quantile:g}, fusion "
                f"{d.fusion}, {self.workers} worker(s), {self.seconds:.1f} s")
        table = format_table(["rank", "assembly", "bases (mm)", f"{q} mm", f"worst {q} mm",
                              "E error mm", f"{q} in {d.confidence:.0%} mm", "meets"], rows)
        best = self.best
        if best is None:
            tail = "no candidate"
        elif best["meets"]:
            tail = (f"best: {best['config']} at " + _bases_text(best["bases"])
                    + f", predicted {q} {best['overall']['error_quantile_mm']:.3f} mm")
        else:
            tail = (f"no candidate meets {d.error_mm:g} mm at {d.quantile:g} in "
                    f"{d.confidence:.0%} of builds; the closest is {best['config']}, within "
                    f"{best['overall']['assured_error_mm']:.3f} mm in {d.confidence:.0%}")
        return "\n".join([head, table, *self.notes, tail])


def _bases_text(bases: Sequence[Sequence[float]]) -> str:
    return "; ".join("(" + ", ".join(f"{v:.0f}" for v in b) + ")" for b in bases)


def _rank_key(c: dict) -> tuple:
    # those that meet: fewest modules first; those that miss: closest to meeting first
    o = c["overall"]
    return ((False, len(c["arms"]), o["error_quantile_mm"]) if c["meets"]
            else (True, o["assured_error_mm"], len(c["arms"])))


class OneCorePerWorker(WorkerPlugin):
    """Pins each local worker process, every thread of it, to a core of its own.

    XLA sizes its thread pool to the cores a process may use and splits some operations over
    it; two unpinned workers on two cores then run four busy threads and each goes at about
    half speed (measured: 0.20 s per candidate instead of 0.115). Pinned, a worker's pool is
    one core and the workers share nothing. The worker's name (0, 1, ... in a LocalCluster,
    kept when a lost worker is restarted) picks the core.
    """

    def __init__(self, cores: Sequence[int]):
        self.cores = tuple(cores)

    def setup(self, worker: Any) -> None:
        try:
            core = self.cores[int(worker.name) % len(self.cores)]
        except (TypeError, ValueError):
            return  # a worker not named by a LocalCluster: leave it as it is
        for tid in os.listdir("/proc/self/task"):
            with contextlib.suppress(OSError):  # a thread that ended meanwhile
                os.sched_setaffinity(int(tid), {core})


@contextlib.contextmanager
def dask_client(scheduler: str | None = None, workers: int = 2) -> Iterator[Any]:
    """A ``dask.distributed`` client: on an existing scheduler, or on a ``LocalCluster`` of
    ``workers`` single-threaded worker processes (closed on exit)."""
    from distributed import Client, LocalCluster

    if scheduler:
        try:
            client = Client(scheduler, timeout="10s")
        except (OSError, TimeoutError) as e:
            raise DesignError(f"--scheduler {scheduler}: cannot reach the Dask scheduler "
                              f"({type(e).__name__}: {e})") from None
        try:
            yield client
        finally:
            client.close()
        return
    saved = {k: os.environ.get(k) for k in WORKER_ENV}
    os.environ.update(WORKER_ENV)  # the nanny's worker processes inherit them at start
    # Ctrl-C reaches every process of the terminal's group: workers that took it would each
    # print a traceback. Started with SIGINT ignored (kept across exec, and Python leaves an
    # ignored SIGINT alone), they leave it to this process, which closes the cluster.
    main_thread = threading.current_thread() is threading.main_thread()
    sigint = signal.signal(signal.SIGINT, signal.SIG_IGN) if main_thread else None
    try:
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                               dashboard_address=None, silence_logs=40)
    finally:
        if main_thread:
            signal.signal(signal.SIGINT, sigint)
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    client = Client(cluster)
    if hasattr(os, "sched_setaffinity"):  # Linux; elsewhere the workers stay unpinned
        client.register_plugin(OneCorePerWorker(sorted(os.sched_getaffinity(0))))
    try:
        yield client
    finally:
        client.close()
        cluster.close()


def run_design(design: DesignSpec, modules: dict[str, Module] | None = None, *,
               scheduler: str | None = None, workers: int = 2, batch: int = BATCH,
               limit: int | None = None, progress: bool = False,
               evaluate: Callable = evaluate_batch, client: Any = None) -> DesignResult:
    """Enumerate, filter, predict (as Dask tasks) and rank the candidate assemblies.

    ``limit``: evaluate only the first ``limit`` candidates (benchmarks). ``client``: an open
    Dask client to use instead of making one. ``evaluate``: the task function (tests wrap it
    to lose a worker mid-run).
    """
    from distributed import as_completed

    from bayesrob.progress import progress as make_progress

    t0 = time.perf_counter()
    modules = modules if modules is not None else load_modules(design)
    if _is_chain(modules) and design.fusion != "equilibrium" and design.max_arms > 1 \
            and design.linked:
        raise DesignError(f"{design.path}: fusion = {design.fusion!r} samples every linked "
                          "chain assembly with NUTS, minutes each; chain modules are designed "
                          "with fusion = \"equilibrium\"")
    targets = task_targets(design.region, design.n_targets, design.seed)
    reach = reach_table(modules, design.mounts, targets)
    placements = len(modules) * len(design.mounts)
    unreachable = [n for n in modules if not any(k[0] == n for k in reach)]
    if not reach:
        raise DesignError(f"{design.path}: no module reaches every target from any mount "
                          "point; move the mounts closer to the task region")
    cands = enumerate_candidates(design, reach)
    if limit is not None:
        cands = cands[:limit]
    notes = [f"module {n!r} reaches the task from no mount point" for n in unreachable]
    job = _Job(modules, targets, reach, design.fusion, design.quantile, design.error_mm,
               design.confidence, design.draws, design.seed, design.tracker_noise_mm,
               design.mounts)
    indexed = list(enumerate(cands))
    batches = [indexed[i:i + batch] for i in range(0, len(indexed), batch)]
    results: dict[int, dict] = {}
    ctx = contextlib.nullcontext(client) if client is not None else dask_client(scheduler,
                                                                               workers)
    with ctx as cl, make_progress(len(cands), "design", "candidate", enabled=progress) as bar:
        n_workers = len(cl.scheduler_info().get("workers", {})) or workers
        shared = cl.scatter(job, broadcast=True)
        futures = [cl.submit(evaluate, shared, b, pure=False, retries=3) for b in batches]
        for fut in as_completed(futures):
            done = fut.result()
            results.update(done)  # kept as soon as it is back
            bar.update(len(done))
    ranked = sorted(({**r, "config": "+".join(r["arms"])} for r in results.values()),
                    key=_rank_key)
    for k, r in enumerate(ranked, start=1):
        r["rank"] = k
    return DesignResult(design, targets, ranked, placements, len(reach), n_workers,
                        scheduler or f"LocalCluster({workers} workers)",
                        time.perf_counter() - t0, notes=notes, reach=reach)


# ------------------------------------------------------------------------------ outputs


def design_figure(result: DesignResult, modules: dict[str, Module] | dict[str, ChainModule],
                  top: int = 4) -> Figure:
    """The top candidates side by side: bases, links (posed at the region's first target) and
    a map over the region of the predicted error quantile, interpolated between the targets
    (white dots). Chain modules are seen from above (x-y): each target a dot coloured by its
    error quantile, each arm a dashed line from its base to the first target."""
    import matplotlib.pyplot as plt

    cands = result.candidates[:top]
    if not cands:
        # nothing to rank (every assembly failed to reach the region): say so, with the task
        # region drawn so the reader sees what was asked, rather than leave an empty frame
        fig, ax = plt.subplots(figsize=(6.0, 4.2), layout="constrained")
        lo, hi = result.design.region.min(axis=0), result.design.region.max(axis=0)
        ax.fill([lo[0], hi[0], hi[0], lo[0]], [lo[1], lo[1], hi[1], hi[1]], color="0.9")
        ax.plot(result.targets[:, 0], result.targets[:, 1], "k.", ms=4)
        ax.set_aspect("equal")
        ax.margins(0.3)
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
        ax.set_title("no assembly reaches every target of the task region (grey)\n"
                     "nothing to rank: see the command's output for why", fontsize=10)
        return fig
    n = len(cands)
    fig, axs = plt.subplots(1, n, figsize=(3.6 * n + 1.2, 4.2), squeeze=False, sharex=True,
                            sharey=True, layout="constrained")
    t = result.targets
    values = [v for c in cands for v in c["error_quantile_mm"]]
    vmin, vmax = (min(values), max(values)) if values else (0.0, 1.0)
    levels = np.linspace(vmin, vmax + 1e-9, 13)  # one scale for every panel and the bar
    d = result.design
    q = f"q{round(100 * d.quantile)}"
    sc = None
    chain = _is_chain(modules)
    for ax, c in zip(axs[0], cands, strict=False):
        if chain:
            lo, hi = d.region.min(axis=0), d.region.max(axis=0)
            ax.fill([lo[0], hi[0], hi[0], lo[0]], [lo[1], lo[1], hi[1], hi[1]], color="0.93",
                    zorder=0)
            sc = ax.scatter(t[:, 0], t[:, 1], c=c["error_quantile_mm"], cmap="viridis",
                            vmin=vmin, vmax=vmax, s=30, edgecolors="white", zorder=3)
            for a, b in zip(c["arms"], c["bases"], strict=True):
                ax.plot([b[0], t[0, 0]], [b[1], t[0, 1]], "--", color="0.35", zorder=2)
                ax.plot(b[0], b[1], "k^", ms=9)
                ax.annotate(a, b[:2], textcoords="offset points", xytext=(5, 5), fontsize=8)
            ax.set_aspect("equal")
            ax.set_title(f"#{c['rank']} {c['config']}\n{q} "
                         f"{c['overall']['error_quantile_mm']:.2f} mm, "
                         f"{'meets' if c['meets'] else 'misses'} {d.error_mm:g}", fontsize=9)
            ax.set_xlabel("x (mm), seen from above")
            continue
        ax.fill(*d.region.T, color="0.93", zorder=0)
        sc = ax.tricontourf(t[:, 0], t[:, 1], c["error_quantile_mm"], levels=levels,
                            cmap="viridis", zorder=1)
        ax.plot(t[:, 0], t[:, 1], "o", color="white", ms=2.5, zorder=3)
        aim = t[0]
        for a, b in zip(c["arms"], c["bases"], strict=True):
            arm = modules[a].at(b)
            e = np.asarray(kin.elbow_point(arm.params, arm.inverse(jnp.asarray(aim))))
            ax.plot([b[0], e[0], aim[0]], [b[1], e[1], aim[1]], "-o", color="0.35", ms=3,
                    zorder=2)
            ax.plot(*b, "k^", ms=9)
            ax.annotate(a, b, textcoords="offset points", xytext=(5, 5), fontsize=8)
        ax.set_aspect("equal")
        ax.set_title(f"#{c['rank']} {c['config']}\n{q} {c['overall']['error_quantile_mm']:.2f} mm"
                     f", {'meets' if c['meets'] else 'misses'} {d.error_mm:g}", fontsize=9)
        ax.set_xlabel("x (mm)")
    axs[0][0].set_ylabel("y (mm)")
    if sc is not None:
        fig.colorbar(sc, ax=list(axs[0]), label=f"predicted error at {d.quantile:g} (mm)",
                     shrink=0.8, format="%.2f")
    return fig


def mounted_truth(module: Module, base: Sequence[float]) -> ArmTruth:
    """A simulated module's true arm, moved with its calibrated base to ``base``: the
    mounting moves the whole module, so its calibration's base error moves with it."""
    shift = np.asarray(base, float) - np.asarray(module.arm.params.base, float)
    b = np.asarray(module.truth.base) + shift
    return replace(module.truth, name=module.name, base=(float(b[0]), float(b[1])))


def write_candidate_rig(candidate: dict, result: DesignResult, modules: dict[str, Module],
                        out_dir: str | Path) -> Path:
    """The candidate as a rig directory: rig.toml (the modules' calibrated values at their new
    bases), measurements.csv (the planned test rows: commands and targets, empty x, y) and,
    when every module is simulated, truth.toml (their physics at the new bases) so that
    ``bayesrob simulate DIR --planned`` can measure it; ``bayesrob collect`` on hardware."""
    import csv

    from bayesrob.chain_design import write_chain_candidate_rig
    from bayesrob.rig import (
        MEASUREMENTS_FILE,
        RIG_FILE,
        dump_toml,
        format_row,
        measurement_header,
        rig_toml_dict,
    )
    from bayesrob.simulator import TRUTH_FILE, round_pulse

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if _is_chain(modules):
        write_chain_candidate_rig(candidate, result.targets, modules, result.design.mounts,
                                  result.reach, out)
        _write_candidate_json(candidate, result, out)
        return out
    names = candidate["arms"]
    specs = {a: replace(modules[a].spec, base=tuple(b))
             for a, b in zip(names, candidate["bases"], strict=True)}
    lo, hi = result.design.region.min(axis=0), result.design.region.max(axis=0)
    workspace = ((float(lo[0]), float(hi[0])), (float(lo[1]), float(hi[1])))
    gravity = modules[names[0]].gravity
    doc = rig_toml_dict(f"design-{candidate['config']}", specs, gravity, workspace)
    (out / RIG_FILE).write_text(dump_toml(doc))
    config = "+".join(names)
    pulses = {a: round_pulse(np.asarray(modules[a].at(b).command(jnp.asarray(result.targets))))
              for a, b in zip(names, candidate["bases"], strict=True)}
    with (out / MEASUREMENTS_FILE).open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(measurement_header(names))
        for i, target in enumerate(result.targets):
            w.writerow(format_row(names, config, "test", target,
                                  {a: u[i] for a, u in pulses.items()}, (math.nan, math.nan)))
    mods = [modules[a] for a in names]
    if all(m.truth is not None for m in mods):
        truth = replace(mods[0].truth_rig, name=doc["name"], arms={
            a: mounted_truth(modules[a], b) for a, b in zip(names, candidate["bases"],
                                                            strict=True)},
            workspace=workspace)
        (out / TRUTH_FILE).write_text(truth.to_toml())
    _write_candidate_json(candidate, result, out)
    return out


def _write_candidate_json(candidate: dict, result: DesignResult, out: Path) -> None:
    (out / "design.json").write_text(json.dumps(
        {"candidate": candidate, "requirement": result.design.requirement}, indent=1))
