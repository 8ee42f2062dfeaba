"""The ``bayesrob`` command: argument parsing and printing only; every command calls the
library for its work and ``bayesrob.report`` for what it writes.

User mistakes (bad rig files, bad arguments) are reported as one line on stderr with exit
code 2, never a traceback.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path
from typing import NamedTuple

from bayesrob.data.vocabulary import (
    ALL_GROUPS,
    CHAIN_EFFECTS,
    DEFAULT_FUSION,
    EFFECTS,
    FUSIONS,
    MASS_SOURCES,
)
from bayesrob.progress import FIRST_LINE_S, progress
from bayesrob.report.output_paths import (
    DIRECTORY,
    FILE,
    OutputPathError,
    check_output,
    save_figure,
    staged_directory,
    write_text,
)


class Command(NamedTuple):
    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]
    progress: bool  # takes --no-progress: reports progress on stderr


COMMANDS: dict[str, Command] = {}

# The library's errors for a user's mistake, by module path: looked up only among the modules
# a command imported, so that argument errors never import them (test_cli_contract checks
# every path still names a class). Each is one line on stderr and exit 2.
USER_ERRORS = (
    "bayesrob.data.rig.RigError",
    "bayesrob.errors.noise_models.ModelFileError",
    "bayesrob.cluster.ClusterError",  # a --scheduler that cannot be reached
    "bayesrob.design.file.DesignError",
    "bayesrob.diagnose.groups.DiagnosisError",
    "bayesrob.hardware.controller.ArgumentError",
    "bayesrob.hardware.controller.HardwareError",  # a port that cannot be opened, a mute device
    "bayesrob.sim.equilibrium.LinkedSimulationError",  # e.g. a linked row that did not settle
    "bayesrob.validation.study.StudyError",
)


class UsageError(ValueError):
    """A command-line argument is wrong; reported like a rig error."""


def command(name: str, help: str, arguments: Callable[[argparse.ArgumentParser], None],
            progress: bool = True):
    def register(run: Callable[[argparse.Namespace], int]):
        COMMANDS[name] = Command(help, arguments, run, progress)
        return run
    return register


@contextlib.contextmanager
def _as_usage_error() -> Iterator[None]:
    """A library's ValueError for what the user asked (an unknown model, a config the rig
    lacks) reported as a usage error; outside such a block a ValueError is a bug's traceback."""
    try:
        yield
    except ValueError as exc:
        raise UsageError(str(exc)) from None


def _write_json(doc: dict, out: str | None) -> None:
    if out is None:
        return
    text = json.dumps(doc, indent=2, allow_nan=True)
    if out == "-":
        print(text)
    else:
        write_text(out, text + "\n")
        print(f"wrote {out}")


def _wrote(path: str | Path, json_out: str | None) -> None:
    """Say that a file was written: on stdout, or stderr when stdout carries the JSON."""
    print(f"wrote {path}", file=sys.stderr if json_out == "-" else sys.stdout)


def _report(doc: dict, table: Callable[[dict], str], json_out: str | None,
            write: Callable[[], list] | None = None) -> None:
    """A command's result: its table (unless stdout carries the JSON), then the files
    ``write`` writes, then the JSON."""
    if json_out != "-":
        print(table(doc))
    for path in write() if write else ():
        _wrote(path, json_out)
    _write_json(doc, json_out)


def _staged(directory: str | Path, write: Callable[[Path], list[Path]]) -> list[Path]:
    """The files ``write`` puts in a scratch directory, moved into ``directory`` all at once
    (none if it fails or is interrupted); returns where they are."""
    with staged_directory(directory) as scratch:
        names = [p.name for p in write(scratch)]
    return [Path(directory) / n for n in names]


def _progress(args: argparse.Namespace) -> bool:
    return not getattr(args, "no_progress", False)


def _clock(args: argparse.Namespace, postfix: str):
    """A step with nothing to count inside: the clock, on the promised five-second beat."""
    return progress(None, args.command, enabled=_progress(args), postfix=postfix,
                    first_after=FIRST_LINE_S)


def _load_rig_arg(path: str | None, chains: bool = True):
    """Load the rig a command was given, or the embedded default rig.

    ``chains`` False: the command is the paper's (reproduce: its Figures 3-8 are of planar
    arms), and a URDF/DH rig is refused with one line rather than failing deep inside.
    """
    from bayesrob.data.rig import default_rig_dir, load_rig

    rig = load_rig(path if path is not None else default_rig_dir())
    if rig.is_chain and not chains:
        raise UsageError(f"{rig.path}: the paper's reproduction (Figures 3-8) is of planar "
                         "arms; arms described by URDF or DH tables are calibrated, predicted, "
                         "compared, sampled and diagnosed by those commands")
    return rig


# ------------------------------------------------------------------------------ argument types


def _number(kind: type = float, low: float | None = None, high: float | None = None, *,
            above: bool = False, finite: bool = False) -> Callable[[str], float]:
    """An argparse type: a number of ``kind``, at least ``low`` (more than, if ``above``), at
    most ``high``, and finite if asked."""
    def parse(text: str):
        try:
            v = kind(text)
        except ValueError:
            what = "a whole number" if kind is int else "a number"
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
        if finite and not math.isfinite(v) and (low is None or above):
            raise argparse.ArgumentTypeError(f"must be finite, got {text}")
        if (low is not None and not (v > low or (v == low and not above))
                or high is not None and v > high or finite and not math.isfinite(v)):
            bound = (f"more than {low:g}" if above else f"{low:g} or more and finite" if finite
                     else f"at least {low:g}")
            bound += f" and at most {high:g}" if high is not None else ""
            raise argparse.ArgumentTypeError(f"must be {bound}, got {text}")
        return v
    return parse


_positive_int = _number(int, 2)  # grids, counts of workers and rows: 2 or more
_at_least_one = _number(int, 1)
_seed_type = _number(int, 0)  # NumPy's generators take whole numbers from 0 up
_non_negative_float = _number(float, 0.0, finite=True)


def _names(known: tuple[str, ...], what: str, empty: bool = True) -> Callable[[str], tuple]:
    """An argparse type: comma-separated names out of ``known`` (none at all if ``empty``)."""
    def parse(text: str) -> tuple[str, ...]:
        items = tuple(e.strip() for e in text.split(",") if e.strip())
        if not items and not empty:
            raise argparse.ArgumentTypeError(f"name at least one {what}")
        for e in items:
            if e not in known:
                raise argparse.ArgumentTypeError(
                    f"unknown {what} {e!r} (choose from {', '.join(known)})")
        return items
    return parse


_effects_list = _names(EFFECTS, "effect")
_param_groups = _names(ALL_GROUPS, "parameter group", empty=False)
_candidate_effects = _names(tuple(dict.fromkeys([*EFFECTS, *CHAIN_EFFECTS])), "effect",
                            empty=False)


class _Once(argparse.BooleanOptionalAction):
    """--flag / --no-flag, refused when both are given (which one was meant is unknown)."""

    def __call__(self, parser, namespace, values, option_string=None):
        given = f"_{self.dest}_given"
        if getattr(namespace, given, None) not in (None, option_string):
            parser.error(f"{getattr(namespace, given)} and {option_string} contradict each "
                         "other: give one")
        setattr(namespace, given, option_string)
        super().__call__(parser, namespace, values, option_string)


# ------------------------------------------------------------------------------ shared options


def _output(action: argparse.Action, kind: str) -> argparse.Action:
    """Mark an option as an output path (FILE or DIRECTORY), checked before any work so that
    a path the command cannot write never costs a run's results."""
    action.output_kind = kind  # type: ignore[attr-defined]
    return action


def _rig_arg(p: argparse.ArgumentParser,
             help: str = "rig directory (default: the embedded default rig)") -> None:
    p.add_argument("rig", nargs="?", help=help)


def _json_arg(p: argparse.ArgumentParser,
              help: str = "write the result as JSON ('-' for stdout)") -> None:
    _output(p.add_argument("--json", metavar="OUT", help=help), FILE)


def _plot_arg(p: argparse.ArgumentParser, help: str) -> None:
    _output(p.add_argument("--plot", metavar="PATH", help=help), FILE)


def _seed_arg(p: argparse.ArgumentParser, help: str = "random seed (0)", default=0) -> None:
    p.add_argument("--seed", type=_seed_type, default=default, help=help)


def _models_args(p: argparse.ArgumentParser, verb: str | None = None) -> None:
    """--models NAME... (if the command takes several, ``verb``-ed) and --models-dir."""
    if verb:
        p.add_argument("--models", nargs="+", metavar="NAME",
                       help=f"model names to {verb} (default: every file in models/)")
    p.add_argument("--models-dir", help="directory of model files (default: the shipped ones)")


def _params_arg(p: argparse.ArgumentParser, help: str = (
        "the parameter groups the arms are calibrated with, as 'bayesrob calibrate --params' "
        "(URDF/DH default frames,offsets,geometric,servo). Given for a planar rig, its arms "
        "are taken as the 2-joint chains they are (the models as marker densities) instead of "
        "the eight-parameter fit")) -> None:
    p.add_argument("--params", type=_param_groups, default=None, metavar="GROUPS", help=help)


def _grid_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--grid", type=_positive_int, default=4, help="N for the N x N grid (4)")


def _device_number_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--device-number", type=_number(int, 0, 127), default=12,
                   help="Maestro device number for the Pololu protocol (12)")


def _pick(args: argparse.Namespace, *names: str) -> dict:
    """The options of these names, as keyword arguments of the same names."""
    return {n: getattr(args, n) for n in names}


# ------------------------------------------------------------------------------ simulate


def _simulate_args(p: argparse.ArgumentParser) -> None:
    _output(p.add_argument("out_dir", help="directory to write rig.toml, measurements.csv, "
                                           "truth.toml"), DIRECTORY)
    p.add_argument("--effects", type=_effects_list, default=(),
                   help="comma-separated physical effects: gravity_sag,backlash,"
                        "servo_nonlinearity (default: none)")
    _grid_arg(p)
    _seed_arg(p)
    p.add_argument("--joint-noise-rad", type=_non_negative_float, default=None,
                   help="joint repeatability noise, sd in rad (0.0008)")
    p.add_argument("--measurement-noise-mm", type=_non_negative_float, default=None,
                   help="measurement noise, sd in mm per axis (0.35)")
    p.add_argument("--force", action="store_true",
                   help="replace the rig files (measurements.csv, rig.toml, truth.toml) the "
                        "directory already holds")
    p.add_argument("--robot", choices=["paper", "three-arm", "arm6"], default="paper",
                   help="paper: the two planar arms (default); three-arm: those two and a third "
                        "(side), linked rows joining all three; arm6: a 6-joint 3-D URDF arm "
                        "with perturbed joint origins, offsets, marker and instrument pose")
    p.add_argument("--planned", action="store_true",
                   help="measure the planned rows (empty x, y) of the rig in out_dir with the "
                        "physics of its truth.toml, e.g. a candidate of bayesrob design")
    p.add_argument("--compliance", action=_Once, default=None,
                   help="arm6: joints give way under gravity (point masses, joint stiffness); "
                        "off by default, on by default with --linked")
    p.add_argument("--play-mrad", type=_non_negative_float, default=None, metavar="MRAD",
                   help="arm6: play in every joint (whole width, mrad), taken up on the side "
                        "gravity pushes the joint to (approach side where the torque is weak)")
    p.add_argument("--poses", nargs="+", default=None, metavar="N",
                   help="arm6: TRAIN VALIDATION HOLDOUT random poses per set (80 40 40), each "
                        "set at its own poses; or a poses.csv (bayesrob plan) to measure, in "
                        "its order, on the simulated rig in OUT_DIR, appending its rows")
    p.add_argument("--linked", action="store_true",
                   help="arm6: two arms (left, right) facing each other, single-arm rows for "
                        "each (--poses per arm) and 24 left+right test rows with their markers "
                        "joined at one point")
    p.add_argument("--third-arm", action="store_true",
                   help="arm6 --linked: a third arm (front) facing the targets from the side, "
                        "its single-arm rows beside the others' and the test rows joining all "
                        "three (left+right+front)")
    p.add_argument("--stiffness-spread", type=_non_negative_float, default=None,
                   metavar="LOG_SD",
                   help="draw each arm's joint stiffnesses for the seed: log k = log(profile) "
                        "+ N(0, LOG_SD) per arm + N(0, LOG_SD) per joint (planar rigs: 0, "
                        "every arm alike, by default; arm6 --linked: 0.3)")
    p.add_argument("--mass-spread", type=_non_negative_float, default=None, metavar="LOG_SD",
                   help="arm6 --linked: draw each arm's true link masses about the URDF's: "
                        "m = m_urdf exp(N(0, LOG_SD)) per arm and link (default 0: as the "
                        "URDF states them)")


def _refuse(rules: list[tuple[object, str]]) -> None:
    """The first rule whose condition holds is the usage error."""
    for condition, message in rules:
        if condition:
            raise UsageError(message)


def _arm6_truth(args: argparse.Namespace):
    """The truth of a simulated arm6 rig, single or linked, from the options."""
    from bayesrob.sim.truth import Arm6Truth, LinkedArm6Truth, three_arm6_truth

    linked = args.linked
    _refuse([
        (args.effects or args.grid != 4, "--effects and --grid describe the planar paper rig; "
                                         "arm6 takes --compliance and --poses"),
        (args.third_arm and not linked, "--third-arm joins a third arm to arm6 --linked; add "
                                        "--linked"),
        (linked and args.play_mrad is not None, "--play-mrad is for a single arm6 (the linked "
                                                "arms have none)"),
        (not linked and args.mass_spread is not None, "--mass-spread is for arm6 --linked"),
        (not linked and args.stiffness_spread is not None,
         "--stiffness-spread is for planar rigs and arm6 --linked (a single arm6 has one "
         "stiffness profile)"),
        (args.mass_spread is not None and args.compliance is False,
         "--mass-spread draws the masses gravity bends the arms with; --no-compliance has "
         "none")])
    if not linked:
        return Arm6Truth(seed=args.seed, compliance=bool(args.compliance),
                         joint_play_rad=1e-3 * (args.play_mrad or 0.0))
    truth = (three_arm6_truth if args.third_arm else LinkedArm6Truth)(seed=args.seed)
    for option, field in (("stiffness_spread", "stiffness_log_sd"),
                          ("mass_spread", "mass_log_sd"), ("compliance", "compliance")):
        if getattr(args, option) is not None:
            truth = replace(truth, **{field: getattr(args, option)})
    return truth


def _truth_options(truth, args: argparse.Namespace):
    """The simulate options every robot shares, applied to its truth: noise levels, and the
    pose counts of the chain arms (refused for the planar rigs before this)."""
    if args.poses:
        truth = replace(truth, n_train=args.poses[0], n_validation=args.poses[1],
                        n_holdout=args.poses[2])
    for option in ("joint_noise_rad", "measurement_noise_mm"):
        if getattr(args, option) is not None:
            truth = replace(truth, **{option: getattr(args, option)})
    return truth


def _simulate_arm6(args: argparse.Namespace, out_dir: Path) -> str:
    """Write an arm6 rig; returns its description for the closing line."""
    from bayesrob.sim.rigs import simulate_arm6_rig, simulate_linked_arm6_rig

    truth = _truth_options(_arm6_truth(args), args)
    counts = f"{truth.n_train}/{truth.n_validation}/{truth.n_holdout} train/validation/holdout"
    compliance = f"compliance {'on' if truth.compliance else 'off'}"
    if args.linked:
        name = f"arm6 {'+'.join(truth.arms)}"
        what = (f"{name}, {counts} poses per arm, {truth.n_linked} linked test rows, "
                f"{compliance}")
    else:
        name = "arm6"
        what = f"arm6, {counts} poses, {compliance}, play {args.play_mrad or 0:g} mrad"
    with _clock(args, name):
        # written whole or not at all: Ctrl-C part-way leaves out_dir as it was
        with staged_directory(out_dir) as scratch:
            (simulate_linked_arm6_rig if args.linked else simulate_arm6_rig)(scratch, truth)
    return f"{what}, seed {args.seed}"


@command("simulate", "write a simulated rig (the paper's two planar arms, or a 6-joint 3-D "
                     "arm) with chosen physical effects", _simulate_args)
def _simulate(args: argparse.Namespace) -> int:
    from bayesrob.data.rig import MEASUREMENTS_FILE, RIG_FILE
    from bayesrob.sim.rigs import measure_planned, simulate_rig
    from bayesrob.sim.truth import TRUTH_FILE, paper_truth, three_arm_truth

    out_dir = Path(args.out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise UsageError(f"{out_dir} is a file, not a directory")
    if args.poses is not None and len(args.poses) == 1:
        from bayesrob.hardware.collect import measure_plan_in_simulation

        poses = Path(args.poses[0])
        n = measure_plan_in_simulation(out_dir, poses, args.seed, _progress(args))
        print(f"measured {n} poses of {poses} into {out_dir / 'measurements.csv'}")
        return 0
    if args.poses is not None:
        if len(args.poses) != 3:
            raise UsageError("--poses takes TRAIN VALIDATION HOLDOUT counts or one poses.csv")
        try:
            args.poses = [_positive_int(v) for v in args.poses]
        except argparse.ArgumentTypeError as exc:
            raise UsageError(f"--poses: {exc}") from None
    if args.planned:
        _refuse([(args.linked or args.third_arm,
                  "--planned measures the rows the rig in OUT_DIR plans, with the arms of its "
                  "truth.toml; --linked and --third-arm make a new rig"),
                 (args.stiffness_spread is not None or args.mass_spread is not None,
                  "--planned measures with the stiffnesses and masses of the rig's truth.toml; "
                  "--stiffness-spread and --mass-spread cannot change them")])
        n, total = measure_planned(out_dir, seed=args.seed, progress=_progress(args))
        print(f"measured {n} planned rows of {out_dir / 'measurements.csv'} ({total} rows in "
              "all)")
        return 0
    names = (MEASUREMENTS_FILE, RIG_FILE, TRUTH_FILE)
    existing = [out_dir / n for n in names if (out_dir / n).exists()]
    if existing and not args.force:
        # measurements.csv first: it may be real data that cannot be made again.
        raise UsageError(f"{existing[0]} already exists; simulate would replace it (pass "
                         "--force to overwrite, or choose another directory)")
    if args.robot == "arm6":
        what = _simulate_arm6(args, out_dir)
        files = "measurements.csv, rig.toml, arm6.urdf, truth.toml"
    else:
        _refuse([(args.compliance is not None or args.poses or args.linked or args.third_arm
                  or args.play_mrad is not None,
                  "--compliance, --play-mrad, --poses and --linked are for --robot arm6 "
                  "(--third-arm for arm6 --linked)"),
                 (args.mass_spread is not None, "--mass-spread is for arm6 --linked")])
        make = three_arm_truth if args.robot == "three-arm" else paper_truth
        truth = _truth_options(make(args.effects, seed=args.seed, grid=args.grid,
                                    stiffness_log_sd=args.stiffness_spread or 0.0), args)
        with staged_directory(out_dir) as scratch:
            simulate_rig(scratch, truth, progress=_progress(args))
        spread = (f", stiffnesses drawn (log sd {args.stiffness_spread:g})"
                  if args.stiffness_spread else "")
        what = (f"grid {args.grid}x{args.grid}, effects: {','.join(truth.effects) or 'none'}, "
                f"seed {args.seed}{spread}")
        files = ", ".join(names)
    if existing:
        print(f"replaced (--force): {', '.join(str(p) for p in existing)}")
    print(f"wrote {out_dir}/ ({what}): {files}")
    return 0


# ------------------------------------------------------------------------------ calibrate


def _calibrate_args(p: argparse.ArgumentParser) -> None:
    _rig_arg(p)
    p.add_argument("--method", choices=["least-squares", "hill-climb", "bayes"],
                   default="least-squares",
                   help="least-squares (default, scipy), hill-climb (the paper's baseline) or "
                        "bayes (NUTS posterior; params = posterior mean, std err = posterior sd)")
    _json_arg(p, "write the report as JSON ('-' for stdout)")
    _params_arg(p, "parameter groups to fit, comma-separated: frames (instrument pose and "
                   "markers; always fitted), offsets (joint zero offsets), geometric (every "
                   "joint origin), servo (command gains), compliance (joints giving way under "
                   "gravity; link masses fitted too), lateral (joints and links bending across "
                   "their axes under the same torques; link masses fitted too), encoder "
                   "(revolute joints read through an eccentric encoder), backlash (play in the "
                   "joints, taken up on the side gravity pushes them to), servo_curve (a "
                   "curved command map: c2 q^2 + c3 q^3 on each joint). Default for URDF/DH "
                   "rigs: the first four; a planar rig without --params fits its eight "
                   "parameters per arm")
    _output(p.add_argument("--urdf-out", metavar="FILE",
                           help="write the calibrated robot as URDF to FILE, and FILE with "
                                "suffix .rig.toml: a rig.toml (instrument poses, markers) that "
                                "loads it back"), FILE)
    p.add_argument("--sag-steps", type=_at_least_one, default=1, metavar="N",
                   help="with compliance or lateral: take the gravity torques N times, first "
                        "at the commanded pose, then each time at the pose the last step "
                        "sagged into, towards torque equilibrium (default 1; the fit reports "
                        "how far one more step would move the markers: docs/robots.md)")
    p.add_argument("--masses", choices=MASS_SOURCES, default=MASS_SOURCES[0],
                   help="with compliance or lateral: the links' masses and first moments "
                        "fitted (default; only their products with the compliances are seen) "
                        "or held at the URDF's <inertial> ones, so each compliance is the "
                        "joint's own")


def _calibrate_groups(args: argparse.Namespace, rig) -> int:
    from bayesrob.calibrate.least_squares import calibrate
    from bayesrob.report.outputs import write_calibrated_robot
    from bayesrob.report.tables import format_group_calibration
    from bayesrob.robot import GROUPS

    bayes = args.method == "bayes"
    _refuse([(args.method == "hill-climb",
              "--method hill-climb is the paper's eight-parameter planar fit; URDF/DH rigs (and "
              "--params) use least-squares or bayes"),
             (args.sag_steps > 1 and bayes, "--sag-steps is for the least-squares fit; --method "
                                            "bayes takes the torques once"),
             (args.masses != "fitted" and bayes, "--masses description is for the "
                                                 "least-squares fit; --method bayes fits the "
                                                 "masses")])
    groups = args.params or GROUPS
    with (progress(None, "calibrate", enabled=_progress(args),
                   postfix=f"{', '.join(groups)}: compiling and fitting") as bar,
          _as_usage_error()):
        if bayes:
            from bayesrob.calibrate.bayes import calibrate_bayes

            cal = calibrate_bayes(rig, groups, progress=bar.set_postfix)
        else:
            cal = calibrate(rig, groups, progress=bar.set_postfix, sag_steps=args.sag_steps,
                            masses=args.masses)
    doc = {"rig": rig.name, **cal.to_json()}
    if args.urdf_out:
        write_calibrated_robot(doc, rig, cal, args.urdf_out)
    _report(doc, format_group_calibration, args.json,
            lambda: [doc[k] for k in ("urdf_out", "rig_toml_out") if k in doc])
    return 0


@command("calibrate", "fit each arm's parameters (planar, URDF or DH arms) and report accuracy",
         _calibrate_args)
def _calibrate(args: argparse.Namespace) -> int:
    from bayesrob.report.outputs import calibration_report
    from bayesrob.report.tables import format_calibration

    rig = _load_rig_arg(args.rig)
    if rig.is_chain or args.params is not None or args.urdf_out:
        return _calibrate_groups(args, rig)
    if args.sag_steps != 1 or args.masses != "fitted":
        raise UsageError(f"{'--sag-steps' if args.sag_steps != 1 else '--masses'} is for "
                         "URDF/DH rigs (and --params); the planar eight-parameter fit has no "
                         "sag")
    # NUTS per arm compiles and samples for tens of seconds; the other methods take about one.
    with progress(None, "calibrate", enabled=_progress(args) and args.method == "bayes",
                  postfix=f"NUTS posterior of {len(rig.arms)} arms"):
        doc = calibration_report(rig, args.method)
    _report(doc, format_calibration, args.json)
    return 0


# ------------------------------------------------------------------------------ reproduce


def _reproduce_args(p: argparse.ArgumentParser) -> None:
    _rig_arg(p)
    _output(p.add_argument("--out", default="reproduction",
                           help="directory for accuracy.json and the figures (default: "
                                "./reproduction)"), DIRECTORY)
    _models_args(p, "fit")
    p.add_argument("--calibration", choices=["least-squares", "hill-climb"],
                   default="least-squares", help="calibration method (default least-squares)")
    p.add_argument("--grid-half-width", type=_number(float, 0.0, above=True, finite=True),
                   default=30.0,
                   help="half width of the prediction grid around each target, mm (30)")
    p.add_argument("--grid-n", type=_positive_int, default=100,
                   help="grid cells per side (100)")


@command("reproduce", "run the paper end to end: calibrate, fit IND/CORR/COND, predict, "
                      "write Figures 3-8 and accuracy.json", _reproduce_args)
def _reproduce(args: argparse.Namespace) -> int:
    from bayesrob.paper.reproduction import bound_notes, grid_warnings, run_reproduction
    from bayesrob.predict.grid import Grid
    from bayesrob.report.outputs import write_reproduction
    from bayesrob.report.tables import format_accuracy, grouped_notes

    rig = _load_rig_arg(args.rig, chains=False)
    rep = run_reproduction(rig, args.models, args.models_dir,
                           Grid(args.grid_half_width, args.grid_n), args.calibration,
                           progress=_progress(args))
    written = _staged(args.out, lambda scratch: write_reproduction(rep, scratch))
    print(f"rig {rig.name}: {len(rep.specs)} models, {len(rep.rows)} setups, "
          f"{rep.seconds:.1f} s")
    print(format_accuracy(rep.accuracy))
    for line in grouped_notes(grid_warnings(rep), bound_notes(rep)):
        print(line, file=sys.stderr)
    print(f"wrote {len(written)} files to {args.out}/")
    return 0


# ------------------------------------------------------------------------------ hardware
# collect and sim-device; the work is in bayesrob.hardware.


def _collect_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("rig", metavar="RIG_DIR",
                   help="rig directory with rig.toml (nominal arms and workspace); "
                        "measurements.csv is written there row by row")
    p.add_argument("--servo-port", required=True, metavar="PORT",
                   help="serial port of the servo controller (e.g. /dev/ttyACM0, COM3)")
    p.add_argument("--protocol", choices=["maestro", "ssc32"], required=True,
                   help="Pololu Maestro or Lynxmotion SSC-32/SSC-32U")
    p.add_argument("--channels", nargs="+", required=True, metavar="ARM=CH1,CH2",
                   help="controller channels of each arm's shoulder and elbow servo, "
                        "e.g. top=0,1 bottom=2,3")
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument("--tracker-port", metavar="PORT",
                        help="serial port of a position tracker streaming $PXYT lines")
    source.add_argument("--manual", action="store_true",
                        help="type each end point ('x y' in mm) at the prompt instead")
    _grid_arg(p)
    p.add_argument("--plan", default="train,validation,test",
                   help="sets to collect, run in this order (train,validation,test); add "
                        "holdout for rows at new poses (the grid's cell centres); or a "
                        "poses.csv of 'bayesrob plan', whose rows are measured in its order")
    p.add_argument("--settle", type=_number(float, 0.0), default=1.0, metavar="SECONDS",
                   help="wait after the controller reports a move done, before measuring (1.0)")
    p.add_argument("--resume", action="store_true",
                   help="continue an interrupted run: keep the rows in measurements.csv and "
                        "collect only the missing ones")
    p.add_argument("--yes", action="store_true",
                   help="do not ask before each arm and before linking (the arms must already "
                        "be set up; for scripts and tests)")
    p.add_argument("--speed", type=_number(float, 0.0, above=True), default=500.0,
                   metavar="US_PER_S", help="servo speed limit, us of pulse width per second "
                                            "(500)")
    p.add_argument("--baud", type=_number(int, 1), default=9600,
                   help="servo port baud rate (9600)")
    p.add_argument("--maestro-protocol", choices=["compact", "pololu"], default="compact",
                   help="Maestro command protocol (compact)")
    _device_number_arg(p)
    p.add_argument("--maestro-model", choices=["micro", "mini12", "mini18", "mini24", "mini"],
                   default=None,
                   help="Maestro model, so channel numbers are checked before anything is "
                        "sent: micro (6 channels), mini12, mini18, mini24, or mini (any Mini "
                        "Maestro, up to 24); default: any Maestro")
    p.add_argument("--auto-baud", action="store_true",
                   help="send the Maestro's baud rate indication byte 0xAA first, for the "
                        "serial mode 'UART, detect baud rate' with the compact protocol (the "
                        "Pololu protocol's first command already starts with it)")
    p.add_argument("--timeout", type=_number(float, 0.0, above=True), default=0.5,
                   metavar="SECONDS", help="reply timeout on every read (0.5)")
    p.add_argument("--retries", type=_number(int, 1), default=5,
                   help="tries per query or move before giving up (5)")
    p.add_argument("--tracker-format", choices=["pxyt", "plain"], default="pxyt",
                   help="tracker lines: $PXYT,x,y*HH with checksum (default) or plain x,y")
    p.add_argument("--tracker-baud", type=_number(int, 1), default=115200,
                   help="tracker port baud rate (115200)")
    p.add_argument("--samples", type=_number(int, 1), default=5,
                   help="tracker readings per point; those far from their median are rejected "
                        "and the mean of the rest is recorded (5)")


@command("collect", "run the paper's data collection on a servo rig, appending to "
                    "measurements.csv", _collect_args)
def _collect(args: argparse.Namespace) -> int:
    from bayesrob.hardware.collect import (
        collect_on_ports,
        parse_channels,
        parse_plan,
        terminal_confirm,
    )

    poses = args.plan if args.plan.endswith(".csv") or Path(args.plan).is_file() else None
    result = collect_on_ports(
        args.rig, channels=parse_channels(args.channels), poses=poses,
        plan=parse_plan("train" if poses else args.plan), settle_s=args.settle,
        speed_us_per_s=args.speed, timeout_s=args.timeout,
        confirm=None if args.yes else terminal_confirm,
        progress=_progress(args) and not args.manual,
        **_pick(args, "servo_port", "protocol", "tracker_port", "manual", "grid", "resume",
                "tracker_format", "tracker_baud", "samples", "baud", "maestro_protocol",
                "device_number", "retries", "maestro_model", "auto_baud"))
    for note in result.notes:
        print(note, file=sys.stderr)
    print(f"{result.path}: {result.recorded} rows recorded, {result.skipped} already there, "
          f"{result.recorded + result.skipped} of {result.total} planned")
    if not result.complete:
        print("stopped before the end; continue with --resume", file=sys.stderr)
        return 1
    return 0


def _sim_device_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("rig", metavar="RIG_DIR",
                   help="a simulated rig (truth.toml) from 'bayesrob simulate'")
    p.add_argument("--protocol", choices=["maestro", "ssc32"], required=True,
                   help="answer as a Pololu Maestro (compact and Pololu protocol) or an SSC-32")
    p.add_argument("--effects", type=_effects_list, default=None,
                   help="physical effects, overriding the truth's (comma-separated; '' = none)")
    _seed_arg(p, "noise seed (the truth's seed)", default=None)
    p.add_argument("--channels", nargs="+", metavar="ARM=CH1,CH2",
                   help="channels of each arm (default: arms in order on 0,1 then 2,3 ...)")
    _device_number_arg(p)
    p.add_argument("--linked", choices=["auto", "always", "never"], default="auto",
                   help="auto: arms are linked while a move commands more than one arm (what "
                        "collect does after the link confirmation); always; never")
    p.add_argument("--tracker-format", choices=["pxyt", "plain"], default="pxyt")
    p.add_argument("--tracker-rate", type=_number(float, 0.0, above=True), default=100.0,
                   metavar="HZ", help="tracker lines per second (100)")
    p.add_argument("--tracker-noise-mm", type=_number(float, 0.0), default=0.02,
                   help="jitter of each tracker reading, sd in mm (0.02)")
    for name, what in (("drop-rate", "bytes sent that are lost"),
                       ("garble-rate", "bytes sent that arrive changed"),
                       ("rx-garble-rate", "servo bytes received that are corrupted"),
                       ("bad-checksum-rate", "tracker lines sent with a wrong checksum"),
                       ("outlier-rate", "tracker lines with a wild reading 5-50 mm off")):
        p.add_argument(f"--{name}", type=_number(float, 0.0, 1.0), default=0.0,
                       metavar="P", help=f"fault: fraction of {what} (0)")
    p.add_argument("--reply-delay", type=_number(float, 0.0), default=0.0, metavar="SECONDS",
                   help="fault: delay every servo reply (0)")
    p.add_argument("--disconnect-after", type=_number(int, 1), default=None, metavar="K",
                   help="fault: close the servo port after K commands")
    p.add_argument("--error-after", type=_number(int, 1), default=None, metavar="K",
                   help="fault: flag a serial error after K commands (once); see --on-error")
    p.add_argument("--on-error", choices=["ignore", "off", "home"], default="ignore",
                   help="Maestro: what outputs do on an error: keep their targets (default), "
                        "off (the factory setting: arms go limp) or home (mid-range)")
    p.add_argument("--moving-state-bug", action="store_true",
                   help="Maestro: Get Moving State answers 0 while outputs still move, as on "
                        "a Micro Maestro 6")
    p.add_argument("--channel-range", default=None, metavar="MIN,MAX",
                   help="Maestro: clamp every target to MIN..MAX us like a channel's Min and "
                        "Max; 'factory' for 992,2000 (default: no clamping)")
    p.add_argument("--serial-mode", choices=["usb", "uart-detect"], default="usb",
                   help="Maestro: uart-detect ignores everything before a 0xAA baud rate "
                        "indication byte (default usb)")
    _output(p.add_argument("--byte-log", metavar="FILE",
                           help="append every byte received on the servo port to FILE"), FILE)


@command("sim-device", "serve a simulated rig on pseudo-terminals as a servo controller and "
                       "tracker (prints the ports; runs until killed)", _sim_device_args,
         progress=False)
def _sim_device(args: argparse.Namespace) -> int:
    from bayesrob.hardware.collect import parse_channels
    from bayesrob.hardware.simdevice import Faults, parse_channel_range, run_sim_device

    faults = Faults(args.drop_rate, args.garble_rate, args.rx_garble_rate,
                    args.bad_checksum_rate, args.reply_delay, args.disconnect_after,
                    args.error_after, args.outlier_rate)
    run_sim_device(args.rig, args.protocol, effects=args.effects, seed=args.seed,
                   channels=parse_channels(args.channels) if args.channels else None,
                   channel_range=(parse_channel_range(args.channel_range)
                                  if args.channel_range is not None else None),
                   tracker_rate_hz=args.tracker_rate, faults=faults,
                   **_pick(args, "device_number", "linked", "tracker_format",
                           "tracker_noise_mm", "byte_log", "moving_state_bug", "on_error",
                           "serial_mode"))
    return 0


# ------------------------------------------------------------------------------ diagnose


def _diagnose_args(p: argparse.ArgumentParser) -> None:
    _rig_arg(p)
    _json_arg(p)
    _output(p.add_argument("--report", metavar="DIR", help="write the figures (PNG) into DIR"),
            DIRECTORY)
    p.add_argument("--effects", type=_candidate_effects, default=None, metavar="LIST",
                   help="comma-separated candidate effects to try (default: all registered: "
                        "gravity_sag (or joint_compliance),backlash,servo_nonlinearity for "
                        "planar rigs; "
                        "joint_compliance,lateral_compliance,encoder_error,backlash for URDF/DH "
                        "chains, backlash tried once joint_compliance is named)")
    _seed_arg(p, "seed of folds and permutations (0)")
    p.add_argument("--published", default=None, metavar="STEP=MM,...",
                   help="URDF/DH rigs: a published ladder to draw beside ours in --report's "
                        "ladder.png, e.g. geometric=10.5,joint_compliance=5.64")
    p.add_argument("--sag-steps", type=_at_least_one, default=1, metavar="N",
                   help="URDF/DH rigs: fit the ladder's steps with joints giving way under "
                        "gravity with their torques taken N times, towards equilibrium; a step "
                        "that has not reached it is reported with one step, noted (default 1; "
                        "the effects are chosen with one step either way)")
    p.add_argument("--plan", type=_at_least_one, default=None, metavar="N",
                   help="URDF/DH rigs: after the diagnosis, plan N poses that tell apart the "
                        "effects it could not (a named effect's rivals within noise, and the "
                        "candidates not named), written to --plan-out")
    _output(p.add_argument("--plan-out", default=None, metavar="FILE",
                           help="where --plan writes its poses.csv (default poses.csv)"), FILE)
    p.add_argument("--pool", default=None, metavar="FILE",
                   help="--plan's candidate poses (as 'bayesrob plan --pool'; default 2000 "
                        "drawn inside the joint limits)")


@command("diagnose", "find the physical effects the forward model is missing, add them and "
                     "show the gap shrink", _diagnose_args)
def _diagnose(args: argparse.Namespace) -> int:
    from bayesrob.diagnose.groups import diagnose_groups, parse_published
    from bayesrob.diagnose.refits import diagnose
    from bayesrob.report.outputs import write_diagnosis_report
    from bayesrob.report.tables import format_diagnosis, format_group_diagnosis
    from bayesrob.robot.effects import resolve_effects

    rig = _load_rig_arg(args.rig)
    published = None
    if rig.is_chain:
        published = parse_published(args.published) if args.published else None
        if args.plan is not None and args.pool is not None:
            from bayesrob.plan.pool import command_limits, read_pool

            # the pool's errors before the diagnosis, not after its report is written
            read_pool(args.pool, rig, command_limits(rig))
        diag = diagnose_groups(rig, args.effects, seed=args.seed, progress=_progress(args),
                               sag_steps=args.sag_steps)
    else:
        _refuse([(args.plan is not None or args.pool is not None or args.plan_out is not None,
                  "--plan, --plan-out and --pool plan discriminating poses for URDF/DH rigs; "
                  f"{rig.name!r} is planar"),
                 (args.published, "--published draws a published ladder for URDF/DH rigs; "
                                  f"{rig.name!r} is planar"),
                 (args.sag_steps != 1, f"--sag-steps is for URDF/DH rigs; {rig.name!r} is "
                                       "planar (its gravity_sag takes the torques at the pose "
                                       "it sags into already)")])
        with _as_usage_error():
            effects = None if args.effects is None else resolve_effects(args.effects)
        diag = diagnose(rig, effects, seed=args.seed, progress=_progress(args))
    doc = diag.to_json()

    def figures() -> list[Path]:
        return _staged(args.report, lambda scratch: write_diagnosis_report(diag, scratch,
                                                                           published))

    _report(doc, format_group_diagnosis if rig.is_chain else format_diagnosis, args.json,
            figures if args.report else None)
    if rig.is_chain and args.plan is not None:
        _diagnose_plan(rig, doc, args)
    return 0


def _diagnose_plan(rig, doc: dict, args: argparse.Namespace) -> None:
    """``diagnose --plan N``: poses that tell apart what the diagnosis could not. The named
    effects without a rival within noise join the base model; every other chain effect (the
    named ones with rivals, their rivals, the candidates not named) is to be told apart."""
    from bayesrob.calibrate.least_squares import base_groups
    from bayesrob.plan import plan_poses, write_poses
    from bayesrob.report.tables import format_plan

    settled = [s["effect"] for s in doc["steps"] if not s.get("rivals")]
    base = (*base_groups(rig.robot), *(CHAIN_EFFECTS[e] for e in settled))
    plan = plan_poses(rig, args.plan, criterion="discriminate", groups=base, pool=args.pool,
                      seed=args.seed)
    out = args.plan_out or "poses.csv"
    write_poses(plan, out)
    say = sys.stderr if args.json == "-" else sys.stdout
    print(f"plan: {', '.join(plan.effects)} to tell apart beside "
          f"{', '.join(base)}: {format_plan(plan)}", file=say)
    _wrote(out, args.json)


# ------------------------------------------------------------------------------ sample


def _sample_args(p: argparse.ArgumentParser) -> None:
    _rig_arg(p)
    p.add_argument("--config", default=None,
                   help="one arm or arms joined by '+' (default: the rig's first linked config)")
    p.add_argument("--target", nargs="+", type=_number(), required=True, metavar="X",
                   help="where every arm of the config is aimed: X Y (X Y Z on a 3-D rig), mm")
    p.add_argument("--model", default="cond", help="joint-error model name (default cond)")
    p.add_argument("--sampler", choices=["nuts", "emcee", "grid", "all"], default="all",
                   help="nuts, emcee, grid or all (default); the grid always runs: it is the "
                        "reference of the check (the chains start around the target, never "
                        "from the grid)")
    _seed_arg(p)
    _models_args(p)
    _params_arg(p)
    _json_arg(p)
    p.epilog = ("Exit status: 0 when every sampler that ran agrees with the grid (mean within "
                "0.1 mm, covariance within 10% Frobenius, r_hat <= 1.01, bulk ESS >= 400), "
                "1 when the check fails (the failures are printed and in the JSON), 2 on a "
                "usage or rig error.")


@command("sample", "sample the end point of one arm or linked arms with NUTS and emcee, and "
                   "check both against the grid", _sample_args)
def _sample(args: argparse.Namespace) -> int:
    # the samplers' libraries take a second or two to import: a clock until sample_linked's own
    with _clock(args, "loading") as loading:
        from bayesrob.inference.sampling import sample_linked
        from bayesrob.report.tables import format_sample

        rig = _load_rig_arg(args.rig)
        loading.close(done=False)
    dim = rig.robot.dim
    if len(args.target) != dim:
        raise UsageError(f"--target needs {dim} numbers on this {dim}-D rig "
                         f"({' '.join('XYZ'[:dim])}), got {len(args.target)}")
    config = args.config
    if config is None:
        if not rig.linked_configs:
            raise UsageError("the rig has no linked config; name one with --config")
        config = rig.linked_configs[0]
    with _as_usage_error():
        report = sample_linked(rig, config, args.target, args.model, args.sampler,
                               seed=args.seed, progress=_progress(args),
                               models_dir=args.models_dir, groups=args.params)
    _report(report.document, lambda _: format_sample(report), args.json)
    return 0 if report.passed else 1


# ------------------------------------------------------------------------------ predict


def _predict_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("rig", help="rig directory: the modules' single-arm rows are enough")
    p.add_argument("--config", required=True,
                   help="one arm, or arms linked at their end point joined by '+' (A+B+C)")
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument("--targets", metavar="FILE",
                       help="CSV of targets with columns x,y (x,y,z for a 3-D rig; mm)")
    where.add_argument("--grid", type=_positive_int, metavar="N",
                       help="an N x N grid of targets over the rig's workspace (N x N x N "
                            "over a 3-D workspace)")
    p.add_argument("--fusion", choices=FUSIONS, default=DEFAULT_FUSION,
                   help="how linked arms share the end point: equilibrium (their stiffnesses "
                        "balance; default) or product (the paper's product of likelihoods)")
    p.add_argument("--model", default=None,
                   help="joint-error model name (default cond; ind or corr where the joint "
                        "errors are latent, on arms with more joints than measured "
                        "coordinates and with --params: default ind)")
    _models_args(p)
    _params_arg(p, "parameter groups the modules are calibrated with, as 'bayesrob calibrate "
                   "--params' (URDF/DH default frames,offsets,geometric,servo; add compliance "
                   "for arms that sag under gravity, backlash for play). Given for a planar "
                   "rig, its arms are aimed and predicted as 2-joint chains with those groups "
                   "(joint-error model ind or corr) instead of the eight-parameter fit")
    p.add_argument("--masses", choices=MASS_SOURCES, default=MASS_SOURCES[0],
                   help="URDF rigs calibrated with compliance: the links' masses fitted "
                        "(default; only their products with the compliances are seen, and the "
                        "arms' stiffnesses come from a prior), or held at the URDF's <inertial> "
                        "ones, so the fitted compliances give each arm's stiffnesses")
    _seed_arg(p, "random seed of the draws (0)")
    _json_arg(p)
    _plot_arg(p, "write the expected-error map and the least accurate target's regions (PNG)")


@command("predict", "predict the accuracy of an assembly (one arm or linked arms) at targets "
                    "before it is built, from its modules' single-arm rows", _predict_args)
def _predict(args: argparse.Namespace) -> int:
    from bayesrob.predict.assembly import grid_targets, predict_assembly, read_targets
    from bayesrob.report.plots.prediction import assembly_figure
    from bayesrob.report.tables import format_prediction

    rig = _load_rig_arg(args.rig)
    targets = (read_targets(args.targets, rig.robot.dim) if args.targets
               else grid_targets(rig, args.grid))
    # calibration, fits and draws in one call
    with _clock(args, f"{args.config}, {len(targets)} targets"), _as_usage_error():
        pred = predict_assembly(rig, args.config, targets, args.model, args.fusion,
                                args.models_dir, args.seed, groups=args.params,
                                masses=args.masses)
    _report(pred.document, lambda _: format_prediction(pred), args.json)
    if args.plot:
        save_figure(assembly_figure(pred, rig), args.plot, dpi=120)
        if args.json != "-":
            print(f"wrote {args.plot}")
    return 0


# ------------------------------------------------------------------------------ compare


def _compare_args(p: argparse.ArgumentParser) -> None:
    _rig_arg(p)
    _models_args(p, "compare")
    _params_arg(p)
    _json_arg(p)
    _plot_arg(p, "write the comparison plot (PNG) here (default: next to --json OUT, as OUT "
                 "with .png)")


@command("compare", "score every joint-error model on held-out end points and by "
                    "leave-one-out, with arviz's comparison table", _compare_args)
def _compare(args: argparse.Namespace) -> int:
    from bayesrob.compare.comparison import compare_models
    from bayesrob.report.plots.comparison import comparison_figure
    from bayesrob.report.tables import format_comparison

    rig = _load_rig_arg(args.rig)
    comp = compare_models(rig, args.models, args.models_dir, progress=_progress(args),
                          groups=args.params)
    doc = comp.document()
    plot = args.plot
    if plot is None and args.json not in (None, "-"):
        plot = str(Path(args.json).with_suffix(".png"))
    if plot is not None:
        save_figure(comparison_figure(comp), plot, dpi=120)
        doc["plot"] = plot
    _report(doc, format_comparison, args.json, plot and (lambda: [plot]))
    return 0


# ------------------------------------------------------------------------------ design


def _design_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("design", help="design file (TOML): modules, mount points, task region, "
                                  "requirement, limits (see examples/design/design.toml)")
    _output(p.add_argument("--out", metavar="DIR", default="design-out",
                           help="where design.json, design.png and the best candidate's rig "
                                "directory (best/) go (default design-out)"), DIRECTORY)
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="a running Dask scheduler (tcp://host:8786); default: a LocalCluster on "
                        "this machine")
    p.add_argument("--workers", type=_positive_int, default=2,
                   help="LocalCluster worker processes (2)")
    p.add_argument("--top", type=_positive_int, default=10,
                   help="candidates shown in the table (10) and, up to 4, in the figure")


@command("design", "find the fewest calibrated modules, mounted and linked, that meet an "
                   "accuracy over a task region (Dask)", _design_args)
def _design(args: argparse.Namespace) -> int:
    from bayesrob.design.file import load_design

    design = load_design(args.design)  # the whole file, before the numerical stack loads
    # the first line before the numerical stack loads and the modules are calibrated (tens of
    # seconds); the search's own count follows
    with _clock(args, "calibrating the modules"):
        from bayesrob.design.modules import load_modules
        from bayesrob.design.search import run_design
        from bayesrob.report.outputs import write_design
        from bayesrob.report.tables import format_design

        modules = load_modules(design)
    result = run_design(design, modules, scheduler=args.scheduler, workers=args.workers,
                        progress=_progress(args))
    print(format_design(result, args.top))
    written = _staged(args.out, lambda scratch: write_design(result, modules, args.top, scratch))
    print(f"wrote {', '.join(str(w) for w in written)}")
    # exit 1: the search ran and nothing met the requirement (the closest is shown above)
    return 0 if result.met else 1


# ------------------------------------------------------------------------------ plan


def _plan_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("rig", help="rig directory (its measurements.csv may be missing or empty)")
    p.add_argument("--n", type=_at_least_one, required=True, help="poses to plan")
    _output(p.add_argument("--out", required=True, metavar="FILE",
                           help="poses.csv to write: config, set, the command columns as the "
                                "pool wrote them, the pool's other columns, gain"), FILE)
    p.add_argument("--for", dest="criterion", choices=["accuracy", "identify", "discriminate"],
                   default="accuracy",
                   help="accuracy: the smallest predicted end-point error over the task region "
                        "(default); identify: D-optimal in the parameters; discriminate: "
                        "poses that tell the candidate effects apart")
    _params_arg(p, "the groups the calibration will fit, as 'bayesrob calibrate --params' "
                   "(default frames,offsets,geometric,servo); for discriminate, the base model "
                   "whose rivals are told apart (default frames,geometric)")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--pool", metavar="FILE",
                     help="candidate poses: a CSV with the rig's command columns (and config)")
    src.add_argument("--samples", type=_at_least_one, metavar="M",
                     help="candidates drawn inside the joint limits (default 2000)")
    p.add_argument("--task", metavar="FILE",
                   help="the task region (accuracy): poses (command columns) or targets (x, y"
                        "[, z]); default the pool")
    _seed_arg(p, "random seed of the samples (0)")
    p.add_argument("--noise-mm", type=_non_negative_float, default=0.1,
                   help="measurement noise sd (mm) the predicted error is taken with (0.1)")
    p.add_argument("--omitted-sd", type=_non_negative_float, default=None, metavar="SD",
                   help="accuracy: prior sd, in typical sizes, of the sag groups (compliance, "
                        "lateral) --params leaves out, whose bias the predicted error adds "
                        "(default 0: the calibration's variance only)")
    p.add_argument("--prior-sd", type=_non_negative_float, default=None, metavar="SD",
                   help="prior sd of the fitted parameters about nominal, in their typical "
                        "sizes (default 100: the rows alone fix them)")
    _json_arg(p, "write the plan's summary as JSON")


@command("plan", "choose the poses to measure: most accuracy over a task region, most "
                 "information, or most separation of the candidate effects", _plan_args,
         progress=False)
def _plan(args: argparse.Namespace) -> int:
    from bayesrob.plan import load_plan_rig, plan_poses, write_poses
    from bayesrob.report.tables import format_plan

    if args.noise_mm <= 0:
        raise UsageError(f"--noise-mm must be positive, not {args.noise_mm:g}")
    rig = load_plan_rig(args.rig)
    plan = plan_poses(rig, args.n, criterion=args.criterion, groups=args.params,
                      pool=args.pool, samples=args.samples, task=args.task, seed=args.seed,
                      noise_mm=args.noise_mm, **{k: v for k in ("omitted_sd", "prior_sd")
                                                 if (v := getattr(args, k)) is not None})
    print(format_plan(plan))
    write_poses(plan, args.out)
    print(f"wrote {args.out}")
    _write_json(plan.to_dict(), args.json)
    return 0


# ------------------------------------------------------------------------------ validate


def _validate_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("names", nargs="*", metavar="NAME",
                   help="studies to run (default: every study; --list names them)")
    _output(p.add_argument("--out", metavar="DIR", default="validation-run",
                           help="where validation.json and validation.md go (default "
                                "validation-run)"), DIRECTORY)
    p.add_argument("--quick", action="store_true",
                   help="each study on its one or two quick seeds: checks that every study "
                        "runs and gives finite figures (targets need the report seeds)")
    p.add_argument("--list", action="store_true", help="list the studies and their seeds")
    p.add_argument("--workers", type=_at_least_one, default=2,
                   help="studies run side by side, each in a LocalCluster worker process "
                        "(2; 1 runs them in this process, in order)")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="a running Dask scheduler (tcp://host:8786) to run the studies on")


@command("validate", "run the validation studies (report seeds, targets fixed before they "
                     "ran) and write validation.json and validation.md", _validate_args,
         progress=False)
def _validate(args: argparse.Namespace) -> int:
    from bayesrob.validation.study import discover_studies
    from bayesrob.validation.suite import run_suite, write_report

    studies = discover_studies(args.names or None)
    if args.list:
        for s in studies:
            print(f"{s.name:28s} report seeds {list(s.report_seeds)}, quick "
                  f"{list(s.quick_seeds)}: {s.title}")
        return 0
    out = Path(args.out)
    workers = min(args.workers, len(studies))
    if args.scheduler or workers > 1:
        from bayesrob.cluster import dask_client

        cluster = dask_client(args.scheduler, workers)
    else:
        cluster = contextlib.nullcontext(None)  # in this process, in order
    with cluster as client:
        report = run_suite(studies, quick=args.quick, client=client,
                           after_each=lambda so_far: write_report(so_far, out))
    json_path, md_path = write_report(report, out)
    passed = sum(s["status"] == "pass" for s in report["studies"].values())
    print(f"validation {report['status']}: {passed}/{len(studies)} studies passed in "
          f"{report['seconds']:.0f} s; wrote {json_path}, {md_path}")
    # exit 1: a study failed or missed a target it had met (validation.md says which)
    return 0 if report["status"] == "pass" else 1


# ------------------------------------------------------------------------------ main
# Further commands register themselves above this line with @command.


class _CommandListFormatter(argparse.HelpFormatter):
    """Every command's summary on one line after its name.

    argparse measures sub-command names without their extra indent, so names longer than
    eight letters would wrap onto a line of their own; the width keeps summaries unbroken.
    """

    def __init__(self, prog: str) -> None:
        super().__init__(prog, max_help_position=30, width=160)

    def add_argument(self, action: argparse.Action) -> None:
        super().add_argument(action)
        if isinstance(action, argparse._SubParsersAction):
            self._action_max_length += 2 * self._indent_increment


class _Parser(argparse.ArgumentParser):
    """Argument errors in one line, as every other error of the command line (the usage is
    what --help is for)."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="bayesrob",
        formatter_class=_CommandListFormatter,
        description="Predict how accurately modular robot arms place their end point, alone "
                    "and linked.")
    from bayesrob import __version__

    parser.add_argument("--version", action="version", version=f"bayesrob {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, c in COMMANDS.items():
        p = sub.add_parser(name, help=c.help, description=c.help)
        c.add_arguments(p)
        if c.progress:
            p.add_argument("--no-progress", action="store_true",
                           help="print no progress on stderr (default: a bar on a terminal, "
                                "a line every 5 s otherwise)")
    return parser


def _read_files(actions: list[argparse.Action], args: argparse.Namespace) -> dict[Path, str]:
    """The files the command reads, each with what names it: the rig's own (its measurements,
    rig.toml, truth.toml and the URDFs rig.toml names) and every existing file an input
    option gives."""
    found: dict[Path, str] = {}
    rig = getattr(args, "rig", None)
    if isinstance(rig, str) and Path(rig).is_dir():
        import tomllib

        from bayesrob.data.rig import MEASUREMENTS_FILE, RIG_FILE
        from bayesrob.sim.truth import TRUTH_FILE

        d = Path(rig)
        for name in (MEASUREMENTS_FILE, RIG_FILE, TRUTH_FILE):
            found[(d / name).resolve()] = f"the rig's {name}"
        try:
            arms = tomllib.loads((d / RIG_FILE).read_text()).get("arms", {})
        except (OSError, ValueError):
            arms = {}  # the command's own loading says what is wrong with it
        for table in arms.values() if isinstance(arms, dict) else ():
            if isinstance(table, dict) and isinstance(table.get("urdf"), str):
                found[(d / table["urdf"]).resolve()] = f"the rig's {table['urdf']}"
    for action in actions:
        value = getattr(args, action.dest, None)
        if hasattr(action, "output_kind") or not action.option_strings:
            continue
        for v in value if isinstance(value, list) else [value]:
            if isinstance(v, str) and v != "-" and Path(v).is_file():
                found[Path(v).resolve()] = f"{action.option_strings[0]}'s input"
    return found


def _check_outputs(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Every output path of the command, checked before any work (see :func:`_output`): one
    it can write, none of the files it reads, no two the same."""
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    actions = sub.choices[args.command]._actions
    read = _read_files(actions, args)
    written: dict[Path, str] = {}
    for action in actions:
        value = getattr(args, action.dest, None)
        if hasattr(action, "output_kind") and value not in (None, "-"):
            option = action.option_strings[0] if action.option_strings else action.dest.upper()
            check_output(value, action.output_kind, option)
            if action.output_kind != FILE:
                continue
            if option == "--plot":
                from matplotlib.backend_bases import FigureCanvasBase

                kinds = FigureCanvasBase.get_supported_filetypes()
                if Path(value).suffix.lower().lstrip(".") not in kinds:
                    raise OutputPathError(f"--plot {value}: a figure's name ends in its format, "
                                          f"one of {', '.join(sorted(kinds))}")
            path = Path(value).resolve()
            if path in read:
                raise OutputPathError(f"{option} {value}: is {read[path]}, which this command "
                                      "reads; give another path")
            if path in written:
                raise OutputPathError(f"{option} {value}: {written[path]} writes there too; "
                                      "give each output its own path")
            written[path] = option


def _user_errors() -> tuple[type[Exception], ...]:
    """UsageError, OutputPathError and those of :data:`USER_ERRORS` already imported."""
    found = []
    for dotted in USER_ERRORS:
        module, name = dotted.rsplit(".", 1)
        if module in sys.modules:
            found.append(getattr(sys.modules[module], name))
    return (UsageError, OutputPathError, *found)


class _CtrlC:
    """Whether a Ctrl-C came and whether ``main`` has caught it: plain attributes, so that
    setting them is the first thing a handler does and no call (where a pending signal runs
    its handler) comes before it."""

    requested = False
    caught = False


def _deliver_ctrl_c_surely() -> _CtrlC:
    """Ctrl-C as a KeyboardInterrupt that cannot be lost: one raised inside a garbage
    collector's callback (JAX has one) is printed and dropped by Python, and the command then
    ran on to its end. So each Ctrl-C is raised again after half a second until ``main`` has
    caught one; from then on the handler raises nothing, since one raised again could land
    inside main's own handler and escape it (exit -2 where 130 is the contract, seen in CI
    on a loaded machine)."""
    state = _CtrlC()

    def again() -> None:
        if not state.caught:
            os.kill(os.getpid(), signal.SIGINT)

    def on_sigint(signum, frame):
        if state.caught:
            return
        state.requested = True
        timer = threading.Timer(0.5, again)
        timer.daemon = True
        timer.start()
        raise KeyboardInterrupt

    def unraisable(info) -> None:
        # the dropped one prints a traceback as it goes: silent, since it is raised again
        if not isinstance(info.exc_value, KeyboardInterrupt):
            default_hook(info)

    default_hook = sys.unraisablehook
    sys.unraisablehook = unraisable
    signal.signal(signal.SIGINT, on_sigint)
    return state


def main(argv: list[str] | None = None) -> int:
    # The commands draw figures into files only: matplotlib's file backend, unless the user
    # chose one (a library caller's backend is left alone: only the command sets this).
    os.environ.setdefault("MPLBACKEND", "Agg")
    parser = build_parser()
    args = parser.parse_args(argv)
    ctrl_c = (_deliver_ctrl_c_surely() if argv is None and signal.getsignal(signal.SIGINT)
              is signal.default_int_handler else _CtrlC())
    try:
        _check_outputs(parser, args)
        return COMMANDS[args.command].run(args)
    except BrokenPipeError:
        # The reader (e.g. `| head`) went away; point stdout at devnull so the interpreter's
        # final flush does not raise again.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    except Exception as exc:
        if ctrl_c.requested:
            # Python turns a KeyboardInterrupt raised in some places into another error
            # (in a descriptor's __set_name__ while a class is built, as an import runs, it
            # becomes a RuntimeError): after a Ctrl-C any error is the interruption.
            ctrl_c.caught = True
            return _interrupted(args.command, argv)
        if not isinstance(exc, _user_errors()):
            raise
        print(f"bayesrob {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        ctrl_c.caught = True
        return _interrupted(args.command, argv)


def _interrupted(command: str, argv: list[str] | None) -> int:
    print(f"bayesrob {command}: interrupted", file=sys.stderr)
    if argv is None:
        # Run as a program: leave at once. The finally blocks on the way here have removed
        # any partial output; tearing the interpreter down under JAX's compiler threads
        # could still crash it (seen once in four interrupts of a compiling simulate).
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(130)
    return 130


if __name__ == "__main__":
    sys.exit(main())
