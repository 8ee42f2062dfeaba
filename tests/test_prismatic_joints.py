"""Robots with slides (prismatic joints), which no study or rig here has: a Cartesian gantry
aimed far from its train poses, and a 5-joint DH arm with a slide taken through calibration,
prediction, comparison and sampling. The rows are made by the robot model itself (a perturbed
geometry as the truth, joint and measurement noise drawn with fixed seeds)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

import bayesrob
from bayesrob.predict.aiming import IK_TOL_MM, aim
from bayesrob.robot.dh import dh_chain

JOINT_NOISE_RAD = 2e-3
NOISE_MM = 0.05


def _rig(arm, u: np.ndarray, sets: np.ndarray, observed: np.ndarray | None = None):
    name = arm.name
    rows = bayesrob.Measurements.from_arrays(
        config=[name] * len(u), set=sets, commands={name: u},
        observed=np.zeros((len(u), 3)) if observed is None else observed)
    return bayesrob.Rig.from_arrays({name: arm}, rows, name=name)


def _points(robot, arm: str, x: np.ndarray, u: np.ndarray) -> np.ndarray:
    return np.asarray(robot.compiled_points(arm)(jnp.asarray(x), jnp.asarray(u), None))


def test_aims_a_gantry_at_targets_far_from_its_train_poses():
    # x, y, z slides and a wrist carrying the marker 50 mm off its axis
    arm = dh_chain("gantry", [[0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, np.pi / 2],
                              [0.0, np.pi / 2, 0.0, np.pi / 2], [100.0, 0.0, 0.0, 0.0]],
                   kinds=["prismatic", "prismatic", "prismatic", "revolute"],
                   marker=[50.0, 0.0, 0.0])
    rng = np.random.default_rng(0)
    lo, hi = [0.0, 0.0, 0.0, -1.0], [800.0, 600.0, 400.0, 1.0]
    u = rng.uniform(lo, hi, size=(60, 4))
    robot = _rig(arm, u, np.full(60, "train")).robot
    x = robot.layout.nominal
    rig = _rig(arm, u, np.full(60, "train"), _points(robot, "gantry", x, u))
    # targets about 100 mm from the nearest of 60 train poses: at 0.3 mm a step on a slide,
    # as when every column's step was limited as if it turned a joint, aim fell 30 mm short
    targets = _points(robot, "gantry", x, rng.uniform(lo, hi, size=(10, 4)))
    commands = aim(rig, robot, x, "gantry", targets)
    miss = np.linalg.norm(_points(robot, "gantry", x, commands) - targets, axis=1)
    assert miss.max() < IK_TOL_MM


@pytest.fixture(scope="module")
def slide_arm():
    """A 5-joint arm (waist, shoulder, elbow, slide, wrist) with its geometry perturbed from
    nominal by half its parameters' typical sizes, joint noise 2 mrad, marker noise 0.05 mm."""
    arm = dh_chain("slide", [[300.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, np.pi / 2],
                             [0.0, 0.0, 250.0, 0.0], [150.0, 0.0, 0.0, np.pi / 2],
                             [0.0, 0.0, 0.0, -np.pi / 2]],
                   kinds=["revolute", "revolute", "revolute", "prismatic", "revolute"],
                   marker=[30.0, 0.0, 40.0], instrument=[900.0, 200.0, -100.0, 0.0, 0.0, 0.3])
    rng = np.random.default_rng(7)
    lo, hi = np.array([-1.5, -1.5, -1.5, 0.0, -2.0]), np.array([1.5, 1.5, 1.5, 120.0, 2.0])
    u = rng.uniform(lo, hi, size=(260, 5))
    sets = np.array(["train"] * 160 + ["validation"] * 60 + ["holdout"] * 40)
    robot = _rig(arm, u, sets).robot
    layout = robot.layout
    truth = layout.nominal + layout.group_mask(("geometric",)) * rng.normal(
        size=layout.nominal.shape) * layout.scales * 0.5

    def measure(commands: np.ndarray) -> np.ndarray:
        e = rng.normal(size=commands.shape) * JOINT_NOISE_RAD * (lo[None] != 0.0)
        return (_points(robot, "slide", truth, commands + e)
                + rng.normal(size=(len(commands), 3)) * NOISE_MM)

    return _rig(arm, u, sets, measure(u)), measure


def test_an_arm_with_a_slide_is_calibrated_predicted_compared_and_sampled(slide_arm):
    rig, measure = slide_arm
    groups = ("frames", "geometric")
    cal = bayesrob.calibrate.calibrate(rig, groups)
    # the joint noise alone moves the marker about 0.85 mm at these levers: a calibration that
    # missed the slide's geometry would sit well above it
    assert cal.errors["validation"]["all"]["mean_mm"] < 1.0

    targets = rig.measurements.observed[rig.measurements.set == "holdout"]
    pred = bayesrob.predict_assembly(rig, "slide", targets, groups=groups).to_dict()
    commands = np.array([t["commands"]["slide"] for t in pred["targets"]])
    # 20 measurements at each of 40 aimed poses: the mean error is known to about 2%, the
    # predicted mean error (calibration uncertainty and fitted population) was 6% below it when
    # this test was written, and 20% is far below what a wrong unit on the slide would give
    measured = np.mean([np.linalg.norm(measure(commands) - targets, axis=1)
                        for _ in range(20)])
    assert pred["summary"]["mean_expected_error_mm"] == pytest.approx(measured, rel=0.2)

    comp = bayesrob.compare_models(rig, ["ind", "cond"], groups=groups).to_dict()
    elpd = {row["model"]: row["elpd"] for row in comp["heldout_compare"]}
    # the rows were made with independent joint noise: IND, the truth's model, must rank first
    assert np.isfinite(list(elpd.values())).all() and elpd["ind"] > elpd["cond"]

    for sampler in ("nuts", "emcee"):
        report = bayesrob.sample_linked(rig, "slide", targets[0], model="ind", sampler=sampler,
                                        groups=groups)
        assert report.passed, sampler
