"""The configuration designer: the design file, candidates, Dask evaluation, outputs, errors.

The Dask tests run a real two-worker LocalCluster (processes), as the command does.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from bayesrob.cli import main
from bayesrob.data.rig import load_rig
from bayesrob.design.file import load_design
from bayesrob.design.modules import load_modules, mounted_truth
from bayesrob.design.search import (
    enumerate_candidates,
    evaluate_batch,
    reach_table,
    run_design,
    task_targets,
    write_candidate_rig,
)

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "design"


def _small_design(tmp_path: Path, **changes: str) -> Path:
    """The worked example cut down: two mounts per module family, few targets and draws."""
    shutil.copytree(EXAMPLE / "modules", tmp_path / "modules")
    text = (EXAMPLE / "design.toml").read_text()
    text = text.replace('grid = { x = [-170.0, 20.0, 3], y = [-20.0, 440.0, 4] }',
                        'points = [[20.0, 440.0], [20.0, -20.0], [-170.0, 287.0], '
                        '[-75.0, 440.0]]')
    text = text.replace("targets = 16", "targets = 6")
    text = text.replace('seed = 1\n', 'seed = 1\ndraws = 400\n')
    for old, new in changes.items():
        assert old in text, old
        text = text.replace(old, new)
    path = tmp_path / "design.toml"
    path.write_text(text)
    return path


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("design")
    design = load_design(_small_design(tmp))
    return design, load_modules(design)


def test_example_design_file_parses():
    d = load_design(EXAMPLE / "design.toml")
    assert set(d.modules) == {"top", "bottom", "side"}
    assert d.mounts.shape == (12, 2)
    assert (d.error_mm, d.quantile, d.confidence, d.max_arms) == (1.2, 0.95, 0.9, 3)


def test_targets_lie_inside_a_polygon_and_are_reproducible():
    tri = np.array([[0.0, 0.0], [100.0, 0.0], [0.0, 100.0]])
    t = task_targets(tri, 40, seed=3)
    assert t.shape == (40, 2)
    assert np.all(t.sum(axis=1) <= 100.0) and np.all(t >= 0)
    np.testing.assert_array_equal(t, task_targets(tri, 40, seed=3))


def test_candidates_use_distinct_mounts_and_only_reaching_placements(small):
    design, modules = small
    targets = task_targets(design.region, design.n_targets, design.seed)
    reach = reach_table(modules, design.mounts, targets)
    cands = enumerate_candidates(design, reach)
    assert cands and all(len(set(c.mounts)) == len(c.mounts) for c in cands)
    assert all((a, j) in reach for c in cands for a, j in zip(c.arms, c.mounts, strict=True))
    # a placement is reachable exactly when its commands aim every target within limits
    for (a, j), u in reach.items():
        arm = modules[a].at(design.mounts[j])
        np.testing.assert_allclose(np.asarray(arm.forward_u(u)), targets, atol=1e-6)
    # the top arm hung from a mount below the task cannot serve it on its elbow branch
    assert ("top", 1) not in reach
    sizes = {len(c.arms) for c in cands}
    assert sizes == {1, 2, 3}


def test_mounted_module_keeps_its_geometry_and_moves_its_truth(small):
    _, modules = small
    m = modules["bottom"]
    moved = m.at((0.0, 0.0))
    np.testing.assert_allclose(np.asarray(moved.params.links), np.asarray(m.arm.params.links))
    np.testing.assert_allclose(np.asarray(moved.params.base), [0.0, 0.0])
    t = mounted_truth(m, (0.0, 0.0))
    shift = -np.asarray(m.arm.params.base)
    np.testing.assert_allclose(t.base, np.asarray(m.truth.base) + shift)


def test_grid_builds_agree_with_the_program_and_meet_by_the_same_rule(tmp_path):
    """Where no program draws a whole assembly (product fusion, histogram COND) the builds come
    from the grid density moved by each build's calibration error. A single arm can take
    both routes: its builds' error quantiles, the share of builds meeting and the spread the
    calibration error adds agree with the equilibrium program's (an independent route:
    numpyro draws of the joint errors and parameters pushed through the arm). A linked
    product candidate is scored by the one rule: ``meets`` is its builds' confidence."""
    from bayesrob.design.modules import PaperModule, _grid_builds
    from bayesrob.design.search import Job, evaluate, score

    design = load_design(_small_design(tmp_path, **{
        "tracker_noise_mm = 0.35": "tracker_noise_mm = 0.0", 'fusion = "equilibrium"':
        'fusion = "product"', "draws = 400": "draws = 3000"}))
    modules = load_modules(design)
    targets = task_targets(design.region, design.n_targets, design.seed)
    reach = reach_table(modules, design.mounts, targets)
    job = Job(modules, targets, reach, design.fusion, design.quantile, design.error_mm,
              design.confidence, design.draws, design.seed, 0.0, design.mounts)
    cand = next(c for c in enumerate_candidates(design, reach) if c.arms == ("side",))
    program, _ = PaperModule.draws(job, cand.arms, cand.mounts, 0)
    m = modules["side"]
    grid = _grid_builds(job, [m], [m.at(cand.bases[0])], [reach["side", cand.mounts[0]]], 0)
    a, b = score(job, cand, program), score(job, cand, grid)
    np.testing.assert_allclose(b["error_quantile_mm"], a["error_quantile_mm"], rtol=0.1)
    assert abs(b["overall"]["assured_error_mm"] / a["overall"]["assured_error_mm"] - 1) < 0.1
    # each build's mean offset over the targets: the calibration error's share of the spread
    spread = [np.std((d - targets[None]).mean(axis=1), axis=0) for d in (program, grid)]
    np.testing.assert_allclose(spread[1], spread[0], rtol=0.15)
    linked = next(c for c in enumerate_candidates(design, reach) if len(c.arms) == 2)
    r = evaluate(job, linked, 1)
    assert 0.0 <= r["confidence"] <= 1.0
    assert r["meets"] == (r["confidence"] >= design.confidence)
    assert r["meets"] == (r["overall"]["assured_error_mm"] <= design.error_mm)


def test_run_on_a_local_cluster_ranks_and_keeps_every_candidate(small, tmp_path):
    design, modules = small
    res = run_design(design, modules, workers=2, batch=8)
    targets = task_targets(design.region, design.n_targets, design.seed)
    n = len(enumerate_candidates(design, reach_table(modules, design.mounts, targets)))
    assert len(res.candidates) == n and res.workers == 2
    # the result's dict is what design.json holds (through JSON: tuples become lists)
    from bayesrob.report.outputs import write_design

    write_design(res, modules, 1, tmp_path)
    assert json.loads((tmp_path / "design.json").read_text()) == json.loads(
        json.dumps(res.to_dict()))
    assert [c["rank"] for c in res.candidates] == list(range(1, n + 1))
    met = [c for c in res.candidates if c["meets"]]
    # ranking: every candidate that meets comes first, fewest modules first among them
    assert res.candidates[: len(met)] == met
    assert [len(c["arms"]) for c in met] == sorted(len(c["arms"]) for c in met)
    for c in res.candidates:
        q = np.asarray(c["error_quantile_mm"])
        assert q.shape == (design.n_targets,) and np.all(q > 0)
        # the pooled quantile lies between the targets' own
        assert q.min() - 1e-9 <= c["overall"]["error_quantile_mm"] <= q.max() + 1e-9
        assert c["meets"] == (c["confidence"] >= design.confidence)
        o = c["overall"]
        assert c["meets"] == (o["assured_error_mm"] <= design.error_mm)
        assert 0 < o["optimistic_error_mm"] <= o["assured_error_mm"]
    # linking helps here: the best linked pair is predicted better than the best single arm
    best = {k: min(c["overall"]["error_quantile_mm"] for c in res.candidates
                   if len(c["arms"]) == k) for k in (1, 2)}
    assert best[2] < best[1]
    doc = res.document
    assert json.loads(json.dumps(doc))["candidates"][0]["arms"] == res.best["arms"]
    rig_dir = write_candidate_rig(res.best, res, modules, tmp_path / "best")
    text = (rig_dir / "measurements.csv").read_text().splitlines()
    assert len(text) == 1 + design.n_targets
    assert all(line.endswith(",,") for line in text[1:])  # planned: x, y empty


def test_a_worker_lost_mid_run_loses_no_result(small, tmp_path):
    """The first attempt of one batch kills its worker process; Dask retries the batch on a
    (restarted) worker and every candidate still comes back once."""
    design, modules = small
    marker = tmp_path / "crashed"
    res = run_design(design, modules, workers=2, batch=6,
                       evaluate=_CrashOnce(str(marker)))
    assert marker.exists()
    targets = task_targets(design.region, design.n_targets, design.seed)
    n = len(enumerate_candidates(design, reach_table(modules, design.mounts, targets)))
    assert len(res.candidates) == n


class _CrashOnce:
    def __init__(self, marker: str):
        self.marker = marker

    def __call__(self, job, batch):
        import os

        if batch[0][0] == 6 and not os.path.exists(self.marker):
            Path(self.marker).write_text("x")
            os._exit(1)
        return evaluate_batch(job, batch)


def test_design_command_writes_its_outputs_and_the_planned_rig_simulates(tmp_path, capsys):
    path = _small_design(tmp_path, **{"max_arms = 3": "max_arms = 2"})
    out = tmp_path / "out"
    rc = main(["design", str(path), "--out", str(out), "--workers", "2", "--no-progress"])
    text = capsys.readouterr().out
    doc = json.loads((out / "design.json").read_text())
    assert rc == (0 if doc["candidates"][0]["meets"] else 1)
    assert "rank" in text and (out / "design.png").stat().st_size > 10_000
    assert doc["candidates"] and all(len(c["arms"]) <= 2 for c in doc["candidates"])
    best = out / "best"
    assert main(["simulate", str(best), "--planned", "--no-progress"]) == 0
    rig = load_rig(best, min_train_rows=0)
    config = "+".join(doc["candidates"][0]["arms"])
    rows = rig.config_rows(config, "test")
    assert len(rows["target"]) == 6
    # measured in simulation: the end points land near the planned targets
    err = np.linalg.norm(rows["observed"] - rows["target"], axis=1)
    assert np.all(err < 5.0)


@pytest.mark.parametrize("edit,message", [
    ({'[modules.side]\nrig = "modules"': '[modules.side]\nrig = "modules"\narm = "elbow"'},
     "unknown module arm 'elbow'"),
    ({"error_mm = 1.2": "error_mm = -1"}, "error_mm = -1 must be a number (must be above 0)"),
    ({"[task]": "[task]\nshape = 1"}, "unknown key 'shape'"),
    ({"tracker_noise_mm = 0.35": "tracker_noise_mm = -0.3"}, "tracker_noise_mm = -0.3 must be 0"),
    ({'[modules.side]\nrig = "modules"': '[modules.side]\nrig = "modules"\nmasses = "cad"'},
     "masses = 'cad' must be \"fitted\" or \"description\""),
    ({'[modules.side]\nrig = "modules"': '[modules.side]\nrig = "modules"\n'
      'masses = "description"'}, "masses is for URDF arms"),
])
def test_bad_design_files_are_one_line_exit_2(tmp_path, capsys, edit, message):
    path = _small_design(tmp_path, **edit)
    rc = main(["design", str(path), "--out", str(tmp_path / "o"), "--no-progress"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and message in err[0], err
    assert not (tmp_path / "o").exists()


def test_no_reachable_mount_is_one_line(tmp_path, capsys):
    path = _small_design(tmp_path)
    text = path.read_text().replace(
        "points = [[20.0, 440.0], [20.0, -20.0], [-170.0, 287.0], [-75.0, 440.0]]",
        "points = [[2000.0, 4400.0], [3000.0, 0.0]]")
    path.write_text(text)
    rc = main(["design", str(path), "--out", str(tmp_path / "o"), "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "no module reaches every target" in err


def test_unreachable_scheduler_is_one_line(tmp_path, capsys, monkeypatch):
    import bayesrob.cluster

    # a shorter wait than the command's 10 s for the same error: nothing listens on port 9
    monkeypatch.setattr(bayesrob.cluster, "CONNECT_TIMEOUT", "1s")
    path = _small_design(tmp_path)
    rc = main(["design", str(path), "--scheduler", "tcp://127.0.0.1:9", "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "cannot reach the Dask scheduler" in err, err


def test_a_requirement_nobody_meets_exits_1_and_names_the_closest(tmp_path, capsys):
    path = _small_design(tmp_path, **{"max_arms = 3": "max_arms = 1",
                                      "error_mm = 1.2": "error_mm = 0.01"})
    out = tmp_path / "out"
    rc = main(["design", str(path), "--out", str(out), "--no-progress"])
    text = capsys.readouterr().out.strip().splitlines()
    doc = json.loads((out / "design.json").read_text())
    closest = doc["candidates"][0]
    assert rc == 1 and not any(c["meets"] for c in doc["candidates"])
    verdict = next(t for t in text if t.startswith("no candidate meets 0.01 mm"))
    assert closest["config"] in verdict
    # the closest is the one nearest to meeting
    assert closest["overall"]["assured_error_mm"] == min(
        c["overall"]["assured_error_mm"] for c in doc["candidates"])
