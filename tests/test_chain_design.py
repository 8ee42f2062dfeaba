"""The configuration designer with chain modules: 6-joint 3-D arms (URDF) placed in space.

One simulated two-arm rig (``simulate_linked_arm6_rig``, seed 0, 40 train poses per arm) is
calibrated once for the module (about 25 s: a least-squares fit and two NUTS fits); the Dask
test runs a real two-worker LocalCluster, as the command does. All draws are seeded. How the
designer's linked chain modules hold against built assemblies on report rigs is measured by
the validation suite (``bayesrob validate design_chain``).
"""

from __future__ import annotations

import csv
import json
import pickle
from dataclasses import replace
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bayesrob.cli import main
from bayesrob.data.rig import load_rig
from bayesrob.design.file import load_design
from bayesrob.design.modules import load_modules
from bayesrob.design.search import (
    Job,
    enumerate_candidates,
    evaluate,
    reach_table,
    run_design,
    task_targets,
    write_candidate_rig,
)
from bayesrob.predict.fusion import equilibrium

RIG_TRUTH = dict(seed=0, n_train=40, n_validation=10, n_holdout=10, n_linked=8)
FAR = [3000.0, 0.0, 0.0]  # no arm6 (about 1 m of reach) serves a task 2.5 m away


def _design_text(rig: Path, mounts: list[list[float]], box: list[list[float]],
                 extra: str = "") -> str:
    return f"""
seed = 3
draws = 400
tracker_noise_mm = 0.1
{extra}
[modules.left]
rig = "{rig}"

[modules.right]
rig = "{rig}"

[mounts]
points = {json.dumps(mounts)}

[task]
box = {json.dumps(box)}
targets = 5

[requirement]
error_mm = 1.0
quantile = 0.95

[limits]
max_arms = 2
"""


BOX = [[350.0, 550.0], [-100.0, 100.0], [150.0, 280.0]]
MOUNTS = [[0.0, 0.0, 0.0], [900.0, 0.0, 0.0], FAR]


@pytest.fixture(scope="module")
def rig_dir(tmp_path_factory) -> Path:
    from bayesrob.sim.rigs import simulate_linked_arm6_rig
    from bayesrob.sim.truth import LinkedArm6Truth

    return simulate_linked_arm6_rig(tmp_path_factory.mktemp("arms") / "rig",
                                     LinkedArm6Truth(**RIG_TRUTH))


@pytest.fixture(scope="module")
def chain(rig_dir, tmp_path_factory):
    path = tmp_path_factory.mktemp("design") / "design.toml"
    path.write_text(_design_text(rig_dir, MOUNTS, BOX))
    design = load_design(path)
    return design, load_modules(design)


def _write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "design.toml"
    path.write_text(text)
    return path


# ------------------------------------------------------------------------- the file, in 3-D


def test_a_3d_design_file_parses(rig_dir, tmp_path):
    d = load_design(_write(tmp_path, _design_text(rig_dir, MOUNTS, BOX)))
    assert d.dim == 3 and d.mounts.shape == (3, 3)
    assert d.region.shape == (8, 3)  # the box's corners
    np.testing.assert_array_equal(d.region.min(axis=0), [350.0, -100.0, 150.0])
    np.testing.assert_array_equal(d.region.max(axis=0), [550.0, 100.0, 280.0])
    t = task_targets(d.region, 40, seed=2)
    assert t.shape == (40, 3) and np.all((t >= [350, -100, 150]) & (t <= [550, 100, 280]))
    np.testing.assert_array_equal(t, task_targets(d.region, 40, seed=2))


def test_a_3d_mount_grid_runs_x_fastest(rig_dir, tmp_path):
    text = _design_text(rig_dir, MOUNTS, BOX).replace(
        f"points = {json.dumps(MOUNTS)}",
        "grid = { x = [0.0, 10.0, 2], y = [0.0, 20.0, 3], z = [5.0, 5.0, 1] }")
    d = load_design(_write(tmp_path, text))
    np.testing.assert_array_equal(d.mounts, [[0, 0, 5], [10, 0, 5], [0, 10, 5], [10, 10, 5],
                                             [0, 20, 5], [10, 20, 5]])


def test_module_params_name_calibration_groups(rig_dir, tmp_path):
    text = _design_text(rig_dir, MOUNTS, BOX).replace(
        '[modules.left]\n', '[modules.left]\nparams = "offsets,geometric,compliance"\n')
    d = load_design(_write(tmp_path, text))
    assert d.modules["left"].params == ("frames", "offsets", "geometric", "compliance")
    assert d.modules["right"].params is None


@pytest.mark.parametrize("change,message", [
    ({f"box = {json.dumps(BOX)}": "polygon = [[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]"},
     "polygon is a region of the plane but the mounts are 3-D"),
    ({json.dumps(BOX): "[[350.0, 550.0], [-100.0, 100.0]]"},
     "box must be [[x0, x1], [y0, y1], [z0, z1]]"),
    ({"[modules.left]\n": '[modules.left]\nparams = "geometric,elastic"\n'},
     "params = 'geometric,elastic' must name calibration groups"),
])
def test_bad_3d_design_files_are_one_line_exit_2(rig_dir, tmp_path, capsys, change, message):
    text = _design_text(rig_dir, MOUNTS, BOX)
    for old, new in change.items():
        assert old in text
        text = text.replace(old, new, 1)
    rc = main(["design", str(_write(tmp_path, text)), "--out", str(tmp_path / "o"),
               "--no-progress"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and message in err[0], err


def test_planar_and_chain_modules_do_not_mix(rig_dir, tmp_path, capsys):
    """Checked before anything is calibrated: one line, exit 2."""
    planar = Path(__file__).resolve().parents[1] / "examples" / "design" / "modules"
    text = _design_text(rig_dir, MOUNTS, BOX).replace(
        "[modules.right]\n", f'[modules.top]\nrig = "{planar}"\n\n[modules.right]\n')
    rc = main(["design", str(_write(tmp_path, text)), "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "is a URDF/DH arm and 'top' a planar arm" in err, err


def test_planar_modules_take_no_params(tmp_path, capsys):
    planar = Path(__file__).resolve().parents[1] / "examples" / "design" / "modules"
    text = _design_text(planar, [[20.0, 440.0]], [[80.0, 260.0], [100.0, 280.0]]).replace(
        "[modules.left]", '[modules.top]\nparams = "geometric"').replace(
        "[modules.right]", "[modules.bottom]")
    rc = main(["design", str(_write(tmp_path, text)), "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "params names calibration groups of URDF/DH arms" in err, err


def test_planar_modules_refuse_3d_mounts(tmp_path, capsys):
    planar = Path(__file__).resolve().parents[1] / "examples" / "design" / "modules"
    text = _design_text(planar, MOUNTS, BOX).replace("[modules.left]", "[modules.top]").replace(
        "[modules.right]", "[modules.bottom]")
    rc = main(["design", str(_write(tmp_path, text)), "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "the mounts are 3-D points but the modules are planar" in err, err


# ------------------------------------------------------------------------- the pieces


def test_equal_robots_built_apart_share_one_compiled_program(rig_dir, monkeypatch):
    """Robots are values: two loads of one rig, and a copy pickled as Dask ships a module to
    its workers, are equal and hash equal. The compiled programs are keyed by the robot's
    structure, its nominal values being arguments: so the unmoved robot, one joint origin
    apart (another value, of the same structure), runs the program the first traced and
    computes its own points, while a robot one axis apart (another structure) traces its
    own."""
    from bayesrob import robot as kin

    traced = []
    marker_points = kin.Robot.marker_points

    def counted(self, *args, **kwargs):
        traced.append(self)
        return marker_points(self, *args, **kwargs)
    monkeypatch.setattr(kin.Robot, "marker_points", counted)

    def moved():
        # a base joint 0.3125 mm along x from the rig's
        robot = load_rig(rig_dir).robot
        origins = robot.chains["left"].origins.copy()
        origins[0, 0] += 0.3125
        left = replace(robot.chains["left"], origins=origins)
        return robot, replace(robot, chains={**robot.chains, "left": left})

    base, one = moved()
    _, two = moved()
    assert one is not two and one == two and hash(one) == hash(two)
    assert base != one and base.structure == one.structure
    assert hash(base.structure) == hash(one.structure)
    x = jnp.asarray(one.layout.nominal)
    u = jnp.zeros((2, 6))
    jax.clear_caches()  # programs an earlier test traced for this structure would serve here
    first = np.asarray(one.compiled_points("left")(x, u))
    assert len(traced) == 1
    copy = pickle.loads(pickle.dumps(two))
    assert copy == one and hash(copy) == hash(one)
    for robot in (two, copy):
        np.testing.assert_array_equal(np.asarray(robot.compiled_points("left")(x, u)), first)
    np.testing.assert_allclose(first - np.asarray(base.compiled_points("left")(x, u)),
                               [[0.3125, 0.0, 0.0]] * 2, atol=1e-9)
    assert len(traced) == 1
    axes = one.chains["left"].axes.copy()
    axes[0] = np.roll(axes[0], 1)  # a unit axis, turned to another
    tilted = replace(one, chains={**one.chains, "left": replace(one.chains["left"], axes=axes)})
    assert tilted.structure != one.structure
    tilted.compiled_points("left")(x, u)
    assert len(traced) == 2


def test_linked_modules_keep_their_normals_whatever_they_are_linked_with(monkeypatch):
    """Stub modules of one rig with fixed sags (1, 2 and 4 mm; no calibration): linked, each
    arm's term is centred at the mean log sag less its own, and a module draws the same
    standard normals with any partner, so its draws in (a, b) and (a, c) differ by the two
    centres alone (the sag prior's sds are the same; to rounding). A module of another rig
    keeps its own prior, and with the arms' centring off the draws are those of the module's
    own prior and seed, as before linked modules were centred."""
    from types import SimpleNamespace

    import bayesrob.predict.stiffness as st
    from bayesrob.design.modules import CalibratedModule, _log_stiffness, linked_priors

    sags = {"a": 1.0, "b": 2.0, "c": 4.0}
    monkeypatch.setattr(st, "arm_sags", lambda rig, cal, arms: {x: sags[x] for x in arms})
    rig = SimpleNamespace(robot=SimpleNamespace(measured_arms=lambda: ["a", "b", "c"]))

    def prior() -> st.StiffnessPrior:
        return st.StiffnessPrior(np.zeros(3), np.full(3, 0.5), np.ones(3, bool),
                                 st.STIFFNESS_SOURCES[2])

    def module(name: str, arm: str, rig_index: int = 0) -> CalibratedModule:
        return CalibratedModule(name, arm, rig, SimpleNamespace(stiffness={arm: prior()},
                                                           calibration=None),
                           np.zeros(3), rig_index, "ind")

    mods = {x: module(x, x) for x in "abc"}
    ab, ac = linked_priors([mods["a"], mods["b"]]), linked_priors([mods["a"], mods["c"]])
    assert ab[0].arm_centre == pytest.approx(0.5 * np.log(2.0))
    assert ab[1].arm_centre == pytest.approx(-0.5 * np.log(2.0))
    assert ac[0].arm_centre == pytest.approx(np.log(2.0))
    assert all(p.source == st.STIFFNESS_SOURCES[3] for p in ab + ac)
    job = SimpleNamespace(cache={}, modules=mods, seed=5, draws=40)
    with_b = np.asarray(_log_stiffness(job, ("a", "b"))[0])
    with_c = np.asarray(_log_stiffness(job, ("a", "c"))[0])
    np.testing.assert_allclose(with_b - ab[0].arm_centre, with_c - ac[0].arm_centre,
                               atol=1e-12)

    other = module("d", "b", rig_index=1)
    assert linked_priors([mods["a"], other]) == [mods["a"].mods.stiffness["a"],
                                                 other.mods.stiffness["b"]]
    monkeypatch.setattr(st, "CHAIN_STIFFNESS_ARM_CENTRE", "equal")
    job = SimpleNamespace(cache={}, modules=mods, seed=5, draws=40)
    plain = np.asarray(_log_stiffness(job, ("a", "b"))[0])
    np.testing.assert_array_equal(plain, np.asarray(st.stiffness_draws(
        [prior()], jax.random.PRNGKey(5 * 104729), 40)[0]))


def test_the_balance_puts_the_tracker_noise_back():
    """Two equally stiff arms with the same Jacobian: each weighs 1/2, so the balance of the
    free points keeps half the tracker's variance and sigma^2 (I - 2 (I/2)^2) = sigma^2 / 2
    is put back: with noiseless free points the linked point's variance is sigma^2 / 2 per
    axis. 20,000 draws give each variance within about 1% (sd sqrt(2 / n)); 5% tolerance."""
    n, sigma = 20_000, 0.3
    jac = jnp.asarray(np.random.default_rng(0).normal(size=(1, 3, 6)))
    zero = jnp.zeros((n, 1, 3))
    log_k = [jnp.zeros((n, 6))] * 2
    d = np.asarray(equilibrium([zero, zero], [jac, jac], log_k, tracker_noise_mm=sigma,
                                     key=jax.random.PRNGKey(0)))[:, 0]
    np.testing.assert_allclose(np.var(d, axis=0), sigma**2 / 2, rtol=0.05)
    assert abs(np.corrcoef(d.T)[0, 1]) < 0.03
    plain = equilibrium([zero, zero], [jac, jac], log_k)
    assert float(jnp.abs(plain).max()) == 0.0


def test_mounting_moves_the_prediction_with_the_base(chain):
    """A module mounted 250 mm further along x serving a task moved by the same 250 mm is the
    same module doing the same work: every error quantile is the same to rounding (its aim
    starts from the same train pose and the draws' seeds follow the mount's index)."""
    design, modules = chain
    shift = np.array([250.0, 0.0, 0.0])
    targets = task_targets(design.region, design.n_targets, design.seed)
    reach = reach_table(modules, design.mounts, targets)
    moved = reach_table(modules, design.mounts + shift, targets + shift)
    assert set(reach) == set(moved)
    for key, u in reach.items():
        np.testing.assert_allclose(moved[key], u, atol=1e-9)
    results = []
    for mounts, t, r in ((design.mounts, targets, reach),
                         (design.mounts + shift, targets + shift, moved)):
        job = Job(modules, t, r, design.fusion, design.quantile, design.error_mm,
                  design.confidence, design.draws, design.seed, design.tracker_noise_mm,
                  mounts)
        results.append([evaluate(job, c, i) for i, c in enumerate(
            enumerate_candidates(design, r))])
    for a, b in zip(*results, strict=True):
        np.testing.assert_allclose(a["error_quantile_mm"], b["error_quantile_mm"], atol=1e-9)
        np.testing.assert_allclose(np.asarray(a["expected_point"]) + shift,
                                   b["expected_point"], atol=1e-9)


# ------------------------------------------------------------------------- the run


def test_chain_design_on_a_local_cluster(chain, tmp_path):
    design, modules = chain
    res = run_design(design, modules, workers=2, batch=2)
    # the far mount serves nothing: two modules on two mounts, 2 singles + 2 linked pairs
    assert res.n_reachable == 4 and len(res.candidates) == 6 and res.workers == 2
    assert not any(2 in c["mounts"] for c in res.candidates)
    met = [c for c in res.candidates if c["meets"]]
    assert res.candidates[: len(met)] == met
    for c in res.candidates:
        assert all(len(b) == 3 for b in c["bases"])
        q = np.asarray(c["error_quantile_mm"])
        assert q.shape == (design.n_targets,) and np.all(q > 0)
        assert c["meets"] == (c["overall"]["assured_error_mm"] <= design.error_mm)
        assert c["models"] == ["ind"] * len(c["arms"])
        # the predicted end point is near its target (the arms are calibrated)
        miss = np.linalg.norm(np.asarray(c["expected_point"]) - res.targets, axis=1)
        assert np.all(miss < 2.0), miss
        # what each linked module's stiffnesses were drawn from: these modules fitted no
        # compliance, so the prior, its arms alike
        if len(c["arms"]) > 1:
            assert [(r["from"], r["arm_log_centre"]) for r in c["stiffness"]] == [
                ("the prior", 0.0)] * 2
            # predict's record: the prior's scale is arbitrary, so relative to joint 1
            assert all(r["relative"][0] == 1.0 and "nmm_per_rad" not in r
                       for r in c["stiffness"])
        else:
            assert "stiffness" not in c
    # two arms holding one point are more accurate than either alone
    best = {k: min(c["overall"]["error_quantile_mm"] for c in res.candidates
                   if len(c["arms"]) == k) for k in (1, 2)}
    assert best[2] < best[1]
    # a worker's results equal the same candidates evaluated here (pickled modules, same
    # draws); workers run one BLAS thread, whose eigenvectors of the parameter covariance
    # differ from this process's by about 1e-7, hence 1e-4 mm rather than rounding
    job = Job(modules, res.targets, res.reach, design.fusion, design.quantile,
              design.error_mm, design.confidence, design.draws, design.seed,
              design.tracker_noise_mm, design.mounts)
    cands = enumerate_candidates(design, res.reach)
    here = {tuple(c.arms) + tuple(c.mounts): evaluate(job, c, i)
            for i, c in enumerate(cands)}
    for c in res.candidates:
        mine = here[tuple(c["arms"]) + tuple(c["mounts"])]
        np.testing.assert_allclose(c["error_quantile_mm"], mine["error_quantile_mm"],
                                   atol=1e-4)

    linked = next(c for c in res.candidates if len(c["arms"]) == 2)
    out = write_candidate_rig(linked, res, modules, tmp_path / "best")
    assert {p.name for p in out.iterdir()} == {"rig.toml", "measurements.csv", "design.json",
                                               "left.urdf", "right.urdf"}
    with (out / "measurements.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == design.n_targets and all(r["x"] == r["z"] == "" for r in rows)
    # the planned rows hold the aimed joint columns; measured (here: the targets written in),
    # the directory is a chain rig whose arms stand on the chosen mounts
    for r, t in zip(rows, res.targets, strict=True):
        r["x"], r["y"], r["z"] = (f"{v:.4f}" for v in t)
    with (out / "measurements.csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]), lineterminator="\n")
        w.writeheader()
        w.writerows(rows)
    rig = load_rig(out, min_train_rows=0)
    assert rig.is_chain and rig.linked_configs == [linked["config"]]
    for a, j in zip(linked["arms"], linked["mounts"], strict=True):
        np.testing.assert_allclose(rig.robot.chains[a].instrument[:3], design.mounts[j])
        m = rig.measurements.config == linked["config"]
        np.testing.assert_allclose(rig.measurements.commands[a][m], res.reach[a, j],
                                   atol=1e-8)
        # the written arm is the calibrated module: at the planned columns it puts its marker
        # on the target, as the module's own model did when it aimed
        x = jnp.asarray(rig.robot.layout.nominal)
        p = np.asarray(rig.robot.compiled_points(a)(x, jnp.asarray(res.reach[a, j])))
        np.testing.assert_allclose(p, res.targets, atol=0.01)


def test_design_command_on_chain_modules(rig_dir, tmp_path, capsys):
    path = _write(tmp_path, _design_text(rig_dir, MOUNTS[:2], BOX,
                                         extra="").replace("max_arms = 2", "max_arms = 1"))
    out = tmp_path / "out"
    rc = main(["design", str(path), "--out", str(out), "--workers", "2", "--no-progress"])
    text = capsys.readouterr().out
    doc = json.loads((out / "design.json").read_text())
    assert rc == (0 if doc["candidates"][0]["meets"] else 1)
    assert len(doc["candidates"]) == 4 and "(900, 0, 0)" in text
    assert (out / "design.png").stat().st_size > 10_000
    assert (out / "best" / "rig.toml").is_file()
