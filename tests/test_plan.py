"""``bayesrob plan``: the greedy selection against direct computation, planned poses against
random ones on a simulated arm, the poses.csv contract, bad input, and the measure round
trip (``simulate --poses``)."""

from __future__ import annotations

import csv
import io
import shutil
from pathlib import Path

import numpy as np
import pytest

from bayesrob.cli import main
from bayesrob.data.rig import RigError, load_rig
from bayesrob.plan import load_plan_rig, plan_poses
from bayesrob.plan.criteria import Accuracy, Identify
from bayesrob.plan.greedy import greedy
from bayesrob.sim.rigs import simulate_arm6_rig
from bayesrob.sim.truth import POSE_HI, POSE_LO, Arm6Truth

POOL = 400


def _write_pool(path: Path, q: np.ndarray, label: bool = False) -> None:
    cols = [f"arm_u{k + 1}" for k in range(6)]
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(cols + (["label"] if label else []))
        for i, row in enumerate(q):
            w.writerow([f"{v:.10g}" for v in row] + ([f"p{i}"] if label else []))


@pytest.fixture(scope="module")
def arm6(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A simulated arm6 with holdout rows only (nothing measured for the calibration yet) and
    a pool of random poses over its working range beside it."""
    d = tmp_path_factory.mktemp("plan")
    simulate_arm6_rig(d / "rig", Arm6Truth(seed=5, n_train=0, n_validation=0,
                                             n_holdout=100))
    q = np.random.default_rng(5).uniform(POSE_LO, POSE_HI, size=(POOL, 6))
    _write_pool(d / "pool.csv", q, label=True)
    return d


def test_greedy_matches_direct_covariance_and_brute_force():
    """Each greedy value is tr(A C) of the chosen prefix computed from scratch (the rank-dim
    updates drift nowhere), and the D-optimal first pick is the brute-force argmax."""
    rng = np.random.default_rng(0)
    jac = rng.normal(size=(60, 3, 8))
    info = np.eye(8) * 0.01
    a = np.cov(rng.normal(size=(8, 50)))
    sel = greedy(jac, info, 12, Accuracy(a))
    for n in (1, 5, 12):
        rows = jac[sel.order[:n]].reshape(-1, 8)
        cov = np.linalg.inv(info + rows.T @ rows)
        assert sel.values[n - 1] == pytest.approx(np.sqrt(np.trace(a @ cov)), rel=1e-9)
    assert len(set(sel.order.tolist())) == 12
    d_first = greedy(jac, info, 1, Identify()).order[0]
    brute = [np.linalg.slogdet(info + jac[i].T @ jac[i])[1] for i in range(60)]
    assert d_first == int(np.argmax(brute))


def test_bias_aware_accuracy_matches_direct_computation():
    """With omitted parameters, each greedy value is sqrt(tr(A C) + s^2 ||G D - H||^2 / T)
    of the chosen prefix computed from scratch (D = C J^T K of the prefix and of the rows
    measured before), and its first pick is the brute-force argmin of that error."""
    rng = np.random.default_rng(1)
    jac, kom = rng.normal(size=(50, 3, 6)), rng.normal(size=(50, 3, 4))
    j0, k0 = rng.normal(size=(2, 3, 6)), rng.normal(size=(2, 3, 4))
    g, h = jac[:20].reshape(-1, 6), kom[:20].reshape(-1, 4)
    sd = 0.7

    def direct(rows: np.ndarray) -> float:
        jj = np.concatenate([j0, jac[rows]]).reshape(-1, 6)
        kk = np.concatenate([k0, kom[rows]]).reshape(-1, 4)
        cov = np.linalg.inv(np.eye(6) * 0.01 + jj.T @ jj)
        d = cov @ jj.T @ kk
        return float(np.sqrt((np.trace(g @ cov @ g.T) + sd**2 * np.sum((g @ d - h) ** 2)) / 20))

    crit = Accuracy(g.T @ g / 20, kom, g.T @ h / 20, float(np.sum(h**2)) / 20,
                    j0.reshape(-1, 6).T @ k0.reshape(-1, 4), sd)
    j00 = j0.reshape(-1, 6)
    sel = greedy(jac, np.eye(6) * 0.01 + j00.T @ j00, 10, crit)
    assert sel.before == pytest.approx(direct(np.array([], int)), rel=1e-9)
    for n in (1, 4, 10):
        assert sel.values[n - 1] == pytest.approx(direct(sel.order[:n]), rel=1e-9)
    assert sel.order[0] == int(np.argmin([direct(np.array([i])) for i in range(50)]))


def test_planned_beats_random_in_prediction_and_prefixes_are_plans(arm6):
    """On the arm6 pool the accuracy plan's predicted error at 30 poses is at least 10% below
    the median of 20 random 30-pose subsets' (the predicted error of a subset: the same
    linearised posterior, computed directly); the 15-pose plan is the 30-pose plan's prefix."""
    from bayesrob.plan.criteria import PRIOR_SD
    from bayesrob.plan.planner import _linearisation, pose_jacobians, resolve_groups

    rig = load_plan_rig(arm6 / "rig")
    plan = plan_poses(rig, 30, pool=arm6 / "pool.csv")
    short = plan_poses(rig, 15, pool=arm6 / "pool.csv")
    assert short.selection.order.tolist() == plan.selection.order[:15].tolist()
    groups, _ = resolve_groups(rig, None, "accuracy")
    robot, x, free, _ = _linearisation(rig, groups, ())
    jac = pose_jacobians(robot, x, plan.pool)[:, :, free] * robot.layout.scales[free]
    a = np.einsum("ndp,ndq->pq", jac, jac) / len(jac)

    def predicted(rows):
        j = jac[rows].reshape(-1, jac.shape[2]) / plan.noise_mm
        cov = np.linalg.inv(np.eye(jac.shape[2]) / PRIOR_SD**2 + j.T @ j)
        return np.sqrt(np.trace(a @ cov))

    rng = np.random.default_rng(1)
    random = np.median([predicted(rng.permutation(POOL)[:30]) for _ in range(20)])
    assert predicted(plan.selection.order) == pytest.approx(plan.after, rel=1e-6)
    assert plan.after < 0.9 * random
    assert plan.before > plan.after


def test_planned_poses_calibrate_better_than_random_ones(arm6, tmp_path):
    """Measured on the simulated arm and calibrated, the plan's first 40 poses leave a smaller
    held-out error against the true arm than the median of three random 40-pose draws (seeds
    801-803 of the tuning run: planned / random 0.70-0.82 at 40 poses)."""
    from bayesrob.validation.calibration_chain import true_vector
    from bayesrob.validation.plan import model_error

    from bayesrob.sim.rigs import measure_arm6_poses

    q = np.loadtxt(arm6 / "pool.csv", delimiter=",", skiprows=1, usecols=range(6))
    rig0 = load_plan_rig(arm6 / "rig")
    order = plan_poses(rig0, 40, pool=arm6 / "pool.csv").selection.order
    q_new = np.random.default_rng(9).uniform(POSE_LO, POSE_HI, size=(200, 6))
    rng = np.random.default_rng(2)
    errors = {}
    for name, rows in [("planned", order)] + [(f"random{k}", rng.permutation(POOL)[:40])
                                               for k in range(3)]:
        d = tmp_path / name
        shutil.copytree(arm6 / "rig", d)
        measure_arm6_poses(d, ["train"] * 40, q[rows], seed=5)
        rig = load_rig(d)
        errors[name] = model_error(rig, ("frames", "offsets", "geometric", "servo"),
                                   true_vector(d, rig), q_new)
    random = np.median([v for k, v in errors.items() if k != "planned"])
    assert errors["planned"] < random, errors


def test_poses_csv_columns_and_simulate_round_trip(arm6, tmp_path):
    """poses.csv: config, set, the command cells exactly as the pool wrote them, the pool's
    other columns, gain; ``simulate --poses`` appends them measured, with approach sides."""
    rig = tmp_path / "rig"
    shutil.copytree(arm6 / "rig", rig)
    out = tmp_path / "poses.csv"
    assert main(["plan", str(rig), "--n", "8", "--out", str(out), "--pool",
                 str(arm6 / "pool.csv")]) == 0
    with out.open() as fh:
        rows = list(csv.reader(fh))
    cols = [f"arm_u{k + 1}" for k in range(6)]
    assert rows[0] == ["config", "set", *cols, "label", "gain"]
    with (arm6 / "pool.csv").open() as fh:
        pool = {r[-1]: r[:-1] for r in list(csv.reader(fh))[1:]}
    for r in rows[1:]:
        assert r[:2] == ["arm", "train"]
        assert r[2:8] == pool[r[8]]  # the pool's text, not re-formatted numbers
    gains = [float(r[-1]) for r in rows[1:]]
    assert all(g > 0 for g in gains)
    assert main(["simulate", str(rig), "--poses", str(out)]) == 0
    loaded = load_rig(rig)
    u, _ = loaded.rows("arm", "train")
    assert len(u) == 8
    np.testing.assert_allclose(u, np.array([[float(v) for v in r[2:8]] for r in rows[1:]]),
                               rtol=1e-9)
    sides = np.array([[float(v) for v in loaded.measurements.extra[f"arm_d{k + 1}"][-8:]]
                      for k in range(6)]).T
    np.testing.assert_array_equal(sides[1:], np.sign(np.diff(u, axis=0)))


def test_plan_before_the_first_measurement(arm6, tmp_path):
    """A rig with no measurements.csv, or a header only, is planned for from its limits."""
    rig = tmp_path / "rig"
    shutil.copytree(arm6 / "rig", rig)
    header = (rig / "measurements.csv").read_text().splitlines()[0]
    (rig / "measurements.csv").write_text(header + "\n")
    plan = plan_poses(load_plan_rig(rig), 5, samples=200, criterion="identify")
    assert plan.n_measured == 0 and len(plan.selection.order) == 5
    (rig / "measurements.csv").unlink()
    assert load_plan_rig(rig).measurements.observed.shape == (0, 3)


@pytest.mark.parametrize("case", ["columns", "too_many", "limits", "unreachable", "config"])
def test_bad_input_is_one_line_exit_2_nothing_written(arm6, tmp_path, capsys, case):
    pool = arm6 / "pool.csv"
    args = ["--n", "3"]
    if case == "columns":
        pool = tmp_path / "p.csv"
        pool.write_text("arm_u1,arm_u2,arm_u3\n0,-1,0\n")
    elif case == "too_many":
        args = ["--n", str(POOL + 1)]
    elif case == "limits":
        pool = tmp_path / "p.csv"
        pool.write_text("arm_u1,arm_u2,arm_u3,arm_u4,arm_u5,arm_u6\n0,-1,0,0,0,0\n"
                        "9,-1,0,0,0,0\n")
    elif case == "unreachable":
        task = tmp_path / "task.csv"
        task.write_text("x,y,z\n50000,0,0\n")
        args += ["--task", str(task)]
    else:
        pool = tmp_path / "p.csv"
        pool.write_text("config,arm_u1,arm_u2,arm_u3,arm_u4,arm_u5,arm_u6\n"
                        "hand,0,-1,0,0,0,0\n")
    out = tmp_path / "poses.csv"
    assert main(["plan", str(arm6 / "rig"), *args, "--out", str(out), "--pool",
                 str(pool)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("bayesrob plan: error:")
    expect = {"columns": "missing column 'arm_u4'", "too_many": "more poses than the pool",
              "limits": "line 3: column 'arm_u1' = 9", "unreachable": "out of reach",
              "config": "'hand' is not a measured arm"}[case]
    assert expect in err
    assert not out.exists()


def test_omitted_sag_and_prior_flags(arm6, tmp_path, capsys):
    """--omitted-sd weighs the sag groups --params leaves out (named in the JSON, the
    predicted error grows by their bias, the plan changes); with the compliances fitted
    nothing is omitted; --prior-sd 0 is one line, exit 2, nothing written."""
    import json

    rig = load_plan_rig(arm6 / "rig")
    base = plan_poses(rig, 10, pool=arm6 / "pool.csv")
    biased = plan_poses(rig, 10, pool=arm6 / "pool.csv", omitted_sd=1.0)
    assert base.omitted == () and biased.omitted == ("compliance", "lateral")
    assert biased.after > base.after
    assert biased.selection.order.tolist() != base.selection.order.tolist()
    full = plan_poses(rig, 3, pool=arm6 / "pool.csv", omitted_sd=1.0,
                      groups=("frames", "geometric", "compliance", "lateral"))
    assert full.omitted == () and full.omitted_sd == 0.0
    out, js = tmp_path / "poses.csv", tmp_path / "plan.json"
    assert main(["plan", str(arm6 / "rig"), "--n", "3", "--out", str(out), "--pool",
                 str(arm6 / "pool.csv"), "--omitted-sd", "1", "--prior-sd", "1",
                 "--json", str(js)]) == 0
    summary = json.loads(js.read_text())
    assert summary["omitted"] == ["compliance", "lateral"] and summary["prior_sd"] == 1.0
    capsys.readouterr()
    bad = tmp_path / "bad.csv"
    assert main(["plan", str(arm6 / "rig"), "--n", "3", "--out", str(bad), "--pool",
                 str(arm6 / "pool.csv"), "--prior-sd", "0"]) == 2
    assert "--prior-sd must be positive" in capsys.readouterr().err and not bad.exists()


def test_discriminate_plans_poses_the_effects_differ_at(arm6):
    """Beside frames,geometric the candidates are every chain effect, and the plan raises
    their own information; with every effect fitted there is nothing left to tell apart."""
    rig = load_plan_rig(arm6 / "rig")
    disc = plan_poses(rig, 20, criterion="discriminate", pool=arm6 / "pool.csv")
    assert disc.effects == ["joint_compliance", "lateral_compliance", "encoder_error",
                            "backlash"]
    assert disc.after > disc.before
    with pytest.raises(RigError, match="no candidate effect"):
        plan_poses(rig, 3, criterion="discriminate", pool=arm6 / "pool.csv",
                   groups=("frames", "geometric", "compliance", "lateral", "encoder",
                           "backlash"))


def test_diagnose_plan_separates_what_the_diagnosis_could_not(arm6, tmp_path):
    """``diagnose --plan``: a named effect with a rival within noise stays to be told apart;
    one named without a rival joins the base model and is no longer a candidate."""
    import argparse

    from bayesrob.cli import _diagnose_plan

    rig = load_plan_rig(arm6 / "rig")
    out = tmp_path / "d.csv"
    args = argparse.Namespace(plan=4, pool=str(arm6 / "pool.csv"), seed=0, plan_out=str(out),
                              json=None)
    _diagnose_plan(rig, {"steps": [{"effect": "joint_compliance",
                                    "rivals": ["lateral_compliance"]}]}, args)
    with out.open() as fh:
        assert len(list(csv.reader(fh))) == 5
    plan = plan_poses(rig, 4, criterion="discriminate", pool=arm6 / "pool.csv",
                      groups=("frames", "geometric", "compliance"))
    assert plan.effects == ["lateral_compliance", "encoder_error", "backlash"]


def test_rig_toml_limits_bound_the_samples_and_are_checked(arm6, tmp_path):
    """rig.toml ``limits`` (command units) win over the URDF's; a malformed one is one line."""
    from bayesrob.plan.pool import command_limits

    rig = tmp_path / "rig"
    shutil.copytree(arm6 / "rig", rig)
    text = (rig / "rig.toml").read_text()
    lim = "limits = [[-1.0, 1.0], [-2.0, -1.0], [0.0, 0.5], [-1.0, 1.0], [-1.0, 1.0], [-1.0, 1.0]]"
    (rig / "rig.toml").write_text(text.replace("[arms.arm]\n", f"[arms.arm]\n{lim}\n"))
    plan = plan_poses(load_plan_rig(rig), 10, samples=200, criterion="identify")
    u = plan.pool.commands["arm"]
    assert u[:, 1].min() >= -2.0 and u[:, 1].max() <= -1.0 and u[:, 2].max() <= 0.5
    (rig / "rig.toml").write_text(text.replace("[arms.arm]\n", "[arms.arm]\nlimits = [1, 2]\n"))
    with pytest.raises(RigError, match=r"arms.arm.limits: expected 6 pairs"):
        command_limits(load_plan_rig(rig))


def test_simulate_poses_measures_each_planned_arm_of_a_linked_arm6_rig(tmp_path, capsys):
    """On a linked arm6 rig, ``simulate --poses`` measures each planned row on its config's
    hidden arm, appended after the linked rows (whose line numbers truth.toml keeps), with
    that arm's approach sides from its own last command in the file (a linked row's
    included). The measured points are the hidden arm's: its true parameters at the commands
    with the simulator's gravity deflection, to within the noise."""
    import tomllib

    from bayesrob.data.rig import load_rig
    from bayesrob.sim.truth import load_true_params

    rig = tmp_path / "linked"
    assert main(["simulate", str(rig), "--robot", "arm6", "--linked", "--poses", "20", "10",
                 "10", "--no-progress"]) == 0
    poses = tmp_path / "poses.csv"
    assert main(["plan", str(rig), "--n", "6", "--samples", "300", "--out", str(poses)]) == 0
    capsys.readouterr()
    before = (rig / "measurements.csv").read_text().splitlines()
    assert main(["simulate", str(rig), "--poses", str(poses)]) == 0
    after = (rig / "measurements.csv").read_text().splitlines()
    planned = list(csv.DictReader(io.StringIO(poses.read_text())))
    added = list(csv.DictReader(io.StringIO("\n".join([after[0], *after[len(before):]]))))
    assert len(after) == len(before) + 6 and len(added) == 6
    assert [r["config"] for r in added] == [r["config"] for r in planned]
    assert {r["config"] for r in added} == {"left", "right"}
    truth = tomllib.loads((rig / "truth.toml").read_text())["linked_chain_truth"]
    for line in truth["linked_rows"]["line"]:
        assert after[line - 1].startswith("left+right,test,")
    for arm in ("left", "right"):
        mine = [r for r in added if r["config"] == arm]
        u = np.array([[float(r[f"{arm}_u{k + 1}"]) for k in range(6)] for r in mine])
        np.testing.assert_array_equal(
            u, [[float(p[f"{arm}_u{k + 1}"]) for k in range(6)]
                for p in planned if p["config"] == arm])
        last = [r for r in csv.DictReader(io.StringIO("\n".join(before))) if r[f"{arm}_u1"]][-1]
        previous = np.array([float(last[f"{arm}_u{k + 1}"]) for k in range(6)])
        d = np.array([[float(r[f"{arm}_d{k + 1}"]) for k in range(6)] for r in mine])
        np.testing.assert_array_equal(d, np.sign(np.diff(np.vstack([previous, u]), axis=0)))
    from bayesrob.sim.equilibrium import gravity_settled
    from bayesrob.sim.truth import GRAVITY

    loaded = load_rig(rig)
    robot = loaded.robot
    x = np.array([load_true_params(rig)[n] for n in robot.layout.names])
    m = loaded.measurements
    for arm in ("left", "right"):
        rows = np.flatnonzero(m.config == arm)[-sum(r["config"] == arm for r in added):]
        u = m.commands[arm][rows]
        q = gravity_settled(robot, x, arm, u, np.asarray(truth["drawn_masses_kg"][arm]),
                            np.asarray(truth["stiffness_nmm_per_rad"][arm]), GRAVITY)
        miss = np.linalg.norm(np.asarray(robot.marker_points(x, arm, q)) - m.observed[rows],
                              axis=1)
        nominal = np.linalg.norm(np.asarray(robot.marker_points(robot.layout.nominal, arm, q))
                                 - m.observed[rows], axis=1)
        # measured 0.13-0.25 mm (0.8 mrad joint and 0.35 mm measurement noise); the nominal
        # arm misses by 8-15 mm, the other arm by its 900 mm base offset
        assert miss.max() < 1.0 < 5.0 < nominal.min()


def test_plan_out_into_a_directory_not_made_yet(arm6, tmp_path):
    """--out DIR/poses.csv where DIR does not exist: the output-path check allows a parent the
    command makes, so the plan is written there rather than dying with a traceback."""
    out = tmp_path / "new" / "deeper" / "poses.csv"
    assert main(["plan", str(arm6 / "rig"), "--n", "3", "--pool", str(arm6 / "pool.csv"),
                 "--out", str(out)]) == 0
    assert out.read_text().splitlines()[0].startswith("config,set,")
    assert len(out.read_text().splitlines()) == 4
