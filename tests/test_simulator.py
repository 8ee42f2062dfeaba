"""The simulator's physics: sag, stiffness, backlash jumps, linked tug of war, determinism."""

from dataclasses import replace
from functools import partial

import jax.numpy as jnp
import numpy as np
import pytest

from bayesrob import robot as kin
from bayesrob.sim.equilibrium import PhysicalRig
from bayesrob.sim.rigs import grid_points, holdout_points, simulate_rig
from bayesrob.sim.truth import TRUTH_FILE, Truth, paper_truth, three_arm_truth


def _sag_mm(truth: Truth, name: str, u) -> float:
    """Distance between the rigid-arm end point and where the loaded arm settles."""
    plant = PhysicalRig(truth)
    arm = truth.arms[name]
    rigid = np.asarray(kin.forward_u(arm.params, jnp.asarray(u)))
    return float(np.linalg.norm(plant.end_point({name: u}, noise=False) - rigid))


@pytest.fixture(scope="module")
def truth():
    return paper_truth(("gravity_sag",), seed=0)


def test_sag_grows_with_mass_and_shrinks_with_stiffness(truth):
    # arm stretched out horizontally: every mass loads the shoulder the same way
    u = np.asarray(kin.servo_inverse(truth.arms["top"].params, jnp.array([0.0, 0.0])))
    base = _sag_mm(truth, "top", u)
    heavy = replace(truth, arms={**truth.arms, "top": replace(truth.arms["top"],
                                                             elbow_mass_kg=0.2)})
    stiff = replace(truth, arms={**truth.arms, "top": replace(
        truth.arms["top"], stiffness_nmm_per_rad=(10000.0, 7200.0))})
    assert base > 1.0  # sag at mid range is millimetres with the default servos
    assert _sag_mm(heavy, "top", u) > 1.5 * base
    assert _sag_mm(stiff, "top", u) < 0.5 * base


def test_no_sag_without_the_effect(truth):
    clean = truth.with_effects(())
    assert _sag_mm(clean, "top", truth.arms["top"].u_mid) < 0.05


def test_sag_points_along_gravity(truth):
    """A horizontal arm sags downwards."""
    arm = truth.arms["bottom"]
    theta = jnp.array([0.0, 0.0])  # stretched out horizontally
    u = np.asarray(kin.servo_inverse(arm.params, theta))
    plant = PhysicalRig(truth)
    d = plant.end_point({"bottom": u}, noise=False)
    rigid = np.asarray(kin.forward(arm.params, theta))
    assert d[1] < rigid[1] - 1.0


def test_backlash_jumps_where_gravity_torque_changes_sign():
    truth = paper_truth(("backlash",), seed=0)
    arm = truth.arms["top"]
    plant = PhysicalRig(truth)
    # sweep the shoulder through the vertical below the base: torque on joint 1 flips sign
    t1 = np.linspace(-np.pi / 2 - 0.15, -np.pi / 2 + 0.15, 31)
    theta_cmd = np.column_stack([t1, np.zeros_like(t1)])
    settled = np.array([plant.settle_arm("top", tc) for tc in theta_cmd])
    dev = settled[:, 0] - t1
    b = arm.backlash_rad[0]
    # on either side the joint rests against one edge of its dead band
    assert np.isclose(dev[0], -b, atol=b * 0.05) or np.isclose(dev[0], b, atol=b * 0.05)
    assert np.isclose(dev[-1], -dev[0], atol=b * 0.05)
    # crossing the band within two 0.01 rad steps of the sweep: a jump of its full width,
    # where a smooth sag would change by a fraction of it
    jump = np.abs(dev[2:] - dev[:-2]).max()
    assert jump > 1.5 * b


def test_linked_arms_settle_near_the_much_stiffer_arm():
    truth = paper_truth(("gravity_sag",), seed=0)
    stiff = replace(truth, arms={**truth.arms, "bottom": replace(
        truth.arms["bottom"], stiffness_nmm_per_rad=(2.5e6, 1.8e6))})
    plant = PhysicalRig(stiff)
    target = np.array([170.0, 190.0])
    # aim the two arms at points 6 mm apart: the tug of war decides where they meet
    u_top = np.asarray(kin.Arm("top", stiff.arms["top"].params, 1).command(
        jnp.asarray(target + [3.0, 0.0])))
    u_bot = np.asarray(kin.Arm("bottom", stiff.arms["bottom"].params, -1).command(
        jnp.asarray(target - [3.0, 0.0])))
    linked = plant.end_point({"top": u_top, "bottom": u_bot}, noise=False)
    free_bot = plant.end_point({"bottom": u_bot}, noise=False)
    free_top = plant.end_point({"top": u_top}, noise=False)
    assert np.linalg.norm(linked - free_bot) < 0.5
    assert np.linalg.norm(linked - free_top) > 5.0


def test_equal_arms_meet_between_their_free_end_points():
    truth = paper_truth((), seed=0)
    plant = PhysicalRig(truth)
    target = np.array([170.0, 190.0])
    u_top = np.asarray(kin.Arm("top", truth.arms["top"].params, 1).command(
        jnp.asarray(target + [2.0, 0.0])))
    u_bot = np.asarray(kin.Arm("bottom", truth.arms["bottom"].params, -1).command(
        jnp.asarray(target - [2.0, 0.0])))
    linked = plant.end_point({"top": u_top, "bottom": u_bot}, noise=False)
    # not an average and not either arm's own point: the compliances are anisotropic, so the
    # meeting point may slide sideways, but it stays between the two aims
    assert target[0] - 2.0 < linked[0] < target[0] + 2.0
    assert abs(linked[1] - target[1]) < 2.0


def _closed_form_energy(theta, theta_cmd, params, masses, stiffness, backlash, gravity):
    # the paper's arm written out: springs with a dead band on the wrapped angle, and four
    # point masses (link 1's middle, the elbow servo, link 2's middle, the end)
    from bayesrob.sim.physics import G_N_PER_KG, dead_band

    elbow, end = kin.elbow_point(params, theta), kin.forward(params, theta)
    points = jnp.stack([(params.base + elbow) / 2, elbow, (elbow + end) / 2, end])
    spring = 0.5 * jnp.sum(stiffness * dead_band(kin.wrap_angle(theta - theta_cmd),
                                                 backlash) ** 2)
    return spring - G_N_PER_KG * jnp.sum(masses * (points @ gravity))


def test_the_planar_energy_is_the_general_energy_on_the_arms_2_joint_chain():
    """The paper's arms are a configuration of the one physics: the energy the simulator
    settles them by (the chains' program on the arm's 2-joint chain, each link's mass at its
    centre of mass) equals, with its gradient and Hessian, the arm's energy written out by
    hand. Joint angles within and beyond the dead bands (0.008 rad); tolerance: rounding
    (energies of hundreds of N mm)."""
    import jax

    from bayesrob.sim.equilibrium import _arm_physics, _arm_program, _at_angles

    @jax.jit
    @partial(jax.vmap, in_axes=(0, 0, None, None, None, None, None))
    def closed_form(*args):
        return (_closed_form_energy(*args), jax.grad(_closed_form_energy)(*args),
                jax.hessian(_closed_form_energy)(*args))

    truth = three_arm_truth(("gravity_sag", "backlash"), stiffness_log_sd=0.3)
    g = jnp.asarray(truth.gravity)
    rng = np.random.default_rng(0)
    for name, arm in truth.arms.items():
        phys = _arm_physics(arm, truth.effects, truth.gravity)
        a = phys.arrays
        k, weight, centre, backlash = a.stiffness, a.weight, a.centre, a.backlash
        masses = jnp.array([arm.link_mass_kg[0], arm.elbow_mass_kg, arm.link_mass_kg[1],
                            arm.end_mass_kg])
        robot = arm.robot()
        theta_cmd = rng.uniform(-2.5, 2.5, (6, 2))
        theta = theta_cmd + rng.uniform(-0.02, 0.02, (6, 2))
        s = _arm_program(robot, name)(jnp.asarray(robot.layout.nominal), theta, theta_cmd,
                                      k, weight, centre, backlash, periodic=True)
        assert np.any(np.abs(theta - theta_cmd) < 0.008)  # some joints inside their band
        energy, grad, hess = closed_form(jnp.asarray(theta), jnp.asarray(theta_cmd),
                                         arm.params, masses, k, backlash, g)
        np.testing.assert_allclose(s["energy"], energy, atol=1e-9)
        np.testing.assert_allclose(s["grad"], grad, atol=1e-8)
        np.testing.assert_allclose(s["hess"], hess, rtol=1e-9, atol=1e-6)
        # what PhysicalRig minimises is that energy, row by row
        for t, tc, e, gr in zip(theta, theta_cmd, energy, grad, strict=True):
            out = np.asarray(_at_angles(phys.structure, name, phys.arrays, jnp.asarray(t),
                                        jnp.asarray(tc)))
            np.testing.assert_allclose(out, np.r_[e, gr], atol=1e-8)


def test_linked_arms_settle_by_the_energy_and_its_gradient_over_the_shared_end_point():
    """What PhysicalRig.settle_linked minimises, from the chains' program (each arm's joints
    by its closed-form inverse, the gradient in the end point J^-T times the joints'), equals
    the sum of the arms' hand-written energies through the same inverse, with jax.grad's
    gradient; commands a turn away (2 pi) from the reached angles too, which the wrap must
    undo. Tolerance: rounding."""
    import jax

    from bayesrob.sim.equilibrium import _at_point

    truth = three_arm_truth(("gravity_sag", "backlash"), stiffness_log_sd=0.3)
    plant = PhysicalRig(truth)
    names = tuple(truth.arms)[:2]
    phys = [plant._physics[n] for n in names]
    g = jnp.asarray(truth.gravity)

    def total(d, commands):
        out = 0.0
        for n, p, tc in zip(names, phys, commands, strict=True):
            a = truth.arms[n]
            theta, _ = kin.inverse(a.params, d, a.elbow)
            masses = jnp.array([a.link_mass_kg[0], a.elbow_mass_kg, a.link_mass_kg[1],
                                a.end_mass_kg])
            out = out + _closed_form_energy(theta, tc, a.params, masses, p.arrays.stiffness,
                                            p.arrays.backlash, g)
        return out

    rng = np.random.default_rng(1)
    for d in ([170.0, 190.0], [150.0, 230.0], [210.0, 160.0]):
        d = jnp.asarray(d)
        commands = tuple(
            kin.inverse(truth.arms[n].params, d + rng.normal(0, 2, 2), truth.arms[n].elbow)[0]
            + 2 * np.pi * rng.integers(-1, 2, 2) for n in names)
        out = np.asarray(_at_point(
            structures=tuple(p.structure for p in phys), arms=names,
            elbows=tuple(int(truth.arms[n].elbow) for n in names),
            arrays=tuple(p.arrays for p in phys),
            params=tuple(truth.arms[n].params for n in names), d=d, theta_cmds=commands))
        np.testing.assert_allclose(out, np.r_[total(d, commands),
                                              jax.grad(total)(d, commands)], atol=1e-8)


def test_simulated_rig_is_deterministic(tmp_path):
    truth = paper_truth(("backlash", "servo_nonlinearity"), seed=7, grid=3)
    a = simulate_rig(tmp_path / "a", truth)
    b = simulate_rig(tmp_path / "b", truth)
    for f in ("rig.toml", "measurements.csv", "truth.toml"):
        assert (a / f).read_bytes() == (b / f).read_bytes()
    assert Truth.from_toml(a / "truth.toml") == truth


def test_noise_levels_match_their_settings():
    truth = replace(paper_truth((), seed=3), joint_noise_rad=0.0)
    plant = PhysicalRig(truth, seed=1)
    u = truth.arms["top"].u_mid
    exact = plant.end_point({"top": u}, noise=False)
    draws = np.array([plant.end_point({"top": u}) - exact for _ in range(400)])
    # sd estimate from 400 draws: relative standard error ~ 1/sqrt(800) = 3.5%; allow 12%
    np.testing.assert_allclose(draws.std(axis=0), truth.measurement_noise_mm, rtol=0.12)


def test_holdout_points_lie_between_the_grid_points_inside_the_workspace():
    ws = ((80.0, 260.0), (100.0, 280.0))
    grid, hold = grid_points(ws, 4), holdout_points(ws, 4)
    assert hold.shape == (9, 2)
    assert np.all((hold[:, 0] > 80.0) & (hold[:, 0] < 260.0))
    assert np.all((hold[:, 1] > 100.0) & (hold[:, 1] < 280.0))
    # Every holdout point is half a cell (30 mm) from the grid in x and in y: a new pose.
    gap = np.abs(hold[:, None, :] - grid[None, :, :]).min(axis=1)
    np.testing.assert_allclose(gap, 30.0)
    assert holdout_points(ws, 1).shape == (0, 2)


def test_holdout_rows_are_appended_without_changing_the_other_rows(tmp_path):
    from bayesrob.data.rig import load_rig

    truth = paper_truth(("gravity_sag", "backlash"), seed=5, grid=3)
    with_h = simulate_rig(tmp_path / "with", truth)
    without = simulate_rig(tmp_path / "without", truth, holdout=False)
    a = (with_h / "measurements.csv").read_text()
    b = (without / "measurements.csv").read_text()
    assert a.startswith(b) and len(a) > len(b)
    for f in ("rig.toml", "truth.toml"):
        assert (with_h / f).read_bytes() == (without / f).read_bytes()
    meas = load_rig(with_h).measurements
    assert meas.mask("top", "holdout").sum() == meas.mask("bottom", "holdout").sum() == 4
    assert meas.mask("top+bottom", "holdout").sum() == 4
    for arm in ("top", "bottom"):
        train = meas.commands[arm][meas.mask(arm, "train")]
        hold = meas.commands[arm][meas.mask(arm, "holdout")]
        # New poses: no holdout command is within 50 us of a training command on both joints.
        near = np.all(np.abs(hold[:, None, :] - train[None]) < 50.0, axis=-1)
        assert not near.any()
    linked = meas.mask("top+bottom", "holdout")
    np.testing.assert_allclose(meas.target[linked], holdout_points(truth.workspace, 3))
    # The linked holdout rows land near their targets, as the test rows do (a few mm).
    assert np.linalg.norm(meas.observed[linked] - meas.target[linked], axis=1).max() < 10.0


def test_the_default_rig_regenerates_byte_for_byte(tmp_path):
    """Its README's command: the files shipped are the simulator's output. A regression pin: a
    change to the simulator's physics, its random streams or the files' formatting that would
    silently leave the embedded default rig (and every figure published from it) behind the
    code fails here. About 10 s on two busy cores."""
    from bayesrob.data.rig import default_rig_dir

    truth = paper_truth(("gravity_sag", "backlash"), seed=2009)
    out = simulate_rig(tmp_path / "rig", truth)
    for f in ("rig.toml", "measurements.csv", "truth.toml"):
        assert (out / f).read_bytes() == (default_rig_dir() / f).read_bytes(), f


def test_drawn_stiffness_differs_per_arm_and_seed_and_leaves_the_rest_of_the_rig(tmp_path):
    """Per-seed stiffness draws: reproducible for a seed, different between arms and seeds,
    recorded in truth.toml, and nothing but the stiffnesses changes (the draws have a stream of
    their own, so the rest of a rig is what the seed always gave)."""
    plain = paper_truth(("gravity_sag",), seed=7)
    drawn = paper_truth(("gravity_sag",), seed=7, stiffness_log_sd=0.3)
    assert drawn == paper_truth(("gravity_sag",), seed=7, stiffness_log_sd=0.3)
    k = {n: np.asarray(a.stiffness_nmm_per_rad) for n, a in drawn.arms.items()}
    assert not np.allclose(k["top"], k["bottom"])
    assert not np.allclose(k["top"], plain.arms["top"].stiffness_nmm_per_rad)
    other = paper_truth(("gravity_sag",), seed=8, stiffness_log_sd=0.3)
    assert not np.allclose(k["top"], other.arms["top"].stiffness_nmm_per_rad)
    for n, a in drawn.arms.items():
        assert replace(a, stiffness_nmm_per_rad=plain.arms[n].stiffness_nmm_per_rad) == \
            plain.arms[n]
    # a factor e^(2 x 0.3 x 4) = 11 would be a four-sigma draw on both terms
    ratio = np.concatenate([k[n] / np.asarray(plain.arms[n].stiffness_nmm_per_rad) for n in k])
    assert np.all((ratio > 1 / 11) & (ratio < 11)), ratio
    simulate_rig(tmp_path, drawn, holdout=False)
    assert Truth.from_toml(tmp_path / TRUTH_FILE).arms == drawn.arms
    three = three_arm_truth(seed=7, stiffness_log_sd=0.3)
    assert len({a.stiffness_nmm_per_rad for a in three.arms.values()}) == 3
    with pytest.raises(ValueError, match="stiffness_log_sd"):
        paper_truth(seed=7, stiffness_log_sd=-0.1)


def test_simulate_command_draws_stiffness_and_refuses_it_where_it_cannot_apply(tmp_path,
                                                                               capsys):
    from bayesrob.cli import main

    out = tmp_path / "r"
    assert main(["simulate", str(out), "--grid", "2", "--seed", "3",
                 "--stiffness-spread", "0.3"]) == 0
    assert "log sd 0.3" in capsys.readouterr().out
    assert Truth.from_toml(out / TRUTH_FILE).arms == \
        paper_truth(seed=3, grid=2, stiffness_log_sd=0.3).arms
    three = tmp_path / "three"
    assert main(["simulate", str(three), "--robot", "three-arm", "--grid", "2", "--seed", "3",
                 "--stiffness-spread", "0.3"]) == 0
    assert Truth.from_toml(three / TRUTH_FILE).arms == \
        three_arm_truth(seed=3, grid=2, stiffness_log_sd=0.3).arms
    capsys.readouterr()
    for argv, words in (
            (["--robot", "arm6"], "--stiffness-spread"),  # one arm, one profile
            (["--planned"], "truth.toml"),
            (["--stiffness-spread", "nan"], "finite"),
            (["--stiffness-spread", "inf"], "finite"),
            (["--stiffness-spread", "-0.1"], "0 or more")):
        if "--stiffness-spread" not in argv:
            argv = [*argv, "--stiffness-spread", "0.3"]
        try:
            code = main(["simulate", str(tmp_path / "c"), *argv])
        except SystemExit as exc:  # argparse's own refusals exit 2 after one usage line
            code = exc.code
        assert code == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert words in err[-1], (argv, err)
    assert not (tmp_path / "c").exists()


def test_a_chain_arm_rests_in_its_play_as_gravity_or_its_approach_decides():
    """The chain plant (single arm6 rigs, linked rigs' arms, planned poses): where a joint's
    gravity torque exceeds the friction it rests on the torque's side of its play, elsewhere on
    the side it was approached from. Noise off, no compliance: the points are the true arm's
    at the commands moved by half the play, to rounding (1e-9 mm)."""
    from dataclasses import replace as copy

    from bayesrob.sim import physics
    from bayesrob.sim.rigs import arm6_plant, random_poses
    from bayesrob.sim.truth import Arm6Truth

    play = 4e-3
    plant = arm6_plant(Arm6Truth(seed=3, joint_play_rad=play, joint_noise_rad=0.0,
                                 measurement_noise_mm=0.0), np.random.default_rng(3))
    q = random_poses(np.random.default_rng(1), 12)
    approach = np.where(np.random.default_rng(2).random(q.shape) < 0.5, -1.0, 1.0)
    tau = physics.gravity_torques(plant.torque_robot, plant.torque_x, "arm", q,
                                  plant.masses_kg["arm"], np.asarray(plant.gravity))

    def measured(stick: float) -> np.ndarray:
        return copy(plant, stick_nmm=stick).measure("arm", q, np.random.default_rng(0),
                                                    approach=approach)

    def at(offset: np.ndarray) -> np.ndarray:
        return np.asarray(plant.robot.marker_points(plant.x_true, "arm", q + offset))

    held = np.abs(tau) < 2000.0
    assert 0 < held.sum() < held.size  # both cases occur at these poses
    side = np.where(held, approach, np.sign(tau))
    np.testing.assert_allclose(measured(2000.0), at(0.5 * play * side), rtol=0, atol=1e-9)
    # no friction: gravity alone decides, whatever the approach
    np.testing.assert_allclose(measured(0.0), at(0.5 * play * np.sign(tau)), rtol=0, atol=1e-9)
    assert np.abs(measured(2000.0) - measured(0.0)).max() > 0.1  # the sides move the marker


def test_a_truth_file_that_is_no_planar_rigs_is_one_line(tmp_path, capsys):
    """A truth.toml that does not parse, or an arm6's where planar arms are needed: the
    file named in one line, exit 2 (no traceback)."""
    from bayesrob.cli import main

    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / TRUTH_FILE).write_text("garbage=\n")
    arm6 = tmp_path / "arm6"
    arm6.mkdir()
    (arm6 / TRUTH_FILE).write_text("[chain_truth]\nseed = 1\n")
    for rig, words in ((bad, "cannot read the simulated rig's truth"),
                       (arm6, "a 6-joint arm's truth")):
        assert main(["simulate", str(rig), "--planned"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and str(rig / TRUTH_FILE) in err[0] and words in err[0], err
