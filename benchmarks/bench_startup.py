"""Start-up of the command line: ``bayesrob --help``, a command's ``--help`` and an argument
error, each in a fresh process, against ``python -c pass`` measured in the same run.

    python benchmarks/bench_startup.py [--repeat 5]

Prints one JSON line per case: the median seconds of ``repeat`` runs, and the same less the
interpreter's own start. Target (issue 47): at most 0.5 s each on a quiet two-core machine.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time

CASES = {
    "python -c pass": [sys.executable, "-c", "pass"],
    "bayesrob --help": [sys.executable, "-m", "bayesrob", "--help"],
    "bayesrob predict --help": [sys.executable, "-m", "bayesrob", "predict", "--help"],
    "bayesrob predict (argument error)": [sys.executable, "-m", "bayesrob", "predict", "--bogus"],
    "bayesrob simulate --effects nope": [sys.executable, "-m", "bayesrob", "simulate", "x",
                                         "--effects", "nope"],
}


def _seconds(cmd: list[str]) -> float:
    t0 = time.perf_counter()
    subprocess.run(cmd, capture_output=True, check=False)
    return time.perf_counter() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    base = None
    for name, cmd in CASES.items():
        median = statistics.median(_seconds(cmd) for _ in range(args.repeat))
        base = median if base is None else base
        print(json.dumps({"case": name, "median_s": round(median, 3),
                          "over_python_s": round(median - base, 3),
                          "target_s": None if name.startswith("python") else 0.5}))


if __name__ == "__main__":
    main()
