"""Simulated 3-D chain rigs: a 6-joint URDF arm whose true geometry differs from its nominal
URDF, measured by an instrument at random poses.

The truth perturbs every joint origin (translations and small rotations), the joint zero
offsets, the marker's position on the tool and the robot's pose in the instrument frame; rows
carry joint repeatability noise and measurement noise, and optionally joint compliance under
gravity: each joint gives way by its gravity torque over its stiffness (point masses at the
links' centres), at the deflected pose's equilibrium. Training, validation and holdout rows are
drawn at different random poses. The planar paper rigs come from :mod:`bayesrob.simulator`.
"""

from __future__ import annotations

import shutil
from dataclasses import asdict, dataclass, field
from importlib.resources import files
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from bayesrob.kinematics import Robot, urdf_chain
from bayesrob.rig import dump_toml

ARM6_URDF = "arm6.urdf"
G_N_PER_KG = 9.81  # weight per kg of mass: torques in N mm with lever arms in mm


def arm6_urdf_path() -> Path:
    return Path(str(files("bayesrob.data") / "arm6" / ARM6_URDF))


@dataclass
class ChainTruth:
    """What a simulated chain rig really is (written to truth.toml)."""

    seed: int = 0
    n_train: int = 80
    n_validation: int = 40
    n_holdout: int = 40
    origin_sd_mm: float = 1.0
    origin_sd_rad: float = 2e-3
    offset_sd_rad: float = 3e-3
    marker_nominal_mm: tuple[float, float, float] = (0.0, 0.0, 50.0)
    marker_sd_mm: float = 2.0
    instrument_nominal: tuple[float, ...] = (1200.0, -300.0, 150.0, 0.0, 0.0, 0.4)
    instrument_sd: tuple[float, float] = (5.0, 5e-3)  # mm, rad
    joint_noise_rad: float = 1e-4
    measurement_noise_mm: float = 0.1
    compliance: bool = False
    masses_kg: tuple[float, ...] = (3.7, 8.4, 2.3, 1.2, 1.2, 0.2)
    stiffness_nmm_per_rad: tuple[float, ...] = (4e6, 4e6, 2e6, 6e5, 6e5, 6e5)
    true_params: dict = field(default_factory=dict)  # filled by simulate_chain_rig


def _poses(rng: np.random.Generator, n: int) -> np.ndarray:
    """Random joint angles over a working range that keeps the arm off its own base."""
    lo = np.array([-2.8, -2.2, -2.4, -2.8, -2.8, -3.0])
    hi = np.array([2.8, -0.6, 2.4, 2.8, 2.8, 3.0])
    return rng.uniform(lo, hi, size=(n, 6))


def _true_vector(robot: Robot, truth: ChainTruth, rng: np.random.Generator) -> np.ndarray:
    layout = robot.layout
    x = layout.nominal.copy()
    for i, p in enumerate(layout.params):
        axis = p.name.rsplit(".", 1)[-1]
        rot = axis in ("rx", "ry", "rz")
        if ".origin." in p.name:
            x[i] += rng.normal(0, truth.origin_sd_rad if rot else truth.origin_sd_mm)
        elif p.name.endswith(".offset"):
            x[i] += rng.normal(0, truth.offset_sd_rad)
        elif ".marker." in p.name:
            x[i] += rng.normal(0, truth.marker_sd_mm)
        elif ".instrument." in p.name:
            x[i] += rng.normal(0, truth.instrument_sd[1] if rot else truth.instrument_sd[0])
    return x


def gravity_deflection(robot: Robot, x: np.ndarray, arm: str, q: np.ndarray,
                       masses_kg: np.ndarray, stiffness: np.ndarray,
                       gravity: np.ndarray, iterations: int = 4) -> np.ndarray:
    """Joint deflections (N, n) at equilibrium: dq = tau(q + dq) / k, by fixed-point steps.

    Each link's mass sits halfway along the next origin's translation (its centre); the
    torque about a joint is that of the masses beyond it about its axis. Deflections are a few
    mrad, so the step contracts fast (four steps change nothing above 1e-9 rad).
    """
    chain = robot.chains[arm]
    half = np.array([np.r_[0.5 * o[:3], 1.0] for o in chain.origins[1:]])  # (n, 4)
    g = np.asarray(gravity, float) * G_N_PER_KG
    dq = np.zeros_like(q)
    for _ in range(iterations):
        joints, links = robot.element_frames(jnp.asarray(x), arm, jnp.asarray(q + dq))
        joints, links = np.asarray(joints), np.asarray(links)
        n = chain.n_joints
        centres = np.einsum("enij,ej->eni", links[:n], half)[..., :3]  # (n, N, 3)
        forces = masses_kg[:, None, None] * g  # (n, 1, 3)
        tau = np.zeros_like(q)
        for i in range(n):
            axis = joints[i, :, :3, :3] @ chain.axes[i]
            origin = joints[i, :, :3, 3]
            moment = np.cross(centres[i:] - origin[None], np.broadcast_to(
                forces[i:], centres[i:].shape)).sum(axis=0)
            tau[:, i] = np.sum(moment * axis, axis=1)
        dq = tau / stiffness
    return dq


def simulate_chain_rig(out_dir: str | Path, truth: ChainTruth) -> Path:
    """Write rig.toml, arm6.urdf (nominal), measurements.csv and truth.toml into out_dir."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(truth.seed)
    nominal = urdf_chain(arm6_urdf_path(), "base_link", "tool0", "arm",
                         marker=truth.marker_nominal_mm, instrument=truth.instrument_nominal)
    robot = Robot({"arm": nominal}, 3)
    x_true = _true_vector(robot, truth, rng)
    # The instrument sees gravity along -z of the robot base; frames for torques are taken with
    # the base at the identity so that direction holds.
    base_robot = Robot({"arm": urdf_chain(arm6_urdf_path(), "base_link", "tool0", "arm")}, 3)
    x_base = x_true.copy()
    x_base[base_robot.layout.slices[("arm", "instrument")]] = 0.0
    rows = []
    for set_name, n in (("train", truth.n_train), ("validation", truth.n_validation),
                        ("holdout", truth.n_holdout)):
        if n == 0:
            continue
        q_cmd = _poses(rng, n)
        q = q_cmd + rng.normal(0, truth.joint_noise_rad, q_cmd.shape)
        if truth.compliance:
            q = q + gravity_deflection(base_robot, x_base, "arm", q,
                                       np.asarray(truth.masses_kg),
                                       np.asarray(truth.stiffness_nmm_per_rad),
                                       np.array([0.0, 0.0, -1.0]))
        p = np.asarray(robot.marker_points(jnp.asarray(x_true), "arm", jnp.asarray(q)))
        p = p + rng.normal(0, truth.measurement_noise_mm, p.shape)
        rows += [(set_name, qc, pc) for qc, pc in zip(q_cmd, p, strict=True)]
    header = ["config", "set", *[f"arm_u{k + 1}" for k in range(6)], "x", "y", "z"]
    lines = [",".join(header)]
    for set_name, qc, pc in rows:
        lines.append(",".join(["arm", set_name, *(f"{v:.10g}" for v in qc),
                               *(f"{v:.4f}" for v in pc)]))
    (out / "measurements.csv").write_text("\n".join(lines) + "\n")
    shutil.copy(arm6_urdf_path(), out / ARM6_URDF)
    rig = {"name": f"arm6-seed{truth.seed}", "gravity": [0.0, 0.0, -1.0],
           "arms": {"arm": {"urdf": ARM6_URDF, "root": "base_link", "tip": "tool0",
                            "marker": list(truth.marker_nominal_mm),
                            "instrument": list(truth.instrument_nominal)}}}
    (out / "rig.toml").write_text(dump_toml(rig))
    truth.true_params = {name: float(v) for name, v in zip(robot.layout.names, x_true,
                                                            strict=True)}
    doc = {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(truth).items()}
    (out / "truth.toml").write_text(dump_toml({"chain_truth": doc}))
    return out


def load_true_params(rig_dir: str | Path) -> dict[str, float]:
    """The true parameter values a simulated chain rig was made with."""
    import tomllib

    doc = tomllib.loads((Path(rig_dir) / "truth.toml").read_text())
    return doc["chain_truth"]["true_params"]
