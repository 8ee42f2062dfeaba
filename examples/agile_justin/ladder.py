"""DLR's Agile Justin: the geometric calibration ladder on the authors' split, beside theirs.

    python examples/agile_justin/ladder.py ../shared/data/agile-justin/measurements.csv

Converts the authors' file into a rig directory (``--out``, default ``justin-rig/``), then
calibrates with ``--params frames``, ``frames,offsets``, ``frames,geometric``, the four rigid
groups, ``frames,geometric,compliance`` and ``...,lateral`` (one to two minutes each), the last
also with its torques at equilibrium (``--sag-steps 6``: about three minutes), each on the 300
train poses, and prints the marker error on the 200 validation poses (400 marker positions) as
a markdown table next to the published figures. Equivalent commands:
``bayesrob calibrate justin-rig --params frames,geometric`` (``--sag-steps 6``). The
validation suite's study ``justin_ladder`` runs the same ladder
(``bayesrob.validation.justin.ladder``) and holds it to its targets.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

# Run from a checkout, the examples use its bayesrob (and its validation/ studies), not an
# installed copy that may predate them.
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from bayesrob.validation.justin import ladder, ladder_table  # noqa: E402
from convert import converted_rig, source_arguments  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    source_arguments(p)
    p.add_argument("--json", type=Path, help="also write the ladder as JSON here")
    args = p.parse_args(argv)
    rig = converted_rig(args.src, args.out)
    if rig is None:
        return 2
    rows = ladder(rig)
    print(ladder_table(rows))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
