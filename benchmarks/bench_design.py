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

The proofs' code and seeds live in ``bayesrob.validation.design_proof``; their report sets run
by ``bayesrob validate design_proof design_proof_second design_chain``.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

from bayesrob.validation.design_proof import (
    CHAIN_SAG_REPORT_SEEDS,
    CHAIN_SEEDS,
    DESCRIBED_MASS_SPREAD,
    REPORT_SEEDS,
    TUNING_SEEDS,
    chain_proof,
    design_file,
    observed_quantile,
    proof,
)

from bayesrob.robot import MASS_SOURCES

TUNING_EVERY = 10  # one multi-arm candidate in this many is built (all single arms are)
SCALE_CANDIDATES = 1000
TARGET_S = 600.0
TARGET_SPEEDUP = 1.7


def scale() -> dict:
    from bayesrob.design.file import load_design
    from bayesrob.design.modules import load_modules
    from bayesrob.design.search import run_design

    with tempfile.TemporaryDirectory() as tmp:
        path = design_file(Path(tmp), None, {
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


def tuning() -> dict:
    from bayesrob.cluster import dask_client
    from bayesrob.design.file import load_design
    from bayesrob.design.modules import load_modules
    from bayesrob.design.search import run_design

    counts: dict[int, list[int]] = {}  # arms -> [built, below optimistic, above assured]
    with tempfile.TemporaryDirectory() as tmp, dask_client(None, 2) as client:
        for seed in TUNING_SEEDS:
            design = load_design(design_file(Path(tmp), seed))
            modules = load_modules(design)
            res = run_design(design, modules, client=client)
            for k, c in enumerate(res.candidates):
                n = len(c["arms"])
                if n > 1 and k % TUNING_EVERY:
                    continue
                o = c["overall"]
                obs = observed_quantile(modules, c, res.targets, seed, design.quantile)
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
        import bayesrob.predict.stiffness as st

        st.CHAIN_STIFFNESS_ARM_CENTRE = args.arm_centre
    chain_seeds = CHAIN_SAG_REPORT_SEEDS if args.sag_report else CHAIN_SEEDS
    chain = (chain_proof("description", DESCRIBED_MASS_SPREAD, chain_seeds)
             if args.masses == "description" else chain_proof(seeds=chain_seeds)
             ) if args.chain_proof else None
    print(json.dumps(proof(seeds) if args.proof else chain if args.chain_proof
                     else tuning() if args.tuning else scale()))


if __name__ == "__main__":
    main()
