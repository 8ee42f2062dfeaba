"""Kernel joint-error densities on any robot whose rows observe its joint errors.

The rule (``joint_errors_observed``): as many joints as measured coordinates, so a residual r
gives the joint errors J^-1 r. A 3-joint arm measured in 3-D is such a robot and no planar arm:
it is predicted and designed through the kernel densities of ``models/``, its joint errors read
through its own Jacobian. The truth is known (the rows are drawn here from the nominal arm with
Gaussian joint errors), so the predictions are checked against it.
"""

from __future__ import annotations

import json
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from bayesrob import robot as kin
from bayesrob.calibrate.arms import ARM_GROUPS, calibrate_arms
from bayesrob.calibrate.least_squares import calibrate
from bayesrob.data.rig import load_rig
from bayesrob.errors.latent_errors import joint_jacobian
from bayesrob.errors.noise_models import (
    joint_errors,
    joint_errors_observed,
    observed_joint_errors,
)
from bayesrob.predict.assembly import predict_assembly
from bayesrob.predict.draws import KernelJointErrors

DEFAULT_RIG = Path(__file__).resolve().parent.parent / "bayesrob" / "data" / "default_rig"

URDF = """<robot name="r3">
  <link name="base"/><link name="l1"/><link name="l2"/><link name="l3"/><link name="tip"/>
  <joint name="yaw" type="revolute"><parent link="base"/><child link="l1"/>
    <axis xyz="0 0 1"/></joint>
  <joint name="shoulder" type="revolute"><parent link="l1"/><child link="l2"/>
    <origin xyz="0 0 0.3"/><axis xyz="0 1 0"/></joint>
  <joint name="elbow" type="revolute"><parent link="l2"/><child link="l3"/>
    <origin xyz="0.3 0 0"/><axis xyz="0 1 0"/></joint>
  <joint name="tool" type="fixed"><parent link="l3"/><child link="tip"/>
    <origin xyz="0.25 0 0"/></joint>
</robot>"""
JOINT_SD = np.array([1.0, 2.0, 0.5]) * 1e-3  # rad: the truth's joint errors, independent
NOISE_MM = 0.02  # the tracker's


def _commands(rng: np.random.Generator, n: int) -> np.ndarray:
    return np.column_stack([rng.uniform(-0.8, 0.8, n), rng.uniform(-0.8, 0.2, n),
                            rng.uniform(0.4, 1.8, n)])


@pytest.fixture(scope="module")
def three_joint(tmp_path_factory) -> tuple[Path, kin.Robot]:
    """A rig directory of a 3-joint arm measured in 3-D: 100 train and 30 validation rows of
    the nominal arm with Gaussian joint errors and tracker noise."""
    d = tmp_path_factory.mktemp("r3")
    (d / "r3.urdf").write_text(URDF)
    (d / "rig.toml").write_text('name = "r3"\n[arms.arm]\nurdf = "r3.urdf"\nroot = "base"\n'
                                'tip = "tip"\n')
    robot = kin.Robot({"arm": kin.urdf_chain(d / "r3.urdf", "base", "tip", "arm")}, 3)
    rng = np.random.default_rng(7)
    u = _commands(rng, 130)
    e = rng.normal(size=u.shape) * JOINT_SD
    x = jnp.asarray(robot.layout.nominal)
    p = np.asarray(robot.marker_points(x, "arm", jnp.asarray(u), jnp.asarray(e)))
    p = p + rng.normal(0.0, NOISE_MM, p.shape)
    lines = ["config,set,target_x,target_y,target_z,arm_u1,arm_u2,arm_u3,x,y,z"]
    for i, (ui, pi) in enumerate(zip(u, p, strict=True)):
        s = "train" if i < 100 else "validation"
        lines.append(",".join(["arm", s, "", "", "", *(f"{v:.10g}" for v in ui),
                               *(f"{v:.6f}" for v in pi)]))
    (d / "measurements.csv").write_text("\n".join(lines) + "\n")
    return d, robot


def _true_expected_error(robot: kin.Robot, u: np.ndarray, rng: np.random.Generator
                         ) -> np.ndarray:
    """E ||J e + eps|| per row of commands u under the truth's joint errors and noise (joint
    errors of a few mrad: linear to parts in a thousand)."""
    jac = np.asarray(joint_jacobian(robot, jnp.asarray(robot.layout.nominal), "arm",
                                    jnp.asarray(u)))
    e = rng.normal(size=(4000, len(u), 3)) * JOINT_SD
    moved = np.einsum("tij,stj->sti", jac, e) + rng.normal(0.0, NOISE_MM, (4000, len(u), 3))
    return np.linalg.norm(moved, axis=-1).mean(axis=0)


def test_the_rule_reads_the_robot_not_its_file_kind(three_joint):
    rig = load_rig(three_joint[0])
    assert rig.is_chain and joint_errors_observed(rig.robot, ["arm"])
    assert joint_errors_observed(load_rig(DEFAULT_RIG).robot, ["top", "bottom"])
    six = kin.Robot({"arm": kin.urdf_chain("six.urdf", "base", "tip", "arm", text=URDF.replace(
        '<joint name="tool" type="fixed">', '<joint name="tool" type="revolute">'))}, 3)
    assert not joint_errors_observed(six, ["arm"])  # four joints, three coordinates


def test_chain_jacobian_reads_the_planar_arms_joint_errors_as_their_inverse_does():
    """The general J^-1 r on the default rig equals the paper's closed-form inverse
    f^-1(d) - g(u) of the same calibration to the linearisation's second order: errors of up
    to 10 mrad differ by at most 5% of their spread, typically by under 1%."""
    rig = load_rig(DEFAULT_RIG)
    cal = calibrate(rig, ARM_GROUPS)
    paper = calibrate_arms(rig)
    for a in rig.arms:
        u, general = observed_joint_errors(rig, cal.robot, cal.x, a)
        closed = joint_errors(paper[a].arm, *rig.rows(a, "train"))
        scale = closed.std(axis=0)
        gap = np.abs(general - closed)
        assert np.all(gap.max(axis=0) < 0.05 * scale), (a, gap.max(axis=0) / scale)
        assert np.all(np.median(gap, axis=0) < 0.01 * scale), a


def test_three_joint_arm_is_predicted_through_kernel_densities(three_joint):
    """Each model of ``models/`` (IND matches the truth's independent joints) predicts the
    mean error at the validation poses within 25% of the truth's, and a fifth of the 90%
    region's size would miss it: the kernel route reads the joint errors right."""
    d, robot = three_joint
    rig = load_rig(d)
    u, p = rig.rows("arm", "validation")
    targets = p[:6]
    truth = _true_expected_error(robot, u[:6], np.random.default_rng(1))
    # the default model where the rows observe the joint errors is the paper's COND
    for model, name in (("ind", "ind"), (None, "cond")):
        pred = predict_assembly(rig, "arm", targets, model=model)
        assert pred.model == name
        ratio = pred.expected_error_mm.mean() / truth.mean()
        assert 0.8 < ratio < 1.25, (name, ratio)


def test_three_joint_modules_are_designed_through_kernel_densities(three_joint, tmp_path):
    from bayesrob.design.file import load_design
    from bayesrob.design.modules import CalibratedModule, load_modules
    from bayesrob.design.search import run_design

    d, _ = three_joint
    path = tmp_path / "design.toml"
    path.write_text(f"""
seed = 3
draws = 400
tracker_noise_mm = {NOISE_MM}
[modules.a]
rig = "{d}"
arm = "arm"
[modules.b]
rig = "{d}"
arm = "arm"
[mounts]
points = {json.dumps([[0.0, -100.0, 0.0], [0.0, 100.0, 0.0]])}
[task]
box = {json.dumps([[270.0, 330.0], [-40.0, 40.0], [250.0, 330.0]])}
targets = 4
[requirement]
error_mm = 2.0
quantile = 0.95
[limits]
max_arms = 2
""")
    design = load_design(path)
    modules = load_modules(design)
    assert all(isinstance(m, CalibratedModule) and isinstance(m.mods.errors["arm"],
                                                               KernelJointErrors)
               for m in modules.values())
    res = run_design(design, modules, workers=1, batch=8)
    singles = [c for c in res.candidates if len(c["arms"]) == 1]
    linked = [c for c in res.candidates if len(c["arms"]) == 2]
    assert len(singles) == 4 and len(linked) == 2
    for c in res.candidates:
        assert c["models"] == ["ind"] * len(c["arms"])
        miss = np.linalg.norm(np.asarray(c["expected_point"]) - res.targets, axis=1)
        assert np.all(miss < 1.0), miss
    # an arm alone errs as its joints do (1-2 mrad at 0.3-0.55 m: about a millimetre), and
    # two arms holding one point err less than either alone
    best = {k: min(c["overall"]["error_quantile_mm"] for c in res.candidates
                   if len(c["arms"]) == k) for k in (1, 2)}
    assert 0.5 < best[1] < 3.0 and best[2] < best[1], best
