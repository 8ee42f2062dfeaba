"""Linked predictions on the default rig's 16 linked targets: equilibrium fusion (draws of the
numpyro program, KDE on zoomed grids) beside the product of likelihoods (the grid), both warm.

    python benchmarks/bench_predict.py [--model cond] [--repeats 3]

Prints one JSON line. Target (2 cores): the 16-target equilibrium prediction under 5 s warm;
the ratio to the product's time in the same run is printed with it.

Three planar arms predicted before they are built, through their fitted physics:

    python benchmarks/bench_predict.py --three-arms tuning|report [--params GROUPS] [--model ind]

On each rig (``simulator.three_arm_truth``: sag and backlash, every arm's stiffnesses drawn),
``predict`` sees the single-arm rows only and gives, per linked target, the commands and the
draws of the shared end point; the simulator then measures the assembly at exactly those
commands (the rig's own linked rows were aimed through the eight-parameter fits, so they are
not what ``predict`` would build). Prints a JSON line per rig and the pooled share of the
measured points inside the 50% / 90% regions, and the predicted / observed mean error. The
study's code and seeds live in ``bayesrob.validation.linked_planar``; its report rigs run by
``bayesrob validate linked_planar_physics``.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
from bayesrob.validation.linked_planar import (
    THREE_ARM_GROUPS,
    THREE_ARM_REPORT_SEEDS,
    THREE_ARM_TUNING_SEEDS,
    three_arm_study,
)

WARM_TARGET_S = 5.0


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--model", default="cond")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--three-arms", choices=("tuning", "report"),
                   help="the three-arm coverage study on its tuning or report rigs")
    p.add_argument("--params", default=",".join(THREE_ARM_GROUPS),
                   help="with --three-arms: the modules' calibration groups")
    args = p.parse_args()
    if args.three_arms:
        seeds = THREE_ARM_TUNING_SEEDS if args.three_arms == "tuning" else THREE_ARM_REPORT_SEEDS
        model = "ind" if args.model == "cond" else args.model  # chains have no cond
        print(json.dumps(three_arm_study(seeds, tuple(args.params.split(",")), model)))
        return

    from bayesrob.data.rig import default_rig_dir, load_rig
    from bayesrob.predict.assembly import predict_assembly

    rig = load_rig(default_rig_dir())
    targets = rig.config_rows("top+bottom", "test")["target"]
    times: dict[str, list[float]] = {"equilibrium": [], "product": []}
    for fusion in times:
        for k in range(args.repeats + 1):  # the first run compiles
            t0 = time.perf_counter()
            predict_assembly(rig, "top+bottom", targets, args.model, fusion, seed=k)
            if k:
                times[fusion].append(time.perf_counter() - t0)
    eq, prod = (float(np.median(times[f])) for f in ("equilibrium", "product"))
    print(json.dumps({"targets": len(targets), "model": args.model,
                      "equilibrium_warm_s": eq, "product_warm_s": prod,
                      "ratio_equilibrium_to_product": eq / prod,
                      "target_s": WARM_TARGET_S, "met": eq < WARM_TARGET_S}))


if __name__ == "__main__":
    main()
