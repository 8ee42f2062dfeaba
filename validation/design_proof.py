"""The configuration designer's proof in simulation (docs/design.md, "Scale and proof"):
designs are built in the simulator and measured, and what was predicted is held against what
the builds give.

Planar proof (:func:`run`): inventories of three simulated arms (``bayesrob simulate --robot
three-arm --stiffness-spread 0.3``) are each designed with the worked example's design file,
the requirement loosened to PROOF_ERROR_MM. Tuning: the worked example's mounts and 1.2 mm
were chosen on seed 5; PROOF_ERROR_MM on seeds 1-4, as the tightest of 1.2, 1.3, ..., 1.8 mm
at which every tuning inventory had a candidate meeting it (seed 2's best is assured within
1.25 mm with the inventories' stiffnesses drawn, 1.29 mm with arms alike, since the tracker's
noise was taken out of the modules' joint errors; 1.5 mm before that, 1.8 mm before the
parameter covariance's jitter was made relative, which had widened every prediction). The best
candidate and the best-ranked candidate predicted to miss (its ``optimistic_error_mm`` beyond
the requirement: a miss in 90% of builds) are then built in the simulator (their modules
moved to the chosen mounts, measured REPEATS times at every target). Every other candidate
predicted to miss is built too, and how many of them missed is reported beside it. The worked
example's own 1.2 mm is read off the same runs (``assured_error_mm``): how many designs have a
candidate meeting it, and whether that one holds once built.

Chain proof (:func:`chain_run`): two 6-joint 3-D arms that sag under gravity (``bayesrob
simulate --robot arm6 --linked``) are the modules, calibrated with joint compliance on their
single-arm rows; the simulator aims its linked rows through the same calibration, so they are
the assembly as a user of the design would build it. At the rig's linked targets and commands
the design's draws of each placement (each arm alone, the two linked, a priori: no linked row
is read) are compared with the simulated measurements: the linked rows, and each arm alone at
the same commands (the truth's free points, plus the tracker's 0.1 mm noise). Reported: the
share of measured errors within the predicted 50% / 90% / 95% quantile of the error at their
target and predicted / observed mean error. Placing a module elsewhere is a translation, which
leaves the simulator's physics (a uniform gravity) and the prediction alike unchanged
(``tests/test_chain_design.py``), so what holds here holds at any mount.
"""

from __future__ import annotations

import json
import shutil
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from bayesrob.validation.study import repository

# The worked example: the proof designs with its file. It is read from the checkout, as the
# validation suite and the benchmarks run there.
EXAMPLE = repository() / "examples" / "design"
REPORT_SEEDS = tuple(range(101, 111))
# The second report set, fixed on 2026-11-26 with its criterion before its first run: only
# one of the first ten designs had a candidate predicted to miss.
SECOND_REPORT_SEEDS = tuple(range(111, 131))
TUNING_SEEDS = (1, 2, 3, 4)
REPEATS = 5
PROOF_ERROR_MM = 1.3  # chosen on the tuning seeds 1-4 (see above)
# Each inventory's arms have their own stiffnesses (drawn per seed as in the report rigs of
# the linked coverage): with every arm alike the stiffness prior would be flattered.
INVENTORY_STIFFNESS_LOG_SD = 0.3
EXAMPLE_ERROR_MM = 1.2
CHAIN_SEEDS = (301, 302, 303)
# The linked modules' arm terms centred on their fitted sags, as `bayesrob predict` centres
# them, reported on rigs of their own (fixed before the first run; 301 and 302 were among the
# rigs that led to that prior, bench_predict_3d.py's 291-302)
CHAIN_SAG_REPORT_SEEDS = tuple(range(331, 337))
CHAIN_PARAMS = "frames,offsets,geometric,compliance"
# --masses description: each simulated arm's true link masses this far (log sd) from the
# URDF's, as the linked coverage study draws them (validation/linked_chain.py)
DESCRIBED_MASS_SPREAD = 0.1
CHAIN_KINDS = ("left+right", "left", "right")
CHAIN_LEVELS = (0.5, 0.9, 0.95)


def design_file(tmp: Path, seed: int | None, text_changes: dict[str, str] | None = None
                ) -> Path:
    """The worked example's design file in ``tmp`` over the inventory of ``seed`` (simulated
    there; None: the example's own modules), with ``text_changes`` made to its text."""
    from bayesrob.sim.rigs import simulate_rig
    from bayesrob.sim.truth import three_arm_truth

    if not (EXAMPLE / "design.toml").is_file():
        raise FileNotFoundError(f"the design proof designs with the worked example "
                                f"{EXAMPLE / 'design.toml'}, found in a checkout only")
    modules = tmp / f"modules-{seed}"
    if seed is None:
        shutil.copytree(EXAMPLE / "modules", modules)
    else:
        simulate_rig(modules, three_arm_truth(seed=seed,
                                              stiffness_log_sd=INVENTORY_STIFFNESS_LOG_SD))
    text = (EXAMPLE / "design.toml").read_text().replace('rig = "modules"',
                                                          f'rig = "{modules.name}"')
    for old, new in (text_changes or {}).items():
        text = text.replace(old, new)
    path = tmp / f"design-{seed}.toml"
    path.write_text(text)
    return path


def built_errors(modules: dict, candidate: dict, targets: np.ndarray, seed: int) -> np.ndarray:
    """Distances from the targets of a candidate built in the simulator (its modules' true
    arms moved to the chosen mounts), measured REPEATS times at every target."""
    import jax.numpy as jnp

    from bayesrob.design.modules import mounted_truth
    from bayesrob.sim.equilibrium import PhysicalRig
    from bayesrob.sim.rigs import round_pulse

    arms, bases = candidate["arms"], candidate["bases"]
    truth = replace(modules[arms[0]].truth_rig, arms={
        a: mounted_truth(modules[a], b) for a, b in zip(arms, bases, strict=True)})
    plant = PhysicalRig(truth, seed=seed)
    aimed = [{a: round_pulse(np.asarray(modules[a].at(b).command(jnp.asarray(t))))
              for a, b in zip(arms, bases, strict=True)} for t in targets]
    return np.array([np.linalg.norm(plant.end_point(cmds) - t)
                     for _ in range(REPEATS) for t, cmds in zip(targets, aimed, strict=True)])


def observed_quantile(modules: dict, candidate: dict, targets: np.ndarray, seed: int,
                      quantile: float) -> float:
    """The ``quantile`` of a built candidate's measured errors."""
    return float(np.quantile(built_errors(modules, candidate, targets, seed), quantile))


def proof(seeds: Sequence[int] = REPORT_SEEDS, say: Callable[[str], None] = print
          ) -> dict[str, Any]:
    """The planar proof on ``seeds``: a row per design (each also said as a JSON line) and the
    summary; ``met`` is the second report set's criterion, written down before it ran: the
    best holds in at least 90% of designs, and of the designs with a candidate predicted to
    miss, the best-ranked one misses in at least 80%."""
    from bayesrob.cluster import dask_client
    from bayesrob.design.file import load_design
    from bayesrob.design.modules import load_modules
    from bayesrob.design.search import run_design

    rows = []
    with tempfile.TemporaryDirectory(prefix="bayesrob-design-proof-") as tmp, \
            dask_client(None, 2) as client:
        for seed in seeds:
            design = load_design(design_file(Path(tmp), seed, {
                f"error_mm = {EXAMPLE_ERROR_MM}": f"error_mm = {PROOF_ERROR_MM}"}))
            modules = load_modules(design)
            res = run_design(design, modules, client=client)
            q, req = design.quantile, design.error_mm
            best = res.best
            row = {"seed": seed, "best": best["config"], "best_bases": best["bases"],
                   "best_predicted_mm": best["overall"]["error_quantile_mm"],
                   "best_assured_mm": best["overall"]["assured_error_mm"],
                   "best_meets_predicted": best["meets"]}
            row["best_observed_mm"] = observed_quantile(modules, best, res.targets, seed, q)
            row["best_holds"] = bool(best["meets"] and row["best_observed_mm"] <= req)
            # every candidate predicted to miss is built, in rank order: the first, the
            # best-ranked (the most marginal), is the proof's; the others are reported beside
            misses = [(c, observed_quantile(modules, c, res.targets, seed, q))
                      for c in res.candidates if c["overall"]["optimistic_error_mm"] > req]
            if misses:
                miss, observed = misses[0]
                row.update({"miss": miss["config"], "miss_bases": miss["bases"],
                            "miss_predicted_mm": miss["overall"]["error_quantile_mm"],
                            "miss_optimistic_mm": miss["overall"]["optimistic_error_mm"],
                            "miss_observed_mm": observed})
                row["miss_misses"] = bool(observed > req)
            row["all_misses"] = len(misses)
            row["all_misses_missed"] = int(sum(obs > req for _, obs in misses))
            # the worked example's requirement, read off the same predictions
            tight = [c for c in res.candidates
                     if c["overall"]["assured_error_mm"] <= EXAMPLE_ERROR_MM]
            if tight:
                b = min(tight, key=lambda c: (len(c["arms"]), c["overall"]["error_quantile_mm"]))
                row["example_best"] = b["config"]
                row["example_observed_mm"] = observed_quantile(modules, b, res.targets, seed,
                                                               q)
            say(json.dumps(row))
            rows.append(row)
    held = sum(r["best_holds"] for r in rows)
    missed = sum(r.get("miss_misses", False) for r in rows)
    with_miss = sum("miss" in r for r in rows)
    example = [r for r in rows if "example_best" in r]
    return {"designs": len(rows), "requirement_mm": PROOF_ERROR_MM, "quantile": design.quantile,
            "best_holds": held, "predicted_misses": with_miss, "predicted_miss_misses": missed,
            "every_predicted_miss": sum(r["all_misses"] for r in rows),
            "every_predicted_miss_missed": sum(r["all_misses_missed"] for r in rows),
            "example_requirement_mm": EXAMPLE_ERROR_MM, "example_with_winner": len(example),
            "example_winner_holds": sum(r["example_observed_mm"] <= EXAMPLE_ERROR_MM
                                        for r in example),
            "met": bool(held >= 0.9 * len(rows) and missed >= 0.8 * with_miss),
            "rows": rows}


def run(seeds: list[int], *, quick: bool, say: Callable[[str], None]) -> dict[str, Any]:
    """The planar proof as a study: shares of designs, and counts recorded beside them."""
    count = iter(range(1, len(seeds) + 1))
    got = proof(seeds, say=lambda line: say(f"design {next(count)}/{len(seeds)}: {line}"))
    n, with_miss = got["designs"], got["predicted_misses"]
    every = got["every_predicted_miss"]
    figures = {
        "designs": n,
        "best_holds": got["best_holds"] / n,
        "best_observed_max_mm": max(r["best_observed_mm"] for r in got["rows"]),
        "designs_with_predicted_miss": with_miss,
        # no design with a candidate predicted to miss leaves the share undefined (NaN)
        "best_ranked_miss_misses": (got["predicted_miss_misses"] / with_miss if with_miss
                                    else float("nan")),
        "every_predicted_miss": every,
        "every_predicted_miss_missed": (got["every_predicted_miss_missed"] / every if every
                                        else float("nan")),
        "example_with_winner": got["example_with_winner"] / n,
        "example_winner_holds": (got["example_winner_holds"] / got["example_with_winner"]
                                 if got["example_with_winner"] else float("nan")),
    }
    return figures | {"details": {"study": "proof", "requirement_mm": PROOF_ERROR_MM,
                                  "rows": got["rows"]}}


def chain_proof(masses: str = "fitted", mass_log_sd: float = 0.0,
                seeds: Sequence[int] = CHAIN_SEEDS, say: Callable[[str], None] = print
                ) -> dict[str, Any]:
    """The chain proof on ``seeds`` (a row per rig in ``rows``, each also said as a JSON
    line). ``masses``: the modules' (``masses = "description"``: held at the URDF's, their
    stiffnesses read from the fitted compliances); ``mass_log_sd``: how far each simulated
    arm's true link masses stray from the URDF's. ``met`` per placement: every quantile's
    share within two standard errors of nominal at the pooled rows, and the error ratio in
    0.85-1.15 (the criterion written down before the first report rigs ran)."""
    from bayesrob.data.rig import load_rig
    from bayesrob.design.file import load_design
    from bayesrob.design.modules import CalibratedModule, load_modules
    from bayesrob.design.search import Job, reach_table
    from bayesrob.sim.rigs import simulate_linked_arm6_rig
    from bayesrob.sim.truth import LinkedArm6Truth, load_linked_truth

    inside = {k: {q: [] for q in CHAIN_LEVELS} for k in CHAIN_KINDS}
    means = {k: ([], []) for k in CHAIN_KINDS}
    rows = []
    with tempfile.TemporaryDirectory(prefix="bayesrob-chain-proof-") as tmp:
        for seed in seeds:
            rig_dir = simulate_linked_arm6_rig(
                Path(tmp) / f"rig-{seed}",
                LinkedArm6Truth(seed=seed, calibration_groups=tuple(CHAIN_PARAMS.split(",")),
                                 mass_log_sd=mass_log_sd))
            path = Path(tmp) / f"design-{seed}.toml"
            # mounts and task only complete the file; the placements are set below
            path.write_text(f"""
seed = {seed}
tracker_noise_mm = 0.1
[modules.left]
rig = "{rig_dir}"
params = "{CHAIN_PARAMS}"
masses = "{masses}"
[modules.right]
rig = "{rig_dir}"
params = "{CHAIN_PARAMS}"
masses = "{masses}"
[mounts]
points = [[0.0, 0.0, 0.0]]
[task]
box = [[0.0, 1.0], [0.0, 1.0], [0.0, 1.0]]
[requirement]
error_mm = 1.0
quantile = 0.95
""")
            design = load_design(path)
            modules = load_modules(design)
            rig = load_rig(rig_dir)
            truth = load_linked_truth(rig_dir)["linked_rows"]
            m = rig.measurements.mask("left+right", "test")
            targets = rig.measurements.target[m]
            built = {a: rig.measurements.commands[a][m] for a in ("left", "right")}
            mounts = np.array([modules["left"].base, modules["right"].base])
            aimed = reach_table(modules, mounts, targets)
            reach = {(a, j): built[a] for j, a in enumerate(("left", "right"))}
            job = Job(modules, targets, reach, "equilibrium", 0.95, 1.0, 0.9, design.draws,
                      seed, design.tracker_noise_mm, mounts)
            noise = np.random.default_rng(seed).normal(0, 0.1, (2, *targets.shape))
            seen = {"left+right": rig.measurements.observed[m],
                    **{a: np.asarray(truth[f"free_{a}"]) + noise[i]
                       for i, a in enumerate(("left", "right"))}}
            # how far the design's own aim is from the built commands (angles wrapped: a
            # turn more is the same pose); predictions are drawn at the built commands
            gap = max(np.abs(np.angle(np.exp(1j * (aimed[a, j] - built[a])))).max()
                      for j, a in enumerate(("left", "right")))
            row = {"seed": seed, "rows": len(targets), "aim_vs_built_rad": float(gap)}
            for kind in CHAIN_KINDS:
                arms = tuple(kind.split("+"))
                d, _ = CalibratedModule.draws(job, arms, tuple(0 if a == "left" else 1
                                                               for a in arms), 0)
                err = np.linalg.norm(d - targets[None], axis=-1)  # (S, T)
                obs = np.linalg.norm(seen[kind] - targets, axis=1)
                means[kind][0].append(err.mean(axis=0))
                means[kind][1].append(obs)
                row[kind] = {"observed_mean_mm": float(obs.mean()),
                             "predicted_mean_mm": float(err.mean())}
                for q in CHAIN_LEVELS:
                    hit = obs <= np.quantile(err, q, axis=0)
                    inside[kind][q].extend(hit.tolist())
                    row[kind][f"within_q{round(100 * q)}"] = float(hit.mean())
            say(json.dumps(row))
            rows.append(row)
    out: dict[str, Any] = {"rigs": len(rows)}
    met = True
    for kind in CHAIN_KINDS:
        n = len(inside[kind][0.5])
        k = {"rows": n, **{f"within_q{round(100 * q)}": float(np.mean(v))
                           for q, v in inside[kind].items()},
             "error_ratio": float(np.concatenate(means[kind][0]).mean()
                                  / np.concatenate(means[kind][1]).mean())}
        # nominal within binomial error: two standard errors at the pooled count
        k["met"] = bool(all(abs(k[f"within_q{round(100 * q)}"] - q)
                            <= 2 * np.sqrt(q * (1 - q) / n) for q in CHAIN_LEVELS)
                        and 0.85 <= k["error_ratio"] <= 1.15)
        met = met and k["met"]
        out[kind] = k
    out["met"] = met
    out["rows"] = rows
    return out


def chain_run(seeds: list[int], *, quick: bool, say: Callable[[str], None]) -> dict[str, Any]:
    """The chain proof as a study, the modules' masses fitted: per placement (``linked``,
    ``left``, ``right``) the shares within the predicted quantiles and the error ratio."""
    count = iter(range(1, len(seeds) + 1))
    got = chain_proof(seeds=seeds,
                      say=lambda line: say(f"rig {next(count)}/{len(seeds)}: {line}"))
    figures: dict[str, Any] = {"rigs": got["rigs"]}
    for kind in CHAIN_KINDS:
        name = "linked" if "+" in kind else kind
        for key, value in got[kind].items():
            if key != "met":
                figures[f"{name}.{key}"] = value
    return figures | {"details": {"study": "chain_proof", "rows": got["rows"]}}


def _mm(value: float | None) -> str:
    return "" if value is None else f"{value:.2f}"


def tables(entry: dict[str, Any]) -> dict[str, str]:
    f, d = entry["figures"], entry.get("details") or {}
    if d.get("study") == "proof":
        rows = d["rows"]
        designs = ["| seed | best | predicted q95 / assured (mm) | built q95 | best-ranked "
                   "predicted miss: optimistic / pooled q95 (mm) | built q95 |",
                   "|---|---|---|---|---|---|"]
        for r in rows:
            miss = (f"{r['miss']}: {_mm(r['miss_optimistic_mm'])} / "
                    f"{_mm(r['miss_predicted_mm'])}" if "miss" in r else "none")
            built = (f"{_mm(r['miss_observed_mm'])} "
                     f"({'misses' if r['miss_misses'] else 'holds'})" if "miss" in r else "")
            designs.append(f"| {r['seed']} | {r['best']} | {_mm(r['best_predicted_mm'])} / "
                           f"{_mm(r['best_assured_mm'])} | {_mm(r['best_observed_mm'])} | "
                           f"{miss} | {built} |")
        misses = ["| seed | best | built q95 (mm) | best-ranked predicted miss | optimistic / "
                  "pooled q95 (mm) | built q95 |", "|---|---|---|---|---|---|"]
        others = [r for r in rows if "miss" not in r]
        for r in rows:
            if "miss" in r:
                where = ", ".join(f"{b[0]:.0f}, {b[1]:.0f}" for b in r["miss_bases"])
                misses.append(f"| {r['seed']} | {r['best']} | {_mm(r['best_observed_mm'])} | "
                              f"{r['miss']} at ({where}) | {_mm(r['miss_optimistic_mm'])} / "
                              f"{_mm(r['miss_predicted_mm'])} | "
                              f"{_mm(r['miss_observed_mm'])} "
                              f"({'misses' if r['miss_misses'] else 'holds'}) |")
        if others:
            bests: dict[str, int] = {}
            for r in others:
                bests[r["best"]] = bests.get(r["best"], 0) + 1
            built = [r["best_observed_mm"] for r in others]
            misses.append(f"| the {len(others)} others | "
                          + ", ".join(f"{k} {v}" for k, v in sorted(bests.items(),
                                                                    key=lambda kv: -kv[1]))
                          + f" | {min(built):.2f}-{max(built):.2f} | none | | |")
        return {"designs": "\n".join(designs), "misses": "\n".join(misses)}
    if d.get("study") == "chain_proof":
        n = f.get("linked.rows", 0)
        out = [f"| placement, {n} rows | predicted / measured mean error | within q50 / q90 / "
               "q95 |", "|---|---|---|"]
        for name, label in (("left", "left alone"), ("right", "right alone"),
                            ("linked", "left+right linked")):
            out.append(f"| {label} | {f[f'{name}.error_ratio']:.3f} | "
                       f"{f[f'{name}.within_q50']:.2f} / {f[f'{name}.within_q90']:.2f} / "
                       f"{f[f'{name}.within_q95']:.2f} |")
        return {"chain": "\n".join(out)}
    return {}
