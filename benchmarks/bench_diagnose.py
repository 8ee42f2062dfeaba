"""Benchmarks of ``bayesrob diagnose``: its speed, and how often it names the right effects.

    python benchmarks/bench_diagnose.py                 # wall time on a 4x4 two-arm rig
    python benchmarks/bench_diagnose.py --confusion     # the report rigs -> markdown tables
    python benchmarks/bench_diagnose.py --tuning        # the tuning rigs, the same tables
    python benchmarks/bench_diagnose.py --sensitivity   # effect size x noise at 4x4
    python benchmarks/bench_diagnose.py --tuning --engine groups   # the chain engine on them

The default run times the command as a person runs it (a fresh process, so JAX compiles
everything) on the embedded default rig (4x4 grid, two arms, gravity sag and backlash) and
prints one JSON line. The sweeps are the validation studies' (``bayesrob validate diagnosis
diagnosis_chain`` runs them one rig after another, checks their targets and records their
figures; :mod:`bayesrob.validation.diagnosis`): each rig is built by
``bayesrob.validation.planar_generators`` (this project's simulator and the deliberately
different generators) or ``chain_generators``, diagnosed from its files alone and what was
named compared with what was hidden. The rigs are split before anything is chosen:
``--tuning`` runs the rigs the decision rule was chosen on (seeds 21-35), ``--confusion`` the
report rigs (seeds 501-534), which only report. Here the rigs are diagnosed as Dask tasks on a
LocalCluster of ``--workers`` processes (``--scheduler`` for a running cluster): the sweep's
wall time on a cluster is this script's to measure.

Each rig's *strength* is how much its hidden effects raise the base model's mean error at new
poses (the holdout rows) over the same rig, seed and noise without them: 2 means the effects
double the gap that noise alone leaves.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bayesrob.validation.chain_generators import (
    CHAIN_TRUTHS,
    REPORT_SEEDS,
    TUNING_SEEDS,
    chain_cases,
)
from bayesrob.validation.diagnosis import (
    STRONG,
    breakdown_table,
    case_line,
    confusion_table,
    strength_table,
    sweep_counts,
    sweep_details,
)
from bayesrob.validation.planar_generators import TRUTHS, Case, report_cases, tuning_cases

LIMIT_S = 30.0  # target for a 4x4 planar rig


def time_command(rig: str | None) -> dict:
    """Wall and CPU time of ``bayesrob diagnose`` in a fresh process."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "diagnosis.json"
        cmd = [sys.executable, "-m", "bayesrob", "diagnose", "--json", str(out)]
        if rig:
            cmd.insert(4, rig)
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
        wall = time.perf_counter() - t0
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        doc = json.loads(out.read_text())
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"benchmark": "diagnose", "rig": rig or "embedded default (4x4, two arms)",
            "wall_s": round(wall, 2), "cpu_s": round(cpu, 2), "cores": os.cpu_count(),
            "load_avg_1min": round(os.getloadavg()[0], 2), "limit_s": LIMIT_S,
            "within_limit": wall < LIMIT_S, "effects": doc["effects"],
            "heldout_error_mm": [doc["baseline_heldout_error_mm"],
                                 doc["final_heldout_error_mm"]]}


def run_case(case, engine: str = "refits") -> dict:
    """One rig's sweep record, planar or chain (a Dask task); ``engine`` for planar rigs."""
    from bayesrob.validation.chain_generators import ChainCase, diagnose_chain_case
    from bayesrob.validation.planar_generators import diagnose_case

    if isinstance(case, ChainCase):
        return diagnose_chain_case(case)
    return diagnose_case(case, engine)


def run_all(cases: list, workers: int, log: Path | None,
            scheduler: str | None = None, engine: str = "refits") -> list[dict]:
    """Diagnose every case as a Dask task; results in the cases' order."""
    from distributed import as_completed

    from bayesrob.cluster import dask_client

    results: dict[int, dict] = {}
    with dask_client(scheduler, workers) as client:
        futures = {client.submit(run_case, c, engine, pure=False): i for i, c in enumerate(cases)}
        for fut in as_completed(futures):
            res = fut.result()
            results[futures[fut]] = res
            print(f"  [{len(results)}/{len(cases)}] {case_line(res)}", file=sys.stderr, flush=True)
            if log:
                with log.open("a") as fh:
                    fh.write(json.dumps(res) + "\n")
    return [results[i] for i in range(len(cases))]


def summary(results: list[dict]) -> str:
    t = sweep_counts(results)
    lines = [f"{t['exactly_right']}/{t['rigs']} rigs named exactly the hidden effects; "
             f"{t['strong_right']}/{t['strong']} of those whose effects at least double the "
             f"base model's error at new poses (strength >= {STRONG:g}); "
             f"{t['false_alarms']} false alarms on {t['clean']} clean rigs."]
    if any(r.get("rivals") for r in results):
        lines.append(f"Counting a named effect as any of its rivals (candidates its selection "
                     f"poses fit as well): {t['strong_right_up_to_rivals']}/{t['strong']} of "
                     "the strong rigs.")
    if t["holdout_ratio"] is not None:
        lines.append(f"Where effects were named ({t['named']} rigs), the error at new poses "
                     f"fell to {100 * t['holdout_ratio']:.0f}% of the base model's on average, "
                     f"and the gap the effects opened (error above the clean twin's) to "
                     f"{100 * t['gap_ratio']:.0f}% (pooled).")
    return "\n".join(lines)


def sweep_report(results: list[dict], truths: list | None = None) -> str:
    truths = truths or TRUTHS
    details = sweep_details(results, truths)
    parts = [confusion_table(details), "", summary(results), ""]
    for src in ("simulator", "generator"):
        rs = [r for r in results if r["case"]["source"] == src]
        if rs:
            parts += [f"{src}:", "", confusion_table(sweep_details(rs, truths)), ""]
    parts += [breakdown_table(details), "", strength_table(details)]
    return "\n".join(parts)


def sensitivity_cases() -> list[Case]:
    """Each effect alone, shrunk, at two noise levels on 4x4; small ones on 6x6; large ones
    at the higher noise."""
    cases = []
    for noise in (0.35, 0.7):
        for eff in TRUTHS[1:4]:
            for scale in (0.25, 0.5, 1.0):
                cases.append(Case("simulator", "paper", eff, 4, 41, scale, noise))
        for seed in (41, 42):
            cases.append(Case("simulator", "paper", (), 4, seed, 1.0, noise))
    for eff in TRUTHS[1:4]:
        for scale in (0.25, 0.5):
            cases.append(Case("simulator", "paper", eff, 6, 43, scale, 0.35))
    for eff in (("gravity_sag",), ("servo_nonlinearity",)):
        cases.append(Case("simulator", "paper", eff, 4, 41, 2.0, 0.7))
    return cases


def physical_size(case: dict) -> str:
    """The hidden effect's size in the simulator's own terms (see bayesrob.sim)."""
    s = case["scale"]
    sizes = {"gravity_sag": f"servo stiffness {2500 / s:.0f}/{1800 / s:.0f} N mm/rad",
             "backlash": f"play +-{0.458 * s:.2f} deg",
             "servo_nonlinearity": f"ripple {0.573 * s:.2f}/{0.458 * s:.2f} deg"}
    return "; ".join(sizes[e] for e in case["effects"]) or "-"


def sensitivity_table(results: list[dict]) -> str:
    lines = ["| grid | noise (mm) | hidden | size | named | held-out before -> after (mm) |",
             "|---|---|---|---|---|---|"]
    for r in sorted(results, key=lambda r: (r["case"]["grid"], r["case"]["noise_mm"],
                                            r["truth"], r["case"]["scale"])):
        c = r["case"]
        lines.append(f"| {c['grid']}x{c['grid']} | {c['noise_mm']} | {r['truth']} | "
                     f"{physical_size(c)} | {r['named']} | "
                     f"{r['baseline_heldout_error_mm']:.2f} -> {r['final_heldout_error_mm']:.2f} |")
    return "\n".join(lines)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rig", help="rig to time (default: the embedded default rig)")
    p.add_argument("--confusion", action="store_true",
                   help="run the report rigs (seeds 501-534; nothing was chosen on them)")
    p.add_argument("--tuning", action="store_true",
                   help="run the tuning rigs (seeds 21-35; the rule was chosen on them)")
    p.add_argument("--chain", action="store_true",
                   help="with --confusion / --tuning: the 6-joint 3-D arms instead "
                        "(report seeds 74-76, tuning seeds 61-62)")
    p.add_argument("--sensitivity", action="store_true", help="effect size x noise at 4x4")
    p.add_argument("--engine", choices=("refits", "groups"), default="refits",
                   help="planar sweeps: the planar engine (default) or the chain engine on "
                        "the arms as 2-joint chains with its own candidates for servo arms "
                        "(gravity_sag is joint_compliance): how far one engine for every robot "
                        "is")
    p.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1))
    p.add_argument("--scheduler", help="address of a running Dask scheduler")
    p.add_argument("--log", type=Path, help="append each rig's result as a JSON line")
    p.add_argument("--json", type=Path, help="write the sweep's results and figures")
    args = p.parse_args()
    if args.engine != "refits" and (args.chain or not (args.confusion or args.tuning
                                                        or args.sensitivity)):
        p.error("--engine groups is for the planar sweeps (--confusion, --tuning, "
                "--sensitivity without --chain)")
    report, tuning = report_cases, tuning_cases
    if args.chain:
        report, tuning = (lambda: chain_cases(REPORT_SEEDS)), (lambda: chain_cases(TUNING_SEEDS))
    sweeps = [(name, make) for name, make, on in (
        ("report", report, args.confusion), ("tuning", tuning, args.tuning),
        ("sensitivity", sensitivity_cases, args.sensitivity)) if on]
    if sweeps:
        out = {}
        for name, make in sweeps:
            res = run_all(make(), args.workers, args.log, args.scheduler, args.engine)
            print(f"## {name} rigs\n")
            print(sensitivity_table(res) if name == "sensitivity" else
                  sweep_report(res, CHAIN_TRUTHS if args.chain else None))
            print()
            out[name] = {"engine": args.engine, "results": res, "targets": sweep_counts(res)}
        if args.json:
            args.json.write_text(json.dumps(out, indent=1))
        return 0
    print(json.dumps(time_command(args.rig)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
