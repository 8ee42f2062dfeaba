"""``bayesrob collect --plan ...,holdout``: rows at new poses, planned and resumed like the rest.

Against the simulated device through real pseudo-terminals, as in test_hardware_collect.
"""

from __future__ import annotations

import numpy as np
import pytest
from test_hardware_collect import device, keys, plant, rig_dir, run, sim_rig  # noqa: F401

from bayesrob.data.rig import RigError, load_rig, load_rig_toml
from bayesrob.hardware.collect import (
    DEFAULT_PLAN,
    linked_steps,
    parse_plan,
    single_arm_steps,
)
from bayesrob.hardware.controller import quantize_us
from bayesrob.robot import Arm
from bayesrob.sim.rigs import holdout_points

ALL = ("train", "validation", "test", "holdout")


def test_the_default_plan_is_the_papers_and_holdout_can_be_asked_for():
    assert DEFAULT_PLAN == ("train", "validation", "test")
    assert parse_plan("holdout,train") == ("train", "holdout")
    assert parse_plan("train,validation,test,holdout") == ALL


def test_holdout_steps_aim_at_the_grids_cell_centres(sim_rig):  # noqa: F811
    meta = load_rig_toml(sim_rig / "rig.toml")
    specs, ws = meta["arms"], meta["workspace"]
    q = lambda u: quantize_us(u, 0.25)  # noqa: E731
    singles = single_arm_steps(specs, ws, 3, q, ALL)
    assert [s.set for s in singles if s.config == "top"] == (
        ["train"] * 9 + ["validation"] * 9 + ["holdout"] * 4)
    train = {s.commands["top"] for s in singles if s.config == "top" and s.set == "train"}
    hold = {s.commands["top"] for s in singles if s.config == "top" and s.set == "holdout"}
    assert not train & hold  # new poses
    nominal = {n: Arm.nominal(s) for n, s in specs.items()}
    linked = linked_steps(specs, nominal, ws, 3, q, ("test", "holdout"))
    assert [s.set for s in linked] == ["test"] * 9 + ["holdout"] * 4
    np.testing.assert_allclose([s.target for s in linked if s.set == "holdout"],
                               holdout_points(ws, 3))
    assert len(linked_steps(specs, nominal, ws, 3, q)) == 9  # the default: test rows only


def test_collect_with_holdout_writes_and_resumes_them(plant, rig_dir):  # noqa: F811
    """Grid 2: 4 train, 4 validation and 1 holdout row per arm, 4 test and 1 linked holdout
    row. A run stopped after the train rows resumes to the same rows as an uncut run."""
    with device(plant, seed=3) as dev:
        first = run(dev, rig_dir, grid=2, plan=("train",))
        assert first.recorded == 8
        res = run(dev, rig_dir, grid=2, plan=ALL, resume=True)
    assert res.complete and (res.recorded, res.skipped, res.total) == (15, 8, 23)
    rig = load_rig(rig_dir, min_train_rows=0)
    m = rig.measurements
    for arm in ("top", "bottom"):
        assert m.mask(arm, "holdout").sum() == 1
    assert m.mask("top+bottom", "holdout").sum() == 1
    np.testing.assert_allclose(m.target[m.mask("top+bottom", "holdout")],
                               holdout_points(rig.workspace, 2))
    # Linked rows come last, test before holdout; each arm's holdout row after its own rows.
    sets = [k[:2] for k in keys(rig_dir)]
    assert sets[-2:] == [("top+bottom", "test"), ("top+bottom", "holdout")]
    with device(plant, seed=3) as dev:
        again = run(dev, rig_dir, grid=2, plan=ALL, resume=True)
    assert (again.recorded, again.skipped) == (0, 23)
    with device(plant, seed=3) as dev, pytest.raises(RigError, match="not part of this plan"):
        run(dev, rig_dir, grid=2, plan=DEFAULT_PLAN, resume=True)
