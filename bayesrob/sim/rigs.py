"""Writing simulated rig directories (rig.toml, measurements.csv, truth.toml) from a truth
(:mod:`bayesrob.sim.truth`), and measuring a rig's planned rows in simulation. Linked rows are
aimed through the arms' models calibrated on their train rows; holdout rows draw their noise
from a stream of their own.
"""

from __future__ import annotations

import csv
import io
import os
import shutil
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, replace
from functools import partial
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np
from threadpoolctl import threadpool_limits

from bayesrob import robot as kin
from bayesrob.data.rig import (
    MEASUREMENTS_FILE,
    RIG_FILE,
    ArmSpec,
    RigError,
    dump_toml,
    format_row,
    is_planned,
    load_rig,
    measurement_header,
    rig_toml_dict,
)
from bayesrob.progress import progress as progress_bar
from bayesrob.robot import Robot, urdf_chain
from bayesrob.sim import physics
from bayesrob.sim.equilibrium import ChainPlant, PhysicalRig, linked_equilibrium
from bayesrob.sim.truth import (
    ARM6_URDF,
    GRAVITY,
    POSE_HI,
    POSE_LO,
    TRUTH_FILE,
    Arm6Truth,
    LinkedArm6Truth,
    Truth,
    _ArmErrors,
    arm6_urdf_path,
    drawn_masses,
    drawn_stiffness,
)

HOLDOUT_STREAM = 1  # spawn key of the holdout rows' noise (see holdout_seed)


def grid_points(workspace, n: int) -> np.ndarray:
    """An n x n grid over the workspace, row by row from the top left."""
    xs = np.linspace(*workspace[0], n)
    ys = np.linspace(*workspace[1], n)[::-1]
    return np.array([(x, y) for y in ys for x in xs])


def holdout_points(workspace, n: int) -> np.ndarray:
    """The centres of the n x n grid's cells, row by row from the top left: as far from the
    training poses as the grid allows, so errors there measure accuracy at new poses."""
    if n < 2:
        return np.zeros((0, 2))
    g = grid_points(workspace, n)
    half = np.array([(workspace[0][1] - workspace[0][0]) / (n - 1),
                     -(workspace[1][1] - workspace[1][0]) / (n - 1)]) / 2
    corners = g.reshape(n, n, 2)[:-1, :-1].reshape(-1, 2)  # drop the last row and column
    return corners + half


def nominal_specs(truth: Truth, rng: np.random.Generator) -> dict[str, ArmSpec]:
    """Nominal values as a person would measure them: the truth plus measuring error."""
    err = truth.nominal_error
    specs = {}
    for name, a in truth.arms.items():
        def r(x, sd, rel=False):
            x = np.asarray(x, float)
            return tuple(float(round(v, 5)) for v in
                         (x * (1 + rng.normal(0, sd, x.shape)) if rel else
                          x + rng.normal(0, sd, x.shape)))
        specs[name] = ArmSpec(
            name, r(a.base, err["base_mm"]), r(a.links, err["links_mm"]),
            r(a.gain, err["gain_rel"], rel=True), r(a.offset, err["offset_rad"]),
            a.elbow, a.pulse_limits)
    return specs


def round_pulse(u: np.ndarray) -> np.ndarray:
    """Controllers resolve a quarter microsecond (the Maestro's unit)."""
    return np.round(np.asarray(u, float) * 4) / 4


def simulate_rig(out_dir: str | Path, truth: Truth, progress: bool = False,
                 holdout: bool = True) -> Path:
    """Write a rig directory (rig.toml, measurements.csv, truth.toml) from the truth: train
    rows aimed at the grid through the *nominal* models (as a person aims), validation repeats,
    linked ``test`` rows through the calibrated models, then ``holdout`` rows from a noise
    stream of their own (the rows before are byte for byte those of ``holdout=False``)."""
    from bayesrob.calibrate.arms import calibrate_arm  # calibration needs rig types only

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(truth.seed)
    specs = nominal_specs(truth, rng)
    plant = PhysicalRig(truth, seed=int(rng.integers(2**31)))
    names = list(truth.arms)
    grid = grid_points(truth.workspace, truth.grid)
    rows = []
    hold = holdout_points(truth.workspace, truth.grid) if holdout else np.zeros((0, 2))
    steps = (2 * len(names) + 1) * len(grid) + (len(names) + (len(names) > 1)) * len(hold)
    bar = progress_bar(steps, "simulate", "pt", enabled=progress)
    train: dict[str, tuple[np.ndarray, np.ndarray]] = {}

    def aim(arms: dict[str, kin.Arm], name: str, points: np.ndarray) -> np.ndarray:
        u = round_pulse(np.asarray(arms[name].command(jnp.asarray(points))))
        _check_limits(name, np.atleast_2d(u), truth.arms[name].pulse_limits)
        return u

    nominals = {name: kin.Arm.nominal(specs[name]) for name in names}
    for name in names:
        u_all = aim(nominals, name, grid)
        for set_name in ("train", "validation"):
            obs = []
            for u in u_all:
                d = plant.end_point({name: u})
                obs.append(d)
                rows.append(format_row(names, name, set_name, None, {name: u}, d))
                bar.update()
            if set_name == "train":
                train[name] = (u_all, np.asarray(obs))
    calibrated = {name: calibrate_arm(specs[name], *train[name]).arm for name in names}
    linked = "+".join(names)

    for target in grid:
        cmds = {name: aim(calibrated, name, target) for name in names}
        d = plant.end_point(cmds)
        rows.append(format_row(names, linked, "test", target, cmds, d))
        bar.update()
    plant.rng = np.random.default_rng(holdout_seed(truth.seed))
    for name in names if len(hold) else ():
        for u in aim(nominals, name, hold):
            rows.append(format_row(names, name, "holdout", None, {name: u},
                                   plant.end_point({name: u})))
            bar.update()
    if len(names) > 1:  # a single arm's test rows are its only ones: nothing is linked
        for target in hold:
            cmds = {name: aim(calibrated, name, target) for name in names}
            rows.append(format_row(names, linked, "holdout", target, cmds,
                                   plant.end_point(cmds)))
            bar.update()
    bar.close()

    (out / RIG_FILE).write_text(dump_toml(rig_toml_dict(
        truth.name, specs, truth.gravity, truth.workspace)))
    with (out / MEASUREMENTS_FILE).open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(measurement_header(names))
        w.writerows(rows)
    (out / TRUTH_FILE).write_text(truth.to_toml())
    return out


def holdout_seed(seed: int) -> np.random.SeedSequence:
    """The holdout rows' noise stream: derived from the rig's seed, apart from the main one."""
    return np.random.SeedSequence([seed, HOLDOUT_STREAM])


def _check_limits(name: str, u: np.ndarray, limits) -> None:
    lim = np.asarray(limits)
    bad = ~np.all((u >= lim[:, 0]) & (u <= lim[:, 1]), axis=-1)
    if bad.any():
        raise ValueError(f"simulated arm {name!r}: a grid point needs pulses "
                         f"{u[bad][0].tolist()} outside its limits {limits}")


def measure_planned(directory: str | Path, seed: int = 0, progress: bool = False
                    ) -> tuple[int, int]:
    """Measure a rig's planned rows (commands given, x and y empty) with its ``truth.toml``'s
    physics, replacing the file in one step at the end. Returns (rows measured, rows in the
    file)."""
    directory = Path(directory)
    truth_path = directory / TRUTH_FILE
    if not truth_path.is_file():
        raise RigError(f"{truth_path}: file not found (only a rig with the simulator's truth "
                       "can be measured in simulation; use bayesrob collect on hardware)")
    truth = Truth.from_toml(truth_path)
    path = directory / MEASUREMENTS_FILE
    if not path.is_file():
        raise RigError(f"{path}: file not found")
    with path.open(newline="", encoding="utf-8") as fh:
        rows = list(csv.reader(fh))
    if not rows:
        raise RigError(f"{path}: empty file (a header row is required)")
    header, body = rows[0], rows[1:]
    idx = {h: i for i, h in enumerate(header)}
    for col in ("config", "x", "y"):
        if col not in idx:
            raise RigError(f"{path}: missing column '{col}'")
    plant = PhysicalRig(truth, seed=seed)
    planned = [r for r, row in enumerate(body) if len(row) == len(header)
               and is_planned(row, idx)]
    bar = progress_bar(len(planned), "measure", "pt", enabled=progress)
    for r in planned:
        row, where = body[r], f"{path}: line {r + 2}"
        members = row[idx["config"]].split("+")
        cmds = {}
        for a in members:
            if a not in truth.arms:
                raise RigError(f"{where}: arm {a!r} is not in {truth_path}")
            try:
                cmds[a] = [float(row[idx[f"{a}_u{j}"]]) for j in (1, 2)]
            except (KeyError, ValueError):
                raise RigError(f"{where}: arm {a!r} needs numbers in {a}_u1 and {a}_u2") \
                    from None
        d = plant.end_point(cmds)
        row[idx["x"]], row[idx["y"]] = (f"{v:.6g}" for v in d)
        bar.update()
    bar.close()
    _replace_csv(path, [header, *body], csv.writer)
    return len(planned), len(body)


def _replace_csv(path: Path, rows: list, writer: Callable) -> None:
    # in one step, so an interrupted run leaves the file as it was
    buf = io.StringIO()
    writer(buf).writerows(rows)
    tmp = path.with_suffix(".csv.tmp")
    tmp.write_text(buf.getvalue())
    os.replace(tmp, path)


def random_poses(rng: np.random.Generator, n: int) -> np.ndarray:
    return rng.uniform(POSE_LO, POSE_HI, size=(n, 6))


def true_parameters(robot: Robot, truth: _ArmErrors, rng: np.random.Generator) -> np.ndarray:
    """A built arm6's parameter vector: the nominal one with every joint origin, offset, the
    marker and the instrument pose perturbed by ``truth``'s spreads."""
    layout = robot.layout
    x = layout.nominal.copy()
    for i, p in enumerate(layout.params):
        axis = p.name.rsplit(".", 1)[-1]
        rot = axis in ("rx", "ry", "rz")
        if ".origin." in p.name:
            x[i] += rng.normal(0, truth.origin_sd_rad if rot else truth.origin_sd_mm)
        elif p.name.endswith(".offset"):
            x[i] += rng.normal(0, truth.offset_sd_rad)
        elif ".marker." in p.name:
            x[i] += rng.normal(0, truth.marker_sd_mm)
        elif ".instrument." in p.name:
            x[i] += rng.normal(0, truth.instrument_sd[1] if rot else truth.instrument_sd[0])
    return x



def arm6_plant(truth: Arm6Truth, rng: np.random.Generator) -> ChainPlant:
    """A simulated arm6 as it really is: its true parameters as ``truth.true_params`` has
    them, or, before that, drawn from ``rng``."""
    nominal = urdf_chain(arm6_urdf_path(), "base_link", "tool0", "arm",
                         marker=truth.marker_nominal_mm, instrument=truth.instrument_nominal)
    robot = Robot({"arm": nominal}, 3)
    x_true = (np.array([truth.true_params[n] for n in robot.layout.names])
              if truth.true_params else true_parameters(robot, truth, rng))
    # The instrument sees gravity along -z of the robot base; frames for torques are taken
    # with the base at the identity so that direction holds.
    base_robot = Robot({"arm": urdf_chain(arm6_urdf_path(), "base_link", "tool0", "arm")}, 3)
    x_base = np.array(x_true, float)
    x_base[base_robot.layout.slices[("arm", "instrument")]] = 0.0
    phase = np.random.default_rng([truth.seed, physics.ENCODER_STREAM]).uniform(
        -np.pi, np.pi, 6)
    return ChainPlant(
        robot, np.asarray(x_true, float), truth.joint_noise_rad, truth.measurement_noise_mm,
        base_robot, x_base, {"arm": np.asarray(truth.masses_kg, float)},
        {"arm": np.asarray(truth.stiffness_nmm_per_rad, float)} if truth.compliance else None,
        encoder_eccentricity=truth.encoder_eccentricity, encoder_phase=phase,
        play_rad=truth.joint_play_rad, stick_nmm=truth.play_stick_nmm)


def linked_plant(robot: Robot, x_true: np.ndarray, truth: Mapping[str, Any]) -> ChainPlant:
    """The arms of a linked arm6 rig as they really are, each measured alone: ``truth`` as its
    truth.toml table has it (the drawn masses and stiffnesses recorded). Gravity is the
    instrument's -z."""
    compliant = bool(truth["compliance"])
    return ChainPlant(
        robot, np.asarray(x_true, float), truth["joint_noise_rad"],
        truth["measurement_noise_mm"], robot, np.asarray(x_true, float),
        {a: np.asarray(truth["drawn_masses_kg"][a], float) for a in truth["arms"]}
        if compliant else {},
        {a: np.asarray(truth["stiffness_nmm_per_rad"][a], float) for a in truth["arms"]}
        if compliant else None)


def simulate_arm6_rig(out_dir: str | Path, truth: Arm6Truth) -> Path:
    """Write rig.toml, arm6.urdf (nominal), measurements.csv and truth.toml into out_dir."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(truth.seed)
    plant = arm6_plant(truth, rng)
    if truth.encoder_eccentricity:
        truth.encoder_phase_rad = tuple(float(v) for v in plant.encoder_phase)
    approach = np.random.default_rng([truth.seed, physics.PLAY_STREAM])
    rows = []
    for set_name, n in (("train", truth.n_train), ("validation", truth.n_validation),
                        ("holdout", truth.n_holdout)):
        if n == 0:
            continue
        q_cmd = random_poses(rng, n)
        p = plant.measure("arm", q_cmd, rng, approach)
        rows += [(set_name, qc, pc) for qc, pc in zip(q_cmd, p, strict=True)]
    write_arm6_rig(out, f"arm6-seed{truth.seed}", rows, truth)
    truth.true_params = {name: float(v) for name, v in zip(plant.robot.layout.names,
                                                            plant.x_true, strict=True)}
    (out / TRUTH_FILE).write_text(dump_toml({"chain_truth": asdict(truth)}))
    return out


POSES_STREAM = 9  # the noise of rows measured at given poses: apart from the rig's own


def approach_sides(q_cmd: np.ndarray, previous: np.ndarray | None) -> np.ndarray:
    """Each joint's approach side (N, n): the sign of its move from the command before (the
    row before, or ``previous`` for the first; 0 where that is unknown or it did not move)."""
    before = np.vstack([np.full((1, q_cmd.shape[1]), np.nan) if previous is None
                        else np.asarray(previous, float)[None], q_cmd[:-1]])
    return np.nan_to_num(np.sign(q_cmd - before))


def measure_arm6_poses(rig_dir: str | Path, sets: Sequence[str], q_cmd: np.ndarray,
                       seed: int = 0,
                       plant: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
                       configs: Sequence[str] | None = None) -> int:
    """Measure the joint commands ``q_cmd`` (N, 6), in order, on the simulated arm6 rig in
    ``rig_dir`` and append them to its measurements.csv with their ``sets`` and approach
    sides (``<arm>_d1..6``: each arm's move from its own previous command in the file). On a
    linked rig ``configs`` names each row's arm (the linked simulator has no play, so the sides
    are recorded, not acted on). ``plant(q_cmd, approach) -> points (N, 3)`` measures a single
    arm instead, for an arm made by other physics (a validation study's). Returns the rows
    appended."""
    out = Path(rig_dir)
    configs = list(configs) if configs is not None else ["arm"] * len(q_cmd)
    measure = ((lambda arm, q, approach: plant(q, approach)) if plant is not None
               else _truth_plant(out, seed))
    path = out / "measurements.csv"
    with path.open(newline="") as fh:
        rows = list(csv.reader(fh))
    header, body = rows[0], rows[1:]
    arms = list(dict.fromkeys(configs))
    for arm in arms:
        if f"{arm}_d1" not in header:
            header = [*header, *(f"{arm}_d{k + 1}" for k in range(6))]
            body = [r + [""] * 6 for r in body]
    idx = {h: i for i, h in enumerate(header)}
    q_cmd = np.asarray(q_cmd, float)
    approach, points = np.zeros_like(q_cmd), np.zeros((len(q_cmd), 3))
    for arm in arms:
        mine = np.flatnonzero(np.array(configs) == arm)
        cols = [idx[f"{arm}_u{k + 1}"] for k in range(6)]
        # the arm's last command in the file, a linked row's included: it moved there too
        last = next((r for r in reversed(body) if r[cols[0]].strip()), None)
        previous = None if last is None else np.array([float(last[c]) for c in cols])
        approach[mine] = approach_sides(q_cmd[mine], previous)
        points[mine] = measure(arm, q_cmd[mine], approach[mine])
    for arm, s, qc, d, pc in zip(configs, sets, q_cmd, approach, points, strict=True):
        row = [""] * len(header)
        row[idx["config"]], row[idx["set"]] = arm, s
        for k in range(6):
            row[idx[f"{arm}_u{k + 1}"]] = f"{qc[k]:.10g}"
            row[idx[f"{arm}_d{k + 1}"]] = f"{d[k]:g}"
        for a, v in zip("xyz", pc, strict=True):
            row[idx[a]] = f"{v:.4f}"
        body.append(row)
    _replace_csv(path, [header, *body], partial(csv.writer, lineterminator="\n"))
    return len(q_cmd)


def _truth_plant(rig_dir: Path, seed: int) -> Callable[[str, np.ndarray, np.ndarray], np.ndarray]:
    """``(arm, q_cmd, approach) -> points`` of the arm6 rig its truth.toml describes (one arm
    or linked), with the noise of rows measured at given poses: a stream of their own."""
    import tomllib

    tables = tomllib.loads((rig_dir / TRUTH_FILE).read_text())
    if "linked_chain_truth" not in tables:
        table = dict(tables["chain_truth"])
        names = [f.name for f in Arm6Truth.__dataclass_fields__.values()]
        truth = Arm6Truth(**{k: (tuple(v) if isinstance(v, list) else v)
                              for k, v in table.items() if k in names})
        rng = np.random.default_rng([seed, truth.seed, POSES_STREAM])
        measure = arm6_plant(truth, rng).measure
        return lambda arm, q_cmd, approach: measure(arm, q_cmd, rng, approach=approach)
    t = tables["linked_chain_truth"]
    robot = Robot({a: urdf_chain(arm6_urdf_path(), "base_link", "tool0", a,
                                 marker=t["marker_nominal_mm"],
                                 instrument=t["instrument_nominal"][a]) for a in t["arms"]}, 3)
    x_true = np.array([t["true_params"][n] for n in robot.layout.names])
    rng = np.random.default_rng([seed, t["seed"], POSES_STREAM])
    # the linked simulator has no play: the sides are recorded, not acted on
    measure = linked_plant(robot, x_true, t).measure
    return lambda arm, q_cmd, approach: measure(arm, q_cmd, rng)


def write_arm6_rig(out: Path, name: str, rows: Sequence[tuple[str, np.ndarray, np.ndarray]],
                   errors: _ArmErrors) -> None:
    """rig.toml, the nominal arm6.urdf and measurements.csv of a single arm6: ``rows`` are
    (set, joint readings (6,), marker point (3,) in mm)."""
    header = ["config", "set", *[f"arm_u{k + 1}" for k in range(6)], "x", "y", "z"]
    lines = [",".join(header)] + [",".join(["arm", set_name, *(f"{v:.10g}" for v in qc),
                                             *(f"{v:.4f}" for v in pc)])
                                   for set_name, qc, pc in rows]
    _write_arm6_files(out, name, {"arm": errors.instrument_nominal}, errors.marker_nominal_mm,
                      lines)


def _write_arm6_files(out: Path, name: str, instruments: Mapping[str, Sequence[float]],
                      marker: Sequence[float], lines: Sequence[str]) -> None:
    """The nominal arm6.urdf, rig.toml (an arm6 per ``instruments`` entry) and the CSV
    ``lines`` of a rig of arm6 arms."""
    shutil.copy(arm6_urdf_path(), out / ARM6_URDF)
    arms = {a: {"urdf": ARM6_URDF, "root": "base_link", "tip": "tool0", "marker": list(marker),
                "instrument": [float(v) for v in pose]} for a, pose in instruments.items()}
    (out / RIG_FILE).write_text(dump_toml({"name": name, "gravity": list(GRAVITY),
                                           "arms": arms}))
    (out / MEASUREMENTS_FILE).write_text("\n".join(lines) + "\n")


def _fmt_row(config: str, set_name: str, target: Sequence[float] | None,
             commands: Mapping[str, np.ndarray], point: np.ndarray,
             arms: Sequence[str]) -> str:
    cells = [config, set_name]
    cells += [f"{v:.4f}" for v in target] if target is not None else ["", "", ""]
    for a in arms:
        cells += [f"{v:.10g}" for v in commands[a]] if a in commands else [""] * 6
    return ",".join(cells + [f"{v:.4f}" for v in point])


def _aim_and_settle(out: Path, robot: Robot, x_true: np.ndarray, truth: LinkedArm6Truth,
                    rng: np.random.Generator) -> tuple:
    """The linked rows of the rig in ``out`` (single-arm rows written): targets (L, 3),
    commands and spring set points per arm (L, 6), and the true equilibrium."""
    from bayesrob.calibrate.least_squares import calibrate
    from bayesrob.predict.aiming import aim

    rig = load_rig(out)
    # the simulator's robot, so one compiled program per arm serves the aim and the physics
    if rig.robot.layout.names != robot.layout.names:
        raise RuntimeError("the written rig does not read back as the simulated robot")
    # aimed as predict aims, through each arm's model calibrated on its train rows (not truth)
    cal = calibrate(rig, tuple(truth.calibration_groups))
    box = np.asarray(truth.target_box_mm, float)
    targets = rng.uniform(box[:, 0], box[:, 1], size=(truth.n_linked, 3))
    commands = {}
    for arm in truth.arms:
        # through the calibration's geometry, its fitted sag left out, as the rigs the studies'
        # targets were fixed on were aimed: with it, a compliance-calibrated rig's linked rows
        # land within 0.2 mm of their targets and design_chain's figures move far beyond noise
        u = aim(rig, rig.robot, cal.x, arm, targets)
        # Ten significant digits, as written: the springs hold what the file says.
        commands[arm] = np.array([[float(f"{v:.10g}") for v in row] for row in u])
    u0 = {a: commands[a] + rng.normal(0, truth.joint_noise_rad, commands[a].shape)
          for a in truth.arms}
    eq = linked_equilibrium(
        rig.robot, x_true, u0,
        {a: np.asarray(truth.stiffness_nmm_per_rad[a], float) for a in truth.arms},
        {a: np.asarray(truth.drawn_masses_kg[a], float) for a in truth.arms}
        if truth.compliance else None,
        GRAVITY if truth.compliance else None)
    return targets, commands, u0, eq


def simulate_linked_arm6_rig(out_dir: str | Path, truth: LinkedArm6Truth) -> Path:
    """Write a rig of linked arm6 arms into out_dir: single-arm rows at random poses, and
    linked ``test`` rows aimed at random targets through each arm's calibrated model, observed
    where the joined markers really settle (:func:`linked_equilibrium`) plus noise."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(truth.seed)
    chains = {a: urdf_chain(arm6_urdf_path(), "base_link", "tool0", a,
                            marker=truth.marker_nominal_mm,
                            instrument=truth.instrument_nominal[a]) for a in truth.arms}
    robot = Robot(chains, 3)
    x_true = true_parameters(robot, truth, rng)
    # a copy: the caller's truth stays the profile, so simulating it again draws the same
    truth = replace(truth, stiffness_nmm_per_rad=drawn_stiffness(truth),
                    drawn_masses_kg={a: m.tolist() for a, m in drawn_masses(truth).items()})
    plant = linked_plant(robot, x_true, asdict(truth))
    lines = [",".join(["config", "set", "target_x", "target_y", "target_z",
                       *[f"{a}_u{k + 1}" for a in truth.arms for k in range(6)],
                       "x", "y", "z"])]
    sets = [(s, n) for s, n in (("train", truth.n_train), ("validation", truth.n_validation),
                                ("holdout", truth.n_holdout)) if n]
    for arm in truth.arms:
        q_cmd = random_poses(rng, sum(n for _, n in sets))
        p = plant.measure(arm, q_cmd, rng)
        names = [s for s, n in sets for _ in range(n)]
        lines += [_fmt_row(arm, s, None, {arm: qc}, pc, truth.arms)
                  for s, qc, pc in zip(names, q_cmd, p, strict=True)]
    _write_arm6_files(out, f"arm6-linked-seed{truth.seed}",
                      {a: truth.instrument_nominal[a] for a in truth.arms},
                      truth.marker_nominal_mm, lines)

    linked: dict = {}
    if truth.n_linked:
        # Small dense solves throughout (the fit's rank analysis, pseudo-inverses, KKT
        # systems): BLAS threads only hand them between busy cores, several times slower.
        with threadpool_limits(limits=1, user_api="blas"):
            targets, commands, u0, eq = _aim_and_settle(out, robot, x_true, truth, rng)
        observed = eq.point + rng.normal(0, truth.measurement_noise_mm, eq.point.shape)
        first_line = len(lines) + 1
        lines += [_fmt_row("+".join(truth.arms), "test", t,
                           {a: commands[a][i] for a in truth.arms}, o, truth.arms)
                  for i, (t, o) in enumerate(zip(targets, observed, strict=True))]
        (out / MEASUREMENTS_FILE).write_text("\n".join(lines) + "\n")
        linked = {
            "line": list(range(first_line, first_line + truth.n_linked)),
            "target": targets.tolist(),
            "point": eq.point.tolist(),
            **{f"free_{a}": eq.free_points[a].tolist() for a in truth.arms},
            **{f"u0_{a}": u0[a].tolist() for a in truth.arms},
            "max_violation_mm": float(eq.violation_mm.max()),
        }
    truth.true_params = {name: float(v) for name, v in zip(robot.layout.names, x_true,
                                                            strict=True)}
    truth.linked_rows = linked
    (out / TRUTH_FILE).write_text(dump_toml({"linked_chain_truth": asdict(truth)}))
    return out


