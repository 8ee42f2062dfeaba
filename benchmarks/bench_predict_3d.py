"""A 3-D two-arm linked prediction at 16 targets: two 6-joint arms (``bayesrob simulate
--robot arm6 --linked``, seed 0) linked at their tool points, equilibrium fusion.

    python benchmarks/bench_predict_3d.py [--repeats 2]

Prints one JSON line: the whole ``predict_assembly`` warm (calibration, both arms' latent
joint-error fits by NUTS, aiming, 4000 draws per target, regions), and its prediction step alone
(aiming, draws and regions from fitted modules). Target (2 cores): the whole prediction under
60 s warm; the single-arm prediction's time in the same run is printed beside it.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

WARM_TARGET_S = 60.0


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--repeats", type=int, default=2)
    args = p.parse_args()

    from bayesrob.assembly import predict_assembly
    from bayesrob.chain_prediction import fit_chain_modules, hdr_sizes, predict_chain_points
    from bayesrob.chain_simulator import LinkedChainTruth, simulate_linked_chain_rig
    from bayesrob.rig import load_rig

    with tempfile.TemporaryDirectory() as tmp:
        rig = load_rig(simulate_linked_chain_rig(Path(tmp) / "rig", LinkedChainTruth(seed=0)))
        targets = rig.measurements.target[rig.measurements.mask("left+right", "test")][:16]
        whole, step, single = [], [], []
        for k in range(args.repeats + 1):  # the first run compiles
            t0 = time.perf_counter()
            predict_assembly(rig, "left+right", targets, seed=k)
            t1 = time.perf_counter()
            predict_assembly(rig, "left", targets, seed=k)
            if k:
                whole.append(t1 - t0)
                single.append(time.perf_counter() - t1)
        mods = fit_chain_modules(rig, ["left", "right"])
        for k in range(args.repeats + 1):
            t0 = time.perf_counter()
            _, draws = predict_chain_points(mods, rig, ["left", "right"], targets,
                                               "equilibrium", seed=k)
            hdr_sizes(draws)
            if k:
                step.append(time.perf_counter() - t0)
    w = float(np.median(whole))
    print(json.dumps({"targets": len(targets), "arms": 2, "joints_per_arm": 6,
                      "predict_warm_s": w, "prediction_step_warm_s": float(np.median(step)),
                      "single_arm_predict_warm_s": float(np.median(single)),
                      "target_s": WARM_TARGET_S, "met": w < WARM_TARGET_S}))


if __name__ == "__main__":
    main()
