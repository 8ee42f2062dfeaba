"""Geometric calibration of a robot tree: DLR's Agile Justin (torso and two 7-joint arms,
about 100 fitted parameters, 300 poses x 2 markers) when its data is at hand, else a simulated
6-joint arm (and it says so).

    python benchmarks/bench_chain_calibration.py [--data PATH/agile-justin/measurements.csv]

Prints one JSON line per case. Targets (2 cores): warm (a second calibration of the same rig in
the same process, compiled programs reused) under 10 s; fresh process under 30 s, timed from
after the imports (interpreter start-up and `import bayesrob`, stated separately, excluded).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from justin_rig import DEFAULT_DATA, justin_or_simulated

WARM_TARGET_S, FRESH_TARGET_S = 10.0, 30.0

FRESH = """
import time, json, sys
t0 = time.perf_counter()
from bayesrob.data.rig import load_rig
from bayesrob.calibrate.least_squares import calibrate
t1 = time.perf_counter()
rig = load_rig(sys.argv[1])
cal = calibrate(rig, ("frames", "geometric"))
t2 = time.perf_counter()
cal2 = calibrate(rig, ("frames", "geometric"))
t3 = time.perf_counter()
print(json.dumps({"imports_s": t1 - t0, "first_s": t2 - t1, "warm_s": t3 - t2,
                  "n_free": int(cal.ident.free.sum()), "n_parameters": len(cal.x),
                  "validation_mean_mm": cal.errors["validation"]["all"]["mean_mm"]}))
"""


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, default=DEFAULT_DATA)
    args = p.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        from bayesrob.sim.truth import Arm6Truth

        rig = Path(tmp) / "rig"
        case = ("agile_justin_frames_geometric"
                if justin_or_simulated(args.data, rig, Arm6Truth(seed=0, n_train=300))
                else "simulated_arm6_frames_geometric (Justin data not found)")
        t0 = time.perf_counter()
        r = subprocess.run([sys.executable, "-c", FRESH, str(rig)], capture_output=True,
                           text=True)
        wall = time.perf_counter() - t0
    if r.returncode != 0:
        sys.exit(f"calibration failed: {r.stderr.strip()[-2000:]}")
    doc = json.loads(r.stdout.strip().splitlines()[-1])
    doc.update(case=case, process_wall_s=round(wall, 2), warm_target_s=WARM_TARGET_S,
               fresh_target_s=FRESH_TARGET_S,
               warm_meets_target=doc["warm_s"] < WARM_TARGET_S,
               fresh_meets_target=doc["first_s"] < FRESH_TARGET_S)
    print(json.dumps({k: round(v, 2) if isinstance(v, float) else v for k, v in doc.items()}))


if __name__ == "__main__":
    main()
