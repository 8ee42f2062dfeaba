"""Predictions for chain robots: latent joint-error populations, push-forward, regions, CLI."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest
import scipy.stats

import bayesrob.predict.aiming as aiming
import bayesrob.predict.draws as cp
import bayesrob.predict.stiffness as st
from bayesrob import robot as kin
from bayesrob.cli import main
from bayesrob.data.rig import RigError, load_rig
from bayesrob.predict.aiming import aim
from bayesrob.predict.assembly import grid_targets, predict_assembly, read_targets
from bayesrob.predict.draws import assembly_draws, fit_modules
from bayesrob.predict.grid import hdr_area
from bayesrob.predict.regions import hdr_levels, hdr_sizes
from bayesrob.predict.stiffness import StiffnessPrior
from bayesrob.sim.rigs import simulate_arm6_rig
from bayesrob.sim.truth import Arm6Truth


@pytest.fixture(scope="module")
def arm6_rig(tmp_path_factory):
    # Joint repeatability 0.5 mrad (five times the default) so that the joints, not the
    # instrument, dominate the error the population has to find.
    d = tmp_path_factory.mktemp("arm6")
    return simulate_arm6_rig(d, Arm6Truth(seed=11, joint_noise_rad=5e-4))


@pytest.fixture(scope="module")
def arm6_modules(arm6_rig):
    rig = load_rig(arm6_rig)
    return rig, fit_modules(rig, ["arm"], "ind", groups=("frames", "offsets", "geometric"))


def test_one_region_routine_serves_grid_cells_and_draws():
    """The 50% / 90% regions of N(0, diag(1, 4)) in the plane have area -2 log(1 - m) pi
    sqrt(det): the paper's grid of cells (100 x 100 over +-8 sd) within 1% (its cells are
    0.16 / 0.32 wide), and the draws' Monte Carlo estimate within 10% of the KDE's (the
    bandwidth widens the covariance by 1 + n^(-1/3))."""
    sd = np.array([1.0, 2.0])
    n, half = 100, 8.0
    axes = [(-half + 2 * half * (np.arange(n) + 0.5) / n) * s for s in sd]
    gx, gy = np.meshgrid(*axes)
    dens = scipy.stats.multivariate_normal(cov=np.diag(sd**2)).pdf(np.dstack([gx, gy]))
    cell = np.prod(2 * half * sd / n)
    prob = (dens / dens.sum()).reshape(1, -1)
    draws = np.random.default_rng(2).normal(size=(4000, 1, 2)) * sd
    inflate = 1 + 4000 ** (-1 / 3)
    for m, drawn in zip((0.5, 0.9), hdr_sizes(draws)[:, 0], strict=True):
        exact = -2 * np.log(1 - m) * np.pi * np.prod(sd)
        assert abs(hdr_area(prob, m, cell)[0] / exact - 1) < 0.01
        assert abs(drawn / (exact * inflate) - 1) < 0.10, (m, drawn, exact)


@pytest.mark.parametrize("dim", [2, 3])
def test_the_population_density_of_a_row_is_scipys_gaussian(dim):
    """The latent fit's closed-form Gaussian log density of residual rows equals scipy's."""
    from bayesrob.errors.latent_errors import _gaussian_log_density

    rng = np.random.default_rng(dim)
    a = rng.normal(size=(20, dim, dim))
    cov = a @ np.swapaxes(a, 1, 2) + 0.1 * np.eye(dim)
    r = rng.normal(size=(20, dim))
    ours = np.asarray(_gaussian_log_density(cov, r))
    ref = [scipy.stats.multivariate_normal(cov=c).logpdf(x) for c, x in zip(cov, r, strict=True)]
    np.testing.assert_allclose(ours, ref, rtol=1e-10)


def test_hdr_sizes_and_levels_of_a_gaussian():
    """Draws of N(0, diag(1, 4, 0.25)): the 50% / 90% regions are ellipsoids of volume
    4/3 pi chi2_3(m)^(3/2) sqrt(det) (the KDE's bandwidth widens the covariance by
    1 + n^(-2/7)); Monte Carlo volumes within 10% (their error at 800 evaluation points is
    about 3%), and the levels of fresh Gaussian points are uniform (KS at 0.01)."""
    rng = np.random.default_rng(1)
    sd = np.array([1.0, 2.0, 0.5])
    draws = rng.normal(size=(4000, 1, 3)) * sd
    inflate = 1 + 4000 ** (-2 / 7)
    sizes = hdr_sizes(draws)[:, 0]
    for m, v in zip((0.5, 0.9), sizes, strict=True):
        exact = 4 / 3 * np.pi * scipy.stats.chi2.ppf(m, 3) ** 1.5 * np.prod(sd) * inflate**1.5
        assert abs(v / exact - 1) < 0.10, (m, v, exact)
    fresh = rng.normal(size=(400, 1, 3)) * sd
    levels = hdr_levels(draws, fresh)[:, 0]
    assert scipy.stats.kstest(levels, "uniform").pvalue > 0.01


def test_latent_population_and_coverage_on_new_poses(arm6_modules):
    """A 6-joint arm with 0.5 mrad joint noise: the fitted joint sds of the well-seen joints
    are within a factor 2 of 0.5 mrad (a 3-D residual sees six joints only through their
    projections, and the wrist's last joint hardly moves the marker); the predicted regions
    on the 80 validation and holdout rows (new poses) cover at nominal within binomial error
    at 0.01 (50%: 0.36-0.64, 90%: 0.81-0.99), and the predicted mean error is within
    [0.8, 1.25] of the observed (80 rows: its sampling error is about 5%).

    2000 draws rather than the default 4000 (the regions' KDE costs in proportion): the
    bounds are those of 80 rows' binomial error (sd 0.056 at 50%), which the draws' own
    error stays far below: each row's level is read off 800 points of the KDE (sd <= 0.018),
    and Scott's kernel widens the draws' covariance by 1 + n^(-2/7), 11.4% at 2000 draws
    against 9.4% at 4000, so the 50% region's coverage moves by about 1 point. Measured on
    this seed: coverage 0.59 / 0.94 and error ratio 1.065 (4000 draws: 0.56 / 0.94, 1.065)."""
    rig, mods = arm6_modules
    le = mods.errors["arm"]
    assert le.diagnostics["max_r_hat"] < 1.05
    sds = le.joint_sd.mean(0)
    assert np.all((sds[:3] > 0.25e-3) & (sds[:3] < 1e-3)), sds
    us, ds = zip(*(rig.rows("arm", s) for s in ("validation", "holdout")), strict=True)
    u, d = np.concatenate(us), np.concatenate(ds)
    draws = assembly_draws(mods, ["arm"], [u], num_samples=2000, seed=3)
    levels = hdr_levels(draws, d)
    assert 0.36 <= np.mean(levels <= 0.5) <= 0.64
    assert 0.81 <= np.mean(levels <= 0.9) <= 0.99
    predicted = np.linalg.norm(draws - draws.mean(0), axis=-1).mean()
    observed = np.linalg.norm(d - draws.mean(0), axis=-1).mean()
    assert 0.8 <= predicted / observed <= 1.25, (predicted, observed)


def test_draws_pushed_in_slices_are_the_draws_pushed_at_once(arm6_modules, monkeypatch):
    """Many draws at many rows are pushed through the chain in slices (memory: Justin's 200
    validation poses with six sag steps took 23 GB in one call); the slices, one short, give
    the same points as one call, to rounding (1e-9 mm: the same operations per draw)."""
    import dataclasses


    rig, mods = arm6_modules
    mods = dataclasses.replace(mods, param_cov=1e-8 * np.eye(len(mods.x)))
    u, _ = rig.rows("arm", "validation")
    whole = assembly_draws(mods, ["arm"], [u], num_samples=300, seed=5)
    monkeypatch.setattr(cp, "POINTS_PER_CALL", 45 * len(u))  # 7 calls: 6 of 43 draws, 42
    sizes = []
    compiled = cp._points_with_errors

    def counted(robot, arm):
        push = compiled(robot, arm)
        return lambda xs, *a: sizes.append(len(xs)) or push(xs, *a)
    monkeypatch.setattr(cp, "_points_with_errors", counted)
    sliced = assembly_draws(mods, ["arm"], [u], num_samples=300, seed=5)
    assert sizes == [43] * 6 + [42]
    assert sliced.shape == whole.shape == (300, len(u), 3)
    # the draws' parameters differ, so a slice given the wrong draws' parameters would show
    assert np.ptp(np.asarray(cp.parameter_draws(mods, cp.jax.random.PRNGKey(0), 3)), 0).max() > 0
    np.testing.assert_allclose(sliced, whole, rtol=0, atol=1e-9)


def test_aim_reaches_targets_and_refuses_what_it_cannot(arm6_modules):
    rig, mods = arm6_modules
    _, d = rig.rows("arm", "holdout")
    targets = d[:6] + np.array([5.0, -5.0, 5.0])
    u = aim(rig, mods.robot, mods.x, "arm", targets)
    got = np.asarray(mods.robot.compiled_points("arm")(mods.x, u))
    assert np.abs(got - targets).max() < 1e-3
    with pytest.raises(RigError, match=r"out of reach of arm 'arm'"):
        aim(rig, mods.robot, mods.x, "arm", np.array([[9000.0, 0.0, 0.0]]))


def test_aim_reaches_targets_with_a_planar_arms_pulse_columns():
    """A planar arm's columns are pulse widths (about 0.0015 rad per us): the step limit is
    in radians, so its Gauss-Newton reaches the default rig's linked targets (a limit read
    as 0.3 us per step stopped 14.6 mm short on a three-arm rig) and lands where the
    eight-parameter fit's closed-form inverse does, the same model fitted the same way to
    within 0.5 us."""
    from bayesrob.calibrate.arms import calibrate_arms
    from bayesrob.calibrate.least_squares import calibrate
    from bayesrob.data.rig import default_rig_dir

    rig = load_rig(default_rig_dir())
    cal = calibrate(rig, kin.GROUPS)
    targets = rig.config_rows("top+bottom", "test")["target"][:6]
    u = aim(rig, cal.robot, cal.x, "top", targets)
    got = np.asarray(cal.robot.compiled_points("top")(cal.x, u))
    assert np.abs(got - targets).max() < 1e-3
    closed = np.asarray(calibrate_arms(rig)["top"].arm.command(targets))
    assert np.abs(u - closed).max() < 0.5


def test_aim_leaves_the_train_range_only_when_no_near_seed_stays_inside(monkeypatch):
    """A redundant arm reaches a target on several branches. The nearest train pose's branch
    is kept where it stays inside the train commands' range; where it leaves it, the next
    nearest seeds are tried and the first inside is taken, else the one least beyond; a
    target no seed reaches is refused. (Gauss-Newton stubbed: seed k's solution is given.)"""
    u_train = np.array([[0.0, 0.0], [1.0, 1.0], [0.5, 0.2], [0.9, 0.9]])
    d_train = np.array([[0.0, 0, 0], [10.0, 0, 0], [20.0, 0, 0], [30.0, 0, 0]])
    rig = SimpleNamespace(rows=lambda arm, s: (u_train, d_train), arms={"arm": None})
    # per target (rows) and seed rank (columns): the solution, and whether it reaches
    answers = {0: [[0.5, 0.5], [1.4, 0.5], [0.2, 0.3], [0.1, 0.1]],  # in range at once
               1: [[1.3, 0.0], [1.2, 0.5], [0.4, 0.4], [0.3, 0.3]],  # third seed is inside
               2: [[2.0, 0.0], [1.5, 0.0], [1.1, 0.0], [1.05, 0.0]]}  # never: least beyond
    reach = {3: [False, False, False, False]}
    calls = []

    def fake(f, xj, targets, seeds, per_rad):
        k = len(calls)
        calls.append(seeds.copy())
        u = np.array([answers[t][k] for t in range(len(targets))])
        miss = np.array([1.0 if not reach.get(t, [True] * 4)[k] else 0.0
                         for t in range(len(targets))])
        return u, miss

    monkeypatch.setattr(aiming, "_aim_from", fake)
    monkeypatch.setattr(aiming, "_column_jacobian", lambda robot, arm: None)
    monkeypatch.setattr(aiming, "_radians_per_unit", lambda robot, arm: np.ones(2))
    targets = np.array([[1.0, 0, 0], [12.0, 0, 0], [19.0, 0, 0]])
    u = aiming.aim(rig, None, np.zeros(1), "arm", targets)
    np.testing.assert_array_equal(u, [[0.5, 0.5], [0.4, 0.4], [1.05, 0.0]])
    # seeds nearest first: target 1 (x = 12) starts from the train pose at x = 10
    np.testing.assert_array_equal(calls[0][1], u_train[1])
    np.testing.assert_array_equal(calls[1][1], u_train[2])
    assert len(calls) == 4  # every seed tried, as target 2 never gets inside
    # targets aimed inside the range start later solves from their own solution
    np.testing.assert_array_equal(calls[1][0], u[0])
    # everything inside at once: the nearest seeds alone, one solve
    calls.clear()
    assert aiming.aim(rig, None, np.zeros(1), "arm", targets[:1]).tolist() == [[0.5, 0.5]]
    assert len(calls) == 1
    # a seed that misses the target is passed over for a later one that reaches it
    calls.clear()
    answers[0] = [[5.0, 5.0], [0.6, 0.6], [0.2, 0.3], [0.1, 0.1]]
    reach[0] = [False, True, True, True]
    assert aiming.aim(rig, None, np.zeros(1), "arm", targets[:1]).tolist() == [[0.6, 0.6]]
    assert len(calls) == 2
    calls.clear()
    answers[3] = answers[0]
    with pytest.raises(RigError, match=r"target \(25, 0, 0\) is out of reach"):
        aiming.aim(rig, None, np.zeros(1), "arm", np.array([[1.0, 0, 0], [12.0, 0, 0],
                                                              [19.0, 0, 0], [25.0, 0, 0]]))


def test_predict_command_on_a_chain_rig(arm6_rig, tmp_path, capsys):
    """``bayesrob predict`` on a 3-D rig: x,y,z targets, volumes in the JSON, a figure; a
    planar-only model and 2-D targets are refused with one line and exit 2."""
    rig = load_rig(arm6_rig)
    _, d = rig.rows("arm", "holdout")
    tfile = tmp_path / "t.csv"
    tfile.write_text("x,y,z\n" + "\n".join(",".join(f"{v:.3f}" for v in p) for p in d[:4]))
    out, png = tmp_path / "p.json", tmp_path / "p.png"
    assert main(["predict", str(arm6_rig), "--config", "arm", "--targets", str(tfile),
                 "--json", str(out), "--plot", str(png)]) == 0
    doc = json.loads(out.read_text())
    assert doc["model"] == "ind" and len(doc["targets"]) == 4
    t0 = doc["targets"][0]
    assert 0 < t0["hdr50_mm3"] < t0["hdr90_mm3"]
    assert 0 < t0["expected_error_mm"] < 2.0
    # how far each target's joint commands leave the train rows' range, column by column
    u_train = rig.rows("arm", "train")[0]
    for t in doc["targets"]:
        u = np.asarray(t["commands"]["arm"])
        excess = np.maximum(u_train.min(0) - u, 0) + np.maximum(u - u_train.max(0), 0)
        np.testing.assert_allclose(t["beyond_train_range"]["arm"], excess, atol=1e-12)
    assert doc["summary"]["targets_beyond_train_range"] == sum(
        any(v > 0 for v in t["beyond_train_range"]["arm"]) for t in doc["targets"])
    assert png.stat().st_size > 10_000
    capsys.readouterr()
    assert main(["predict", str(arm6_rig), "--config", "arm", "--targets", str(tfile),
                 "--model", "cond"]) == 2
    # the error in one line, after the clock's lines ("predict: ...") if any
    err = [x for x in capsys.readouterr().err.strip().splitlines()
           if not x.startswith("predict: ")]
    assert len(err) == 1 and "latent joint-error models ind, corr" in err[0]
    flat = tmp_path / "flat.csv"
    flat.write_text("x,y\n1,2\n")
    assert main(["predict", str(arm6_rig), "--config", "arm", "--targets", str(flat)]) == 2
    err = [x for x in capsys.readouterr().err.strip().splitlines()
           if not x.startswith("predict: ")]
    assert len(err) == 1 and "columns x,y,z" in err[0]


def test_targets_in_3d(tmp_path):
    f = tmp_path / "t.csv"
    f.write_text("x,y,z\n1,2,3\n4,5,six\n")
    with pytest.raises(RigError, match=r"line 3: x, y, z must be numbers"):
        read_targets(f, 3)


def test_grid_targets_run_x_fastest_in_3d(arm6_rig):
    rig = load_rig(arm6_rig)
    rig.workspace = ((0.0, 2.0), (10.0, 12.0), (20.0, 22.0))
    g = grid_targets(rig, 2)
    assert g.shape == (8, 3)
    np.testing.assert_allclose(g[:3], [[0.5, 10.5, 20.5], [1.5, 10.5, 20.5], [0.5, 11.5, 20.5]])


def test_predict_assembly_rejects_targets_of_the_wrong_dimension(arm6_rig):
    with pytest.raises(RigError, match="3-D points but the targets have 2"):
        predict_assembly(load_rig(arm6_rig), "arm", np.zeros((2, 2)))


# ------------------------------------------------------------------------- linked 3-D arms


@pytest.fixture(scope="module")
def linked_calibration(tmp_path_factory):
    """Two arm6 arms linked at their tool points (seed 1), and a calibration with compliance
    that is the simulator's own physics: its parameters, each joint's compliance the inverse
    of its true stiffness (the simulator keeps stiffness apart from the calibration's
    parameters). The sag-centred priors are relations that hold for any calibration with
    compliance; a fitted one costs a least-squares fit whose compilation alone takes a minute
    (how well fitted arms predict linked points is a study: ``bayesrob validate
    linked_chain_checks``)."""
    from bayesrob.calibrate.least_squares import Calibration, with_gravity
    from bayesrob.sim.rigs import simulate_linked_arm6_rig
    from bayesrob.sim.truth import LinkedArm6Truth, load_linked_truth, load_true_params

    d = simulate_linked_arm6_rig(tmp_path_factory.mktemp("linked") / "rig",
                                  LinkedArm6Truth(seed=1))
    rig = load_rig(d)
    robot = with_gravity(rig)
    true = load_true_params(d)
    x = np.array([true[n] for n in robot.layout.names])
    for arm, k in load_linked_truth(d)["stiffness_nmm_per_rad"].items():
        x[robot.layout.slices[arm, "compliance"]] = 1.0 / np.asarray(k, float)
    cal = Calibration(robot=robot, x=x, groups=("frames", "offsets", "geometric",
                                                     "compliance"),
                           ident=None, se=np.full(x.size, np.nan), errors={}, nfev=0,
                           seconds=0.0)
    return rig, cal


def test_linked_arms_prior_is_centred_on_their_fitted_sags(linked_calibration, monkeypatch):
    """Where both linked arms take the prior, each arm's term is centred on its fitted sag
    against the other's: the arm that sags further is the softer. The sag is linear in the
    compliance at one step of the torques, so tripling the right arm's fitted compliances
    triples its sag (to 1%: the sag's own pull on the pose is second order) and moves the
    arms' centres apart by log 3 more; draws of the log stiffnesses take those centres (20,000
    draws: the mean's error about 0.005; tolerance 0.02). Not where an arm's stiffnesses are
    given, nor for one arm alone, nor with CHAIN_STIFFNESS_ARM_CENTRE "equal"."""
    from dataclasses import replace

    import jax


    rig, cal = linked_calibration
    prior = {a: st.stiffness_prior(rig, a, cal) for a in ("left", "right")}
    assert all(p.source == "the prior" and p.arm_centre == 0 for p in prior.values())
    scaled = st.sag_scaled_priors(rig, cal, prior)
    # what fit_modules keeps
    assert _same_priors(st.stiffness_priors(rig, ["left", "right"], cal), scaled)
    sags = st.arm_sags(rig, cal, ["left", "right"])
    assert all(v > 0.05 for v in sags.values()), sags  # mm: gravity bends both arms
    gap = scaled["left"].arm_centre - scaled["right"].arm_centre
    assert gap == pytest.approx(np.log(sags["right"] / sags["left"]), abs=1e-9)
    assert scaled["left"].arm_centre == pytest.approx(-scaled["right"].arm_centre)
    assert all(p.source == st.STIFFNESS_SOURCES[3] for p in scaled.values())
    np.testing.assert_array_equal(scaled["left"].centre, prior["left"].centre)
    assert np.all(scaled["left"].sd == st.SAG_SCALED_LOG_SD)
    assert scaled["left"].arm_sd == st.SAG_SCALED_ARM_LOG_SD

    x = np.array(cal.x, float)
    x[cal.robot.layout.slices["right", "compliance"]] *= 3.0
    softer = replace(cal, x=x)
    tripled = st.arm_sags(rig, softer, ["left", "right"])
    assert tripled["left"] == pytest.approx(sags["left"], rel=1e-9)
    assert tripled["right"] == pytest.approx(3.0 * sags["right"], rel=0.01)
    wider = st.sag_scaled_priors(rig, softer, prior)
    assert wider["left"].arm_centre - wider["right"].arm_centre == pytest.approx(
        gap + np.log(3.0), abs=0.01)

    draws = st.stiffness_draws([wider["left"], wider["right"]], jax.random.PRNGKey(0), 20_000)
    for d, p in zip(draws, (wider["left"], wider["right"]), strict=True):
        np.testing.assert_allclose(np.asarray(d).mean(0), p.centre + p.arm_centre, atol=0.02)

    given = dict(prior, right=st.StiffnessPrior(np.zeros(6), np.zeros(6), np.zeros(6, bool),
                                                "the rig"))
    assert _same_priors(st.sag_scaled_priors(rig, cal, given), given)
    alone = {"left": prior["left"]}
    assert _same_priors(st.sag_scaled_priors(rig, cal, alone), alone)
    monkeypatch.setattr(st, "CHAIN_STIFFNESS_ARM_CENTRE", "equal")
    assert _same_priors(st.sag_scaled_priors(rig, cal, prior), prior)


def test_the_designer_links_modules_of_one_rig_as_predict_links_its_arms(linked_calibration):
    """``bayesrob design`` fits each module's prior alone; linked, two modules that are the
    two arms of one rig take the sag-centred priors ``predict`` gives those arms, in either
    order. Modules of different rigs, or one arm mounted twice, keep their own. A module's
    stiffness draws come from its own seed whatever it is linked with, so the same module
    pair draws the same stiffnesses in either order (common random numbers)."""
    from types import SimpleNamespace

    import jax

    from bayesrob.design.modules import (
        CalibratedModule,
        _log_stiffness,
        linked_priors,
        stiffness_record,
    )

    rig, cal = linked_calibration
    own = {a: st.stiffness_prior(rig, a, cal) for a in ("left", "right")}

    def module(arm: str, rig_index: int = 0) -> CalibratedModule:
        # no joint errors: the priors and stiffness draws never read them
        m = cp.CalibratedModules(cal, {arm: None}, {arm: own[arm]}, None)
        return CalibratedModule(arm, arm, rig, m, np.zeros(3), rig_index, "ind")

    left, right = module("left"), module("right")

    def named(arms: tuple[str, str], priors: list) -> dict:
        return dict(zip(arms, priors, strict=True))

    scaled = st.sag_scaled_priors(rig, cal, own)
    assert scaled["left"].source == st.STIFFNESS_SOURCES[3]
    assert _same_priors(named(("left", "right"), linked_priors([left, right])), scaled)
    assert _same_priors(named(("right", "left"), linked_priors([right, left])), scaled)
    other_rig = module("right", rig_index=1)
    assert _same_priors(named(("left", "right"), linked_priors([left, other_rig])), own)
    twice = linked_priors([left, module("left")])
    assert all(_same_priors({"left": p}, {"left": own["left"]}) for p in twice)

    job = SimpleNamespace(cache={}, modules={"left": left, "right": right}, seed=3, draws=50)
    # the record predict's JSON gives per arm, in the candidate's order
    assert stiffness_record(job, ("right", "left")) == [
        scaled[a].record() for a in ("right", "left")]
    assert [r["from"] for r in stiffness_record(job, ("right", "left"))] == [
        st.STIFFNESS_SOURCES[3]] * 2
    ab = _log_stiffness(job, ("left", "right"))
    ba = _log_stiffness(job, ("right", "left"))
    np.testing.assert_array_equal(np.asarray(ab[0]), np.asarray(ba[1]))
    np.testing.assert_array_equal(np.asarray(ab[1]), np.asarray(ba[0]))
    # the centres moved the draws: the sag-centred left arm is not the left arm alone
    alone = st.stiffness_draws([own["left"]], jax.random.PRNGKey(3 * 104729), 50)[0]
    assert not np.allclose(np.asarray(ab[0]), np.asarray(alone))


def _same_priors(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(
        np.array_equal(u, v) for k in a for u, v in zip(a[k], b[k], strict=True))


def test_stiffness_prior_from_the_rig_or_the_default(arm6_rig, arm6_modules, tmp_path):
    """A rig's ``stiffness`` is taken as known (sd 0); without it every joint gets the
    default prior, centred on its URDF torque limit (arm6: 150 N m on the first three joints,
    28 on the wrist); a non-positive stiffness is refused naming the key."""
    import dataclasses
    import shutil

    from bayesrob.predict.stiffness import CHAIN_STIFFNESS_LOG_SD, stiffness_prior

    rig, _ = arm6_modules
    loc, sd, shared, source, *_ = stiffness_prior(rig, "arm")
    assert source == "the prior"
    np.testing.assert_allclose(np.exp(loc), [150, 150, 150, 28, 28, 28])
    np.testing.assert_array_equal(sd, CHAIN_STIFFNESS_LOG_SD)
    assert shared.all()
    k = np.array([4e6, 4e6, 2e6, 6e5, 6e5, 6e5])
    given = dataclasses.replace(rig, arms={"arm": dataclasses.replace(rig.arms["arm"],
                                                                      stiffness=k)})
    loc, sd, shared, source, *_ = stiffness_prior(given, "arm")
    assert source == "the rig"
    np.testing.assert_allclose(np.exp(loc), k)
    np.testing.assert_array_equal(sd, 0.0)
    assert not shared.any()
    bad = tmp_path / "bad"
    shutil.copytree(arm6_rig, bad)
    toml = (bad / "rig.toml").read_text()
    (bad / "rig.toml").write_text(toml.replace('tip = "tool0"',
                                               'tip = "tool0"\nstiffness = [1, 1, 1, 1, 1, -1]'))
    with pytest.raises(RigError, match=r"arms\.arm\.stiffness: must be positive"):
        load_rig(bad)


def test_stiffness_from_compliances_fitted_under_the_described_masses(arm6_modules):
    """With compliances fitted under the URDF's masses the prior is updated by the fit: a
    joint seen sharply keeps its fitted stiffness (sd about the masses' 0.1); a joint gravity
    never turns sits in the torque-limit profile at the arm's fitted scale, its sd the
    prior's and the scale's; a joint seen poorly (standard error three times its compliance)
    stays near the profile (a tenth of its fit's error at most) and moves the scale by under
    1% of that error; no joint takes the prior's shared arm term."""
    from types import SimpleNamespace


    rig, mods = arm6_modules
    lay = mods.robot.layout
    comp = np.arange(lay.nominal.size)[lay.slices["arm", "compliance"]]
    true_k = np.array([4e6, 5e6, 2.5e6, 5e5, 4e5, 6e5])

    def fitted(wrist2_k):
        x, se = np.zeros(lay.nominal.size), np.full(lay.nominal.size, np.nan)
        free = np.zeros(lay.nominal.size, bool)
        k = true_k.copy()
        k[4] = wrist2_k
        x[comp] = 1.0 / k
        se[comp] = 1e-3 / k  # a sharp fit: 0.1% of each compliance
        se[comp[4]] = 3.0 / k[4]
        free[comp[1:]] = True  # the first joint's axis is vertical: never seen
        cal = SimpleNamespace(masses="description", groups=("frames", "compliance"),
                              robot=mods.robot, x=x, se=se, ident=SimpleNamespace(free=free))
        return st.stiffness_prior(rig, "arm", cal)

    p = fitted(4e5)
    assert not p.shared.any() and p.source == "compliances fitted under the URDF's masses"
    np.testing.assert_allclose(np.exp(p.centre[[1, 2, 3, 5]]), true_k[[1, 2, 3, 5]], rtol=0.02)
    assert np.all(np.abs(p.sd[[1, 2, 3, 5]] - st.DESCRIBED_MASS_LOG_SD) < 0.01)
    # the arm's scale about the profile (150 N m on the first three joints, 28 on the wrist)
    seen = [1, 2, 3, 5]
    profile = np.log([150, 150, 150, 28, 28, 28])
    scale = np.mean(np.log(true_k[seen]) - profile[seen])
    assert p.centre[0] == pytest.approx(profile[0] + scale, abs=0.02)
    # the profile's own spread, and the scale's: four sharp joints, each off the profile by
    # the prior's sd, fix it to sd / 2
    tau = st.CHAIN_STIFFNESS_LOG_SD
    assert p.sd[0] == pytest.approx(np.sqrt(tau**2 + (tau**2 + 0.01) / 4), abs=0.01)
    far = fitted(4e5 / 50)  # the poorly seen wrist fitted 50 times too soft
    # its weight beside a sharp joint's: 0.26 / 9.3 of it, over four sharp joints
    assert abs(far.centre[0] - p.centre[0]) < 0.01 * np.log(50)
    assert abs(far.centre[4] - (profile[4] + scale)) < 0.1 * np.log(50)


def test_stiffness_draws_share_an_arm_term_only_where_unknown(monkeypatch):
    """With a shared per-arm sd a and a per-joint sd j, two joints of one arm have log
    stiffnesses correlated a^2 / (a^2 + j^2) (0.5 at a = j = 0.5), joints of different arms
    are independent, and a known stiffness (sd 0) stays exactly as given. 20,000 draws give
    each correlation within about 0.01 (sd (1 - r^2) / sqrt(n)); tolerance 0.03."""
    import jax


    monkeypatch.setattr(st, "CHAIN_STIFFNESS_ARM_LOG_SD", 0.5)
    unknown = st.StiffnessPrior(np.zeros(3), np.full(3, 0.5), np.ones(3, bool), "the prior")
    known = st.StiffnessPrior(np.log([4e6, 2e6, 6e5]), np.zeros(3), np.zeros(3, bool),
                                "the rig")
    a, b, c = st.stiffness_draws([unknown, unknown, known], jax.random.PRNGKey(0), 20_000)
    a, b, c = (np.asarray(v) for v in (a, b, c))
    r = np.corrcoef(np.hstack([a, b]).T)
    assert abs(r[0, 1] - 0.5) < 0.03 and abs(r[1, 2] - 0.5) < 0.03
    assert abs(r[0, 3]) < 0.03 and abs(r[2, 5]) < 0.03
    np.testing.assert_allclose(a.std(axis=0), np.sqrt(0.5**2 + 0.5**2), rtol=0.03)
    np.testing.assert_array_equal(c, np.broadcast_to(known[0], c.shape))


def test_linked_draws_put_the_tracker_noise_back(monkeypatch):
    """The linked point is measured once with the tracker's whole noise, where the balance
    would average the noise each free point carried: ``assembly_draws`` balances the free points
    as they are (no noise) and adds the mean of the arms' fitted noise sds (0.1 and 0.3 mm
    here: 0.2) once. With the free points at zero the draws are that noise alone: 20,000 x 2
    x 3 draws give its sd to about 0.3%; tolerance 2%."""
    from types import SimpleNamespace

    import jax.numpy as jnp


    asked = []

    def free(mods, a, u, xs, key, side=None, measured=True, drawn=None):
        asked.append(measured)
        return np.zeros((xs.shape[0], len(u), 3))

    rng = np.random.default_rng(0)
    jac = jnp.asarray(rng.normal(size=(2, 3, 6)))
    monkeypatch.setattr(cp, "free_draws", free)
    monkeypatch.setattr(cp, "joint_jacobian", lambda robot, x, a, u: jac)
    monkeypatch.setattr(cp, "parameter_draws", lambda mods, key, n: jnp.zeros((n, 1)))
    errors = {"a": SimpleNamespace(noise_sd=np.array([0.08, 0.12])),
              "b": SimpleNamespace(noise_sd=np.array([0.3, 0.3]))}
    prior = st.StiffnessPrior(np.zeros(6), np.full(6, 0.5), np.ones(6, bool), "the prior")
    mods = SimpleNamespace(errors=errors, stiffness={"a": prior, "b": prior}, robot=None,
                           x=np.zeros(1))
    d = cp.assembly_draws(mods, ["a", "b"], [np.zeros((2, 6)), np.zeros((2, 6))],
                       num_samples=20_000)
    assert asked == [False, False]
    assert d.std() == pytest.approx(0.2, rel=0.02)
    assert abs(np.corrcoef(d[:, 0, 0], d[:, 0, 1])[0, 1]) < 0.03


def test_stiffness_record_names_where_the_balance_drew_from():
    """``predict``'s JSON and ``design.json`` say where each linked arm's stiffnesses came
    from: the rig's (N mm/rad, sd 0), compliances fitted under the URDF's masses (N mm/rad and
    log sds), or the prior, whose scale is arbitrary (relative to the first joint, with its
    arm term); every record gives the arm's log scale against the others'."""
    from bayesrob.predict.stiffness import CHAIN_STIFFNESS_ARM_LOG_SD, STIFFNESS_SOURCES

    k = np.array([4e6, 2e6, 5e5])
    rig = StiffnessPrior(np.log(k), np.zeros(3), np.zeros(3, bool), "the rig").record()
    assert rig["from"] == "the rig" and np.allclose(rig["nmm_per_rad"], k)
    assert rig["log_sd"] == [0.0] * 3 and rig["arm_log_centre"] == 0.0
    assert "relative" not in rig and "arm_log_sd" not in rig
    fit = StiffnessPrior(np.log(k), np.full(3, 0.1), np.zeros(3, bool),
                         STIFFNESS_SOURCES[1]).record()
    assert fit["from"].startswith("compliances fitted") and fit["log_sd"] == [0.1] * 3
    prior = StiffnessPrior(np.log([150.0, 150.0, 28.0]), np.full(3, 0.5), np.ones(3, bool),
                           "the prior").record()
    assert prior["from"] == "the prior" and "nmm_per_rad" not in prior
    np.testing.assert_allclose(prior["relative"], [1.0, 1.0, 28 / 150])
    assert prior["arm_log_sd"] == CHAIN_STIFFNESS_ARM_LOG_SD
    assert prior["arm_log_centre"] == 0.0
    scaled = StiffnessPrior(np.log([150.0, 150.0, 28.0]), np.full(3, 0.5), np.ones(3, bool),
                            STIFFNESS_SOURCES[3], -0.4).record()
    assert scaled["from"].endswith("scaled by their fitted sags")
    assert scaled["arm_log_centre"] == -0.4
    # the record is JSON as it stands
    assert json.loads(json.dumps(scaled)) == scaled


def test_predict_points_from_the_prior_to_the_described_masses(forearm_unweighed):
    """``predict`` notes, under its stiffness lines, that linked arms whose stiffnesses came
    from the prior could read them from their URDF's masses, naming those arms; not when
    another source gave them, nor when a chain on an arm's path leaves a link unweighed."""
    from bayesrob.predict.assembly import stiffness_note
    from bayesrob.predict.stiffness import STIFFNESS_SOURCES
    from bayesrob.sim.truth import arm6_urdf_path

    def robot(right_urdf):
        return kin.Robot({a: kin.urdf_chain(u, "base_link", "tool0", a)
                          for a, u in (("left", arm6_urdf_path()), ("right", right_urdf))})

    rig, fitted, prior = STIFFNESS_SOURCES[0], STIFFNESS_SOURCES[1], STIFFNESS_SOURCES[2]
    weighed = robot(arm6_urdf_path())
    note = stiffness_note(weighed, {"left": prior, "right": prior})
    assert note.startswith("note: ") and "left, right took their stiffnesses from the prior" \
        in note and "--masses description" in note
    assert "yet right took" in stiffness_note(weighed, {"left": rig, "right": prior})
    scaled = STIFFNESS_SOURCES[3]  # the prior still, its arm terms centred on the sags
    assert "yet left, right took" in stiffness_note(weighed, {"left": scaled, "right": scaled})
    assert stiffness_note(weighed, {"left": fitted, "right": fitted}) is None
    assert stiffness_note(robot(forearm_unweighed), {"left": prior, "right": prior}) is None


TREE_RIG = """
name = "two hands on a torso"
[arms.torso]
dh = [[0.0, 0.0, 0.0, 0.0]]
origin = [0.0, 0.0, 300.0, 0.0, 0.0, 0.0]
[arms.left]
mount = "torso"
origin = [0.0, 200.0, 0.0, 0.0, 0.0, 0.0]
dh = [[0.0, 0.0, 0.0, 1.5707963267948966], [0.0, 0.0, 300.0, 0.0]]
tool = [250.0, 0.0, 0.0, 0.0, 0.0, 0.0]
marker = [0.0, 0.0, 0.0]
[arms.right]
mount = "torso"
origin = [0.0, -200.0, 0.0, 0.0, 0.0, 0.0]
dh = [[0.0, 0.0, 0.0, 1.5707963267948966], [0.0, 0.0, 300.0, 0.0]]
tool = [250.0, 0.0, 0.0, 0.0, 0.0, 0.0]
marker = [0.0, 0.0, 0.0]
"""


def test_linked_hands_of_one_torso_share_one_population(tmp_path, monkeypatch):
    """Two hands on one torso, linked: one joint-error population of all five joints, fitted
    on both hands' rows, so the torso's error is one value for both hands (not averaged away
    as two independent torsos' would be) and the config's order does not choose whose torso
    estimate counts. Each hand alone keeps its own rows' population. The rows' torso joint
    errs by 5 mrad, the arms' by 1 mrad: the pooled torso sd lies within a factor 1.6 of 5
    mrad (80 rows, 240 coordinates: its posterior median is good to about 15%)."""
    import jax

    (tmp_path / "rig.toml").write_text(TREE_RIG)
    header = "config,set,x,y,z,torso_u1,left_u1,left_u2,right_u1,right_u2"
    # one placeholder row to read the robot from, before its rows are made
    (tmp_path / "measurements.csv").write_text(f"{header}\nleft,train,0,0,0,0,0,0,,\n")
    robot = load_rig(tmp_path, min_train_rows=0).robot
    x = np.asarray(robot.layout.nominal)
    rng = np.random.default_rng(7)
    lines = [header]
    for hand in ("left", "right"):
        for k in range(50):
            u = np.r_[rng.uniform(-0.6, 0.6), rng.uniform(-1.0, 0.2), rng.uniform(0.3, 1.5)]
            e = rng.normal(0.0, [5e-3, 1e-3, 1e-3])
            p = np.asarray(robot.marker_points(x, hand, (u + e)[None]))[0]
            p = p + rng.normal(0.0, 0.1, 3)
            cols = [f"{u[0]:.6f}", *([f"{v:.6f}" for v in u[1:]] if hand == "left" else
                                     ["", ""]),
                    *([f"{v:.6f}" for v in u[1:]] if hand == "right" else ["", ""])]
            lines.append(",".join([hand, "train" if k < 40 else "validation",
                                   *(f"{v:.4f}" for v in p), *cols]))
    (tmp_path / "measurements.csv").write_text("\n".join(lines) + "\n")
    rig = load_rig(tmp_path)
    from dataclasses import replace

    from bayesrob.calibrate.least_squares import calibrate
    from bayesrob.errors.latent_errors import fit_latent_errors

    cal = calibrate(rig, ("frames",))
    # fewer draws than a prediction takes: the test's questions need no more
    pops: dict = {}
    left, right = (fit_latent_errors(rig, cal.robot, cal.x, hand, "ind",
                                     int(cal.ident.free.sum()), seed=0, warmup=200,
                                     samples=200, chains=1, populations=pops)
                   for hand in ("left", "right"))
    assert left.population is right.population is not None and len(pops) == 1
    assert left.joints[0] == right.joints[0] == "torso.j1"
    torso_sd = float(np.median(left.population.joint_sd[:, 0]))
    assert 5e-3 / 1.6 < torso_sd < 5e-3 * 1.6
    u = np.zeros((3, 3))
    mods = SimpleNamespace(errors={"left": left, "right": right})
    (el, _), (er, _) = cp._linked_joint_errors(mods, ["left", "right"], [u, u],
                                               jax.random.PRNGKey(0), 200)
    np.testing.assert_array_equal(np.asarray(el)[..., 0], np.asarray(er)[..., 0])
    assert np.abs(np.asarray(el)[..., 1:] - np.asarray(er)[..., 1:]).max() > 0
    # predict's fits: one population where the hands are linked, each hand's own alone
    asked = []

    def fit(*args, populations=None, **kwargs):
        asked.append(populations)
        return left

    monkeypatch.setattr(cp, "fit_latent_errors", fit)
    fit_modules(rig, ["left", "right"], "ind", calibration=cal, latent=True, linked=True)
    fit_modules(rig, ["left", "right"], "ind", calibration=cal, latent=True)
    assert isinstance(asked[0], dict) and asked[1] is asked[0] and asked[2:] == [None, None]
    alone = SimpleNamespace(errors={"left": replace(left, population=None),
                                    "right": replace(right, population=None)})
    assert cp._linked_joint_errors(alone, ["left", "right"], [u, u], jax.random.PRNGKey(0),
                                   5) == [None, None]
