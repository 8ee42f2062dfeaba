"""DLR's Agile Justin: does each hand's predicted region hold its stated coverage on the
validation poses?

    python examples/agile_justin/coverage.py ../shared/data/agile-justin/measurements.csv

Converts the authors' file (``--out``, default ``justin-rig/``), calibrates on the 300 train
poses with the groups ``bayesrob diagnose`` names (``--groups``, default
frames,geometric,compliance,lateral; ``frames,geometric`` for the geometric model alone),
fits each hand's joint-error population (``--model``, default ind), and predicts each hand at
its 200 validation poses (the other arm's pose given: its weight bends the torso). Prints,
per hand, the share of validation points inside the predicted 50% and 90% regions and the
predicted / observed mean error (observed: distance from the predicted mean point). Nothing
here is tuned on the validation rows. ``--sag-steps 6`` calibrates with the gravity torques
taken six times, the model of ``bayesrob diagnose --sag-steps 6`` (about 7 minutes). The
validation suite's study ``justin_coverage`` runs the default
(``bayesrob.validation.justin.coverage``) and holds it to its targets.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

# Run from a checkout, the examples use its bayesrob (and its validation/ studies), not an
# installed copy that may predate them.
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from bayesrob.validation.justin import coverage  # noqa: E402
from convert import converted_rig, source_arguments  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    source_arguments(p)
    p.add_argument("--groups", default="frames,geometric,compliance,lateral")
    p.add_argument("--model", default="ind", choices=["ind", "corr"])
    p.add_argument("--sag-steps", type=int, default=1,
                   help="take the gravity torques this many times, towards their equilibrium "
                        "(6 as `bayesrob diagnose --sag-steps 6`)")
    p.add_argument("--json", type=Path, help="also write the rows as JSON here")
    args = p.parse_args(argv)
    if args.sag_steps < 1:
        p.error(f"--sag-steps must be at least 1, not {args.sag_steps}")
    rig = converted_rig(args.src, args.out)
    if rig is None:
        return 2
    rows = coverage(rig, tuple(args.groups.split(",")), args.model, sag_steps=args.sag_steps)
    print("| hand | groups | model | 50% / 90% coverage | predicted / observed error (mm) |")
    print("|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['hand']} | {','.join(r['groups'])} | {r['model']} | "
              f"{r['coverage50']:.3f} / {r['coverage90']:.3f} | "
              f"{r['predicted_error_mm']:.2f} / {r['observed_error_mm']:.2f} "
              f"({r['ratio']:.2f}) |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
