"""`bayesrob plan`: how fast it plans, and how much its poses are worth against random ones.

    python benchmarks/bench_plan.py [--data PATH/agile-justin/measurements.csv]
                                    [--seeds 801 802] [--figure docs/img/plan.png]

Speed (target: 40 poses from a pool of 5,000 for a 7-joint arm in at most 30 s on two
cores): Agile Justin's right hand (torso 3 + arm 7 columns, 11 joints with the torso's
passive one), a pool of 5,000 poses drawn inside the range of its train commands, the
default ``accuracy`` criterion with ``frames,offsets,geometric,servo``; timed warm (its
Jacobian program compiled by a first, small plan) and cold. Without Justin's data, the
simulator's 6-joint arm stands in (the case name says so).

Planned against random: simulated 6-joint arms, one per seed (validation/plan.py's
``sim_curves``): the held-out error against the true arm after calibrating the first N planned
poses, and the median of five random draws of N from the same pool; the figure shows both
against N. Prints one JSON line.
"""

from __future__ import annotations

import argparse
import csv
import json
import tempfile
import time
from pathlib import Path

import numpy as np
from justin_rig import DEFAULT_DATA

TARGET_S = 30.0


def speed(data: Path, work: Path) -> dict:
    from bayesrob.validation.justin import convert
    from bayesrob.validation.plan import subset

    from bayesrob.plan import load_plan_rig, plan_poses

    if data.is_file():
        convert(data, work / "rig")
        case = "agile_justin right hand (10 columns, 11 joints)"
    else:
        from bayesrob.sim.rigs import simulate_arm6_rig
        from bayesrob.sim.truth import Arm6Truth

        simulate_arm6_rig(work / "rig", Arm6Truth(seed=1))
        case = "simulated arm6 (6 joints; Justin data not found)"
    rig = load_plan_rig(work / "rig")
    with (work / "rig" / "measurements.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    cols = [c for c in rows[0] if "_u" in c]
    u = np.array([[float(r[c]) for c in cols] for r in rows if r["set"] == "train"])
    rng = np.random.default_rng(0)
    pool = rng.uniform(u.min(axis=0), u.max(axis=0), size=(5000, len(cols)))
    arm = "right" if "right" in rig.robot.chains else "arm"
    with (work / "pool.csv").open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["config", *cols])
        w.writerows([[arm, *(f"{v:.10g}" for v in row)] for row in pool])
    empty = subset(rig, np.zeros(len(rig.measurements), bool))  # nothing measured yet
    t0 = time.perf_counter()
    plan_poses(empty, 40, pool=work / "pool.csv")
    cold = time.perf_counter() - t0
    t0 = time.perf_counter()
    plan = plan_poses(empty, 40, pool=work / "pool.csv")
    warm = time.perf_counter() - t0
    return {"case": case, "pool": 5000, "n": 40, "cold_s": cold, "warm_s": warm,
            "target_s": TARGET_S, "met": cold <= TARGET_S,
            "predicted_mm": [plan.before, plan.after]}


def figure(curves: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    ns = curves["ns"]
    runs = list(curves["seeds"].values())
    for key, color, mark, label in (("planned", "C0", "o-", "planned"),
                                    ("random_median", "C1", "s--", "random (median of draws)")):
        for c in runs:
            ax.plot(ns, c[key], mark, color=color, alpha=0.25, lw=0.8, ms=3)
        ax.plot(ns, np.median([c[key] for c in runs], axis=0), mark, color=color, lw=2.2,
                label=f"{label}, median of {len(runs)} arms")
    ax.set_xlabel("poses measured (N)")
    ax.set_ylabel("held-out error against the true arm (mm)")
    ax.set_yscale("log")
    ax.set_title("arm6: accuracy plan against random poses from one pool")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def justin_figure(table: dict, path: Path) -> None:
    """Agile Justin: held-out error against rows measured, the plans' first N rows against
    random subsets (median and quartiles of the draws), one panel per parameter set."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sets = list(table)
    fig, axes = plt.subplots(1, len(sets), figsize=(5.2 * len(sets), 4), squeeze=False)
    for ax, name in zip(axes[0], sets, strict=True):
        t = table[name]
        sizes = sorted(int(n) for n in t["random"] if t["random"][n])
        draws = [np.array(t["random"][str(n)]) for n in sizes]
        ax.fill_between(sizes, [np.percentile(d, 25) for d in draws],
                        [np.percentile(d, 75) for d in draws], color="C1", alpha=0.2)
        ax.plot(sizes, [np.median(d) for d in draws], "s--", color="C1", label="random "
                f"(median, quartiles of {'/'.join(str(len(d)) for d in draws)} draws)")
        opts = " ".join(f"--{k.replace('_', '-')} {v:g}"
                        for k, v in t.get("accuracy_options", {}).items())
        for key, color, mark, label in (
                ("accuracy", "C0", "o-", f"plan --for accuracy {opts}"),
                ("accuracy_default", "C0", "o:", "plan --for accuracy (defaults)"),
                ("identify", "C2", "^-", "plan --for identify")):
            if key in t:
                ax.plot(t["ns"], t[key], mark, color=color, lw=2, label=label)
        ax.set_xscale("log")
        ax.minorticks_off()
        ax.set_xticks(sizes, [str(n) for n in sizes])
        ax.set_xlabel("rows measured")
        ax.set_ylabel("mean error on the 400 validation markers (mm)")
        ax.set_title(f"Agile Justin, --params {name}", fontsize=10)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, default=DEFAULT_DATA)
    p.add_argument("--seeds", type=int, nargs="*", default=[801, 802])
    p.add_argument("--figure", type=Path, default=None)
    p.add_argument("--speed-only", action="store_true")
    p.add_argument("--from-validation", type=Path, default=None, metavar="JSON",
                   help="draw --figure from a validation.json holding plan_sim's run instead")
    p.add_argument("--justin-table", type=Path, default=None, metavar="JSON",
                   help="draw --figure from Agile Justin's table (validation/plan.py's "
                        "justin_table) instead")
    args = p.parse_args()
    if args.justin_table is not None:
        justin_figure(json.loads(args.justin_table.read_text()), args.figure)
        return
    if args.from_validation is not None:
        details = json.loads(args.from_validation.read_text())["studies"]["plan_sim"][
            "details"]
        figure({"ns": details["ns"], "seeds": {
            r["seed"]: {"planned": r["planned_mm"], "random_median": r["random_median_mm"]}
            for r in details["rigs"]}}, args.figure)
        return
    from bayesrob.validation.plan import NS, sim_curves

    out: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        out["speed"] = speed(args.data, Path(tmp))
    if not args.speed_only:
        curves: dict = {"ns": list(NS), "seeds": {}}
        for seed in args.seeds:
            with tempfile.TemporaryDirectory() as tmp:
                c = sim_curves(seed, Path(tmp))
            rnd = np.median([c[k] for k in c if k.startswith("random")], axis=0)
            curves["seeds"][seed] = {"planned": c["planned"], "random_median": rnd.tolist()}
        out["planned_vs_random"] = curves
        if args.figure is not None:
            figure(curves, args.figure)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
