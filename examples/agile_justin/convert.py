"""Convert DLR's Agile Justin calibration data into a bayesrob rig directory.

    python examples/agile_justin/convert.py SRC_CSV OUT_DIR [--split 300]

SRC_CSV is the authors' ``measurements.csv`` (500 rows: an index, ``joints``, a numpy-printed
array of 19 joint angles in rad, and ``markers``, a 2 x 3 array in metres: right hand, left
hand). Rows keep the file's order (the authors shuffled it): the first ``--split`` poses are
``train``, the rest ``validation``, as in the authors' scripts. Each pose becomes two rows, one
per hand marker (config ``right`` / ``left``), in mm, each with the whole pose (the torso's
three joint columns and both arms' seven: the other arm's weight bends the torso); rig.toml
(this directory's, from the published nominal values) is copied beside it. The data carries
no license: it is read from where the user keeps it, never shipped. The conversion itself is
``bayesrob.validation.justin.convert``, which the validation suite's Justin studies run.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

# Run from a checkout, the examples use its bayesrob (and its validation/ studies), not an
# installed copy that may predate them.
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from bayesrob.validation.justin import convert  # noqa: E402


def source_arguments(p: argparse.ArgumentParser) -> None:
    """What the examples built on this converter take: the authors' file and the rig it
    becomes."""
    p.add_argument("src", type=Path, help="the authors' measurements.csv")
    p.add_argument("--out", type=Path, default=Path("justin-rig"), help="rig directory")


def converted_rig(src: Path, out: Path) -> Path | None:
    """``out`` with the rig converted from ``src``; None, after a one-line error on stderr,
    when ``src`` is not a file."""
    if not src.is_file():
        print(f"{src}: file not found", file=sys.stderr)
        return None
    convert(src, out)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("src", type=Path, help="the authors' measurements.csv")
    p.add_argument("out", type=Path, help="rig directory to write")
    p.add_argument("--split", type=int, default=300, help="poses used for training (300)")
    args = p.parse_args(argv)
    if not args.src.is_file():
        print(f"{args.src}: file not found", file=sys.stderr)
        return 2
    n = convert(args.src, args.out, args.split)
    print(f"wrote {args.out}/rig.toml and measurements.csv ({n} poses, {2 * n} marker rows; "
          f"{min(n, args.split)} train, {max(n - args.split, 0)} validation)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
