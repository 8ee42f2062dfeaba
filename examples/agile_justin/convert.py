"""Convert DLR's Agile Justin calibration data into a bayesrob rig directory.

    python examples/agile_justin/convert.py SRC_CSV OUT_DIR [--split 300]

SRC_CSV is the authors' ``measurements.csv`` (500 rows: an index, ``joints``, a numpy-printed
array of 19 joint angles in rad, and ``markers``, a 2 x 3 array in metres: right hand, left
hand). Rows keep the file's order (the authors shuffled it): the first ``--split`` poses are
``train``, the rest ``validation``, as in the authors' scripts. Each pose becomes two rows, one
per hand marker (config ``right`` / ``left``), in mm, each with the whole pose (the torso's
three joint columns and both arms' seven: the other arm's weight bends the torso); rig.toml
(this directory's, from the published nominal values) is copied beside it. The data carries
no license: it is read from where the user keeps it, never shipped.
"""

from __future__ import annotations

import argparse
import csv
import shutil
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
TORSO, RIGHT, LEFT = slice(0, 3), slice(3, 10), slice(10, 17)


def _array(text: str, shape: tuple[int, ...], where: str) -> np.ndarray:
    try:
        values = np.array(text.replace("[", " ").replace("]", " ").split(), float)
    except ValueError:
        raise SystemExit(f"{where}: not a numeric array: {text[:40]!r}...") from None
    if values.size != int(np.prod(shape)) or not np.all(np.isfinite(values)):
        raise SystemExit(f"{where}: expected {np.prod(shape)} finite numbers, got {values.size}")
    return values.reshape(shape)


def convert(src: Path, out: Path, split: int = 300) -> int:
    with open(src, newline="") as f:
        rows = list(csv.reader(f))
    header = [h.strip() for h in rows[0]]
    if header[1:] != ["joints", "markers"]:
        raise SystemExit(f"{src}: header must be ',joints,markers', got {','.join(header)!r}")
    out.mkdir(parents=True, exist_ok=True)
    cols = ([f"torso_u{k + 1}" for k in range(3)] + [f"right_u{k + 1}" for k in range(7)]
            + [f"left_u{k + 1}" for k in range(7)])
    lines = [["config", "set", *cols, "x", "y", "z", "pose"]]
    for i, row in enumerate(rows[1:]):
        where = f"{src}: line {i + 2}"
        q = _array(row[1], (19,), where + ": joints")
        markers = _array(row[2], (2, 3), where + ": markers") * 1000.0  # m -> mm
        st = "train" if i < split else "validation"
        # every row carries the whole pose: the other arm's weight bends the shared torso
        u = [f"{v:.10g}" for v in (*q[TORSO], *q[RIGHT], *q[LEFT])]
        for arm, m in (("right", markers[0]), ("left", markers[1])):
            lines.append([arm, st, *u, *(f"{v:.4f}" for v in m), row[0]])
    with open(out / "measurements.csv", "w", newline="") as f:
        csv.writer(f).writerows(lines)
    shutil.copy(HERE / "rig.toml", out / "rig.toml")
    return len(rows) - 1


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
