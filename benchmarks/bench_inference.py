"""Benchmark the samplers of the linked-arms posterior against each other and the grid.

    python benchmarks/bench_inference.py [--model cond] [--config top+bottom]

One JSON line per (method, number of targets) on the embedded default rig: the first linked
target alone, then all 16 targets. Every timing is warm: compilation is done first and
reported separately (``compile_s``), and each method runs once untimed before the timed run.

- ``grid``: :func:`bayesrob.predict.grid.grid_posterior` (the checks' reference: a coarse
  +-30 mm grid, then a zoomed grid over the mass) and, for comparison, the paper's plain
  100 x 100 grid (:func:`bayesrob.predict.grid.predict`).
- ``nuts``: numpyro's NUTS with the package defaults (4 chains x (300 warm-up + 4000 draws)
  per target, acceptance target 0.8), all targets and chains in one vectorised, compiled run.
- ``emcee``: 32 walkers x 2500 steps (500 burned) per target, one ensemble per target.

``ess_bulk_min`` is the smallest bulk ESS over every coordinate of every target (arviz), and
``ess_per_s`` that divided by the sampling wall time: the rate at which the worst-resolved
coordinate of the whole job gains effective draws. The machine may be shared, so NUTS runs
three times (and emcee on one target too) and the run with the median rate is reported, with
the range. ``check`` is the grid cross-check of the reported run.
"""

from __future__ import annotations

import argparse
import json
import time

import jax.numpy as jnp
import numpy as np

import bayesrob  # noqa: F401  (float64)
from bayesrob.calibrate.arms import calibrate_arms
from bayesrob.data.rig import default_rig_dir, load_rig
from bayesrob.errors.noise_models import discover_models, fit_noise_models
from bayesrob.inference import sampling as inf
from bayesrob.predict.grid import Grid, predict


def emit(**fields) -> None:
    print(json.dumps(fields), flush=True)


def timed(fn, *args):
    t0 = time.perf_counter()
    out = fn(*args)
    return out, time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default="cond")
    ap.add_argument("--config", default="top+bottom")
    args = ap.parse_args()

    rig = load_rig(default_rig_dir())
    members = args.config.split("+")
    arms = {n: c.arm for n, c in calibrate_arms(rig).items()}
    fitted = fit_noise_models(rig, arms, discover_models(names=[args.model]))[args.model]
    models = [fitted[a] for a in members]
    arm_list = [arms[a] for a in members]
    all_targets = rig.config_rows(args.config, "test")["target"]
    ratio = {}
    for count in (1, len(all_targets)):
        targets = all_targets[:count]
        cmds = [np.asarray(arms[a].command(jnp.asarray(targets))) for a in members]
        base = {"config": args.config, "model": args.model, "targets": count}

        job = (models, arm_list, cmds, targets)
        grid, compile_s = timed(inf.grid_posterior, *job)
        grid, seconds = timed(inf.grid_posterior, *job)
        emit(**base, method="grid", seconds=seconds, compile_s=compile_s - seconds,
             cells=int(2 * grid.n**2), cell_mm=float(grid.cell_mm.max()))

        job = (args.config, fitted, arms, dict(zip(members, cmds, strict=True)), targets, Grid())
        _, compile_s = timed(predict, *job)
        _, seconds = timed(predict, *job)
        emit(**base, method="grid_paper_100x100", seconds=seconds,
             compile_s=compile_s - seconds, cells=100 * 100)

        def starts(seed: int, n: int, cmds=cmds, targets=targets) -> np.ndarray:
            # as `sample` does: around the target, never from the grid the check uses
            return inf.initial_points(models, arm_list, cmds, targets, n, seed)

        nuts_sampler = inf.NutsSampler()
        nuts_sampler.run(models, arm_list, cmds, starts(0, 4), seed=0)  # compile + warm
        # The machine is shared: repeat the cheap runs and keep the median-rate one. emcee on
        # 16 targets is already 16 runs in a row (about a minute), so it runs once.
        nuts_runs = [nuts_sampler.run(models, arm_list, cmds, starts(k, 4), seed=k)
                     for k in range(1, 4)]
        inf.run_emcee(models, arm_list, cmds, starts(4, 32)[:, :1], n_steps=50, burn=0)
        emcee_runs = [inf.run_emcee(models, arm_list, cmds, starts(k, 32), seed=k)
                      for k in range(5, 8 if count == 1 else 6)]
        for runs in (nuts_runs, emcee_runs):
            runs.sort(key=lambda r: r.ess_per_s)
            res = runs[len(runs) // 2]
            check = inf.cross_check(grid, [res])
            emit(**base, method=res.name, repeats=len(runs), seconds=res.seconds,
                 compile_s=res.compile_seconds, ess_bulk_min=res.ess_bulk,
                 ess_bulk_mean=float(res.summary["ess_bulk"].mean()),
                 r_hat_max=res.r_hat, ess_per_s=res.ess_per_s,
                 ess_per_s_range=[runs[0].ess_per_s, runs[-1].ess_per_s],
                 draws=int(res.idata.posterior.sizes["chain"] * res.idata.posterior.sizes["draw"]),
                 check_passed=check["passed"], failures=check["failures"])
        nuts, emc = nuts_runs[len(nuts_runs) // 2], emcee_runs[len(emcee_runs) // 2]
        ratio[count] = nuts.ess_per_s / emc.ess_per_s
        emit(**base, method="nuts_vs_emcee", ess_per_s_ratio=ratio[count],
             nuts_under_30s=nuts.seconds < 30.0)


if __name__ == "__main__":
    main()
