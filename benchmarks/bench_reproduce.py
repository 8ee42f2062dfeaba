"""End-to-end wall time of `bayesrob reproduce` on the default data, cold (a fresh process).

Prints one JSON line. Target: under 60 s on 2 cores, JAX start-up and compilation included.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time

TARGET_S = 60.0


def main() -> None:
    with tempfile.TemporaryDirectory() as out:
        t0 = time.perf_counter()
        r = subprocess.run([sys.executable, "-m", "bayesrob", "reproduce", "--out", out],
                           capture_output=True, text=True)
        seconds = time.perf_counter() - t0
    if r.returncode != 0:
        sys.exit(f"reproduce failed: {r.stderr.strip()}")
    print(json.dumps({"case": "reproduce_default_cold", "seconds": round(seconds, 2),
                      "target_s": TARGET_S, "ratio_to_target": round(seconds / TARGET_S, 3),
                      "meets_target": seconds < TARGET_S}))


if __name__ == "__main__":
    main()
