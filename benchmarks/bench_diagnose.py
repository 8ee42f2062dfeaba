"""Benchmarks of ``bayesrob diagnose``: its speed, and how often it names the right effects.

    python benchmarks/bench_diagnose.py                 # wall time on a 4x4 two-arm rig
    python benchmarks/bench_diagnose.py --confusion     # 40-rig sweep -> markdown table
    python benchmarks/bench_diagnose.py --sensitivity   # effect size x noise at 4x4

The default run times the command as a person runs it (a fresh process, so JAX compiles
everything) on the embedded default rig (4x4 grid, two arms, gravity sag and backlash) and
prints one JSON line. The sweeps build each rig from ``tests/generators.py`` (this project's
simulator and the deliberately different generators), diagnose it from its files alone and
compare what was named with what was hidden.
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
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict
from multiprocessing import get_context
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))

from generators import TRUTHS, Case, confusion_cases, make_rig  # noqa: E402

LIMIT_S = 60.0


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


def run_case(case: Case) -> dict:
    """Make the rig, diagnose it from its files, report what was named."""
    import bayesrob  # noqa: F401  (x64 before any JAX work)
    from bayesrob.diagnosis import diagnose
    from bayesrob.rig import load_rig

    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        rig = load_rig(make_rig(case, tmp))
        doc = diagnose(rig).to_json()
    return {"case": asdict(case), "truth": case.label,
            "named": "+".join(sorted(doc["effects"])) or "none",
            "order": doc["effects"], "seconds": round(time.perf_counter() - t0, 1),
            "baseline_heldout_error_mm": doc["baseline_heldout_error_mm"],
            "final_heldout_error_mm": doc["final_heldout_error_mm"],
            "rounds": [[{k: s[k] for k in ("effect", "arms", "elpd_diff", "elpd_diff_se",
                                             "heldout_error_before_mm", "heldout_error_after_mm",
                                             "cv_error_before_mm", "cv_error_after_mm",
                                             "passes")} for s in r] for r in doc["rounds"]]}


def run_all(cases: list[Case], jobs: int, log: Path | None) -> list[dict]:
    results = []
    ctx = get_context("spawn")  # JAX's threads do not survive fork
    with ProcessPoolExecutor(jobs, mp_context=ctx) as pool:
        for res in pool.map(run_case, cases):
            results.append(res)
            print(f"  {res['case']['source']:9s} {res['case']['geometry']:10s} "
                  f"{res['case']['grid']}x{res['case']['grid']} scale {res['case']['scale']:<5g} "
                  f"truth {res['truth']:28s} named {res['named']:28s} {res['seconds']:5.1f} s",
                  file=sys.stderr, flush=True)
            if log:
                with log.open("a") as fh:
                    fh.write(json.dumps(res) + "\n")
    return results


def _key(label: str) -> str:
    return "+".join(sorted(label.split("+"))) if label != "none" else "none"


def confusion_table(results: list[dict]) -> str:
    """Markdown: hidden effects (rows) against named effects (columns)."""
    truths = [_key("+".join(t) or "none") for t in TRUTHS]
    named = sorted({r["named"] for r in results}, key=lambda k: (k not in truths,
                   truths.index(k) if k in truths else 0, k))
    count = Counter((_key(r["truth"]), r["named"]) for r in results)
    lines = ["| hidden \\ named | " + " | ".join(named) + " | correct |",
             "|---" * (len(named) + 2) + "|"]
    for t in truths:
        row = [str(count[(t, n)]) for n in named]
        total = sum(count[(t, x)] for x in named)
        lines.append(f"| {t} | " + " | ".join(row) + f" | {count[(t, t)]}/{total} |")
    ok = sum(count[(t, t)] for t in truths)
    lines.append(f"\n{ok}/{len(results)} rigs named exactly the hidden effects.")
    shrink = [r for r in results if r["truth"] != "none" and r["named"] != "none"]
    if shrink:
        ratio = [r["final_heldout_error_mm"] / r["baseline_heldout_error_mm"] for r in shrink]
        lines.append(f"Where effects were named, the held-out error fell to "
                     f"{100 * sum(ratio) / len(ratio):.0f}% of the base model's on average.")
    return "\n".join(lines)


def breakdown(results: list[dict]) -> str:
    rows = ["| source | geometry | grid | rigs | correct |", "|---|---|---|---|---|"]
    groups: dict = {}
    for r in results:
        c = r["case"]
        groups.setdefault((c["source"], c["geometry"], c["grid"]), []).append(
            _key(r["truth"]) == r["named"])
    for (src, geo, grid), oks in sorted(groups.items()):
        rows.append(f"| {src} | {geo} | {grid}x{grid} | {len(oks)} | {sum(oks)} |")
    return "\n".join(rows)


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
    """The hidden effect's size in the simulator's own terms (see bayesrob.simulator)."""
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
    p.add_argument("--confusion", action="store_true", help="run the 40-rig sweep")
    p.add_argument("--sensitivity", action="store_true", help="effect size x noise at 4x4")
    p.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1))
    p.add_argument("--log", type=Path, help="append each rig's result as a JSON line")
    args = p.parse_args()
    if args.confusion or args.sensitivity:
        if args.confusion:
            res = run_all(confusion_cases(), args.jobs, args.log)
            print(confusion_table(res))
            print()
            print(breakdown(res))
        if args.sensitivity:
            res = run_all(sensitivity_cases(), args.jobs, args.log)
            print(sensitivity_table(res))
        return 0
    print(json.dumps(time_command(args.rig)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
