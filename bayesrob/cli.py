"""The ``bayesrob`` command: argument parsing only; every command calls one library function.

User mistakes (bad rig files, bad arguments) are reported as one line on stderr with exit
code 2, never a traceback.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from pathlib import Path

from bayesrob.rig import RigError

# name -> (one-line help, add_arguments(parser), run(args) -> exit code)
Command = tuple[str, Callable[[argparse.ArgumentParser], None], Callable[[argparse.Namespace], int]]
COMMANDS: dict[str, Command] = {}


class UsageError(ValueError):
    """A command-line argument is wrong; reported like a rig error."""


def command(name: str, help: str):
    def register(add_arguments):
        def with_run(run):
            COMMANDS[name] = (help, add_arguments, run)
            return run
        return with_run
    return register


def _write_json(doc: dict, out: str | None) -> None:
    if out is None:
        return
    text = json.dumps(doc, indent=2, allow_nan=True)
    if out == "-":
        print(text)
    else:
        Path(out).parent.mkdir(parents=True, exist_ok=True)
        Path(out).write_text(text + "\n")


def _effects_list(text: str) -> tuple[str, ...]:
    from bayesrob.simulator import EFFECTS

    items = tuple(e.strip() for e in text.split(",") if e.strip())
    for e in items:
        if e not in EFFECTS:
            raise argparse.ArgumentTypeError(
                f"unknown effect {e!r} (choose from {', '.join(EFFECTS)})")
    return items


def _positive_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if v < 2:
        raise argparse.ArgumentTypeError(f"must be at least 2, got {v}")
    return v


def _load_rig_arg(path: str | None):
    """Load the rig a command was given, or the embedded default rig."""
    from bayesrob.rig import default_rig_dir, load_rig

    return load_rig(path if path is not None else default_rig_dir())


# ------------------------------------------------------------------------------ simulate


def _simulate_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("out_dir", help="directory to write rig.toml, measurements.csv, truth.toml")
    p.add_argument("--effects", type=_effects_list, default=(),
                   help="comma-separated physical effects: gravity_sag,backlash,"
                        "servo_nonlinearity (default: none)")
    p.add_argument("--grid", type=_positive_int, default=4, help="N for the N x N grid (4)")
    p.add_argument("--seed", type=int, default=0, help="random seed (0)")
    p.add_argument("--joint-noise-rad", type=float, default=None,
                   help="joint repeatability noise, sd in rad (0.0008)")
    p.add_argument("--measurement-noise-mm", type=float, default=None,
                   help="measurement noise, sd in mm per axis (0.35)")


@command("simulate", "write a simulated rig (paper's two-arm setup) with chosen physical effects")(
    _simulate_args)
def _simulate(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from bayesrob.simulator import paper_truth, simulate_rig

    truth = paper_truth(args.effects, seed=args.seed, grid=args.grid)
    if args.joint_noise_rad is not None:
        truth = replace(truth, joint_noise_rad=args.joint_noise_rad)
    if args.measurement_noise_mm is not None:
        truth = replace(truth, measurement_noise_mm=args.measurement_noise_mm)
    out = simulate_rig(args.out_dir, truth, progress=sys.stderr.isatty())
    effects = ",".join(truth.effects) or "none"
    print(f"wrote {out}/ (grid {args.grid}x{args.grid}, effects: {effects}, seed {args.seed})")
    return 0


# ------------------------------------------------------------------------------ calibrate


def _calibrate_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("rig", nargs="?", help="rig directory (default: the embedded default rig)")
    p.add_argument("--method", choices=["least-squares", "hill-climb"], default="least-squares",
                   help="least-squares (default, scipy) or hill-climb (the paper's baseline)")
    p.add_argument("--json", metavar="OUT", help="write the report as JSON ('-' for stdout)")


@command("calibrate", "fit each arm's eight parameters and report observed accuracy")(
    _calibrate_args)
def _calibrate(args: argparse.Namespace) -> int:
    from bayesrob.calibration import calibration_report
    from bayesrob.report import format_calibration
    rig = _load_rig_arg(args.rig)
    doc = calibration_report(rig, args.method)
    if args.json != "-":
        print(format_calibration(doc))
    _write_json(doc, args.json)
    return 0


# ------------------------------------------------------------------------------ reproduce


def _reproduce_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("rig", nargs="?", help="rig directory (default: the embedded default rig)")
    p.add_argument("--out", default="reproduction",
                   help="directory for accuracy.json and the figures (default: ./reproduction)")
    p.add_argument("--models", nargs="+", metavar="NAME",
                   help="model names to fit (default: every file in models/)")
    p.add_argument("--models-dir", help="directory of model files (default: the shipped ones)")
    p.add_argument("--calibration", choices=["least-squares", "hill-climb"],
                   default="least-squares", help="calibration method (default least-squares)")
    p.add_argument("--grid-half-width", type=float, default=30.0,
                   help="half width of the prediction grid around each target, mm (30)")
    p.add_argument("--grid-n", type=_positive_int, default=100,
                   help="grid cells per side (100)")


@command("reproduce", "run the paper end to end: calibrate, fit IND/CORR/COND, predict, "
                      "write Figures 3-8 and accuracy.json")(_reproduce_args)
def _reproduce(args: argparse.Namespace) -> int:
    from bayesrob.noise_models import ModelFileError
    from bayesrob.prediction import Grid
    from bayesrob.reproduction import format_accuracy, run_reproduction, write_reproduction

    rig = _load_rig_arg(args.rig)
    try:
        rep = run_reproduction(rig, args.models, args.models_dir,
                               Grid(args.grid_half_width, args.grid_n), args.calibration,
                               progress=sys.stderr.isatty())
    except ModelFileError as exc:
        raise UsageError(str(exc)) from None
    written = write_reproduction(rep, args.out)
    print(f"rig {rig.name}: {len(rep.specs)} models, {len(rep.rows)} setups, "
          f"{rep.seconds:.1f} s")
    print(format_accuracy(rep.accuracy))
    print(f"wrote {len(written)} files to {args.out}/")
    return 0


# ------------------------------------------------------------------------------ main
# Further commands register themselves above this line with @command.


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="bayesrob",
        description="Predict how accurately modular robot arms place their end point, alone "
                    "and linked.")
    from bayesrob import __version__

    parser.add_argument("--version", action="version", version=f"bayesrob {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, (help_text, add_arguments, _) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        add_arguments(p)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    _, _, run = COMMANDS[args.command]
    try:
        return run(args)
    except (RigError, UsageError) as exc:
        print(f"bayesrob {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"bayesrob {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
