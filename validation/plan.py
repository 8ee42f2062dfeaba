"""Planned poses against random ones (``bayesrob plan``, issue 46): held-out error after the
calibration, against the number of poses measured.

``run_sim``: simulated 6-joint arms (arm6, geometry, offsets, marker and instrument pose
perturbed; compliance off), one per seed. A pool of 2,000 poses is drawn over the arm's
working range; the ``accuracy`` plan orders 120 of them; random orders draw 120 from the same
pool. Each is measured on the simulated arm in its order, and for N in 20..120 the first N
rows are calibrated (``frames,offsets,geometric,servo``) and scored on 200 holdout poses of
their own (new poses). A figure per N: the planned error over the median of the random
draws' (below 1: the plan wins).

``justin_table``: Agile Justin's 300 train poses (600 rows, one per hand) as the pool, scored on
its validation poses: the accuracy and identify plans' first N rows against random subsets of
N and 2N rows (``justin_curves``, ``justin_random``).
"""

from __future__ import annotations

import shutil
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from tempfile import TemporaryDirectory
from typing import Any

import numpy as np
from bayesrob.validation.calibration_chain import true_vector

from bayesrob import release_compiled_programs
from bayesrob.calibrate.least_squares import calibrate
from bayesrob.data.rig import Measurements, Rig, load_rig
from bayesrob.plan import load_plan_rig, plan_poses
from bayesrob.sim.rigs import measure_arm6_poses, simulate_arm6_rig
from bayesrob.sim.truth import POSE_HI, POSE_LO, Arm6Truth

NS = (20, 40, 60, 80, 100, 120)
POOL = 2000
N_RANDOM = 5
SIM_GROUPS = ("frames", "offsets", "geometric", "servo")


def subset(rig: Rig, keep: np.ndarray) -> Rig:
    """The rig with only the rows ``keep`` (bool, N)."""
    m = rig.measurements
    return replace(rig, measurements=Measurements(
        m.config[keep], m.set[keep], m.target[keep], {c: u[keep] for c, u in m.commands.items()},
        m.observed[keep], m.line[keep]))


def first_train(rig: Rig, n: int) -> Rig:
    """The rig with its first ``n`` train rows (file order) and every other row."""
    train = rig.measurements.set == "train"
    keep = ~train | (np.cumsum(train) <= n) & train
    return subset(rig, keep)


def heldout_error(rig: Rig, groups: Sequence[str], set: str) -> float:
    """Mean marker error (mm) on the rows of ``set`` after calibrating on the train rows."""
    release_compiled_programs()
    cal = calibrate(rig, tuple(groups), polish=False)
    return float(cal.errors[set]["all"]["mean_mm"])


def model_error(rig: Rig, groups: Sequence[str], x_true: np.ndarray, q: np.ndarray) -> float:
    """Mean distance (mm) between the calibrated and the true arm's marker at poses ``q``:
    the held-out error without the noise of the rows it is scored on."""
    import jax.numpy as jnp

    release_compiled_programs()
    cal = calibrate(rig, tuple(groups), polish=False)
    f = rig.robot.compiled_points("arm")
    diff = np.asarray(f(jnp.asarray(cal.x), jnp.asarray(q))) - np.asarray(
        f(jnp.asarray(x_true), jnp.asarray(q)))
    return float(np.linalg.norm(diff, axis=1).mean())


def _write_pool(path: Path, q: np.ndarray) -> None:
    lines = ["arm_u1,arm_u2,arm_u3,arm_u4,arm_u5,arm_u6"]
    lines += [",".join(f"{v:.10g}" for v in row) for row in q]
    path.write_text("\n".join(lines) + "\n")


def sim_curves(seed: int, work: Path, ns: Sequence[int] = NS, n_random: int = N_RANDOM,
               groups: Sequence[str] = SIM_GROUPS) -> dict[str, Any]:
    """One simulated arm's held-out errors (mm) at each N: planned, and each random draw."""
    base = work / "rig"
    simulate_arm6_rig(base, Arm6Truth(seed=seed, n_train=0, n_validation=0, n_holdout=200))
    rng = np.random.default_rng([seed, 46])
    q = rng.uniform(POSE_LO, POSE_HI, size=(POOL, 6))
    _write_pool(work / "pool.csv", q)
    n_max = max(ns)
    plan = plan_poses(load_plan_rig(base), n_max, pool=work / "pool.csv", groups=tuple(groups))
    orders = {"planned": plan.selection.order}
    for r in range(n_random):
        orders[f"random{r}"] = rng.permutation(POOL)[:n_max]
    out: dict[str, Any] = {"plan_seconds": plan.seconds, "predicted_mm": plan.after}
    q_new = rng.uniform(POSE_LO, POSE_HI, size=(200, 6))
    for name, order in orders.items():
        d = work / name
        shutil.copytree(base, d)
        measure_arm6_poses(d, ["train"] * n_max, q[order], seed=seed)
        rig = load_rig(d)
        x_true = true_vector(d, rig)
        out[name] = [model_error(first_train(rig, n), groups, x_true, q_new) for n in ns]
    return out


def run_sim(seeds: list[int], *, quick: bool, say: Callable[[str], None]) -> dict[str, Any]:
    ns = (20, 60) if quick else NS
    rows = []
    for seed in seeds:
        with TemporaryDirectory() as tmp:
            c = sim_curves(seed, Path(tmp), ns, 2 if quick else N_RANDOM)
        med = np.median([c[k] for k in c if k.startswith("random")], axis=0)
        rows.append({"seed": seed, "planned_mm": c["planned"], "random_median_mm": med.tolist(),
                     "plan_seconds": c["plan_seconds"]})
        say(f"seed {seed}: planned {np.round(c['planned'], 3).tolist()} random median "
            f"{np.round(med, 3).tolist()} mm at N={list(ns)}")
    ratio = np.array([np.array(r["planned_mm"]) / np.array(r["random_median_mm"])
                      for r in rows])
    figures: dict[str, Any] = {f"ratio_n{n}": float(np.median(ratio[:, i]))
                               for i, n in enumerate(ns)}
    figures["worst_ratio"] = float(ratio.max())
    figures["planned_wins_share"] = float(np.mean(ratio < 1.0))
    figures["details"] = {"ns": list(ns), "rigs": rows}
    return figures


def _justin_pool(rig_dir: Path) -> tuple[Rig, np.ndarray, Path]:
    """Justin's rig, its train rows (the pool, in file order) and the pool file of them."""
    rig = load_rig(rig_dir)
    train = rig.measurements.set == "train"
    lines = (rig_dir / "measurements.csv").read_text().splitlines()
    set_col = lines[0].split(",").index("set")
    pool = rig_dir / "pool.csv"
    pool.write_text("\n".join([lines[0], *(ln for ln in lines[1:]
                                            if ln.split(",")[set_col] == "train")]) + "\n")
    return rig, train, pool


def _justin_score(rig: Rig, train: np.ndarray, chosen: np.ndarray,
                  groups: Sequence[str]) -> float:
    keep = ~train
    keep[np.flatnonzero(train)[chosen]] = True
    return heldout_error(subset(rig, keep), groups, "validation")


# the accuracy plan's settings for Justin, chosen on inner splits of its 300 train poses
# (plans from 200, scored on the other 100; three splits): the sag frames,geometric leaves out
# as a nuisance of one typical size, the fitted parameters one typical size about nominal
JUSTIN_ACCURACY = {"omitted_sd": 1.0, "prior_sd": 1.0}


def justin_curves(rig_dir: Path, groups: Sequence[str], ns: Sequence[int],
                  criteria: Sequence[str] = ("accuracy", "identify"),
                  accuracy: dict[str, float] | None = None) -> dict[str, Any]:
    """Agile Justin: each criterion's plan's first N train rows, calibrated with ``groups`` and
    scored on the validation rows (mean mm); ``accuracy``: that plan's options."""
    rig, train, pool = _justin_pool(rig_dir)
    out: dict[str, Any] = {"ns": list(ns), "accuracy_options": accuracy or {}}
    for criterion in criteria:
        plan = plan_poses(subset(rig, ~train), max(ns), criterion=criterion, pool=pool,
                          groups=tuple(groups),
                          **(accuracy or {} if criterion == "accuracy" else {}))
        out[criterion] = [_justin_score(rig, train, plan.selection.order[:n], groups)
                          for n in ns]
        out[f"{criterion}_seconds"] = plan.seconds
    return out


def justin_random(rig_dir: Path, groups: Sequence[str], sizes: Sequence[int], n_random: int,
                  seed: int) -> dict[int, list[float]]:
    """Agile Justin: ``n_random`` random orders of the train rows, each scored (as
    :func:`justin_curves`) at its first n rows for every n of ``sizes``."""
    rig, train, _ = _justin_pool(rig_dir)
    rng = np.random.default_rng(seed)
    orders = [rng.permutation(int(train.sum())) for _ in range(n_random)]
    return {n: [_justin_score(rig, train, o[:n], groups) for o in orders] for n in sizes}


JUSTIN_PARAMS = ("frames,geometric", "frames,geometric,compliance,lateral")


def justin_table(rig_dir: Path, ns: Sequence[int] = (40, 80), n_random: int = 20,
                 seed: int = 4620) -> dict[str, Any]:
    """Issue 46's Agile Justin table, per parameter set: the accuracy and identify plans'
    first N rows, and ``n_random`` random orders scored at N and 2N rows (the figure's JSON,
    ``benchmarks/bench_plan.py --justin-table``). Run once, after the choices were made on
    inner splits of the train poses: the validation rows choose nothing."""
    sizes = sorted({k * n for n in ns for k in (1, 2)})
    table = {}
    for params in JUSTIN_PARAMS:
        groups = tuple(params.split(","))
        table[params] = justin_curves(rig_dir, groups, ns, accuracy=JUSTIN_ACCURACY)
        table[params]["random"] = {str(n): v for n, v in
                                   justin_random(rig_dir, groups, sizes, n_random, seed).items()}
    return table
