"""Two simulated 6-joint arms linked at their markers (``simulate_linked_arm6_rig``): the rig
loads with its ``left+right`` rows, calibration ignores them, the linked point is the exact
constrained minimum of the arms' energy between their free points, and malformed linked rows
are one-line errors naming the file and line.

One rig (seed 0, fewer validation, holdout and linked rows than the default, to keep the
module quick) serves every test; all random draws are seeded.
"""

from __future__ import annotations

import csv
import re
import shutil
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from threadpoolctl import threadpool_limits

from bayesrob.calibrate.least_squares import calibrate
from bayesrob.cli import main
from bayesrob.data.rig import MEASUREMENTS_FILE, RigError, load_rig
from bayesrob.sim.equilibrium import linked_energy, linked_equilibrium
from bayesrob.sim.physics import gravity_torques
from bayesrob.sim.rigs import simulate_linked_arm6_rig
from bayesrob.sim.truth import (
    GRAVITY,
    LINKED_ARMS,
    POSE_HI,
    POSE_LO,
    LinkedArm6Truth,
    load_linked_truth,
    load_true_params,
)

TRUTH = LinkedArm6Truth(seed=0, n_validation=10, n_holdout=10, n_linked=12)
GROUPS = ("frames", "offsets", "geometric")
HEADER = ["config", "set", "target_x", "target_y", "target_z",
          *[f"{a}_u{k}" for a in LINKED_ARMS for k in range(1, 7)], "x", "y", "z"]


@pytest.fixture(scope="module")
def rig_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return simulate_linked_arm6_rig(tmp_path_factory.mktemp("linked"), TRUTH)


@pytest.fixture(scope="module")
def world(rig_dir: Path) -> dict:
    """The rig and what it really is: true parameters, spring set points, stiffnesses."""
    rig = load_rig(rig_dir)
    table = load_linked_truth(rig_dir)
    params = load_true_params(rig_dir)
    rows = table["linked_rows"]
    return {
        "rig": rig, "table": table, "rows": rows,
        "x": np.array([params[n] for n in rig.robot.layout.names]),
        "u0": {a: np.array(rows[f"u0_{a}"]) for a in LINKED_ARMS},
        "k": {a: np.array(table["stiffness_nmm_per_rad"][a]) for a in LINKED_ARMS},
        "masses": {a: np.array(table["masses_kg"]) for a in LINKED_ARMS},
    }


def _rows(path: Path) -> list[list[str]]:
    with open(path, newline="") as f:
        return list(csv.reader(f))


def _write_rows(path: Path, rows: list[list[str]]) -> None:
    with open(path, "w", newline="") as f:
        csv.writer(f, lineterminator="\n").writerows(rows)


def _fraction_along(point: np.ndarray, start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """Where each point projects on the segment start -> end: 0 at start, 1 at end."""
    d = end - start
    return np.sum((point - start) * d, axis=1) / np.sum(d * d, axis=1)


def test_the_rig_loads_with_its_linked_rows(rig_dir, world):
    assert _rows(rig_dir / MEASUREMENTS_FILE)[0] == HEADER
    rig = world["rig"]
    meas = rig.measurements
    assert rig.configs == ["left", "right", "left+right"]
    assert rig.linked_configs == ["left+right"]
    linked = meas.config == "left+right"
    assert linked.sum() == TRUTH.n_linked and set(meas.set[linked]) == {"test"}
    assert np.isfinite(meas.target[linked]).all() and np.isnan(meas.target[~linked]).all()
    for a in LINKED_ARMS:
        assert np.isfinite(meas.commands[a][linked]).all()
        other = meas.config == ({"left", "right"} - {a}).pop()
        assert np.isnan(meas.commands[a][other]).all()
        assert meas.mask(a, "train").sum() == TRUTH.n_train
    assert world["rows"]["line"] == meas.line[linked].tolist()


def test_calibration_is_the_same_without_the_linked_rows(rig_dir, world, tmp_path):
    """The linked rows are test rows of another config: a chain fit reads single-arm rows
    only. Identical inputs give identical fits; the 1e-9 tolerance only allows for a
    recompiled program summing in another order (a leaked linked row would move parameters
    by its millimetre residuals)."""
    bare = tmp_path / "bare"
    shutil.copytree(rig_dir, bare)
    rows = _rows(bare / MEASUREMENTS_FILE)
    _write_rows(bare / MEASUREMENTS_FILE, [r for r in rows if r[0] != "left+right"])
    # one BLAS thread: the fit's small dense solves only contend for two busy cores
    with threadpool_limits(limits=1, user_api="blas"):
        with_linked = calibrate(world["rig"], GROUPS)
        without = calibrate(load_rig(bare), GROUPS)
    assert not load_rig(bare).linked_configs
    np.testing.assert_array_equal(with_linked.ident.free, without.ident.free)
    np.testing.assert_allclose(with_linked.x, without.x, rtol=0, atol=1e-9)
    assert set(with_linked.errors) == {"train", "validation", "holdout"}  # no "test" set
    for s, by_arm in with_linked.errors.items():
        for arm, stats in by_arm.items():
            assert stats["n"] == without.errors[s][arm]["n"]
            assert stats["mean_mm"] == pytest.approx(without.errors[s][arm]["mean_mm"],
                                                     abs=1e-9)


def test_truth_reproduces_the_linked_points(rig_dir, world):
    """truth.toml holds all the physics needs: the recorded points come back exactly, and the
    observed points sit within measurement noise of them (sd 0.1 mm per axis: 0.5 mm is five
    sd, for 36 coordinates)."""
    rig, rows = world["rig"], world["rows"]
    eq = linked_equilibrium(rig.robot, world["x"], world["u0"], world["k"], world["masses"])
    assert eq.violation_mm.max() < 1e-9
    assert rows["max_violation_mm"] < 1e-9
    np.testing.assert_allclose(eq.point, rows["point"], rtol=0, atol=1e-9)
    for a in LINKED_ARMS:
        np.testing.assert_allclose(eq.free_points[a], rows[f"free_{a}"], rtol=0, atol=1e-9)
    observed = rig.measurements.observed[rig.measurements.config == "left+right"]
    assert np.abs(observed - eq.point).max() < 0.5


def test_free_equilibria_are_the_fixed_point_of_gravity_over_stiffness(world):
    """Two solvers of one physics: the simulator's Newton steps on the energy with
    closed-form derivatives, and the fixed point of gravity torques over stiffness (12 steps leave
    ~1e-15 rad). 1e-10 rad is far above their rounding and far below any physical effect."""
    rig = world["rig"]
    eq = linked_equilibrium(rig.robot, world["x"], world["u0"], world["k"], world["masses"])
    for a in LINKED_ARMS:
        dq = np.zeros_like(world["u0"][a])
        for _ in range(12):
            dq = gravity_torques(rig.robot, world["x"], a, world["u0"][a] + dq,
                                 world["masses"][a], np.asarray(GRAVITY)) / world["k"][a]
        assert np.abs(dq).max() > 1e-3  # the sag is real: milliradians
        np.testing.assert_allclose(eq.free_joints[a], world["u0"][a] + dq, rtol=0, atol=1e-10)


def _points_and_jacobian(robot, x, arm: str):
    """u (N, 6) -> (``arm``'s markers (N, 3), their Jacobians (N, 3, 6)), compiled once (run
    eagerly, each Newton step dispatched every op of the sag on its own)."""
    xj = jnp.asarray(x)

    def point(row):
        return robot.marker_points(xj, arm, row[None])[0]

    return jax.jit(lambda u: (jax.vmap(point)(u), jax.vmap(jax.jacfwd(point))(u)))


def _onto(points_and_jacobian, targets: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Minimum-norm Newton steps from ``u`` (N, 6) putting the arm's marker on ``targets``:
    the nearest posture, to rounding (predict's aim stops at 1e-3 mm)."""
    for _ in range(20):
        p, jac = (np.asarray(v) for v in points_and_jacobian(jnp.asarray(u)))
        u = u + np.einsum("nij,nj->ni", np.linalg.pinv(jac), targets - p)
    return u


def test_the_linked_point_is_a_constrained_energy_minimum(world):
    """Every nearby configuration that keeps the markers together has more energy. Feasible
    neighbours: turn one arm's joints by ~1 mrad (and, for half of them, move the other arm
    along its own redundancy too), then bring the other arm's marker back onto the first one
    by inverse kinematics under the true parameters. A 1 mrad step raises the energy by
    ~0.1 N mm against rounding of ~1e-11 on ~1e4 N mm."""
    rig, x = world["rig"], world["x"]
    robot = rig.robot
    eq = linked_equilibrium(robot, x, world["u0"], world["k"], world["masses"])
    assert eq.violation_mm.max() < 1e-9
    best = linked_energy(robot, x, eq.joints, world["u0"], world["k"], world["masses"])
    rng = np.random.default_rng(5)
    newton = {a: _points_and_jacobian(robot, x, a) for a in LINKED_ARMS}
    for trial in range(6):
        moved, follows = LINKED_ARMS if trial % 2 == 0 else LINKED_ARMS[::-1]
        u = {a: eq.joints[a].copy() for a in LINKED_ARMS}
        u[moved] = u[moved] + rng.normal(0, 1e-3, u[moved].shape)
        start = u[follows] + (rng.normal(0, 1e-3, u[follows].shape) if trial >= 3 else 0.0)
        target = np.asarray(newton[moved](jnp.asarray(u[moved]))[0])
        u[follows] = _onto(newton[follows], target, start)
        gap = target - np.asarray(newton[follows](jnp.asarray(u[follows]))[0])
        assert np.abs(gap).max() < 1e-9
        energy = linked_energy(robot, x, u, world["u0"], world["k"], world["masses"])
        assert np.all(energy - best > 1e-4), (trial, (energy - best).min())


def test_the_linked_point_lies_between_the_free_points(world):
    """Each arm gives way along its own compliance, so the joined point is between the free
    points but not on the segment: it projects inside it, and lies off the line by less than
    half the gap (a quarter of it at most on this rig)."""
    rows = world["rows"]
    point, left, right = (np.array(rows[k]) for k in ("point", "free_left", "free_right"))
    t = _fraction_along(point, left, right)
    assert np.all((t > 0.05) & (t < 0.95)), t
    gap = np.linalg.norm(right - left, axis=1)
    off = np.linalg.norm(point - left - t[:, None] * (right - left), axis=1)
    assert np.all(off < 0.5 * gap)
    assert 1.0 < gap.mean() < 20.0  # the arms really disagree, by millimetres


def test_the_softer_arm_gives_way_more(world):
    """Without gravity the free points do not depend on the stiffnesses, so only the ratio
    moves the joined point: the softer the right arm, the nearer every row's point to the
    left arm's free point. The exact point agrees with the linearised balance of the arms'
    Cartesian compliances J K^-1 J^T to second order in the gap (within 3e-3 / mm times the
    gap squared; 7.7e-4 observed), and scaling both arms alike changes nothing."""
    import jax

    rig, x, u0 = world["rig"], world["x"], world["u0"]
    robot = rig.robot
    k_left = world["k"]["left"]
    # Without gravity each arm rests at its set point, where its marker Jacobian is taken.
    jac = {a: np.asarray(jax.jit(jax.vmap(jax.jacfwd(
        lambda u, a=a: robot.marker_points(jnp.asarray(x), a, u[None])[0])))(
        jnp.asarray(u0[a]))) for a in LINKED_ARMS}
    fractions = []
    for ratio in (0.36, 0.6, 1.0, 1 / 0.6):
        k = {"left": k_left, "right": ratio * k_left}
        eq = linked_equilibrium(robot, x, u0, k, None, None)
        left, right = eq.free_points["left"], eq.free_points["right"]
        np.testing.assert_allclose(left, robot.marker_points(x, "left", u0["left"]), atol=1e-9)
        fractions.append(_fraction_along(eq.point, left, right))
        compliance = {a: jac[a] @ np.diag(1 / k[a]) @ np.swapaxes(jac[a], 1, 2)
                      for a in LINKED_ARMS}
        share = compliance["left"] @ np.linalg.inv(compliance["left"] + compliance["right"])
        gap = right - left
        linear = left + np.einsum("nij,nj->ni", share, gap)
        assert np.all(np.linalg.norm(eq.point - linear, axis=1)
                      < 3e-3 * np.sum(gap * gap, axis=1))
    for softer, stiffer in zip(fractions, fractions[1:], strict=False):
        assert np.all(softer < stiffer)
    scaled = linked_equilibrium(robot, x, u0, {a: 3.0 * k_left for a in LINKED_ARMS}, None,
                                None)
    same = linked_equilibrium(robot, x, u0, {a: k_left for a in LINKED_ARMS}, None, None)
    np.testing.assert_allclose(scaled.point, same.point, rtol=0, atol=1e-9)


def test_linked_points_miss_their_targets_by_millimetres(world):
    """The commands aim through models calibrated by geometry alone, which cannot express the
    arms' sag under gravity, so each arm's free point misses the target by millimetres and
    the joined point, between them, does too (2.9 mm here, 3.5 mm on the default seed-0
    rig), but by less than the worse arm does on average (7.3 mm here). The bounds 0.5-10 mm
    say "millimetres": neither the noise floor (0.1 mm) nor an arm aimed wrong."""
    rig, rows = world["rig"], world["rows"]
    meas = rig.measurements
    linked = meas.config == "left+right"
    target = meas.target[linked]
    miss = np.linalg.norm(meas.observed[linked] - target, axis=1).mean()
    worse = max(np.linalg.norm(np.array(rows[f"free_{a}"]) - target, axis=1).mean()
                for a in LINKED_ARMS)
    assert 0.5 < miss < 10.0, miss
    assert miss < worse


def test_commands_stay_in_the_working_range(world):
    """The linked commands come from predict's aim, which keeps to the train rows' command
    range where it can (inside POSE_LO..POSE_HI): a shoulder lift outside that would reach
    through the base."""
    meas = world["rig"].measurements
    linked = meas.config == "left+right"
    for a in LINKED_ARMS:
        u = meas.commands[a][linked]
        assert np.all((u >= POSE_LO) & (u <= POSE_HI))


@pytest.fixture
def rig_copy(rig_dir: Path, tmp_path: Path) -> Path:
    dest = tmp_path / "rig"
    shutil.copytree(rig_dir, dest)
    return dest


def _first_linked(rows: list[list[str]]) -> int:
    return next(i for i, r in enumerate(rows) if r[0] == "left+right")


def _load_error(rig: Path) -> str:
    with pytest.raises(RigError) as exc:
        load_rig(rig)
    message = str(exc.value)
    assert len(message.splitlines()) == 1, message
    return message


def test_a_linked_row_missing_a_members_column_is_named(rig_copy):
    path = rig_copy / MEASUREMENTS_FILE
    rows = _rows(path)
    i = _first_linked(rows)
    rows[i][rows[0].index("right_u3")] = ""
    _write_rows(path, rows)
    message = _load_error(rig_copy)
    assert message.startswith(f"{path}: line {i + 1}: ")
    assert "a linked row for 'left+right' is missing arm 'right''s 'right_u3'" in message


@pytest.mark.parametrize(("config", "expected"), [
    ("left+middle", "config 'left+middle' names unknown arm 'middle' (rig.toml has left, right)"),
    ("right+right", "config 'right+right' names the same arm twice"),
])
def test_a_bad_linked_config_is_named(rig_copy, config, expected):
    path = rig_copy / MEASUREMENTS_FILE
    rows = _rows(path)
    i = _first_linked(rows)
    rows[i][0] = config
    _write_rows(path, rows)
    message = _load_error(rig_copy)
    assert message.startswith(f"{path}: line {i + 1}: ") and expected in message


def test_linking_an_arm_that_carries_another_is_refused(rig_copy):
    """With right mounted on left's tip, left carries no marker of its own to link."""
    toml = rig_copy / "rig.toml"
    text = toml.read_text()
    right = text.index("[arms.right]")
    body = re.sub(r"instrument = \[[^\]]*\]\n", 'mount = "left"\n', text[right:])
    toml.write_text(text[:right] + body)
    rows = _rows(rig_copy / MEASUREMENTS_FILE)
    _write_rows(rig_copy / MEASUREMENTS_FILE, [rows[0], rows[_first_linked(rows)]])
    message = _load_error(rig_copy)
    assert re.search(r"measurements\.csv: line 2: linked config 'left\+right' names 'left', "
                     r"an arm other arms are mounted on", message), message


def test_a_malformed_linked_row_is_one_line_and_exit_2_on_the_command_line(rig_copy, capsys):
    path = rig_copy / MEASUREMENTS_FILE
    rows = _rows(path)
    i = _first_linked(rows)
    rows[i][rows[0].index("left_u6")] = ""
    _write_rows(path, rows)
    assert main(["calibrate", str(rig_copy)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert f"{path}: line {i + 1}: a linked row for 'left+right' is missing arm 'left''s" in err


def test_linked_is_for_arm6_only(tmp_path, capsys):
    assert main(["simulate", str(tmp_path / "r"), "--linked"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--linked are for --robot arm6" in err
    assert not (tmp_path / "r" / MEASUREMENTS_FILE).exists()


def test_simulate_linked_on_the_command_line(tmp_path, capsys):
    """The command's default linked rig (80/40/40 poses per arm, 24 linked rows, compliance
    on): about 12 s after the module's rig has compiled the programs it shares."""
    out = tmp_path / "r"
    assert main(["simulate", str(out), "--robot", "arm6", "--linked", "--seed", "4"]) == 0
    printed = capsys.readouterr().out
    assert "arm6 left+right" in printed and "24 linked test rows" in printed
    assert "compliance on" in printed
    rig = load_rig(out)
    assert (rig.measurements.config == "left+right").sum() == 24
    assert load_linked_truth(out)["seed"] == 4


def test_three_arms_joined_at_one_point_on_the_command_line(tmp_path, capsys):
    """``simulate --robot arm6 --linked --third-arm``: a front arm beside left and right, each
    with single-arm rows, and test rows where all three markers settle at one point (the
    simulator's solve leaves them at most 1e-6 mm apart, or it fails); the front arm's
    stiffnesses are the left profile's times THIRD_ARM_STIFFNESS_SCALE, drawn about per seed
    like the others', and the left and right arms draw what a two-arm rig of the seed draws."""
    from bayesrob.sim.truth import THIRD_ARM, THIRD_ARM_STIFFNESS_SCALE, drawn_stiffness

    out = tmp_path / "r"
    assert main(["simulate", str(out), "--robot", "arm6", "--linked", "--third-arm",
                 "--poses", "30", "4", "4", "--seed", "5"]) == 0
    assert "arm6 left+right+front" in capsys.readouterr().out
    rig = load_rig(out)
    assert rig.robot.measured_arms() == [*LINKED_ARMS, THIRD_ARM]
    assert (rig.measurements.config == "left+right+front").sum() == 24
    for arm in rig.robot.measured_arms():
        assert (rig.measurements.config == arm).sum() == 38
    table = load_linked_truth(out)
    assert table["arms"] == ["left", "right", "front"]
    assert table["linked_rows"]["max_violation_mm"] <= 1e-6
    # the joined point is not any one arm's own: each free point lies off it
    point = np.array(table["linked_rows"]["point"])
    for a in table["arms"]:
        assert np.linalg.norm(np.array(table["linked_rows"][f"free_{a}"]) - point,
                              axis=1).mean() > 0.1
    # the front arm's stiffnesses are drawn about its profile, 0.8 of the left one's, per
    # arm and per joint (log sd 0.3 each: all 6 joints within 4 sd of the profile, and not
    # one common factor)
    profile = THIRD_ARM_STIFFNESS_SCALE * np.array(LinkedArm6Truth().stiffness_nmm_per_rad[
        "left"])
    log_ratio = np.log(np.array(table["stiffness_nmm_per_rad"][THIRD_ARM]) / profile)
    assert np.all(np.abs(log_ratio) < 4 * np.hypot(0.3, 0.3)) and np.ptp(log_ratio) > 0.05
    # the left and right arms draw what a two-arm rig of the seed draws
    two = drawn_stiffness(LinkedArm6Truth(seed=5))
    assert all(table["stiffness_nmm_per_rad"][a] == list(two[a]) for a in LINKED_ARMS)


@pytest.mark.parametrize("arms, message", [
    (("left", "left"), "two or more distinct names"),
    (("left",), "two or more distinct names"),
    (("left", "right", "front"), "instrument_nominal has no entry for front"),
])
def test_linked_truth_names_what_its_arms_lack(arms, message):
    with pytest.raises(ValueError, match=message):
        LinkedArm6Truth(arms=arms)


def test_third_arm_needs_linked(tmp_path, capsys):
    assert main(["simulate", str(tmp_path / "r"), "--robot", "arm6", "--third-arm"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--third-arm joins a third arm" in err, err
    assert not (tmp_path / "r").exists()


def test_each_seed_draws_its_arms_stiffnesses():
    """Rigs of different seeds are different arm pairs: their stiffnesses are drawn about the
    profile (log sd 0.3 per arm and per joint), the same seed draws the same, and sd 0 keeps
    the profile. Over 200 seeds the log ratio to the profile has sd sqrt(0.3^2 + 0.3^2) =
    0.42 (within 10%: its sampling error at 1,200 values, correlated in sixes, is about 4%)."""
    from bayesrob.sim.truth import drawn_stiffness

    profile = LinkedArm6Truth().stiffness_nmm_per_rad
    a, b = drawn_stiffness(LinkedArm6Truth(seed=1)), drawn_stiffness(LinkedArm6Truth(seed=2))
    assert a != b and a == drawn_stiffness(LinkedArm6Truth(seed=1))
    assert drawn_stiffness(LinkedArm6Truth(seed=1, stiffness_log_sd=0.0)) == {
        k: tuple(v) for k, v in profile.items()}
    logs = np.array([np.log(np.divide(drawn_stiffness(LinkedArm6Truth(seed=s))[arm],
                                      profile[arm]))
                     for s in range(200) for arm in LINKED_ARMS])
    assert abs(logs.std() / np.hypot(0.3, 0.3) - 1) < 0.1
    assert abs(logs.mean()) < 0.1


def test_linked_arms_true_masses_are_drawn_about_the_urdfs(tmp_path, capsys):
    """``mass_log_sd`` 0 keeps every arm's link masses as arm6.urdf states them; above it
    each arm's are the URDF's times a log-normal factor per link, the same for a seed every
    time and different between the arms. ``--mass-spread`` sets it for arm6 --linked only
    (one line, exit 2, elsewhere)."""
    from bayesrob.robot import urdf_chain
    from bayesrob.sim.truth import arm6_urdf_path, drawn_masses

    described = np.array(urdf_chain(arm6_urdf_path(), "base_link", "tool0", "a")
                         .source["link_masses_kg"])
    same = drawn_masses(LinkedArm6Truth(seed=5))
    assert all(np.array_equal(m, described) for m in same.values())
    drawn = drawn_masses(LinkedArm6Truth(seed=5, mass_log_sd=0.1))
    again = drawn_masses(LinkedArm6Truth(seed=5, mass_log_sd=0.1))
    assert all(np.array_equal(drawn[a], again[a]) for a in drawn)
    ratios = np.log(np.concatenate([drawn[a] / described for a in ("left", "right")]))
    assert not np.allclose(drawn["left"], drawn["right"])
    # twelve log-normal factors of sd 0.1: all within 4 sd, spread between a third and three
    # times the sd (chi-square with 12 degrees of freedom: far outside its 1e-4 tails)
    assert np.all(np.abs(ratios) < 0.4) and 0.033 < ratios.std() < 0.3
    for argv in ([], ["--robot", "arm6"]):
        assert main(["simulate", str(tmp_path / "r"), "--mass-spread", "0.1", *argv]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "--mass-spread is for arm6 --linked" in err, err
