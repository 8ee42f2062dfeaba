"""NUTS and emcee against the exact grid: every shipped joint-error model's linked posterior at
the default rig's 16 linked test targets, checked as ``bayesrob sample --sampler all`` checks
one target, with the default tolerances (mean within 0.1 mm of the grid's, covariance within
10%, r_hat at most 1.01, bulk ESS at least 400, and no more than 1e-6 of the grid's mass on
the edge of its box).

Each seed is a run of both samplers: NUTS with the package's defaults (4 chains) started from
``initial_points`` seed 2s and run with seed s, emcee (32 walkers) started from seed 2s + 1 and
run with seed s for 1000 steps, 200 burned instead of the command's 2500 and 500: 32 x 800
draws still give a bulk ESS near 5000 per coordinate, far above 400. A (model, target) pair
passes when both samplers meet every tolerance there (r_hat and ESS over that target's two
coordinates) and the grid's box holds its posterior.

A quick run checks one model (ind) at two targets (the docs' (80, 280) and (140, 220)): the
rest is the same code.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence
from typing import Any

import jax.numpy as jnp
import numpy as np

from bayesrob import release_compiled_programs
from bayesrob.calibrate.arms import calibrate_arms
from bayesrob.data.rig import Rig, default_rig_dir, load_rig
from bayesrob.errors.noise_models import discover_models, joint_errors
from bayesrob.inference import sampling as inf
from bayesrob.predict.grid import grid_posterior
from bayesrob.robot import Arm

SAMPLERS = ("nuts", "emcee")
EMCEE_STEPS, EMCEE_BURN = 1000, 200
QUICK_MODELS = ("ind",)
QUICK_TARGETS = (0, 5)  # (80, 280) and (140, 220)
_COORD = re.compile(r"d\[(\d+), ?([xy])\]")


def per_target(res: inf.SamplerResult, n_targets: int) -> tuple[np.ndarray, np.ndarray]:
    """(largest r_hat, smallest bulk ESS) of each target over its two coordinates."""
    r_hat, ess = np.full(n_targets, -np.inf), np.full(n_targets, np.inf)
    for label, row in res.summary.iterrows():
        t = int(_COORD.fullmatch(str(label)).group(1))
        r_hat[t] = max(r_hat[t], row["r_hat"])
        ess[t] = min(ess[t], row["ess_bulk"])
    return r_hat, ess


def check_model(rig: Rig, arms: dict[str, Arm], name: str, target_index: Sequence[int],
                seed: int, tol: inf.CheckTolerances) -> list[dict[str, Any]]:
    """One row per target: each sampler's distance from the grid's mean and covariance, its
    r_hat and bulk ESS there, the grid's edge mass, and whether the pair passes."""
    (spec,) = discover_models(names=[name])
    fitted = {}
    for a in ("top", "bottom"):
        u, d = rig.rows(a, "train")
        fitted[a] = spec.fit(joint_errors(arms[a], u, d), u)
    targets = rig.config_rows("top+bottom", "test")["target"][list(target_index)]
    am = [arms["top"], arms["bottom"]]
    ms = [fitted["top"], fitted["bottom"]]
    cmds = [np.asarray(a.command(jnp.asarray(targets))) for a in am]
    grid = grid_posterior(ms, am, cmds, targets)
    results = {
        "nuts": inf.run_nuts(ms, am, cmds, inf.initial_points(ms, am, cmds, targets, 4, 2 * seed),
                             seed=seed),
        "emcee": inf.run_emcee(ms, am, cmds,
                               inf.initial_points(ms, am, cmds, targets, 32, 2 * seed + 1),
                               seed=seed, n_steps=EMCEE_STEPS, burn=EMCEE_BURN),
    }
    rows = [{"model": name, "seed": seed, "target": [float(v) for v in t],
             "grid_edge_mass": float(grid.edge_mass[k])} for k, t in enumerate(targets)]
    for sampler, res in results.items():
        mean_err = np.linalg.norm(res.mean - grid.mean, axis=-1)
        cov_rel = inf.cov_rel_error(res.cov, grid.cov)
        r_hat, ess = per_target(res, len(targets))
        for k, row in enumerate(rows):
            row[sampler] = {"mean_error_mm": float(mean_err[k]), "cov_rel": float(cov_rel[k]),
                            "r_hat": float(r_hat[k]), "ess_bulk": float(ess[k])}
    for row in rows:
        row["passed"] = bool(row["grid_edge_mass"] <= tol.edge_mass and all(
            row[s]["mean_error_mm"] <= tol.mean_mm and row[s]["cov_rel"] <= tol.cov_rel
            and row[s]["r_hat"] <= tol.r_hat and row[s]["ess_bulk"] >= tol.ess_bulk
            for s in SAMPLERS))
    return rows


def run(seeds: list[int], *, quick: bool, say: Callable[[str], None]) -> dict[str, Any]:
    rig = load_rig(default_rig_dir())
    arms = {n: c.arm for n, c in calibrate_arms(rig).items()}
    names = QUICK_MODELS if quick else tuple(s.name for s in discover_models())
    n_targets = len(rig.config_rows("top+bottom", "test")["target"])
    target_index = QUICK_TARGETS if quick else tuple(range(n_targets))
    tol = inf.CheckTolerances()
    rows: list[dict[str, Any]] = []
    for seed in seeds:
        for name in names:
            got = check_model(rig, arms, name, target_index, seed, tol)
            rows += got
            say(f"seed {seed}, {name}: {sum(r['passed'] for r in got)}/{len(got)} targets pass")
            release_compiled_programs()  # each model's programs are its own
    figures: dict[str, Any] = {
        "pairs": len(rows),
        "pairs_passing_share": float(np.mean([r["passed"] for r in rows])),
        "grid.edge_mass_max": max(r["grid_edge_mass"] for r in rows),
    }
    for s in SAMPLERS:
        figures[f"{s}.mean_error_max_mm"] = max(r[s]["mean_error_mm"] for r in rows)
        figures[f"{s}.cov_rel_max"] = max(r[s]["cov_rel"] for r in rows)
        figures[f"{s}.r_hat_max"] = max(r[s]["r_hat"] for r in rows)
        figures[f"{s}.ess_bulk_min"] = min(r[s]["ess_bulk"] for r in rows)
    figures["details"] = {"pairs": rows, "emcee_steps": EMCEE_STEPS, "emcee_burn": EMCEE_BURN}
    return figures


def tables(entry: dict[str, Any]) -> dict[str, str]:
    """Per model, the worst figure over every target and seed of each sampler."""
    pairs = entry["details"]["pairs"]
    models = list(dict.fromkeys(r["model"] for r in pairs))

    def worst(rows: list[dict], s: str) -> str:
        return (f"{max(r[s]['mean_error_mm'] for r in rows):.3f} / "
                f"{max(r[s]['cov_rel'] for r in rows):.1%} / "
                f"{max(r[s]['r_hat'] for r in rows):.3f} / "
                f"{min(r[s]['ess_bulk'] for r in rows):.0f}")

    lines = ["| model | NUTS: worst mean error / covariance / r_hat / bulk ESS | emcee: the same "
             "| targets passing |", "|---|---|---|---|"]
    for m in models:
        rows = [r for r in pairs if r["model"] == m]
        lines.append(f"| {m} | {worst(rows, 'nuts')} | {worst(rows, 'emcee')} | "
                     f"{sum(r['passed'] for r in rows)} of {len(rows)} |")
    return {"check": "\n".join(lines)}
