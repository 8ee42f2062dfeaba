"""Diagnosis of URDF/DH chains: the simulator's 6-joint arm with joints giving way under
gravity, and without."""

from __future__ import annotations

import hashlib
import inspect
import json

import numpy as np
import pytest

from bayesrob.cli import main
from bayesrob.data.rig import load_rig
from bayesrob.diagnose.groups import (
    DiagnosisError,
    diagnose_groups,
    parse_published,
)
from bayesrob.diagnose.rule import Z
from bayesrob.report.tables import format_group_diagnosis
from bayesrob.robot.effects import resolve_effects
from bayesrob.sim.physics import play_offsets
from bayesrob.sim.rigs import simulate_arm6_rig
from bayesrob.sim.truth import Arm6Truth

COMPLIANT = {"compliance": True}


@pytest.fixture(scope="module")
def compliant_rig(tmp_path_factory):
    """The compliant arm (seed 11), simulated once for the module: the naming test's first
    case, the residual figure and the torque-step ladder all diagnose it. Read it, never write
    to it (diagnose writes its JSON and report elsewhere)."""
    return simulate_arm6_rig(tmp_path_factory.mktemp("compliant"),
                              Arm6Truth(seed=11, **COMPLIANT))


@pytest.fixture(scope="module")
def _fits_done() -> dict:
    return {}


@pytest.fixture
def shared_fits(_fits_done, monkeypatch):
    """``diagnose.groups.calibrate``, each distinct fit computed once per module.

    Three tests diagnose the same compliant rig, through the command and through the library,
    and so ask for the same least-squares fits (the geometric and joint-compliance selection
    fits and ladder steps): a fit asked again with the same rows (the rig's directory and a
    digest of its sets, commands and observed points) and the same arguments (groups,
    polish, max_nfev, start, sag_steps, masses) is the one already computed, which
    calibrate, deterministic, would compute again. A fit asked with any other argument
    (a wrong ``sag_steps``, another start, another split) is computed afresh, so what each
    test asserts about which fit the diagnosis makes is checked as before. Returns the
    wrapper (call it for a test's own fits)."""
    import bayesrob.diagnose.groups as cd

    real = cd.calibrate
    signature = inspect.signature(real)

    def fits(*args, **kwargs):
        bound = signature.bind(*args, **kwargs)
        bound.apply_defaults()
        a = bound.arguments
        if a["progress"] is not None:  # a callback to call: not a result to share
            return real(*args, **kwargs)
        meas = a["rig"].measurements
        rows = hashlib.sha256()
        for part in (meas.config, meas.set, meas.observed,
                     *(meas.commands[k] for k in sorted(meas.commands))):
            rows.update(np.asarray(part).astype(str if part.dtype.kind in "OU" else float)
                        .tobytes())
        start = None if a["start"] is None else np.asarray(a["start"], float).tobytes()
        key = (str(a["rig"].path), rows.hexdigest(), tuple(a["groups"]), a["polish"],
               a["max_nfev"], start, a["sag_steps"], a["masses"])
        if key not in _fits_done:
            _fits_done[key] = real(*args, **kwargs)
        return _fits_done[key]

    monkeypatch.setattr(cd, "calibrate", fits)
    return fits


@pytest.mark.parametrize("physics,named", [
    ({"compliance": True}, ["joint_compliance"]),
    ({"encoder_eccentricity": 1e-3}, ["encoder_error"]),
    ({"compliance": True, "encoder_eccentricity": 1e-3}, ["joint_compliance", "encoder_error"]),
    ({}, [])])
def test_diagnose_names_what_the_arm_has_and_nothing_else(tmp_path, capsys, physics, named,
                                                        request, shared_fits):
    """Seed 11 (the threshold is the usual 2 standard errors; the per-parameter choice was
    settled on this seed, and named every case of seeds 12 and 13 right too): the compliant arm
    gets joint compliance, and neither lateral bending, which the simulator does not have, nor
    the encoder sinusoid, which passes alone in round 1 by taking up part of the shoulder's
    sag; the arm with eccentric encoders (1e-3 of the disk radius: about 1 mrad) gets the
    encoder terms; with both, both; the clean arm nothing. The ladder is reported on the
    validation rows. The clean arm's run shows its progress, which ends at its last fit (the
    bar's total is an upper bound until the selection stops). The compliant arm is the
    module's (``compliant_rig``), whose fits the other tests of it share (``shared_fits``)."""
    rig = (request.getfixturevalue("compliant_rig") if physics == COMPLIANT
           else simulate_arm6_rig(tmp_path / "r", Arm6Truth(seed=11, **physics)))
    out = tmp_path / "d.json"
    assert main(["diagnose", str(rig), "--json", str(out), "--report", str(tmp_path / "rep"),
                 *(["--no-progress"] if named else []),
                 "--published", "geometric=3.0,+joint_compliance=0.3"]) == 0
    printed = capsys.readouterr()
    if not named:
        last = [ln for ln in printed.err.splitlines() if ln.startswith("diagnose:")][-1]
        assert "(100%)" in last and "done" in last, last
    doc = json.loads(out.read_text())
    assert doc["effects"] == named
    # each naming round compares the named effect with every other candidate that passed;
    # those within Z standard errors of it are its rivals
    for r, effect in enumerate(named):
        others = [s for s in doc["rounds"][r] if s["passes"] and s["effect"] != effect]
        assert all("z_vs_named" in s for s in others)
        assert doc["steps"][r]["rivals"] == [s["effect"] for s in others
                                             if abs(s["z_vs_named"]) <= Z]
    assert (tmp_path / "rep" / "ladder.png").stat().st_size > 5_000
    assert (tmp_path / "rep" / "residuals.png").stat().st_size > 20_000
    for key in ("steps", "baseline_heldout_error_mm", "final_heldout_error_mm"):
        assert key in doc
    if named:
        step = doc["steps"][-1]
        assert step["heldout_error_mm"] < 0.5 * doc["baseline_heldout_error_mm"]
        assert step["heldout_error_sd_mm"] > 0 and step["heldout_error_max_mm"] > 0
    else:
        assert doc["final_heldout_error_mm"] == doc["baseline_heldout_error_mm"]
    assert "ladder on the validation rows" in printed.out


def test_effects_are_resolved_per_robot_and_unknown_ones_refused_in_one_line(compliant_rig):
    """Every effect has a chain model; a servo's curve is a default candidate only where the
    robot has a servo map (the arm6's columns are its joint values; the planar arms' are
    pulse widths), an encoder's error only where it has none, and each is tried when asked
    for."""
    from bayesrob.data.rig import default_rig_dir

    rig = load_rig(compliant_rig)
    planar = load_rig(default_rig_dir())
    assert resolve_effects(["gravity_sag"], chain=True) == ["joint_compliance"]  # planar alias
    assert resolve_effects(["backlash"], chain=True) == ["backlash"]
    assert resolve_effects(None, chain=True)[0] == "joint_compliance"
    assert not rig.robot.servo_mapped and planar.robot.servo_mapped
    assert "servo_nonlinearity" not in resolve_effects(None, chain=True, robot=rig.robot)
    assert "servo_nonlinearity" in resolve_effects(None, chain=True, robot=planar.robot)
    assert resolve_effects(["servo_nonlinearity"], chain=True, robot=rig.robot) == [
        "servo_nonlinearity"]
    assert "encoder_error" in resolve_effects(None, chain=True, robot=rig.robot)
    assert "encoder_error" not in resolve_effects(None, chain=True, robot=planar.robot)
    assert resolve_effects(["encoder_error"], chain=True, robot=planar.robot) == [
        "encoder_error"]
    assert "encoder_error" in resolve_effects(None, chain=True)  # no robot: every one
    with pytest.raises(DiagnosisError, match="'wobble' is not modelled for URDF/DH chains"):
        diagnose_groups(rig, ["wobble"])


def test_the_base_fits_a_servo_maps_gains_and_few_poses_are_scored_over_folds(compliant_rig):
    """The geometric calibration a diagnosis starts from takes the servo gains where the
    commands are pulse widths (the default rig's arms: 3.6 mm at the train rows without them,
    the paper's 1.2 with), and nothing more where they are joint values. A rig of 80 train
    poses is decided on one selection draw; the default rig's 32 on three disjoint folds of
    8 poses (20 scored at the least), the first the draw one fold would make."""
    from bayesrob.calibrate.least_squares import base_groups, calibrate
    from bayesrob.data.rig import default_rig_dir
    from bayesrob.diagnose.groups import MIN_SCORED_POSES, _folds

    arm6, planar = load_rig(compliant_rig), load_rig(default_rig_dir())
    assert base_groups(arm6.robot) == ("frames", "geometric")
    assert base_groups(planar.robot) == ("frames", "geometric", "servo")
    errs = [calibrate(planar, g).errors["train"]["all"]["mean_mm"]
            for g in (("frames", "geometric"), base_groups(planar.robot))]
    assert errs[1] < 0.5 * errs[0]
    assert len(_folds(arm6, 0)) == 1
    folds = _folds(planar, 0)
    chosen = [np.flatnonzero(f.measurements.set == "selection") for f in folds]
    assert [len(c) for c in chosen] == [8, 8, 8] and sum(map(len, chosen)) >= MIN_SCORED_POSES
    assert len(np.unique(np.concatenate(chosen))) == 24  # disjoint
    train = np.flatnonzero(planar.measurements.set == "train")
    assert all(np.isin(c, train).all() for c in chosen)
    rng = np.random.default_rng(0)
    first = rng.choice(np.unique(train.astype(str)), size=8, replace=False)
    assert sorted(chosen[0].astype(str)) == sorted(first)


def test_play_rests_on_the_gravity_side_or_where_it_was_approached_from():
    torque = np.array([[5000.0, -3000.0, 100.0, -100.0]] * 400)
    offsets = play_offsets(torque, 2e-3, 2000.0, np.random.default_rng(0))
    assert np.all(offsets[:, 0] == 1e-3) and np.all(offsets[:, 1] == -1e-3)
    weak = offsets[:, 2:]
    assert set(np.unique(weak)) == {-1e-3, 1e-3}
    assert 0.4 < np.mean(weak > 0) < 0.6  # either side, as approached (800 draws: sd 0.018)


def test_published_ladder_is_parsed_or_refused_in_one_line():
    assert parse_published("geometric=10.5, +joint_compliance=5.64,gravity_sag=5") == {
        "geometric": 10.5, "+joint_compliance": 5.0}
    for bad, message in (("geometric", "expected STEP=MM"), ("wobble=1", "expected STEP=MM"),
                         ("geometric=ten", "expected a number"), ("geometric=-1", ">= 0")):
        with pytest.raises(DiagnosisError, match=message):
            parse_published(bad)


def test_residual_figure_draws_every_validation_marker_on_two_planes(compliant_rig,
                                                                     shared_fits):
    """The report's residual arrows: one arrow per validation row, in the x-y and x-z
    planes, for the geometric and the final model, all on one magnification. On the
    module's compliant arm (seed 11), its fits shared (``shared_fits``)."""
    from bayesrob.report.plots.diagnosis import marker_residual_figure

    rig = load_rig(compliant_rig)
    diag = diagnose_groups(rig)
    assert list(diag.residuals) == ["geometric", "+ joint_compliance"]
    n = len(rig.rows(rig.robot.measured_arms()[0], "validation")[0])
    res = [r for by_arm in diag.residuals.values() for _, r in by_arm.values()]
    assert [r.shape for r in res] == [(n, 3), (n, 3)]
    # the final model's residuals are the ones its ladder step reports
    assert np.linalg.norm(res[1], axis=1).mean() == pytest.approx(
        diag.steps[-1]["heldout_error_mm"], rel=1e-9)
    fig = marker_residual_figure(diag.residuals, rig.name)
    quivers = [c for ax in fig.axes for c in ax.collections if hasattr(c, "U")]
    assert len(quivers) == 4 and all(len(q.U) == n for q in quivers)
    # panels in reading order: (geometric x-y, x-z), (final x-y, x-z)
    planes = [(0, 1), (0, 2)] * 2
    gains = [np.hypot(q.U, q.V).max() / np.linalg.norm(r[:, list(p)], axis=1).max()
             for q, r, p in zip(quivers, [res[0], res[0], res[1], res[1]], planes, strict=True)]
    assert np.ptp(gains) < 1e-9 * max(gains)


def test_play_is_simulated_for_a_single_arm6_only(tmp_path, capsys):
    for argv, message in (([], "--play-mrad, --poses and --linked are for --robot arm6"),
                          (["--robot", "arm6", "--linked"], "--play-mrad is for a single arm6")):
        assert main(["simulate", str(tmp_path / "r"), "--play-mrad", "2", *argv]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and message in err, err
    with pytest.raises(SystemExit) as exc:
        main(["simulate", str(tmp_path / "r"), "--robot", "arm6", "--play-mrad", "-1"])
    assert exc.value.code == 2 and "must be 0 or more" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()
    assert main(["simulate", str(tmp_path / "r"), "--robot", "arm6", "--compliance",
                 "--play-mrad", "2", "--poses", "4", "2", "2"]) == 0
    assert "play 2 mrad" in capsys.readouterr().out
    truth = (tmp_path / "r" / "truth.toml").read_text()
    assert "joint_play_rad = 0.002" in truth


def test_ladder_with_torque_steps_is_at_equilibrium_or_says_why_not(tmp_path, capsys,
                                                                   monkeypatch, compliant_rig,
                                                                   shared_fits):
    """``--sag-steps 6``: the compliant arm (seed 11; the simulator writes its rows at the
    torque equilibrium) gets its joint compliance fitted with six steps of the torques, and the
    fit is at equilibrium (a seventh step moves no train marker by more than the 0.01 mm
    threshold). The names are chosen with one step either way, so they are the one-step
    run's. Its validation error is within 10% of the one-step ladder's: both sit near the
    noise floor here (the simulated sag is a few mrad, where one step is a fair model), so
    10% bounds a real regression without asking the equilibrium to beat noise. With a
    threshold no fit can meet, the step falls back to one step and a note says why, whether
    the one-step ladder fit's sag already fails to settle (no equilibrium fit is tried) or
    the six-step fit ends off its equilibrium; either way the step is that one-step fit.

    The arm is the module's (``compliant_rig``) and each distinct fit is computed once
    (``shared_fits``): the one-step ladder, the command's run and the two fallbacks ask for
    the same geometric, one-step and six-step fits again; a fallback that asked for another
    fit than the one-step ladder's would be computed afresh and fail the 1e-9 comparison."""
    rig = compliant_rig
    one = diagnose_groups(load_rig(rig), ["joint_compliance"]).to_json()
    out = tmp_path / "d.json"
    assert main(["diagnose", str(rig), "--effects", "joint_compliance", "--sag-steps", "6",
                 "--json", str(out), "--no-progress"]) == 0
    assert "torques at equilibrium, 6 steps" in capsys.readouterr().out
    doc = json.loads(out.read_text())
    assert doc["effects"] == one["effects"] == ["joint_compliance"] and doc["sag_steps"] == 6
    step = doc["steps"][0]
    assert step["sag_steps"] == 6 and step["sag_next_step_mm"] <= 0.01
    assert one["steps"][0]["sag_steps"] == 1
    assert step["heldout_error_mm"] == pytest.approx(one["steps"][0]["heldout_error_mm"],
                                                     rel=0.1)
    import bayesrob.diagnose.groups as cd

    groups = ("frames", "geometric", "compliance")
    first = shared_fits(load_rig(rig), groups)
    # the one-step fit's sag does not settle (a threshold none can meet): no equilibrium fit
    monkeypatch.setattr(cd, "SAG_CONVERGED_MM", -1.0)
    asked: list[int] = []
    monkeypatch.setattr(cd, "calibrate", lambda *a, **k: asked.append(k.get("sag_steps", 1))
                        or shared_fits(*a, **k))
    notes: list[str] = []
    cal = cd._ladder_fit(load_rig(rig), groups, 6, notes)
    assert cal.robot.sag_steps == 1 and "does not settle in 6 steps" in notes[0], notes
    assert asked == [1]  # the six-step fit was not tried
    np.testing.assert_array_equal(cal.x, first.x)
    assert cal.errors["validation"]["all"]["mean_mm"] == pytest.approx(
        one["steps"][0]["heldout_error_mm"], abs=1e-9)
    # it settles, but the six-step fit does not reach its equilibrium: back to one step
    monkeypatch.setattr(cd, "sag_convergence", lambda *a: {"sag_next_step_mm": -2.0})
    notes = []
    cal = cd._ladder_fit(load_rig(rig), groups, 6, notes)
    assert cal.robot.sag_steps == 1 and "not at equilibrium after 6 steps" in notes[0], notes
    assert asked == [1, 1, 6]  # tried, and the step is the one-step fit
    np.testing.assert_array_equal(cal.x, first.x)


def test_torque_steps_are_refused_for_planar_rigs_in_one_line(capsys):
    assert main(["diagnose", "--sag-steps", "3"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--sag-steps is for URDF/DH rigs" in err, err


def test_the_report_says_which_candidates_the_selection_poses_cannot_tell_apart():
    """A candidate that passed beside the named one, with errors within Z standard errors
    of its, gets a line of its own, as does one clearly better with more parameters; one the
    named effect clearly beats does not."""
    row = {"parameters": 13, "selection_error_before_mm": 0.4, "passes": True,
           "elpd_diff": 40.0, "elpd_diff_se": 8.0, "guard_nats": 13.0, "guard_passes": True}
    doc = {"rig": "r", "rule": "rule", "rule_z": Z, "effects": ["joint_compliance"],
           "rounds": [[{**row, "effect": "joint_compliance", "selection_error_after_mm": 0.20,
                        "z": 5.0},
                       {**row, "effect": "lateral_compliance", "selection_error_after_mm": 0.19,
                        "z": 5.1, "z_vs_named": -1.5},
                       {**row, "effect": "encoder_error", "selection_error_after_mm": 0.3,
                        "z": 2.5, "z_vs_named": 4.0},
                       {**row, "effect": "backlash", "parameters": 30, "z": 6.0,
                        "selection_error_after_mm": 0.15, "z_vs_named": -3.0}]],
           "baseline": {"n_free": 76, "heldout_error_mm": 0.4, "heldout_error_sd_mm": 0.1,
                        "heldout_error_max_mm": 1.0},
           "steps": [{"effect": "joint_compliance", "rivals": ["lateral_compliance"],
                      "n_free": 89, "heldout_error_mm": 0.2, "heldout_error_sd_mm": 0.1,
                      "heldout_error_max_mm": 0.5}], "seconds": 1.0, "notes": []}
    text = format_group_diagnosis(doc)
    assert ("lateral_compliance fits the selection poses as well as joint_compliance (paired "
            "z -1.5") in text
    notes = [ln.strip() for ln in text.splitlines() if ln.startswith("  ")]
    assert len(notes) == 2 and not any(n.startswith("encoder_error") for n in notes), notes
    assert ("backlash leaves smaller errors than joint_compliance (paired z -3.0) with 30 "
            "parameters") in text


def test_a_candidate_with_nothing_identifiable_to_fit_never_passes():
    """On a planar rig gravity acts in the arms' plane, so lateral bending has no torque and
    the rank analysis leaves it no parameter: its selection errors move by rounding alone,
    whose paired z is noise (measured 2.3 on the default rig before this guard, naming an
    effect that changed nothing)."""
    from bayesrob.data.rig import default_rig_dir

    doc = diagnose_groups(load_rig(default_rig_dir()), ["lateral_compliance"]).to_json()
    (cand,) = doc["rounds"][0]
    assert cand["parameters"] == 0
    assert abs(cand["selection_error_after_mm"] - cand["selection_error_before_mm"]) < 1e-6
    assert not cand["passes"] and doc["effects"] == []


def test_the_chain_engine_on_a_planar_rig_reports_in_the_planar_words():
    """``bench_diagnose.py --engine groups``'s measure of one engine for every robot: a planar
    tuning rig (the simulator's paper arms, sag, seed 21) diagnosed by the chain engine on its
    arms as 2-joint chains, its effects in the planar sweep's names. The pinned names are that
    sweep's for this rig: joint compliance, as gravity_sag."""
    from bayesrob.validation.planar_generators import Case, diagnose_case

    res = diagnose_case(Case("simulator", "paper", ("gravity_sag",), 4, 21), engine="groups")
    assert res["named"] == "gravity_sag"
    assert all(s["effect"] != "joint_compliance" for r in res["rounds"] for s in r)
    assert res["rivals"] == {"gravity_sag": []}
    # the strength is the planar base model's for either engine (0.80 / 0.50 mm at new
    # poses), so both engines count the same rigs as strong; the gap the effects opened is
    # measured against the chain base's own clean twin
    assert res["strength"] == pytest.approx(1.62, abs=0.02)
    assert (res["clean_holdout_error_mm"] < res["final_holdout_error_mm"]
            < res["baseline_holdout_error_mm"])


def test_play_is_tried_with_the_compliance_that_gives_it_a_side_where_nothing_passes_alone():
    """A planar tuning rig (the generator's paper-like arms, sag and backlash, seed 31) on
    which no effect passes alone: joint compliance falls short (its z under the rule's) and
    the play has no side without a fitted deflection, so the pair is tried and named, both
    members, as it beats the current model and compliance alone by the rule's z (the planar
    engine's pairs) and clears the parameter guard (a pair of many parameters tried because
    nothing passed alone is where over-fitting lies: on the clean arm6 of seed 11 a pair of 17
    parameters passed both z's, 2.09 and 2.50, on a gain of 4.9 nats, and made the validation
    rows worse). The pinned names are the tuning sweep's for this rig."""
    from bayesrob.validation.planar_generators import Case, diagnose_case

    res = diagnose_case(Case("generator", "paper_like", ("gravity_sag", "backlash"), 4, 31),
                        engine="groups")
    assert res["named"] == "backlash+gravity_sag"
    first = {s["effect"]: s for s in res["rounds"][0]}
    assert not first["gravity_sag"]["passes"] and first["gravity_sag"]["z"] < Z
    pair = first["gravity_sag+backlash"]
    assert pair["passes"] and pair["z"] > Z and pair["z_vs_alone"] > Z
    assert pair["elpd_diff"] > pair["guard_nats"]
    assert res["final_holdout_error_mm"] < res["baseline_holdout_error_mm"]


def test_the_report_shows_a_pair_named_in_one_round():
    """Two steps named by one round (a pair) are read back from their ``round``: the round's
    named candidate is the pair, whose guard verdict is told, and the ladder has both steps."""
    row = {"n_free": 16, "heldout_error_mm": 1.0, "heldout_error_sd_mm": 0.5,
           "heldout_error_max_mm": 2.0}
    pair = {"effect": "joint_compliance+backlash", "parameters": 12, "z": 3.1, "passes": True,
            "selection_error_before_mm": 1.2, "selection_error_after_mm": 0.9,
            "guard_passes": False, "elpd_diff": 8.0, "guard_nats": 12.0}
    alone = {**pair, "effect": "joint_compliance", "parameters": 4, "z": 1.0, "passes": False}
    doc = {"rig": "r", "rule": "the rule", "rule_z": Z, "rounds": [[alone, pair]],
           "steps": [{"effect": "joint_compliance", "rivals": [], "round": 1, **row},
                     {"effect": "backlash", "rivals": [], "round": 1, **row}],
           "baseline": row, "effects": ["joint_compliance", "backlash"], "seconds": 1.0,
           "notes": []}
    text = format_group_diagnosis(doc)
    assert "joint_compliance+backlash gains +8.0 nats" in text
    assert "+ joint_compliance" in text and "+ backlash" in text


def test_paired_z_of_rows_that_did_not_move_is_zero_not_nan():
    from bayesrob.diagnose.rule import paired_z

    rows = np.array([0.4, 0.7, 1.1, 0.2])
    assert paired_z(rows, rows) == 0.0
    assert paired_z(rows, rows - 0.1 * np.arange(4)) > 0
    assert paired_z(rows[:1], rows[:1] - 1.0) == 0.0
