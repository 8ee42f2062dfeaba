"""The design search (``bayesrob design``): which calibrated modules, mounted where and linked
how, reach a required accuracy over a task region.

Every assembly of ``min_arms`` to ``max_arms`` modules on distinct mounts that reaches every
target is predicted a priori from single-arm data, and ranked: requirement met, fewest
modules, smaller predicted error quantile. Each draw is one build (calibration errors the
same at every target, joint errors and tracker noise per target). A pooled quantile that
just meets the requirement misses it half the time once built, so the requirement means one
thing for every module kind and fusion: at least ``confidence`` of the builds have their own
``quantile`` within ``error_mm`` (:func:`score`).

Candidates run as Dask tasks in batches, so each worker compiles one program per kind of
assembly (modules' arrays and bases are traced arguments); the modules are scattered once.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from bayesrob import release_compiled_programs
from bayesrob.cluster import dask_client, share
from bayesrob.design.file import DesignError, DesignSpec
from bayesrob.design.modules import Module, load_modules

__all__ = ["Candidate", "Job", "DesignResult", "task_targets", "reach_table",
           "enumerate_candidates", "score", "evaluate", "evaluate_batch",
           "run_design", "write_candidate_rig"]

BATCH = 25  # candidates per Dask task: enough to hide a task's overhead, small to spread well
MAX_CANDIDATES = 200_000


def task_targets(region: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """``n`` targets inside the polygon (or 3-D box) ``region``: a scrambled Halton sequence
    over its bounding box, keeping the points inside."""
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


def reach_table(modules: dict[str, Module], mounts: np.ndarray, targets: np.ndarray
                ) -> dict[tuple[str, int], np.ndarray]:
    """{(module, mount index): commands (T, c)} for every placement reaching every target."""
    out = {}
    for name, m in modules.items():
        for j, mount in enumerate(mounts):
            u = m.aim(targets, mount)
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


@dataclass(frozen=True)
class Job:
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
    tracker_noise_mm: float
    mounts: np.ndarray  # (P, dim)
    # each worker's draws that candidates share (placements, rigs' parameters, priors)
    cache: dict = field(default_factory=dict, compare=False)


def score(job: Job, cand: Candidate, d: np.ndarray) -> dict:
    """A candidate's record from its builds d (S, T, dim): quantiles of the distance from the
    targets, and whether ``confidence`` of its builds have their own ``quantile`` within
    ``error_mm``."""
    dist = np.linalg.norm(d - job.targets[None], axis=-1).T  # (T, S)
    per = np.quantile(dist, job.quantile, axis=1)
    pooled = float(np.quantile(dist, job.quantile))
    expected = dist.mean(axis=1)
    # each draw is one possible built assembly: its own quantile over the targets
    own = np.quantile(dist, job.quantile, axis=0)
    confidence = float(np.mean(own <= job.error_mm))
    # the error kept within in `confidence` of the builds (the inverted CDF makes "meets"
    # exactly "assured <= error_mm"), and the error exceeded in `confidence` of them
    assured = float(np.quantile(own, job.confidence, method="inverted_cdf"))
    optimistic = float(np.quantile(own, 1.0 - job.confidence, method="inverted_cdf"))
    return {
        "arms": list(cand.arms), "bases": [list(b) for b in cand.bases],
        "mounts": list(cand.mounts), "linking": cand.linking,
        "models": [job.modules[a].model for a in cand.arms], "fusion": job.fusion,
        "error_quantile_mm": [float(v) for v in per],
        "expected_error_mm": [float(v) for v in expected],
        "expected_point": [[float(v) for v in p] for p in d.mean(axis=0)],
        "overall": {"error_quantile_mm": pooled,
                    "worst_target_quantile_mm": float(per.max()),
                    "expected_error_mm": float(expected.mean()),
                    "assured_error_mm": assured, "optimistic_error_mm": optimistic},
        "confidence": confidence,
        "meets": confidence >= job.confidence,
    }


def evaluate(job: Job, cand: Candidate, index: int) -> dict:
    """A candidate's record: its builds drawn by its modules' kind (seeded by ``index``)."""
    d, extra = type(job.modules[cand.arms[0]]).draws(job, cand.arms, cand.mounts, index)
    return score(job, cand, d) | extra


def evaluate_batch(job: Job, batch: Sequence[tuple[int, Candidate]]) -> list[tuple[int, dict]]:
    """Predict every candidate of a batch (one Dask task): (index, result) pairs."""
    release_compiled_programs()  # a worker lives through many batches
    return [(i, evaluate(job, c, i)) for i, c in batch]


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

    def to_dict(self) -> dict:
        """``design.json``: the name every result's JSON goes by (bayesrob.__all__)."""
        return self.document


def _rank_key(c: dict) -> tuple:
    # those that meet: fewest modules first; those that miss: closest to meeting first
    o = c["overall"]
    return ((False, len(c["arms"]), o["error_quantile_mm"]) if c["meets"]
            else (True, o["assured_error_mm"], len(c["arms"])))


def run_design(design: DesignSpec, modules: dict[str, Module] | None = None, *,
               scheduler: str | None = None, workers: int = 2, batch: int = BATCH,
               limit: int | None = None, progress: bool = False,
               evaluate: Callable = evaluate_batch, client: Any = None) -> DesignResult:
    """Enumerate, filter, predict (as Dask tasks) and rank the candidate assemblies;
    ``limit``: the first candidates only (benchmarks); ``evaluate``: the task function."""
    from distributed import as_completed

    from bayesrob.progress import progress as make_progress

    t0 = time.perf_counter()
    modules = modules if modules is not None else load_modules(design)
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
    job = Job(modules, targets, reach, design.fusion, design.quantile, design.error_mm,
              design.confidence, design.draws, design.seed, design.tracker_noise_mm,
              design.mounts)
    indexed = list(enumerate(cands))
    batches = [indexed[i:i + batch] for i in range(0, len(indexed), batch)]
    results: dict[int, dict] = {}
    ctx = contextlib.nullcontext(client) if client is not None else dask_client(scheduler,
                                                                               workers)
    with ctx as cl, make_progress(len(cands), "design", "candidate", enabled=progress) as bar:
        n_workers = len(cl.scheduler_info().get("workers", {})) or workers
        shared = share(cl, job)
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


def write_candidate_rig(candidate: dict, result: DesignResult, modules: dict[str, Module],
                        out_dir: str | Path) -> Path:
    """The candidate as a rig directory (``Module.write_rig``) to measure, and design.json:
    the candidate and the requirement."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    kind = type(modules[candidate["arms"][0]])
    kind.write_rig(candidate, result.targets, modules, result.reach, result.design.region, out)
    (out / "design.json").write_text(json.dumps(
        {"candidate": candidate, "requirement": result.design.requirement}, indent=1))
    return out
