"""The configuration designer at scale, and its proof in simulation.

    python benchmarks/bench_design.py            # scale: 1,000 candidates, 1 worker then 2
    python benchmarks/bench_design.py --proof    # 10 report inventories, designs simulated
    python benchmarks/bench_design.py --proof --seeds 111-130   # the second report set
    python benchmarks/bench_design.py --chain-proof   # 6-joint 3-D modules, assemblies built
    python benchmarks/bench_design.py --chain-proof --masses description   # stiffnesses from masses
    python benchmarks/bench_design.py --chain-proof --sag-report   # fresh rigs 331-336
    python benchmarks/bench_design.py --tuning   # tuning inventories: predicted builds vs built

Scale (prints one JSON line): 1,000 candidate assemblies of 2-3 planar arms at 16 targets each
on a LocalCluster, first with one worker, then with two (each single-threaded, so one worker
does not quietly use both cores). Targets: two workers under 10 minutes; speed-up of two over
one at least 1.7x.

Proof (prints a line per design and a JSON summary): ten inventories of three simulated arms
(``bayesrob simulate --robot three-arm --stiffness-spread 0.3``, report seeds 101-110) are each
designed with the worked example's design file, the requirement loosened to PROOF_ERROR_MM. Tuning:
the worked example's mounts and 1.2 mm were chosen on seed 5; PROOF_ERROR_MM on seeds 1-4, as the
tightest of 1.2, 1.3, ..., 1.8 mm at which every tuning inventory had a candidate meeting it (seed
2's best is assured within 1.25 mm with the inventories' stiffnesses drawn, 1.29 mm with arms alike,
since the tracker's noise was taken out of the modules' joint errors; 1.5 mm before that, 1.8 mm
before the parameter covariance's jitter was made relative, which had widened every prediction). The
report seeds were not used to choose anything. The best candidate and the best-ranked candidate
predicted to miss (its ``optimistic_error_mm`` beyond the requirement: a miss in 90% of builds) are
then built in the simulator (their modules moved to the chosen mounts, measured five times at every
target); the requirement holds for the best in at least 9 of 10 designs, and the predicted miss
misses. Every other candidate predicted to miss is built too, and how many of them missed is
reported beside it (``every_predicted_miss``). The worked example's own 1.2 mm is read off the same
runs (``assured_error_mm``): how many designs have a candidate meeting it, and whether that one
holds once built.

Second report set (``--seeds 111-130``): twenty more inventories, fixed on 2026-11-26 before
their first run, because only one of the first ten designs had a candidate predicted to miss,
so the first set could not say whether predicted misses miss. Nothing is chosen on them; the
criterion was written down before they ran: the best holds in at least 90% of designs, and of
the designs with a candidate predicted to miss, the best-ranked one (the most marginal: a miss
in about 90% of its builds, by construction) misses in at least 80% (at a handful of designs,
80% is within binomial error of the 90% claimed).

Tuning (``--tuning``; a line per built candidate and a JSON summary): on the tuning
inventories TUNING_SEEDS, every single arm and one multi-arm candidate in ten is built as in
the proof, and each built q95 is placed among its predicted builds: how many fall below the
optimistic (10%) point and above the assured (90%) point (a tenth of them each, when the
predictions are right). Changes to the predictions are judged here, never on the report seeds.

Chain proof (a line per rig and a JSON summary): two 6-joint 3-D arms that sag under gravity
(``bayesrob simulate --robot arm6 --linked``, report seeds CHAIN_SEEDS, fixed before any run;
nothing was tuned on them or on any other rig for this) are the modules, calibrated with
joint compliance on their single-arm rows; the simulator aims its linked rows through the
same calibration, so they are the assembly as a user of the design would build it. At the
rig's linked targets and commands the design's draws of each placement (each arm alone, the
two linked, a priori: no linked row is read) are compared with the simulated measurements:
the linked rows, and each arm alone at the same commands (the truth's free points, plus the
tracker's 0.1 mm noise). Reported: the share of measured errors within the predicted 50% /
90% / 95% quantile of the error at their target (nominal within binomial error over the
pooled rows) and predicted / observed mean error. Placing a module elsewhere is a
translation, which leaves the simulator's physics (a uniform gravity) and the prediction
alike unchanged (``tests/test_chain_design.py``), so what holds here holds at any mount.
``--sag-report`` runs it on CHAIN_SAG_REPORT_SEEDS, the rigs that report the designer's
linked modules centred on their fitted sags; ``--arm-centre equal`` draws them as before.
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from bayesrob.kinematics import MASS_SOURCES

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "design"
REPORT_SEEDS = tuple(range(101, 111))
TUNING_SEEDS = (1, 2, 3, 4)
TUNING_EVERY = 10  # one multi-arm candidate in this many is built (all single arms are)
REPEATS = 5
SCALE_CANDIDATES = 1000
TARGET_S = 600.0
TARGET_SPEEDUP = 1.7
PROOF_ERROR_MM = 1.3  # chosen on the tuning seeds 1-4 (see above)
# Each inventory's arms have their own stiffnesses (drawn per seed as in the report rigs of
# the linked coverage): with every arm alike the stiffness prior would be flattered.
INVENTORY_STIFFNESS_LOG_SD = 0.3
EXAMPLE_ERROR_MM = 1.2
CHAIN_SEEDS = (301, 302, 303)
# --sag-report: the linked modules' arm terms centred on their fitted sags, as `bayesrob
# predict` centres them, reported on rigs of their own (fixed before the first run; 301 and
# 302 were among the rigs that led to that prior, bench_predict_3d.py's 291-302)
CHAIN_SAG_REPORT_SEEDS = tuple(range(331, 337))
CHAIN_PARAMS = "frames,offsets,geometric,compliance"
# --masses description: each simulated arm's true link masses this far (log sd) from the
# URDF's, as the linked coverage study draws them (bench_predict_3d.py)
DESCRIBED_MASS_SPREAD = 0.1


def _design(tmp: Path, seed: int | None, text_changes: dict[str, str] | None = None) -> Path:
    from bayesrob.simulator import simulate_rig, three_arm_truth

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

    from bayesrob.design import mounted_truth
    from bayesrob.simulator import PhysicalRig, round_pulse

    arms, bases = candidate["arms"], candidate["bases"]
    truth = replace(modules[arms[0]].truth_rig, arms={
        a: mounted_truth(modules[a], b) for a, b in zip(arms, bases, strict=True)})
    plant = PhysicalRig(truth, seed=seed)
    aimed = [{a: round_pulse(np.asarray(modules[a].at(b).command(jnp.asarray(t))))
              for a, b in zip(arms, bases, strict=True)} for t in targets]
    return np.array([np.linalg.norm(plant.end_point(cmds) - t)
                     for _ in range(REPEATS) for t, cmds in zip(targets, aimed, strict=True)])


def scale() -> dict:
    from bayesrob.design import load_design, load_modules, run_design

    with tempfile.TemporaryDirectory() as tmp:
        path = _design(Path(tmp), None, {
            "grid = { x = [-170.0, 20.0, 3], y = [-20.0, 440.0, 4] }":
                "grid = { x = [-170.0, 20.0, 4], y = [-20.0, 440.0, 5] }",
            "max_arms = 3": "max_arms = 3\nmin_arms = 2"})
        design = load_design(path)
        modules = load_modules(design)
        seconds = {}
        for workers in (1, 2):
            t0 = time.perf_counter()
            res = run_design(design, modules, workers=workers, limit=SCALE_CANDIDATES)
            seconds[workers] = time.perf_counter() - t0
            n = len(res.candidates)
    speedup = seconds[1] / seconds[2]
    return {"candidates": n, "targets": design.n_targets, "arms": "2-3",
            "one_worker_s": seconds[1], "two_workers_s": seconds[2], "speedup": speedup,
            "target_s": TARGET_S, "target_speedup": TARGET_SPEEDUP,
            "met": bool(seconds[2] < TARGET_S and speedup >= TARGET_SPEEDUP)}


def _observed(modules: dict, candidate: dict, targets: np.ndarray, seed: int,
              quantile: float) -> float:
    return float(np.quantile(built_errors(modules, candidate, targets, seed), quantile))


def proof(seeds: tuple[int, ...] = REPORT_SEEDS) -> dict:
    from bayesrob.design import dask_client, load_design, load_modules, run_design

    rows = []
    with tempfile.TemporaryDirectory() as tmp, dask_client(None, 2) as client:
        for seed in seeds:
            design = load_design(_design(Path(tmp), seed, {
                f"error_mm = {EXAMPLE_ERROR_MM}": f"error_mm = {PROOF_ERROR_MM}"}))
            modules = load_modules(design)
            res = run_design(design, modules, client=client)
            q, req = design.quantile, design.error_mm
            best = res.best
            row = {"seed": seed, "best": best["config"], "best_bases": best["bases"],
                   "best_predicted_mm": best["overall"]["error_quantile_mm"],
                   "best_assured_mm": best["overall"]["assured_error_mm"],
                   "best_meets_predicted": best["meets"]}
            row["best_observed_mm"] = _observed(modules, best, res.targets, seed, q)
            row["best_holds"] = bool(best["meets"] and row["best_observed_mm"] <= req)
            # every candidate predicted to miss is built, in rank order: the first, the
            # best-ranked (the most marginal), is the proof's; the others are reported beside
            misses = [(c, _observed(modules, c, res.targets, seed, q)) for c in res.candidates
                      if c["overall"]["optimistic_error_mm"] > req]
            if misses:
                miss, observed = misses[0]
                row.update({"miss": miss["config"], "miss_bases": miss["bases"],
                            "miss_predicted_mm": miss["overall"]["error_quantile_mm"],
                            "miss_optimistic_mm": miss["overall"]["optimistic_error_mm"],
                            "miss_observed_mm": observed})
                row["miss_misses"] = bool(observed > req)
            row["all_misses"] = len(misses)
            row["all_misses_missed"] = sum(obs > req for _, obs in misses)
            # the worked example's requirement, read off the same predictions
            tight = [c for c in res.candidates
                     if c["overall"]["assured_error_mm"] <= EXAMPLE_ERROR_MM]
            if tight:
                b = min(tight, key=lambda c: (len(c["arms"]), c["overall"]["error_quantile_mm"]))
                row["example_best"] = b["config"]
                row["example_observed_mm"] = _observed(modules, b, res.targets, seed, q)
            print(json.dumps(row), flush=True)
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
            "met": bool(held >= 0.9 * len(rows) and missed >= 0.8 * with_miss)}


def tuning() -> dict:
    from bayesrob.design import dask_client, load_design, load_modules, run_design

    counts: dict[int, list[int]] = {}  # arms -> [built, below optimistic, above assured]
    with tempfile.TemporaryDirectory() as tmp, dask_client(None, 2) as client:
        for seed in TUNING_SEEDS:
            design = load_design(_design(Path(tmp), seed))
            modules = load_modules(design)
            res = run_design(design, modules, client=client)
            for k, c in enumerate(res.candidates):
                n = len(c["arms"])
                if n > 1 and k % TUNING_EVERY:
                    continue
                o = c["overall"]
                obs = _observed(modules, c, res.targets, seed, design.quantile)
                tally = counts.setdefault(n, [0, 0, 0])
                tally[0] += 1
                tally[1] += obs < o["optimistic_error_mm"]
                tally[2] += obs > o["assured_error_mm"]
                print(json.dumps({"seed": seed, "config": c["config"], "bases": c["bases"],
                                  "optimistic_mm": o["optimistic_error_mm"],
                                  "assured_mm": o["assured_error_mm"],
                                  "observed_mm": obs}), flush=True)
    return {"seeds": list(TUNING_SEEDS), **{
        f"{n}_arms": {"built": t[0], "below_optimistic": t[1], "above_assured": t[2]}
        for n, t in sorted(counts.items())}}


def chain_proof(masses: str = "fitted", mass_log_sd: float = 0.0,
                seeds: tuple[int, ...] = CHAIN_SEEDS) -> dict:
    """``masses``: the modules' (``masses = "description"``: held at the URDF's, their
    stiffnesses read from the fitted compliances); ``mass_log_sd``: how far each simulated
    arm's true link masses stray from the URDF's."""
    from bayesrob.chain_design import chain_candidate_draws
    from bayesrob.chain_simulator import (
        LinkedChainTruth,
        load_linked_truth,
        simulate_linked_chain_rig,
    )
    from bayesrob.design import _Job, load_design, load_modules, reach_table
    from bayesrob.rig import load_rig

    levels = (0.5, 0.9, 0.95)
    kinds = ("left+right", "left", "right")
    inside = {k: {q: [] for q in levels} for k in kinds}
    means = {k: ([], []) for k in kinds}
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in seeds:
            rig_dir = simulate_linked_chain_rig(
                Path(tmp) / f"rig-{seed}",
                LinkedChainTruth(seed=seed, calibration_groups=tuple(CHAIN_PARAMS.split(",")),
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
            job = _Job(modules, targets, reach, "equilibrium", 0.95, 1.0, 0.9, design.draws,
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
            for kind in kinds:
                arms = tuple(kind.split("+"))
                d = chain_candidate_draws(job, arms, tuple(0 if a == "left" else 1
                                                           for a in arms), 0)
                err = np.linalg.norm(d - targets[None], axis=-1)  # (S, T)
                obs = np.linalg.norm(seen[kind] - targets, axis=1)
                means[kind][0].append(err.mean(axis=0))
                means[kind][1].append(obs)
                row[kind] = {"observed_mean_mm": float(obs.mean()),
                             "predicted_mean_mm": float(err.mean())}
                for q in levels:
                    hit = obs <= np.quantile(err, q, axis=0)
                    inside[kind][q].extend(hit.tolist())
                    row[kind][f"within_q{round(100 * q)}"] = float(hit.mean())
            print(json.dumps(row), flush=True)
            rows.append(row)
    out: dict = {"rigs": len(rows)}
    met = True
    for kind in kinds:
        n = len(inside[kind][0.5])
        k = {"rows": n, **{f"within_q{round(100 * q)}": float(np.mean(v))
                           for q, v in inside[kind].items()},
             "error_ratio": float(np.concatenate(means[kind][0]).mean()
                                  / np.concatenate(means[kind][1]).mean())}
        # nominal within binomial error: two standard errors at the pooled count
        k["met"] = bool(all(abs(k[f"within_q{round(100 * q)}"] - q)
                            <= 2 * np.sqrt(q * (1 - q) / n) for q in levels)
                        and 0.85 <= k["error_ratio"] <= 1.15)
        met = met and k["met"]
        out[kind] = k
    out["met"] = met
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--proof", action="store_true", help="the proof in simulation instead")
    p.add_argument("--chain-proof", action="store_true",
                   help="6-joint 3-D modules: predictions against the built assembly")
    p.add_argument("--masses", choices=MASS_SOURCES, default=MASS_SOURCES[0],
                   help="with --chain-proof: the modules' link masses fitted, or held at the "
                        "URDF's (then each simulated arm's true masses are drawn 10%% about "
                        "them)")
    p.add_argument("--sag-report", action="store_true",
                   help=f"with --chain-proof: report rigs {CHAIN_SAG_REPORT_SEEDS[0]}-"
                        f"{CHAIN_SAG_REPORT_SEEDS[-1]} instead of {CHAIN_SEEDS[0]}-"
                        f"{CHAIN_SEEDS[-1]}")
    p.add_argument("--arm-centre", choices=("sags", "equal"), default=None,
                   help="with --chain-proof: centre the linked arms' stiffness terms on their "
                        "fitted sags (the default) or alike (before the designer did so)")
    p.add_argument("--tuning", action="store_true",
                   help="tuning inventories: where built assemblies fall in their predictions")
    p.add_argument("--seeds", default=f"{REPORT_SEEDS[0]}-{REPORT_SEEDS[-1]}",
                   help="report inventories of the proof, FIRST-LAST (default %(default)s)")
    args = p.parse_args()
    try:
        first, last = (int(v) for v in args.seeds.split("-"))
    except ValueError:
        p.error(f"--seeds: expected FIRST-LAST, e.g. 111-130, got {args.seeds!r}")
    seeds = tuple(range(first, last + 1))
    if args.arm_centre is not None:
        import bayesrob.chain_prediction as cp

        cp.CHAIN_STIFFNESS_ARM_CENTRE = args.arm_centre
    chain_seeds = CHAIN_SAG_REPORT_SEEDS if args.sag_report else CHAIN_SEEDS
    chain = (chain_proof("description", DESCRIBED_MASS_SPREAD, chain_seeds)
             if args.masses == "description" else chain_proof(seeds=chain_seeds)
             ) if args.chain_proof else None
    print(json.dumps(proof(seeds) if args.proof else chain if args.chain_proof
                     else tuning() if args.tuning else scale()))


if __name__ == "__main__":
    main()
