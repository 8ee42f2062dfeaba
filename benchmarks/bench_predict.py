"""Linked predictions on the default rig's 16 linked targets: equilibrium fusion (draws of the
numpyro program, KDE on zoomed grids) beside the product of likelihoods (the grid), both warm.

    python benchmarks/bench_predict.py [--model cond] [--repeats 3]

Prints one JSON line. Target (2 cores): the 16-target equilibrium prediction under 5 s warm;
the ratio to the product's time in the same run is printed with it.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

WARM_TARGET_S = 5.0


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--model", default="cond")
    p.add_argument("--repeats", type=int, default=3)
    args = p.parse_args()

    from bayesrob.assembly import predict_assembly
    from bayesrob.rig import default_rig_dir, load_rig

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
