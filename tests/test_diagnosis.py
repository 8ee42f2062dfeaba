"""The model-criticism workflow: effects, scoring, naming, the command and its figures.

The representative rigs here are each diagnosed once per session (a few seconds each after
JAX has compiled); the sweep of report rigs behind the confusion matrix is the validation
study ``bayesrob validate diagnosis``. Every rig is diagnosed from its files alone.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from bayesrob.validation.planar_generators import Case, make_rig

import bayesrob  # noqa: F401  (x64)
from bayesrob import robot as kin
from bayesrob.data.rig import default_rig_dir, load_rig
from bayesrob.diagnose.refits import (
    ArmData,
    ArmEval,
    _crossfit,
    diagnose,
    evaluate_arm,
    neighbour_pairs,
    workspace_regions,
)
from bayesrob.diagnose.rule import DecisionRule, Z, elpd_diff, paired_z
from bayesrob.robot import effects as fx
from bayesrob.robot.chain import G_N_PER_KG

CONTRACT_KEYS = {"effects", "steps", "baseline_heldout_error_mm", "final_heldout_error_mm"}
STEP_KEYS = {"effect", "arms", "heldout_error_before_mm", "heldout_error_after_mm", "elpd_diff",
             "elpd_diff_se"}


# ------------------------------------------------------------------------------ effects


def _ctx() -> fx.EffectContext:
    return fx.EffectContext((0.0, -1.0), (1500.0, 1500.0), (300.0, 300.0))


def test_the_three_named_effects_are_registered():
    assert {"gravity_sag", "backlash", "servo_nonlinearity"} <= set(fx.REGISTRY)


@pytest.mark.parametrize("name", ["gravity_sag", "backlash", "servo_nonlinearity"])
def test_an_effect_at_its_initial_values_changes_nothing(name):
    eff = fx.REGISTRY[name](_ctx())
    s = eff.settings(kin.ArmParams.from_vector(jnp.array([0, 0, 200, 200, 1.5e-3, 1.5e-3,
                                                          -2.0, -1.0])),
                     np.array([[1400.0, 1500.0], [1600.0, 1550.0]]))
    if s is not None:
        eff = replace(eff, setting=jnp.asarray(s[0]))
    theta = jnp.array([[0.3, 1.2], [1.1, -0.4]])
    params = kin.ArmParams.from_vector(jnp.array([0, 0, 200, 200, 1.5e-3, 1.5e-3, 0, 0.0]))
    out = eff.apply(params, jnp.asarray(eff.initial()), jnp.full((2, 2), 1500.0), theta)
    np.testing.assert_allclose(out, theta, atol=0)
    assert len(eff.param_names()) == len(eff.scales()) == len(eff.initial())


def test_gravity_sag_deflects_towards_the_gravity_torque():
    """A level arm pointing right under gravity (0, -1) sags clockwise (negative angles)."""
    eff = fx.REGISTRY["gravity_sag"](_ctx())
    params = kin.ArmParams.from_vector(jnp.array([0, 0, 200, 150, 1e-3, 1e-3, 0, 0.0]))
    out = eff.apply(params, jnp.array([0.01, 0.005, 0.02]), None, jnp.array([0.0, 0.0]))
    assert out[0] < 0 and out[1] < 0
    # Small deflections: to first order the sum of the coefficients (tolerance: the pose
    # moves by 0.015 rad, so the torque changes by 1 - cos(0.015) ~ 1e-4 of itself).
    np.testing.assert_allclose(out, [-0.015, -0.02], rtol=1e-3)


def test_gravity_sag_magnitude_is_the_sag_of_a_straight_level_arm():
    eff = fx.REGISTRY["gravity_sag"](_ctx())
    params = kin.ArmParams.from_vector(jnp.array([0, 0, 200, 150, 1e-3, 1e-3, 0, 0.0]))
    rep = eff.magnitude_report(params, np.array([0.01, 0.002, 0.004]), np.eye(11) * 1e-8)
    assert rep["values"]["sag_full_reach_mm"]["value"] == pytest.approx(350 * 0.012 + 150 * 0.004)
    assert rep["values"]["sag_full_reach_mm"]["se"] > 0
    assert "sag at full reach" in rep["text"]


def _planar_params(shoulder_offset: float) -> kin.ArmParams:
    return kin.ArmParams.from_vector(jnp.array([20.0, -10.0, 180.0, 150.0, 1.2e-3, -1.1e-3,
                                                shoulder_offset, 2.4]))


def _compliant_planar_chain(params: kin.ArmParams, sag_steps: int = 1
                            ) -> tuple[kin.Robot, np.ndarray, jax.Array]:
    """The planar arm as a chain under gravity (0, -1), its links' masses along them (first
    moments h1 = m1 a1, h2 = m2 a2) on soft joints (deflections of 0.01-0.03 rad, where the
    torque iteration matters): the robot, its parameter vector, and the planar
    ``gravity_sag``'s terms for the same arm, c11 = k1 g (h1 + m2 L1), c12 = k1 g h2,
    c22 = k2 g h2."""
    m1, m2, a1, a2 = 0.4, 0.25, 90.0, 70.0  # kg, mm (centres of mass along the links)
    k1, k2 = 2e-5, 3e-5  # rad per N mm
    robot = kin.Robot({"arm": kin.planar_chain("arm", params)}, dim=2,
                      gravity=np.array([0.0, -1.0, 0.0]), sag_steps=sag_steps)
    x = robot.layout.nominal.copy()
    x[robot.layout.slices["arm", "compliance"]] = [k1, k2]
    x[robot.layout.slices["arm", "links"]] = [m1, m1 * a1, 0, 0, m2, m2 * a2, 0, 0]
    g = G_N_PER_KG
    c = jnp.array([k1 * g * (m1 * a1 + m2 * params.links[0]), k1 * g * m2 * a2,
                   k2 * g * m2 * a2])
    return robot, x, c


@pytest.mark.parametrize("steps", [1, 3])
def test_gravity_sag_is_joint_compliance_on_the_planar_chain(steps):
    """The planar ``gravity_sag`` is the chain effect ``joint_compliance`` on a two-link arm in
    a vertical plane: links with their masses along them (first moments h1, h2; the forearm's
    mass m2 also at the elbow's lever L1 from the shoulder) and joint compliances k1, k2 (rad
    per N mm) give c11 = k1 g (h1 + m2 L1), c12 = k1 g h2, c22 = k2 g h2, and the chain's
    compliance group on ``kinematics.planar_chain`` then deflects every pose as the planar
    effect does. ``steps``: the planar effect's torque iterations against the chain's
    ``sag_steps`` (one step each; and the planar default, three). Tolerance 1e-12 rad: the
    same arithmetic in another order."""
    params = _planar_params(shoulder_offset=-1.9)
    robot, x, c = _compliant_planar_chain(params, steps)
    u = np.stack(np.meshgrid(np.linspace(700, 2300, 7), np.linspace(800, 2200, 7)),
                 -1).reshape(-1, 2)
    theta = kin.servo(params, jnp.asarray(u))
    sag = fx.GravitySag(_ctx())
    planar = sag.apply(params, c, jnp.asarray(u), theta) if steps == sag.ITERATIONS else \
        theta + sag._deflection(c, theta)
    defl = np.asarray(robot.deflections(jnp.asarray(x), "arm", jnp.asarray(u)))
    assert np.abs(defl).max() > 0.01 and np.all(defl[:, 2] == 0)  # the tool has no joint
    np.testing.assert_allclose(defl[:, :2], np.asarray(planar - theta), atol=1e-12)
    # the name of the chain effect is accepted for a planar rig, as its planar instance
    assert fx.resolve_effects(["joint_compliance", "gravity_sag"]) == ["gravity_sag"]


def test_backlash_takes_the_chain_plays_sides_on_the_planar_chain():
    """The planar ``backlash`` with mass position rho = c12 / (c11 + c12) takes, away from
    where a torque changes sign, the side the chains' play takes on ``kinematics.planar_chain``
    (its fitted deflection's side): the same half play on the same side. Only the smoothing
    near the sign change differs (planar: 0.05 of the lever signature; chain: 1e-4 rad of
    deflection), so poses within that of the line are left out. Tolerance 1e-9 rad: both
    steps are saturated there to better than that."""
    # the shoulder swings through the vertical, so both joints' torques change sign
    params = _planar_params(shoulder_offset=-0.3)
    robot, x, c = _compliant_planar_chain(params)
    play = np.array([0.004, 0.006])
    with_play = x.copy()
    # the group's last entry is the chain's stick deflection, which acts on recorded
    # approach sides only (none here)
    with_play[[i for i, p in enumerate(robot.layout.params) if p.name.endswith(".play")]] = play
    u = np.stack(np.meshgrid(np.linspace(600, 2400, 13), np.linspace(600, 2400, 13)),
                 -1).reshape(-1, 2)
    chain_side = np.asarray(robot.deflections(jnp.asarray(with_play), "arm", jnp.asarray(u))
                            - robot.deflections(jnp.asarray(x), "arm", jnp.asarray(u)))[:, :2]
    rho = float(c[1] / (c[0] + c[1]))
    eff = fx.Backlash(_ctx(), jnp.array([rho]))
    theta = kin.servo(params, jnp.asarray(u))
    planar_side = np.asarray(eff.apply(params, jnp.asarray(play), jnp.asarray(u), theta)
                             - theta)
    s1, s12 = (np.asarray(v) for v in fx.lever_signatures(theta, (0.0, -1.0)))
    clear = (np.abs((1 - rho) * s1 + rho * s12) > 0.4) & (np.abs(s12) > 0.4)
    assert clear.sum() >= 40
    assert all({-1.0, 1.0} <= set(np.sign(planar_side[clear, j])) for j in (0, 1))
    np.testing.assert_allclose(chain_side[clear], planar_side[clear], atol=1e-9)


def test_every_chain_effect_is_a_planar_effect_or_says_why_not():
    """A chain effect's name on a planar rig is either its planar instance or a reason: a new
    chain effect must be placed in one of them, not left to a bare 'unknown effect'."""
    from bayesrob.diagnose.groups import CHAIN_EFFECTS

    for name in CHAIN_EFFECTS:
        assert (name in fx.REGISTRY) + (name in fx.ALIASES) + (name in fx.CHAIN_ONLY) == 1, name
    assert set(fx.ALIASES.values()) <= set(fx.REGISTRY)


def test_chain_only_effects_are_a_one_line_error_for_planar_rigs():
    for name, why in (("lateral_compliance", "no torque across"),
                      ("encoder_error", "servo_nonlinearity")):
        with pytest.raises(ValueError, match=why) as err:
            fx.resolve_effects(["backlash", name])
        assert len(str(err.value).splitlines()) == 1
    with pytest.raises(ValueError, match="unknown effect 'droop'"):
        fx.resolve_effects(["droop"])


def test_backlash_keeps_one_setting_per_sign_pattern():
    eff = fx.REGISTRY["backlash"](_ctx())
    params = kin.ArmParams.from_vector(jnp.array([0, 0, 200, 200, 1.5e-3, 1.5e-3, -1.0, -3.0]))
    u = np.stack(np.meshgrid(np.linspace(1100, 1900, 5), np.linspace(1100, 1900, 5)),
                 -1).reshape(-1, 2)
    settings = eff.settings(params, u)
    theta = kin.servo(params, jnp.asarray(u))
    patterns = {np.asarray(replace(eff, setting=jnp.asarray(s)).signs(theta)).tobytes()
                for s in settings}
    assert len(patterns) == len(settings) <= len(fx.Backlash.RHO_GRID)


@dataclass(frozen=True)
class _Droop(fx.Effect):
    """A test effect: the shoulder droops by a constant times its own angle squared."""

    name: ClassVar[str] = "droop_for_test"

    def param_names(self):
        return ("k",)

    def scales(self):
        return np.array([0.01])

    def apply(self, params, extra, u, theta):
        return theta.at[..., 0].add(extra[0] * theta[..., 0] ** 2)


def test_a_new_effect_is_one_registered_class(clean_rig_dir):
    fx.register(_Droop)
    try:
        rig = load_rig(clean_rig_dir)
        diag = diagnose(rig, ["droop_for_test"])
        assert diag.candidates == ["droop_for_test"]
        assert [s["effect"] for s in diag.rounds[0]] == ["droop_for_test"]
        # Its Jacobian comes from JAX like every other effect's.
        ev = evaluate_arm(ArmData.from_rig(rig, "top"), ("droop_for_test",))
        assert np.all(np.isfinite(ev.cov))
    finally:
        fx.REGISTRY.pop("droop_for_test")


def test_registering_a_second_class_under_a_taken_name_fails():
    @dataclass(frozen=True)
    class Other(_Droop):
        name: ClassVar[str] = "gravity_sag"

    with pytest.raises(ValueError, match="already registered"):
        fx.register(Other)


# ------------------------------------------------------------------------------ pieces


def test_regions_and_neighbours_of_a_grid():
    pts = np.array([(x, y) for y in (3.0, 2.0, 1.0, 0.0) for x in (0.0, 1.0, 2.0, 3.0)])
    regions = workspace_regions(pts)
    assert regions[0] == "upper-left" and regions[-1] == "lower-right"
    pairs = neighbour_pairs(pts)
    assert len(pairs) == 24  # 4 x 3 horizontal + 3 x 4 vertical


def test_base_model_matches_the_calibration(clean_rig_dir):
    """The diagnosis's base fit is the geometric calibration (same data, same model)."""
    from bayesrob.calibrate.arms import calibrate_arms

    rig = load_rig(clean_rig_dir)
    ev = evaluate_arm(ArmData.from_rig(rig, "bottom"), ())
    cal = calibrate_arms(rig)["bottom"]
    # Tolerance: both are least-squares optima of the same residuals; they differ by the
    # solvers' stopping rules, far below a micrometre at the end point.
    assert np.mean(ev.train_errors) == pytest.approx(cal.train_error_mm, abs=1e-4)


def test_decision_rule_text_and_logic():
    """One rule for every robot: the paired error drop's z decides, the largest drop per
    added parameter is named, a pair also beats each member alone and clears the guard."""
    rule = DecisionRule()
    s = {"arms": ["top"], "z": 2.5, "drop_per_parameter_mm": 0.05, "elpd_diff": 10.0,
         "parameters": 3}
    assert rule.passes(s)
    assert not rule.passes({**s, "z": 1.9})
    assert not rule.passes({**s, "arms": []})
    # validation and holdout errors report only: a worse validation error does not stop it
    assert rule.passes({**s, "heldout_error_before_mm": 1.0, "heldout_error_after_mm": 1.1})
    assert "validation and holdout rows only report" in rule.text()
    # the parameter guard: max(4, 1 nat per added parameter), deciding for pairs
    assert rule.threshold(2) == 4 and rule.threshold(20) == 20
    assert rule.guard_passes(s) and not rule.guard_passes({**s, "parameters": 20})
    assert rule.pair_passes(s, [2.1, 3.0])
    assert not rule.pair_passes(s, [2.1, 1.9])  # one member alone does as well
    assert not rule.pair_passes({**s, "parameters": 17}, [3.0, 3.0])  # 10 nats < 17
    assert not rule.pair_passes({**s, "z": 1.0}, [3.0, 3.0])
    # of those that pass, the largest drop per added parameter is named, not the largest gain
    assert rule.best([{**s, "effect": "a", "elpd_diff": 30.0, "drop_per_parameter_mm": 0.01},
                      {**s, "effect": "b"}])["effect"] == "b"
    # the gain and its standard error are arviz's paired ones: the summed pointwise
    # difference and sqrt(n) times its sd (to rounding)
    rng = np.random.default_rng(1)
    before, after = rng.normal(size=40), rng.normal(0.3, 1.0, size=40)
    d = after - before
    assert elpd_diff(before, after) == pytest.approx((d.sum(), np.sqrt(40 * d.var())),
                                                     rel=1e-12)
    # the paired z: mean drop over its standard error
    e = before - after
    assert paired_z(before, after) == pytest.approx(e.mean() / (e.std(ddof=1) / np.sqrt(40)),
                                                    rel=1e-12)


def _arm_eval(name: str, cv_lpd: np.ndarray) -> ArmEval:
    n = len(cv_lpd)
    z = np.zeros(n)
    return ArmEval(arm=name, effects=(), v=np.zeros(8), settings=(), cov=np.eye(8),
                   sigma_mm=0.3, dof=1, train_errors=z, train_lpd=cv_lpd, val_errors=z[:0],
                   val_lpd=z[:0], cv_errors=np.ones(n), cv_lpd=cv_lpd,
                   resid_train=np.zeros((n, 2)), resid_val=np.zeros((0, 2)))


def test_choosing_the_arms_an_effect_helps_does_not_flatter_its_score():
    """Six arms, and a candidate that changes each arm's pointwise log density by pure noise
    (mean zero). Giving it to the arms it happens to help, and scoring those same rows, makes
    a gain out of nothing; choosing the arms on one half of the rows and scoring the other
    half does not. Seeded; over 200 such candidates the in-sample choice gains 4.6 nats on
    average (sd 2.8; in expectation 6 x 2 x 0.40 = 4.8, the positive parts of six N(0, 2)
    gains) and the cross-fitted one 0.04 (sd 3.6): the bounds below are six and four
    standard errors of the mean (0.2 and 0.26 nats) away."""
    rng = np.random.default_rng(7)
    crossfit, naive = [], []
    for trial in range(200):
        cur = {f"a{i}": _arm_eval(f"a{i}", rng.normal(-1.0, 0.1, 16)) for i in range(6)}
        cand = {a: _arm_eval(a, e.cv_lpd + rng.normal(0.0, 0.5, 16)) for a, e in cur.items()}
        cv, _ = _crossfit(cur, cand, seed=trial)
        base = np.concatenate([e.cv_lpd for e in cur.values()])
        crossfit.append(np.sum(cv - base))
        helped = [a for a in cur if np.sum(cand[a].cv_lpd - cur[a].cv_lpd) > 0]
        naive.append(sum(np.sum(cand[a].cv_lpd - cur[a].cv_lpd) for a in helped))
    assert np.mean(naive) > 3.0
    assert abs(np.mean(crossfit)) < 1.0


# ------------------------------------------------------------------------------ rigs


REPRESENTATIVE = {
    # name: (how the rig is made, the effects that must be named)
    "clean_simulator": (None, []),
    "default_rig": ("default", ["backlash", "gravity_sag"]),
    "sag_generator": (Case("generator", "paper_like", ("gravity_sag",), 4, 31), ["gravity_sag"]),
    "backlash_hysteresis": (Case("generator", "paper_like", ("backlash",), 4, 31), ["backlash"]),
    "tanh_servo": (Case("generator", "paper_like", ("servo_nonlinearity",), 4, 31),
                   ["servo_nonlinearity"]),
}


@pytest.fixture(scope="session")
def diagnoses(clean_rig_dir, tmp_path_factory) -> dict:
    out = {}
    for name, (how, _) in REPRESENTATIVE.items():
        if how is None:
            path = clean_rig_dir
        elif how == "default":
            path = default_rig_dir()
        else:
            path = make_rig(how, tmp_path_factory.mktemp(name))
        out[name] = diagnose(load_rig(path))
    return out


# Sag on hardening springs (stiffness doubling by 0.1 rad, as the generator makes it since the
# proof on report rigs) is more than the linear-compliance candidate can take: its misfit is
# then named as backlash too (on this rig backlash passes first, +15.0 +- 5.4 nats, and the
# sag after it). A known miss, kept visible.
HARDENING_MISS = pytest.mark.xfail(strict=True, raises=AssertionError,
                                   reason="hardening springs: the linear sag candidate leaves a "
                                   "misfit that backlash takes")


@pytest.mark.parametrize("name", [pytest.param(n, marks=HARDENING_MISS)
                                  if n == "sag_generator" else n for n in REPRESENTATIVE])
def test_names_exactly_the_hidden_effects(diagnoses, name):
    expected = REPRESENTATIVE[name][1]
    assert sorted(diagnoses[name].effects) == sorted(expected)


@pytest.mark.parametrize("name", [n for n, (_, e) in REPRESENTATIVE.items() if e])
def test_naming_the_effects_wins_back_a_clear_part_of_the_held_out_gap(diagnoses, name):
    """Each step already passed the decision rule (its cross-validated errors down by more
    than 2 se) or it would not be a step, so re-checking that says nothing. What the rule does not
    require: a hidden effect of the size used here costs 0.3-1 mm, and naming it must win
    back a clear part of that (20%, far beyond the 2-3% run-to-run wobble of held-out noise)."""
    doc = diagnoses[name].to_json()
    assert doc["final_heldout_error_mm"] < 0.8 * doc["baseline_heldout_error_mm"]


def test_the_planar_rounds_decide_by_the_one_rule(diagnoses):
    """Every single candidate of every round passes exactly when its cross-validated errors'
    paired z exceeds the rule's (and it goes to some arm), and the effect a round names is
    the passing one with the largest drop per added parameter: the planar refits decide as
    the chain engine does, whatever the elpd gain says."""
    checked = 0
    for diag in diagnoses.values():
        doc = diag.to_json()
        for k, scores in enumerate(doc["rounds"]):
            if any("pair" in s for s in scores):
                break  # a round of pairs names two steps at once
            for s in scores:
                assert s["passes"] == (bool(s["arms"]) and s["z"] > Z), s
                checked += 1
            passing = [s for s in scores if s["passes"]]
            if passing:  # the k-th round named the k-th step
                best = max(passing, key=lambda s: s["drop_per_parameter_mm"])
                assert doc["steps"][k]["effect"] == best["effect"]
    assert checked >= 10  # the five rigs' rounds hold this many single candidates at least


def test_json_contract(diagnoses):
    for diag in diagnoses.values():
        doc = diag.to_json()
        assert CONTRACT_KEYS <= set(doc)
        assert doc["effects"] == [s["effect"] for s in doc["steps"]]
        for step in doc["steps"]:
            assert STEP_KEYS <= set(step)
            assert set(step["arms"]) <= set(diag.arms) and step["arms"]
        json.dumps(doc)  # plain JSON types only
    clean = diagnoses["clean_simulator"].to_json()
    assert clean["effects"] == [] and clean["steps"] == []
    assert clean["final_heldout_error_mm"] == clean["baseline_heldout_error_mm"]


def test_clean_residuals_look_like_noise(diagnoses):
    """On a rig with no hidden effect the residual tests see noise.

    Tolerance: each p value is uniform under noise; 0.001 leaves a 1-in-1000 chance per test
    of a false alarm on this fixed seed (the seed is fixed, so the test is deterministic).
    """
    for arm, t in diagnoses["clean_simulator"].tests_before.items():
        assert t["lack_of_fit"]["p_value"] > 0.001, arm
        assert t["morans_i"]["p_value"] > 0.001, arm
        for name, st in t["score_tests"].items():
            assert st["p_value"] > 0.001, (arm, name)


def test_hidden_sag_shows_in_the_residual_tests(diagnoses):
    """Before any effect is added, the structure is there to see (p < 0.001 with 16 points)."""
    tests = diagnoses["sag_generator"].tests_before
    assert all(t["lack_of_fit"]["p_value"] < 1e-3 for t in tests.values())
    assert any(t["score_tests"]["gravity_sag"]["p_value"] < 1e-3 for t in tests.values())


def test_default_rig_magnitudes_are_physical(diagnoses):
    doc = diagnoses["default_rig"].to_json()
    steps = {s["effect"]: s for s in doc["steps"]}
    # The bottom arm's shoulder torque changes sign in the workspace: its play is resolved.
    bl = steps["backlash"]["magnitudes"]["bottom"]["values"]["shoulder_play_deg"]
    assert 0.1 < abs(bl["value"]) < 2.0 and bl["se"] < abs(bl["value"]) / 2
    sag = steps["gravity_sag"]["magnitudes"]
    assert all(m["values"]["sag_full_reach_mm"]["value"] > 0 for m in sag.values())


# ------------------------------------------------------------------------------ command


def test_command_writes_json_and_figures(clean_rig_dir, tmp_path, capsys):
    from bayesrob.cli import main

    out, report = tmp_path / "d.json", tmp_path / "report"
    code = main(["diagnose", str(clean_rig_dir), "--json", str(out), "--report", str(report),
                 "--effects", "gravity_sag,backlash"])
    assert code == 0
    doc = json.loads(out.read_text())
    assert CONTRACT_KEYS <= set(doc) and doc["candidates"] == ["gravity_sag", "backlash"]
    printed = capsys.readouterr().out
    assert "named effects: none" in printed and "round 1" in printed
    pngs = sorted(p.name for p in report.glob("*.png"))
    assert pngs == ["gap_per_step.png", "residuals_bottom.png", "residuals_top.png"]
    assert all((report / p).stat().st_size > 10_000 for p in pngs)
    # the library's result says what the command wrote (NaN included, hence compared as text)
    lib = diagnose(load_rig(clean_rig_dir), ["gravity_sag", "backlash"]).to_dict()
    assert (json.dumps(json.loads(json.dumps(lib)), sort_keys=True)
            == json.dumps(doc, sort_keys=True))


def test_command_rejects_an_unknown_effect(clean_rig_dir, capsys):
    from bayesrob.cli import main

    with pytest.raises(SystemExit) as exc:
        main(["diagnose", str(clean_rig_dir), "--effects", "friction"])
    assert exc.value.code == 2
    assert "unknown effect 'friction'" in capsys.readouterr().err


def test_figures_are_figures(diagnoses):
    from matplotlib.figure import Figure

    from bayesrob.report.plots.diagnosis import gap_figure, residual_quiver_figure

    diag = diagnoses["default_rig"]
    assert isinstance(gap_figure(diag), Figure)
    fig = residual_quiver_figure(diag, "bottom")
    assert len(fig.axes) == 3  # before, after, colour bar


def test_jacobian_of_every_model_is_finite(clean_rig_dir):
    from bayesrob.diagnose.refits import model_fns

    rig = load_rig(clean_rig_dir)
    data = ArmData.from_rig(rig, "top")
    base = evaluate_arm(data, ())
    for names in (("gravity_sag",), ("backlash",), ("servo_nonlinearity",)):
        fns = model_fns(names)
        v = np.concatenate([base.v, *fns.initial_extra])
        settings = tuple(None if n != "backlash" else jnp.array([0.3]) for n in names)
        r, J = fns.residuals(v, data.ctx_array, settings, jnp.asarray(data.u),
                             jnp.asarray(data.d), jnp.ones(len(data.u)))
        assert np.all(np.isfinite(J)) and J.shape == (r.size, fns.n_params)
    assert jax.config.jax_enable_x64


def test_three_arm_rig_from_another_tool(handmade_rig_dir, tmp_path):
    """Other arm names, three arms, no repeated commands: runs, and names nothing on data
    that follow the nominal model."""
    from bayesrob.report.outputs import write_diagnosis_report

    diag = diagnose(load_rig(handmade_rig_dir))
    assert diag.arms == ["left", "right", "middle"] and diag.effects == []
    assert "lack_of_fit" not in diag.tests_before["left"]  # no repeats to test against
    assert len(write_diagnosis_report(diag, tmp_path)) == 4


def test_rig_without_validation_rows(rig_copy):
    """Without validation rows (which only report) the rig is still diagnosed, by its
    cross-validated errors."""
    path = rig_copy / "measurements.csv"
    lines = path.read_text().splitlines()
    path.write_text("\n".join(ln for ln in lines if ",validation," not in ln) + "\n")
    doc = diagnose(load_rig(rig_copy), ["gravity_sag"]).to_json()
    assert doc["baseline_heldout_error_mm"] is None and doc["effects"] == []
    assert doc["baseline_cv_error_mm"] > 0


def test_default_rig_magnitudes_match_the_simulators_truth(diagnoses):
    """The fitted sizes, read against truth.toml (which the diagnosis never sees).

    Tolerances: the candidates' forms are not the simulator's (a smooth step for a dead
    band, three compliance terms for point masses on springs), so the play is asked to be
    within a factor of two, and the level-arm elbow sag within three standard errors.
    """
    import math

    from bayesrob.sim.physics import G_N_PER_KG
    from bayesrob.sim.truth import Truth

    truth = Truth.from_toml(default_rig_dir() / "truth.toml")
    doc = diagnoses["default_rig"].to_json()
    for name, arm in truth.arms.items():
        mags = doc["arms"][name]["magnitudes"]
        play = abs(mags["backlash"]["values"]["shoulder_play_deg"]["value"])
        assert 0.5 < play / math.degrees(arm.backlash_rad[0]) < 2.0, name
        l2 = arm.links[1]
        elbow_torque = G_N_PER_KG * (arm.link_mass_kg[1] * l2 / 2 + arm.end_mass_kg * l2)
        expected = math.degrees(elbow_torque / arm.stiffness_nmm_per_rad[1])
        fit = mags["gravity_sag"]["values"]["elbow_deflection_deg"]
        assert abs(fit["value"] - expected) < 3 * fit["se"], (name, fit, expected)


# ------------------------------------------------------------------------------ the studies


def _row(truth: str, named: str, strength: float, before: float = 1.0, after: float = 1.0,
         clean: float = 1.0, **extra) -> dict:
    case = {"source": "generator", "geometry": "arm6", "effects": truth.split("+"), "seed": 1,
            "scale": 1.0}
    return {"case": case, "truth": truth, "named": named, "order": extra.pop("order", []),
            "strength": strength, "baseline_holdout_error_mm": before,
            "final_holdout_error_mm": after, "clean_holdout_error_mm": clean, **extra}


def test_the_sweeps_counts_and_tables_from_per_rig_rows():
    """The proof's figures on hand-made rows: a clean rig with a false alarm, a strong rig
    named right, a strong one named wrong that its rival accounts for, a weak one missed.
    The gap ratio pools the named rigs' error above the clean twin's: (0.2 + 0.5) over
    (1.0 + 1.0)."""
    from bayesrob.validation.diagnosis import sweep_details, sweep_figures, tables
    from bayesrob.validation.diagnosis_chain import rival_figures

    rows = [_row("none", "backlash", 1.0),
            _row("joint_compliance", "joint_compliance", 3.0, 2.0, 1.2, 1.0),
            _row("lateral_compliance", "joint_compliance", 2.0, 2.0, 1.5, 1.0,
                 order=["joint_compliance"], rivals={"joint_compliance": ["lateral_compliance"]}),
            _row("encoder_error", "none", 1.2, 1.2, 1.2, 1.0)]
    f = sweep_figures(rows)
    assert (f["rigs"], f["clean"], f["false_alarms"], f["named"]) == (4, 1, 1, 2)
    assert (f["strong"], f["strong_right"], f["strong_exact_share"]) == (2, 1, 0.5)
    assert f["gap_ratio"] == pytest.approx(0.7 / 2.0)
    assert f["holdout_ratio"] == pytest.approx((0.6 + 0.75) / 2)
    r = rival_figures(rows)
    assert r["strong_right_up_to_rivals"] == 2 and r["lateral.right_up_to_rivals_share"] == 1.0
    details = sweep_details(rows, [(), ("joint_compliance",), ("lateral_compliance",),
                                   ("encoder_error",)])
    assert details["confusion"]["lateral_compliance"] == {"joint_compliance": 1}
    entry = {"figures": f, "details": details, "checks": {"false_alarms": "fail"}}
    out = tables(entry)
    # columns: the sweep's truths in their order, then any other set named
    assert out["confusion"].splitlines()[:3] == [
        "| hidden \\ named | none | joint_compliance | backlash | correct |",
        "|---|---|---|---|---|", "| none | 0 | 0 | 1 | 0/1 |"]
    assert "**1 of 1: missed**" in out["targets"]
    assert out["readme"].splitlines()[-1] == "| planar, generator | 4 | 1 | 1/2 | 1/1 |"
