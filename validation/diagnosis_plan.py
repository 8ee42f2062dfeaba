"""The diagnosis on planned poses (issue 46): 6-joint arms with the effects the chain diagnosis
confused on random poses (bearings tilting across their axes against joint compliance, play
beside compliance, encoder error beside compliance) and clean arms, measured at the poses
``bayesrob diagnose --plan`` chose, with each joint's approach side recorded.

Each arm is one of :mod:`bayesrob.validation.chain_generators`'s (the generators' physics, or
the simulator's own arm6), made with the pose budget of that study's report rigs:
:data:`N_POSES` train poses, 40 validation and 40 holdout rows at random poses (which decide
nothing). Its *strength* is as there: the geometric calibration's mean validation error over
its clean twin's, on all :data:`N_POSES` random train poses. Then, per arm:

1. keep the first :data:`N_FIRST` random train poses and run ``diagnose RIG --plan N_PLAN
   --pool POOL`` (the rest of the budget; the pool: 2000 random poses of the same working
   range, drawn per seed) -- the *before* figures;
2. measure the planned poses, in their order, on the same hidden arm (approach sides
   ``arm_d1..6`` recorded; where gravity does not hold a joint against one side of its play
   it rests on the side it came from) and append them to the train rows;
3. run ``diagnose RIG`` again -- the *after* figures, on :data:`N_POSES` train poses.

Every arm is planned for, whatever the first diagnosis said: a missed effect leaves no rival
to show it, and the plan then tells apart every candidate not named.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import shutil
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import numpy as np
from bayesrob.validation.diagnosis import (
    right_up_to_rivals,
    run_sweep,
    sweep_counts,
    sweep_details,
    sweep_figures,
)

N_POSES = 80  # train poses per rig: diagnosis_chain's report rigs' (Arm6Truth.n_train)
N_FIRST = 40  # measured at random first
N_PLAN = N_POSES - N_FIRST  # chosen by diagnose --plan
POOL_SIZE = 2000
POOL_STREAM = 46  # the pool's random stream, per seed
TRUTHS = [(), ("lateral_compliance",), ("encoder_error", "joint_compliance"),
          ("backlash", "joint_compliance")]
SIMULATOR_TRUTHS = [(), ("backlash", "joint_compliance")]
# a --quick run: a clean arm and one with tilting bearings, choosing between the two effects
# that were confused
QUICK_CASES = (("generator", ()), ("generator", ("lateral_compliance",)))
QUICK_EFFECTS = ("joint_compliance", "lateral_compliance")


def plan_cases(seeds: list[int]) -> list:
    from bayesrob.validation.chain_generators import ChainCase

    return ([ChainCase(eff, s) for s in seeds for eff in TRUTHS] +
            [ChainCase(eff, s, source="simulator") for s in seeds for eff in SIMULATOR_TRUTHS])


def _keep_first_train(rig: Path, n: int) -> None:
    """Drop every train row after the first ``n`` of measurements.csv."""
    path = rig / "measurements.csv"
    with path.open(newline="") as fh:
        rows = list(csv.reader(fh))
    k = rows[0].index("set")
    seen, body = 0, []
    for row in rows[1:]:
        seen += row[k] == "train"
        if row[k] != "train" or seen <= n:
            body.append(row)
    with path.open("w", newline="") as fh:
        csv.writer(fh, lineterminator="\n").writerows([rows[0], *body])


def _write_pool(path: Path, seed: int) -> None:
    from bayesrob.sim.rigs import random_poses

    q = random_poses(np.random.default_rng([seed, POOL_STREAM]), POOL_SIZE)
    with path.open("w", newline="") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow([f"arm_u{k + 1}" for k in range(6)])
        w.writerows([[f"{v:.10g}" for v in row] for row in q])


def _diagnose(rig: Path, out: Path, effects: tuple[str, ...] | None, *extra: str) -> dict:
    """``bayesrob diagnose RIG [extra]`` as a user runs it; its JSON report."""
    from bayesrob.cli import main

    argv = ["diagnose", str(rig), "--json", str(out), "--no-progress", *extra]
    if effects:
        argv += ["--effects", ",".join(effects)]
    with contextlib.redirect_stdout(io.StringIO()):
        code = main(argv)
    if code != 0:
        raise RuntimeError(f"bayesrob {' '.join(argv)}: exit {code}")
    return json.loads(out.read_text())


def _summary(doc: dict) -> dict:
    return {"named": "+".join(sorted(doc["effects"])) or "none", "order": doc["effects"],
            "rivals": {s["effect"]: s["rivals"] for s in doc["steps"]},
            "heldout_error_mm": doc["final_heldout_error_mm"],
            "baseline_heldout_error_mm": doc["baseline_heldout_error_mm"]}


def diagnose_planned_case(case, effects: tuple[str, ...] | None = None) -> dict:
    """One arm through the protocol of the module's docstring: its row for the sweep (the
    after figures under the sweep's keys, the before ones under ``before``)."""
    from bayesrob.validation.chain_generators import (
        make_chain_rig,
        measure_generated_poses,
        simulator_truth,
    )

    from bayesrob.calibrate.least_squares import calibrate
    from bayesrob.data.rig import load_rig
    from bayesrob.sim.rigs import measure_arm6_poses, simulate_arm6_rig

    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bayesrob-plandiag-") as tmp:
        tmp = Path(tmp)
        rig = tmp / "rig"
        if case.source == "simulator":
            simulate_arm6_rig(rig, simulator_truth(case))
            shutil.move(rig / "truth.toml", tmp / "truth.toml")  # not for the diagnosis
        else:
            make_chain_rig(case, rig)

        def geometric_error(path: Path) -> float:
            cal = calibrate(load_rig(path), ("frames", "geometric"))
            return cal.errors["validation"]["all"]["mean_mm"]

        base = geometric_error(rig)
        twin = (geometric_error(make_chain_rig(replace(case, effects=()), tmp / "twin"))
                if case.effects else base)
        _keep_first_train(rig, N_FIRST)
        pool, poses = tmp / "pool.csv", tmp / "poses.csv"
        _write_pool(pool, case.seed)
        before = _diagnose(rig, tmp / "before.json", effects, "--plan", str(N_PLAN),
                           "--pool", str(pool), "--plan-out", str(poses))
        with poses.open(newline="") as fh:
            planned = list(csv.DictReader(fh))
        q = np.array([[float(r[f"arm_u{k + 1}"]) for k in range(6)] for r in planned])
        if case.source == "simulator":
            shutil.move(tmp / "truth.toml", rig / "truth.toml")
            measure_arm6_poses(rig, ["train"] * len(q), q)
            (rig / "truth.toml").unlink()
        else:
            measure_generated_poses(case, rig, q)
        after = _diagnose(rig, tmp / "after.json", effects)
        n_train = int((load_rig(rig).measurements.set == "train").sum())
    b, a = _summary(before), _summary(after)
    return {"case": asdict(case), "truth": case.label, "named": a["named"], "order": a["order"],
            "rivals": a["rivals"], "seconds": round(time.perf_counter() - t0, 1),
            "strength": base / twin, "train_poses": n_train, "planned_poses": len(q),
            "baseline_heldout_error_mm": a["baseline_heldout_error_mm"],
            "final_heldout_error_mm": a["heldout_error_mm"], "clean_heldout_error_mm": twin,
            # the validation rows are new random poses that decide nothing: they play the
            # planar holdout rows' part in the sweep's figures, as in diagnosis_chain
            "baseline_holdout_error_mm": a["baseline_heldout_error_mm"],
            "final_holdout_error_mm": a["heldout_error_mm"], "clean_holdout_error_mm": twin,
            "before": {**b, "case": asdict(case), "truth": case.label, "strength": base / twin,
                       "final_holdout_error_mm": b["heldout_error_mm"],
                       "baseline_holdout_error_mm": b["baseline_heldout_error_mm"],
                       "clean_holdout_error_mm": twin}}


def _line(res: dict) -> str:
    c = res["case"]
    return (f"{c['source']:9s} seed {c['seed']} truth {res['truth']:28s} named "
            f"{res['before']['named']:28s} -> {res['named']:28s} strength "
            f"{res['strength']:4.1f} {res['train_poses']} poses {res['seconds']:5.1f} s")


def _figures(results: list[dict], prefix: str = "") -> dict[str, float]:
    f = sweep_figures(results)
    t = sweep_counts(results)
    f["strong_up_to_rivals_share"] = (t["strong_right_up_to_rivals"] / t["strong"]
                                      if t["strong"] else float("nan"))
    return {prefix + k: v for k, v in f.items()}


def run(seeds: list[int], *, quick: bool, say: Callable[[str], None]) -> dict[str, Any]:
    """Every case of :func:`plan_cases` at each seed (``quick``: two arms, two candidates)."""
    cases = plan_cases(seeds)
    effects = None
    if quick:
        cases = [c for c in cases if (c.source, c.effects) in QUICK_CASES]
        effects = QUICK_EFFECTS
    results = run_sweep(cases, lambda c: diagnose_planned_case(c, effects), _line, say)
    before = [r["before"] for r in results]
    poses = [r["train_poses"] for r in results]
    out = {**_figures(results), **_figures(before, "before."),
           "poses_per_rig": max(poses), "poses_random": N_FIRST,
           "poses_planned": max(r["planned_poses"] for r in results),
           "poses_report_rigs": N_POSES,
           "before.strong_right_up_to_rivals": sum(map(right_up_to_rivals,
                                                       [b for b in before if b["truth"] != "none"
                                                        and b["strength"] >= 2.0]))}
    from bayesrob.validation.chain_generators import CHAIN_TRUTHS

    details = sweep_details(results, CHAIN_TRUTHS)
    for row, r in zip(details["rigs"], results, strict=True):
        row.update(before={k: v for k, v in r["before"].items() if k != "case"},
                   train_poses=r["train_poses"])
    out["details"] = {**details,
                      "before_confusion": sweep_details(before, CHAIN_TRUTHS)["confusion"]}
    return out


def tables(entry: dict[str, Any]) -> dict[str, str]:
    """docs/plan.md, "Diagnosis on planned poses": the figures before and after the plan,
    and what was named for each hidden set, before -> after."""
    from bayesrob.validation.diagnosis import verdict

    f, d = entry["figures"], entry.get("details") or {}
    if "rigs" not in d:
        return {}

    def share(prefix: str) -> str:
        right, strong = f[prefix + "strong_right"], f[prefix + "strong"]
        return f"{right}/{strong} ({100 * right / strong:.0f}%)" if strong else "no strong rig"

    def ratio(key: str) -> str:
        return "-" if f.get(key) is None else f"{f[key]:.2f}"

    rows = ["| figure | before the plan | after it | target |", "|---|---|---|---|",
            f"| train poses per rig | {f['poses_random']} random | {f['poses_random']} random "
            f"+ {f['poses_planned']} planned = **{f['poses_per_rig']}** | at most "
            f"{f['poses_report_rigs']} (diagnosis_chain's report rigs)"
            f"{verdict(entry, 'poses_per_rig')} |",
            f"| strong rigs named exactly | {share('before.')} | **{share('')}** | at least "
            f"90%{verdict(entry, 'strong_exact_share')} |",
            f"| strong rigs right up to rivals | {f['before.strong_right_up_to_rivals']}/"
            f"{f['before.strong']} | {round(f['strong_up_to_rivals_share'] * f['strong'])}/"
            f"{f['strong']} | recorded |" if f["strong"] else "",
            f"| false alarms on clean arms | {f['before.false_alarms']} of {f['before.clean']} "
            f"| **{f['false_alarms']} of {f['clean']}** | 0{verdict(entry, 'false_alarms')} |",
            f"| gap at new poses after / before where named | {ratio('before.gap_ratio')} | "
            f"{ratio('gap_ratio')} | recorded |",
            f"| exactly right, all rigs | {f['before.exactly_right']}/{f['before.rigs']} | "
            f"{f['exactly_right']}/{f['rigs']} | recorded |"]
    named: dict[str, dict[str, int]] = {}
    for r in d["rigs"]:
        key = f"{r['before']['named']} -> {r['named']}"
        named.setdefault(r["truth"], {}).setdefault(key, 0)
        named[r["truth"]][key] += 1
    lines = ["| hidden | named before -> after (rigs) | strength |", "|---|---|---|"]
    for truth, got in named.items():
        s = [r["strength"] for r in d["rigs"] if r["truth"] == truth]
        lines.append(f"| {truth} | " + "; ".join(f"{k} ({v})" for k, v in got.items())
                     + f" | {min(s):.1f}-{max(s):.1f} |")
    return {"targets": "\n".join(r for r in rows if r), "named": "\n".join(lines)}
