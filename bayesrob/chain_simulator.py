"""Simulated 3-D chain rigs: a 6-joint URDF arm whose true geometry differs from its nominal
URDF, measured by an instrument at random poses.

The truth perturbs every joint origin (translations and small rotations), the joint zero
offsets, the marker's position on the tool and the robot's pose in the instrument frame; rows
carry joint repeatability noise and measurement noise, and optionally joint compliance under
gravity: each joint gives way by its gravity torque over its stiffness (point masses at the
links' centres), at the deflected pose's equilibrium. Training, validation and holdout rows are
drawn at different random poses. The planar paper rigs come from :mod:`bayesrob.simulator`.

:func:`simulate_linked_chain_rig` writes a rig of two such arms facing each other, with
single-arm rows for each and ``left+right`` rows where their markers are joined at one point:
the arms settle at the exact minimum of their summed spring and gravity energy with the
markers together (:func:`linked_equilibrium`). :func:`three_linked_chain_truth` adds a third
arm (``front``) and joins all three.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from functools import partial
from importlib.resources import files
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from threadpoolctl import threadpool_limits

from bayesrob.kinematics import Robot, RobotStructure, urdf_chain
from bayesrob.kinematics.chain import G_N_PER_KG
from bayesrob.rig import dump_toml
from bayesrob.simulator import draw_stiffnesses

ARM6_URDF = "arm6.urdf"


def arm6_urdf_path() -> Path:
    return Path(str(files("bayesrob.data") / "arm6" / ARM6_URDF))


@dataclass
class _ArmErrors:
    """How far a simulated arm6 is from its nominal URDF and how noisy its rows are: the
    settings a single-arm and a linked chain rig share."""

    seed: int = 0
    n_train: int = 80
    n_validation: int = 40
    n_holdout: int = 40
    origin_sd_mm: float = 1.0
    origin_sd_rad: float = 2e-3
    offset_sd_rad: float = 3e-3
    marker_nominal_mm: tuple[float, float, float] = (0.0, 0.0, 50.0)
    marker_sd_mm: float = 2.0
    instrument_sd: tuple[float, float] = (5.0, 5e-3)  # mm, rad
    joint_noise_rad: float = 1e-4
    measurement_noise_mm: float = 0.1
    masses_kg: tuple[float, ...] = (3.7, 8.4, 2.3, 1.2, 1.2, 0.2)


@dataclass
class ChainTruth(_ArmErrors):
    """What a simulated chain rig really is (written to truth.toml)."""

    instrument_nominal: tuple[float, ...] = (1200.0, -300.0, 150.0, 0.0, 0.0, 0.4)
    compliance: bool = False
    stiffness_nmm_per_rad: tuple[float, ...] = (4e6, 4e6, 2e6, 6e5, 6e5, 6e5)
    # each joint's encoder disk sits off its axis by this fraction of its radius (0: none),
    # at a phase drawn per joint: the angle read is off by atan2(e sin, 1 + e cos), a
    # sinusoid once per revolution and its harmonics
    encoder_eccentricity: float = 0.0
    encoder_phase_rad: tuple[float, ...] = ()  # filled by simulate_chain_rig
    # each joint's play (rad, whole width; 0: none): the joint rests against the side its
    # gravity torque pushes it to; where that torque is weaker than the friction that holds
    # it (play_stick_nmm), on the side it was approached from, drawn per row
    joint_play_rad: float = 0.0
    play_stick_nmm: float = 2000.0
    true_params: dict = field(default_factory=dict)  # filled by simulate_chain_rig


# The working range of arm6's joints (rad): the shoulder lift keeps the arm off its own base.
POSE_LO = np.array([-2.8, -2.2, -2.4, -2.8, -2.8, -3.0])
POSE_HI = np.array([2.8, -0.6, 2.4, 2.8, 2.8, 3.0])


def _poses(rng: np.random.Generator, n: int) -> np.ndarray:
    """Random joint angles over the working range."""
    return rng.uniform(POSE_LO, POSE_HI, size=(n, 6))


def _true_vector(robot: Robot, truth: _ArmErrors, rng: np.random.Generator) -> np.ndarray:
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


ENCODER_STREAM = 7  # the encoder phases' own random stream: other draws stay as they were


def encoder_error(q_read: np.ndarray, eccentricity: float, phase: np.ndarray) -> np.ndarray:
    """How far each joint really is from the angle its eccentric encoder reads (rad): a disk
    of radius 1 whose centre sits ``eccentricity`` off the axis at ``phase``, read by a fixed
    head, puts the read angle ahead of the true one by atan2(e sin(q - phase), 1 + e cos(q -
    phase))."""
    d = np.asarray(q_read) - np.asarray(phase)
    return -np.arctan2(eccentricity * np.sin(d), 1.0 + eccentricity * np.cos(d))


@partial(jax.jit, static_argnames=("structure", "arm"))
def _element_frames(structure: RobotStructure, arm: str, values: dict, x: jax.Array,
                    u: jax.Array) -> tuple[jax.Array, jax.Array]:
    return structure.robot(values).element_frames(x, arm, u)


def _frames_program(robot: Robot, arm: str) -> Callable:
    """``robot.element_frames`` of one arm, compiled once per process for all robots of
    ``robot``'s structure: the fixed-point steps below call it repeatedly, and run eagerly
    it took most of a simulation's time."""
    return partial(_element_frames, robot.structure, arm, robot.nominal_values)


def gravity_torques(robot: Robot, x: np.ndarray, arm: str, q: np.ndarray,
                    masses_kg: np.ndarray, gravity: np.ndarray) -> np.ndarray:
    """The gravity torque (N, n) about each joint's axis at joint values q (N mm).

    Each link's mass sits halfway along the next origin's translation (its centre); the
    torque about a joint is that of the masses beyond it about its axis.
    """
    chain = robot.chains[arm]
    half = np.array([np.r_[0.5 * o[:3], 1.0] for o in chain.origins[1:]])  # (n, 4)
    g = np.asarray(gravity, float) * G_N_PER_KG
    joints, links = _frames_program(robot, arm)(jnp.asarray(x), jnp.asarray(q))
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
    return tau


def gravity_deflection(robot: Robot, x: np.ndarray, arm: str, q: np.ndarray,
                       masses_kg: np.ndarray, stiffness: np.ndarray,
                       gravity: np.ndarray, iterations: int = 4) -> np.ndarray:
    """Joint deflections (N, n) at equilibrium: dq = tau(q + dq) / k, by fixed-point steps
    (torques of :func:`gravity_torques`). Deflections are a few mrad, so the step contracts
    fast: at the default masses and stiffnesses four steps leave about 1e-6 rad, eight about
    1e-12 rad (more for softer joints).
    """
    dq = np.zeros_like(q)
    for _ in range(iterations):
        dq = gravity_torques(robot, x, arm, q + dq, masses_kg, gravity) / stiffness
    return dq


PLAY_STREAM = 8  # the approach sides' own random stream: other draws stay as they were


def play_offsets(tau: np.ndarray, play: float, stick_nmm: float,
                 rng: np.random.Generator, approach: np.ndarray | None = None) -> np.ndarray:
    """Where each joint rests in its play (N, n) rad: half the play towards its gravity torque
    ``tau`` (N mm), or, where the torque is weaker than ``stick_nmm``, towards the side it
    was approached from: ``approach`` (N, n; +1, -1) where given and non-zero, else drawn
    from ``rng``."""
    drawn = rng.choice([-1.0, 1.0], size=tau.shape)
    if approach is not None:
        drawn = np.where(approach != 0, np.sign(approach), drawn)
    side = np.where(np.abs(tau) > stick_nmm, np.sign(tau), drawn)
    return 0.5 * play * side


@dataclass
class _Arm6Plant:
    """A simulated arm6 as it really is: the robots and true parameters its rows come from."""

    truth: ChainTruth
    robot: Robot
    x_true: np.ndarray
    base_robot: Robot
    x_base: np.ndarray
    phase: np.ndarray

    @classmethod
    def build(cls, truth: ChainTruth, rng: np.random.Generator) -> _Arm6Plant:
        """The plant of ``truth``: its true parameters as ``truth.true_params`` has them, or,
        before they are drawn, drawn from ``rng``."""
        nominal = urdf_chain(arm6_urdf_path(), "base_link", "tool0", "arm",
                             marker=truth.marker_nominal_mm,
                             instrument=truth.instrument_nominal)
        robot = Robot({"arm": nominal}, 3)
        x_true = (np.array([truth.true_params[n] for n in robot.layout.names])
                  if truth.true_params else _true_vector(robot, truth, rng))
        # The instrument sees gravity along -z of the robot base; frames for torques are
        # taken with the base at the identity so that direction holds.
        base_robot = Robot({"arm": urdf_chain(arm6_urdf_path(), "base_link", "tool0",
                                              "arm")}, 3)
        x_base = np.array(x_true, float)
        x_base[base_robot.layout.slices[("arm", "instrument")]] = 0.0
        phase = np.random.default_rng([truth.seed, ENCODER_STREAM]).uniform(-np.pi, np.pi, 6)
        return cls(truth, robot, np.asarray(x_true, float), base_robot, x_base, phase)

    def measure(self, q_cmd: np.ndarray, rng: np.random.Generator,
                approach_rng: np.random.Generator, approach: np.ndarray | None = None
                ) -> np.ndarray:
        """Marker points (N, 3) mm at the commanded joint angles ``q_cmd`` (N, 6); each
        joint's ``approach`` side (N, 6; +1, -1, 0: unknown) where the rows record it."""
        truth, masses, down = self.truth, np.asarray(self.truth.masses_kg), np.array(
            [0.0, 0.0, -1.0])
        q = q_cmd + rng.normal(0, truth.joint_noise_rad, q_cmd.shape)
        if truth.encoder_eccentricity:
            q = q + encoder_error(q_cmd, truth.encoder_eccentricity, self.phase)
        if truth.joint_play_rad:
            q = q + play_offsets(gravity_torques(self.base_robot, self.x_base, "arm", q,
                                                 masses, down),
                                 truth.joint_play_rad, truth.play_stick_nmm, approach_rng,
                                 approach)
        if truth.compliance:
            q = q + gravity_deflection(self.base_robot, self.x_base, "arm", q, masses,
                                       np.asarray(truth.stiffness_nmm_per_rad), down)
        p = np.asarray(self.robot.marker_points(jnp.asarray(self.x_true), "arm",
                                                jnp.asarray(q)))
        return p + rng.normal(0, truth.measurement_noise_mm, p.shape)


def simulate_chain_rig(out_dir: str | Path, truth: ChainTruth) -> Path:
    """Write rig.toml, arm6.urdf (nominal), measurements.csv and truth.toml into out_dir."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(truth.seed)
    plant = _Arm6Plant.build(truth, rng)
    if truth.encoder_eccentricity:
        truth.encoder_phase_rad = tuple(float(v) for v in plant.phase)
    approach = np.random.default_rng([truth.seed, PLAY_STREAM])
    robot, x_true = plant.robot, plant.x_true
    rows = []
    for set_name, n in (("train", truth.n_train), ("validation", truth.n_validation),
                        ("holdout", truth.n_holdout)):
        if n == 0:
            continue
        q_cmd = _poses(rng, n)
        p = plant.measure(q_cmd, rng, approach)
        rows += [(set_name, qc, pc) for qc, pc in zip(q_cmd, p, strict=True)]
    write_arm6_rig(out, f"arm6-seed{truth.seed}", rows, truth)
    truth.true_params = {name: float(v) for name, v in zip(robot.layout.names, x_true,
                                                            strict=True)}
    doc = {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(truth).items()}
    (out / "truth.toml").write_text(dump_toml({"chain_truth": doc}))
    return out


def write_arm6_rig(out: Path, name: str, rows: Sequence[tuple[str, np.ndarray, np.ndarray]],
                   errors: _ArmErrors) -> None:
    """rig.toml, the nominal arm6.urdf and measurements.csv of a single arm6: ``rows`` are
    (set, joint readings (6,), marker point (3,) in mm)."""
    header = ["config", "set", *[f"arm_u{k + 1}" for k in range(6)], "x", "y", "z"]
    lines = [",".join(header)]
    for set_name, qc, pc in rows:
        lines.append(",".join(["arm", set_name, *(f"{v:.10g}" for v in qc),
                               *(f"{v:.4f}" for v in pc)]))
    (out / "measurements.csv").write_text("\n".join(lines) + "\n")
    shutil.copy(arm6_urdf_path(), out / ARM6_URDF)
    rig = {"name": name, "gravity": [0.0, 0.0, -1.0],
           "arms": {"arm": {"urdf": ARM6_URDF, "root": "base_link", "tip": "tool0",
                            "marker": list(errors.marker_nominal_mm),
                            "instrument": list(errors.instrument_nominal)}}}
    (out / "rig.toml").write_text(dump_toml(rig))


POSES_STREAM = 9  # the noise of rows measured at given poses: apart from the rig's own


def approach_sides(q_cmd: np.ndarray, previous: np.ndarray | None) -> np.ndarray:
    """Each joint's approach side (N, n): the sign of its move from the command before (the
    row before, or ``previous`` for the first; 0 where that is unknown or it did not move)."""
    before = np.vstack([np.full((1, q_cmd.shape[1]), np.nan) if previous is None
                        else np.asarray(previous, float)[None], q_cmd[:-1]])
    return np.nan_to_num(np.sign(q_cmd - before))


def measure_chain_poses(rig_dir: str | Path, sets: Sequence[str], q_cmd: np.ndarray,
                        seed: int = 0) -> int:
    """Measure the joint commands ``q_cmd`` (N, 6), in this order, on the simulated arm6 in
    ``rig_dir`` (its truth.toml) and append them to its measurements.csv with their ``sets``
    and each joint's approach side (``arm_d1..6``, from the command before: the arm moves
    from pose to pose). Returns the rows appended."""
    import csv
    import io
    import os
    import tomllib

    out = Path(rig_dir)
    table = dict(tomllib.loads((out / "truth.toml").read_text())["chain_truth"])
    names = [f.name for f in ChainTruth.__dataclass_fields__.values()]
    truth = ChainTruth(**{k: (tuple(v) if isinstance(v, list) else v)
                          for k, v in table.items() if k in names})
    rng = np.random.default_rng([seed, truth.seed, POSES_STREAM])
    plant = _Arm6Plant.build(truth, rng)
    path = out / "measurements.csv"
    with path.open(newline="") as fh:
        rows = list(csv.reader(fh))
    header, body = rows[0], rows[1:]
    cmd_cols = [f"arm_u{k + 1}" for k in range(6)]
    dir_cols = [f"arm_d{k + 1}" for k in range(6)]
    if dir_cols[0] not in header:
        header = [*header, *dir_cols]
        body = [r + [""] * 6 for r in body]
    idx = {h: i for i, h in enumerate(header)}
    previous = (np.array([float(body[-1][idx[c]]) for c in cmd_cols]) if body else None)
    approach = approach_sides(np.asarray(q_cmd, float), previous)
    p = plant.measure(np.asarray(q_cmd, float), rng, rng, approach)
    for s, qc, d, pc in zip(sets, q_cmd, approach, p, strict=True):
        row = [""] * len(header)
        row[idx["config"]], row[idx["set"]] = "arm", s
        for c, v in zip(cmd_cols, qc, strict=True):
            row[idx[c]] = f"{v:.10g}"
        for c, v in zip(dir_cols, d, strict=True):
            row[idx[c]] = f"{v:g}"
        for a, v in zip("xyz", pc, strict=True):
            row[idx[a]] = f"{v:.4f}"
        body.append(row)
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerows([header, *body])
    tmp = path.with_suffix(".csv.tmp")
    tmp.write_text(buf.getvalue())
    os.replace(tmp, path)
    return len(q_cmd)


def load_true_params(rig_dir: str | Path) -> dict[str, float]:
    """The true parameter values a simulated chain rig (one arm or two linked) was made with."""
    import tomllib

    doc = tomllib.loads((Path(rig_dir) / "truth.toml").read_text())
    table = doc["chain_truth"] if "chain_truth" in doc else doc["linked_chain_truth"]
    return table["true_params"]


# ----------------------------------------------------------------------------- linked arms
# Two arm6 arms facing each other over a shared workspace (and, for assemblies of three, a
# third from the side), their markers joined by a ball joint for the linked rows. The joined
# point is found exactly, as the minimum of the arms' summed spring and gravity energy under
# the constraint that the markers coincide: the prediction code under test balances
# linearised stiffnesses, so the simulator must not.

LINKED_ARMS = ("left", "right")
# A third arm for assemblies of three: facing the targets from the side (its base 450 mm from
# the box's middle line, turned a quarter turn), so the box lies where it lies for the left
# arm in the arm's own frame; stiffer than the right arm, softer than the left.
THIRD_ARM = "front"
THIRD_ARM_INSTRUMENT = (450.0, -450.0, 0.0, 0.0, 0.0, np.pi / 2)
THIRD_ARM_STIFFNESS_SCALE = 0.8
GRAVITY = (0.0, 0.0, -1.0)  # unit gravity in the instrument frame


class LinkedSimulationError(RuntimeError):
    """A linked row cannot be made: no joint solution reaches a target within the working
    range, or the joined arms' equilibrium did not settle."""


def _left_stiffness() -> tuple[float, ...]:
    return ChainTruth().stiffness_nmm_per_rad


@dataclass
class LinkedChainTruth(_ArmErrors):
    """What a simulated rig of linked arm6 arms (two, or ``arms``) really is (truth.toml).

    Per-arm settings are tables keyed by arm name (``left``, ``right``; ``arms`` names the
    arms, in order: :func:`three_linked_chain_truth` adds ``front``); everything else is
    shared. ``true_params`` holds every arm's parameters under their full names
    (``left.marker.x``); ``linked_rows`` what the linked rows really did (filled by
    :func:`simulate_linked_chain_rig`).
    """

    n_linked: int = 24
    arms: tuple[str, ...] = LINKED_ARMS
    # Bases 900 mm apart on the x axis, facing each other (the right one turned half a turn).
    instrument_nominal: dict[str, tuple[float, ...]] = field(default_factory=lambda: {
        "left": (0.0, 0.0, 0.0, 0.0, 0.0, 0.0), "right": (900.0, 0.0, 0.0, 0.0, 0.0, np.pi)})
    compliance: bool = True
    # The right arm is the softer one (0.6 of the left's stiffness): where the linked point
    # settles between the arms depends on the ratio.
    stiffness_nmm_per_rad: dict[str, tuple[float, ...]] = field(default_factory=lambda: {
        "left": _left_stiffness(), "right": tuple(0.6 * k for k in _left_stiffness())})
    # Two arms of one model are not equally stiff, nor are two rigs' arms: each seed draws its
    # arms' stiffnesses about the profile above, log k = log(profile) + N(0, sd) per arm +
    # N(0, sd) per joint, from a stream of its own (the rest of the rig is what the seed always
    # gave); truth.toml records what was drawn. 0: the profile as it is, on every seed.
    stiffness_log_sd: float = 0.3
    # Nor is a built arm's link mass what its description (arm6.urdf, masses_kg at the links'
    # middles) says: each arm's true masses are those scaled by a log-normal factor per arm and
    # per link, from a stream of their own; ``drawn_masses_kg`` records them. 0: as described.
    mass_log_sd: float = 0.0
    drawn_masses_kg: dict = field(default_factory=dict)
    # Linked targets are drawn uniformly in this box (instrument frame, mm): between the bases,
    # 300-600 mm in front of each, within both arms' reach at their working joint ranges.
    target_box_mm: tuple[tuple[float, float], ...] = ((300.0, 600.0), (-150.0, 150.0),
                                                      (100.0, 300.0))
    calibration_groups: tuple[str, ...] = ("frames", "offsets", "geometric")
    true_params: dict = field(default_factory=dict)
    linked_rows: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        # said here, not as a KeyError halfway through writing the rig
        if len(self.arms) < 2 or len(set(self.arms)) != len(self.arms):
            raise ValueError(f"linked arms must be two or more distinct names, not {self.arms}")
        for table in ("instrument_nominal", "stiffness_nmm_per_rad"):
            missing = [a for a in self.arms if a not in getattr(self, table)]
            if missing:
                raise ValueError(f"LinkedChainTruth.{table} has no entry for "
                                 f"{', '.join(missing)}")


def three_linked_chain_truth(**kwargs: Any) -> LinkedChainTruth:
    """Three arm6 arms joined at one point: ``left`` and ``right`` as in
    :class:`LinkedChainTruth` and ``front`` (:data:`THIRD_ARM`) facing the targets from the
    side; ``kwargs`` as the class takes them. Its stiffness profile is the left arm's times
    :data:`THIRD_ARM_STIFFNESS_SCALE`, drawn about per seed as the others are."""
    base = LinkedChainTruth()
    instrument = {**base.instrument_nominal, THIRD_ARM: THIRD_ARM_INSTRUMENT}
    stiffness = {**base.stiffness_nmm_per_rad,
                 THIRD_ARM: tuple(THIRD_ARM_STIFFNESS_SCALE * k
                                  for k in base.stiffness_nmm_per_rad["left"])}
    return LinkedChainTruth(**{"arms": (*LINKED_ARMS, THIRD_ARM),
                               "instrument_nominal": instrument,
                               "stiffness_nmm_per_rad": stiffness, **kwargs})


@dataclass
class LinkedEquilibrium:
    """Where arms whose markers are joined settle, row by row (N rows, mm and rad)."""

    point: np.ndarray  # (N, 3) the joined marker point in the instrument frame
    joints: dict[str, np.ndarray]  # arm -> (N, n) joint columns at the linked equilibrium
    free_points: dict[str, np.ndarray]  # arm -> (N, 3) the marker at the arm's own equilibrium
    free_joints: dict[str, np.ndarray]  # arm -> (N, n) joint columns there
    multipliers: np.ndarray  # (N, 3 (A - 1)) Lagrange multipliers: the joint's forces (N)
    violation_mm: np.ndarray  # (N,) largest distance between joined markers
    iterations: int  # Newton steps on the Lagrange conditions (all rows step together)


def _gravity_forces(masses_kg: np.ndarray | None, gravity: Sequence[float] | None,
                    n: int) -> np.ndarray:
    """Weights (n, 3) in N of the links' point masses; zero without gravity."""
    if masses_kg is None or gravity is None:
        return np.zeros((n, 3))
    g = np.asarray(gravity, float)
    return np.asarray(masses_kg, float)[:, None] * (G_N_PER_KG * g / np.linalg.norm(g))[None]


def _arm_program(robot: Robot, arm: str) -> Callable:
    """A compiled ``(x, u, u0, k, weight) -> dict`` of one arm over rows u (N, n), compiled
    once per process for all robots of ``robot``'s structure: the energy of springs (stiffness k,
    N mm/rad) holding the joint columns at u0 plus the potential of the link weights (N, at
    the links' centres as in :func:`gravity_deflection`), its gradient and Hessian, and the
    marker with its first and second derivatives.

    The derivatives are closed forms on the frames of one forward pass (no automatic
    differentiation through the chain's scan, which took seconds to compile): a point r
    carried beyond joint j moves by a_j x (r - o_j) when j turns (axis a_j through o_j), and
    d2 r / du_i du_j = a_i x (a_j x (r - o_j)) for i <= j, since joint i carries axis j and
    its origin along.
    """
    chain = robot.chains[arm]
    if len(robot.path(arm)) != 1 or any(k != "revolute" for k in chain.kinds):
        raise ValueError(f"arm {arm!r}: linked equilibria are computed for arms of revolute "
                         "joints standing on their own (not mounted on another arm)")
    return partial(_arm_evaluate, robot.structure, arm, robot.nominal_values)


@partial(jax.jit, static_argnames=("structure", "arm"))
def _arm_evaluate(structure: RobotStructure, arm: str, values: dict, x: jax.Array,
                  u: jax.Array, u0: jax.Array, k: jax.Array, weight: jax.Array
                  ) -> dict[str, jax.Array]:
    # _arm_program's function, for an arm it has checked
    robot = structure.robot(values)
    chain = robot.chains[arm]
    n = chain.n_joints
    half = jnp.concatenate([0.5 * chain.origins[1:, :3], jnp.ones((n, 1))], axis=1)
    axes = jnp.asarray(chain.axes)
    marker = robot.layout.slices[(arm, "marker")]
    upper = np.triu(np.ones((n, n), bool))  # [i, j]: i <= j
    ordered = jnp.asarray(upper[:, :, None] & upper[None, :, :])  # [i, j, k]: i <= j <= k
    joints, links = robot.element_frames(x, arm, u)  # (E, N, 4, 4)
    a = jnp.einsum("enij,ej->nei", joints[:n, :, :3, :3], axes)  # (N, n, 3)
    o = jnp.swapaxes(joints[:n, :, :3, 3], 0, 1)  # (N, n, 3)
    centres = jnp.swapaxes(jnp.einsum("enij,ej->eni", links[:n], half)[..., :3], 0, 1)
    tip = links[-1]
    p = jnp.einsum("nij,j->ni", tip[:, :3, :3], x[marker]) + tip[:, :3, 3]
    jp = jnp.cross(a, p[:, None] - o)  # (N, n, 3): row j = dp/du_j
    hp = jnp.cross(a[:, :, None], jp[:, None, :])  # [i, j] = a_i x dp/du_j
    hp = jnp.where(upper[None, :, :, None], hp, jnp.swapaxes(hp, 1, 2))
    # s[:, j, k] = d centre_k / du_j where j <= k (joint j carries link k)
    s = jnp.cross(a[:, :, None], centres[:, None, :] - o[:, :, None])
    torque = jnp.einsum("njkd,kd,jk->nj", s, weight, upper)  # of the weights beyond j
    t = jnp.einsum("nijkd,kd,ijk->nij", jnp.cross(a[:, :, None, None], s[:, None]),
                   weight, ordered)
    hv = -jnp.where(upper[None], t, jnp.swapaxes(t, 1, 2))  # Hessian of the potential
    d = u - u0
    return {"energy": 0.5 * jnp.sum(k * d * d, axis=1)
            - jnp.einsum("nkd,kd->n", centres, weight),
            "grad": k * d - torque, "hess": jnp.diag(k)[None] + hv,
            "point": p, "jac": jnp.swapaxes(jp, 1, 2), "point_hess": hp}


def _arm_states(robot: Robot, arms: Sequence[str], x: jax.Array, us: Sequence[np.ndarray],
                u0s: Sequence[np.ndarray], ks: Sequence[jax.Array],
                weights: Sequence[jax.Array]) -> list[dict[str, np.ndarray]]:
    return [{key: np.asarray(v) for key, v in _arm_program(robot, a)(
        x, jnp.asarray(u), jnp.asarray(u0), k, w).items()}
        for a, u, u0, k, w in zip(arms, us, u0s, ks, weights, strict=True)]


def _physics_arguments(robot: Robot, arms: Sequence[str], stiffness: Mapping[str, np.ndarray],
                       masses_kg: Mapping[str, np.ndarray] | None,
                       gravity: Sequence[float] | None) -> tuple[list, list]:
    ks = [jnp.asarray(np.asarray(stiffness[a], float)) for a in arms]
    weights = [jnp.asarray(_gravity_forces(None if masses_kg is None else masses_kg[a],
                                           gravity, robot.chains[a].n_joints)) for a in arms]
    return ks, weights


def linked_energy(robot: Robot, x: np.ndarray, u: Mapping[str, np.ndarray],
                  u0: Mapping[str, np.ndarray], stiffness: Mapping[str, np.ndarray],
                  masses_kg: Mapping[str, np.ndarray] | None = None,
                  gravity: Sequence[float] | None = GRAVITY) -> np.ndarray:
    """Total potential energy (N mm) of the arms at joint columns ``u[arm]`` (N, n), per row:
    springs of stiffness ``stiffness[arm]`` (N mm/rad) holding the columns at ``u0[arm]``,
    plus the potential of the link masses (``masses_kg[arm]``, kg, at the links' centres)
    under ``gravity`` (instrument frame; None or no masses: none). The markers need not meet.
    """
    arms = tuple(u)
    ks, weights = _physics_arguments(robot, arms, stiffness, masses_kg, gravity)
    states = _arm_states(robot, arms, jnp.asarray(x, float),
                         [np.atleast_2d(u[a]) for a in arms],
                         [np.atleast_2d(u0[a]) for a in arms], ks, weights)
    return sum(s["energy"] for s in states)


def _kkt_system(states: list[dict[str, np.ndarray]], lam: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Gradient and Hessian of the Lagrangian, the constraints (each marker on the next) and
    their Jacobian, over rows: (N, Z), (N, Z, Z), (N, M), (N, M, Z)."""
    n_rows, n_arms = len(lam), len(states)
    sizes = [s["grad"].shape[1] for s in states]
    cuts = np.cumsum([0, *sizes])
    lam = lam.reshape(n_rows, n_arms - 1, 3)
    zero = np.zeros((n_rows, 1, 3))
    # c_j = p_j - p_{j+1}: arm a's marker carries lam_a - lam_{a-1}
    mu = np.concatenate([lam, zero], 1) - np.concatenate([zero, lam], 1)
    grad = np.concatenate([s["grad"] + np.einsum("ndj,nd->nj", s["jac"], mu[:, a])
                           for a, s in enumerate(states)], axis=1)
    hess = np.zeros((n_rows, cuts[-1], cuts[-1]))
    jc = np.zeros((n_rows, 3 * (n_arms - 1), cuts[-1]))
    for a, s in enumerate(states):
        block = slice(cuts[a], cuts[a + 1])
        hess[:, block, block] = s["hess"] + np.einsum("nijd,nd->nij", s["point_hess"], mu[:, a])
        if a < n_arms - 1:
            jc[:, 3 * a:3 * a + 3, block] = s["jac"]
        if a > 0:
            jc[:, 3 * a - 3:3 * a, block] = -s["jac"]
    c = np.concatenate([states[a]["point"] - states[a + 1]["point"]
                        for a in range(n_arms - 1)], axis=1)
    return grad, hess, c, jc


def linked_equilibrium(robot: Robot, x: np.ndarray, u0: Mapping[str, np.ndarray],
                       stiffness: Mapping[str, np.ndarray],
                       masses_kg: Mapping[str, np.ndarray] | None = None,
                       gravity: Sequence[float] | None = GRAVITY, tol_mm: float = 1e-9,
                       max_iter: int = 40) -> LinkedEquilibrium:
    """The exact equilibrium of arms whose markers are joined by a ball joint, row by row.

    Each arm's joints are torsional springs (``stiffness[arm]``, N mm/rad) holding its joint
    columns at ``u0[arm]`` (N, n) (commanded plus joint noise); the links' point masses
    (``masses_kg[arm]``, kg, at the links' centres as in :func:`gravity_deflection`) hang
    under ``gravity`` (a direction in the instrument frame; None: no gravity). The arms settle
    at the minimum of their summed energy subject to every marker (true parameters ``x``)
    being at one point; the joint's orientation is free. Solved by Newton's method on the
    Lagrange conditions with exact first and second derivatives, started from each arm's own
    (free) equilibrium, itself found by Newton on its energy. Raises LinkedSimulationError
    when a row does not converge (markers more than ``tol_mm`` apart, at most 1e-6 mm) or
    stops at a point that is not a constrained minimum.
    """
    arms = tuple(u0)
    if len(arms) < 2:
        raise ValueError("a linked equilibrium needs two arms or more")
    xj = jnp.asarray(x, float)
    ks, weights = _physics_arguments(robot, arms, stiffness, masses_kg, gravity)
    u0s = [np.atleast_2d(np.asarray(u0[a], float)) for a in arms]

    def states(us):
        return _arm_states(robot, arms, xj, us, u0s, ks, weights)

    us = [u.copy() for u in u0s]
    for _ in range(max_iter):
        steps = [-np.linalg.solve(s["hess"], s["grad"][..., None])[..., 0] for s in states(us)]
        us = [u + d for u, d in zip(us, steps, strict=True)]
        if max(np.abs(d).max() for d in steps) < 1e-12:
            break
    else:
        raise LinkedSimulationError(f"free equilibrium did not converge in {max_iter} Newton steps")
    free = states(us)
    free_joints = [u.copy() for u in us]
    cuts = np.cumsum([0, *(u.shape[1] for u in us)])
    n_rows = len(us[0])
    lam = np.zeros((n_rows, 3 * (len(arms) - 1)))
    iterations = 0
    while True:
        grad, hess, c, jc = _kkt_system(states(us), lam)
        m = c.shape[1]
        kkt = np.block([[hess, np.swapaxes(jc, 1, 2)], [jc, np.zeros((n_rows, m, m))]])
        step = np.linalg.solve(kkt, -np.concatenate([grad, c], axis=1)[..., None])[..., 0]
        dz = step[:, :cuts[-1]]
        us = [u + dz[:, cuts[i]:cuts[i + 1]] for i, u in enumerate(us)]
        lam = lam + step[:, cuts[-1]:]
        iterations += 1
        if np.abs(dz).max() < 1e-12 or iterations == max_iter:
            break
    final = states(us)
    _, hess, c, jc = _kkt_system(final, lam)
    violation_mm = np.linalg.norm(c.reshape(n_rows, -1, 3), axis=2).max(axis=1)
    worst = int(np.argmax(violation_mm))
    if not np.all(np.isfinite(violation_mm)) or violation_mm[worst] > min(tol_mm, 1e-6):
        raise LinkedSimulationError(
            f"linked equilibrium did not converge in {iterations} Newton steps: row {worst}'s "
            f"markers are {violation_mm[worst]:.3g} mm apart")
    # A stationary point of the Lagrangian is the minimum only if the energy curves upwards
    # along every direction that keeps the markers together.
    for r in range(n_rows):
        _, sv, vt = np.linalg.svd(jc[r])
        tangent = vt[int(np.sum(sv > 1e-12 * sv[0])):].T
        lowest = np.linalg.eigvalsh(tangent.T @ hess[r] @ tangent).min()
        if lowest <= 0:
            raise LinkedSimulationError(f"linked equilibrium of row {r} is not a minimum "
                                        f"(reduced Hessian eigenvalue {lowest:.3g})")
    return LinkedEquilibrium(
        point=np.mean([s["point"] for s in final], axis=0),
        joints=dict(zip(arms, us, strict=True)),
        free_points={a: s["point"] for a, s in zip(arms, free, strict=True)},
        free_joints=dict(zip(arms, free_joints, strict=True)),
        multipliers=lam, violation_mm=violation_mm, iterations=iterations)


def position_ik(robot: Robot, x: np.ndarray, arm: str, targets: np.ndarray, seeds: np.ndarray,
                lo: np.ndarray = POSE_LO, hi: np.ndarray = POSE_HI, tol_mm: float = 1e-8,
                max_iter: int = 60, max_step_rad: float = 0.3) -> np.ndarray:
    """Joint columns (N, n) that put ``arm``'s marker on each of ``targets`` (N, 3) (mm)
    under parameters x, all rows at once.

    Gauss-Newton on the 3-D marker point from ``seeds`` (N, S, n), best first, or (S, n) for
    every row: a 6-joint arm is redundant for a point, so each step is the minimum-norm one
    (the pseudo-inverse), which keeps near the seed's posture; steps longer than
    ``max_step_rad`` are shortened while far from the target. A row takes the first solution
    within ``tol_mm`` whose joints lie in [lo, hi], and moves on to its next seed when a
    solution leaves the range or ``max_iter`` steps do not converge; LinkedSimulationError
    when a row's seeds run out.
    """
    targets = np.atleast_2d(np.asarray(targets, float))
    n_rows = len(targets)
    seeds = np.asarray(seeds, float)
    if seeds.ndim == 2:
        seeds = np.broadcast_to(seeds, (n_rows, *seeds.shape))
    program = _arm_program(robot, arm)
    n = robot.chains[arm].n_joints
    xj, k0, w0 = jnp.asarray(x, float), jnp.zeros(n), jnp.zeros((n, 3))
    rows = np.arange(n_rows)
    which = np.zeros(n_rows, int)
    u = seeds[:, 0].copy()
    steps = np.zeros(n_rows, int)
    done = np.zeros(n_rows, bool)
    while True:
        state = program(xj, jnp.asarray(u), jnp.asarray(u), k0, w0)
        err = targets - np.asarray(state["point"])
        close = np.linalg.norm(err, axis=1) < tol_mm
        done |= close & np.all((u >= lo) & (u <= hi), axis=1)
        if done.all():
            return u
        restart = ~done & (close | (steps >= max_iter))
        which[restart] += 1
        if np.any(which >= seeds.shape[1]):
            r = int(np.flatnonzero(which >= seeds.shape[1])[0])
            raise LinkedSimulationError(
                f"arm {arm!r}: no joint solution in the working range reaches "
                f"{targets[r].round(1).tolist()} mm from {seeds.shape[1]} seeds")
        u[restart] = seeds[rows[restart], which[restart]]
        steps[restart] = 0
        move = ~done & ~restart
        step = np.einsum("nij,nj->ni", np.linalg.pinv(np.asarray(state["jac"])), err)
        size = np.linalg.norm(step, axis=1)
        scale = np.minimum(1.0, max_step_rad / np.maximum(size, 1e-300))
        u[move] += (step * scale[:, None])[move]
        steps[move] += 1


def _arm_table(name: str, marker: Sequence[float], instrument: Sequence[float]) -> dict:
    return {"urdf": ARM6_URDF, "root": "base_link", "tip": "tool0", "marker": list(marker),
            "instrument": [float(v) for v in instrument]}


def _fmt_row(config: str, set_name: str, target: Sequence[float] | None,
             commands: Mapping[str, np.ndarray], point: np.ndarray,
             arms: Sequence[str]) -> str:
    cells = [config, set_name]
    cells += [f"{v:.4f}" for v in target] if target is not None else ["", "", ""]
    for a in arms:
        cells += [f"{v:.10g}" for v in commands[a]] if a in commands else [""] * 6
    return ",".join(cells + [f"{v:.4f}" for v in point])


def _aim_and_settle(out: Path, robot: Robot, x_true: np.ndarray, truth: LinkedChainTruth,
                    rng: np.random.Generator) -> tuple:
    """The linked rows of the rig in ``out`` (single-arm rows written): targets (L, 3),
    commands and spring set points per arm (L, 6), and the true equilibrium."""
    from bayesrob.calibration import calibrate_chain
    from bayesrob.rig import load_rig

    rig = load_rig(out)
    # The rig's robot is the simulator's (same URDF, names and layout): one compiled program
    # per arm then serves the inverse kinematics and the physics.
    if rig.robot.layout.names != robot.layout.names:
        raise RuntimeError("the written rig does not read back as the simulated robot")
    # The commands come from what a user would have: each arm's model calibrated on its own
    # train rows, not the truth.
    cal = calibrate_chain(rig, tuple(truth.calibration_groups))
    box = np.asarray(truth.target_box_mm, float)
    targets = rng.uniform(box[:, 0], box[:, 1], size=(truth.n_linked, 3))
    commands = {}
    for arm in truth.arms:
        u_train, p_train = rig.rows(arm, "train")
        nearest = np.argsort(np.linalg.norm(p_train[None] - targets[:, None], axis=2), axis=1)
        u = position_ik(cal.robot, cal.x, arm, targets, u_train[nearest])
        # Ten significant digits, as written: the springs hold what the file says.
        commands[arm] = np.array([[float(f"{v:.10g}") for v in row] for row in u])
    u0 = {a: commands[a] + rng.normal(0, truth.joint_noise_rad, commands[a].shape)
          for a in truth.arms}
    eq = linked_equilibrium(
        rig.robot, x_true, u0,
        {a: np.asarray(truth.stiffness_nmm_per_rad[a], float) for a in truth.arms},
        {a: np.asarray(truth.drawn_masses_kg[a], float) for a in truth.arms}
        if truth.compliance else None,
        GRAVITY if truth.compliance else None)
    return targets, commands, u0, eq


def drawn_stiffness(truth: LinkedChainTruth) -> dict[str, tuple[float, ...]]:
    """Each arm's joint stiffnesses (N mm/rad) for the rig of ``truth.seed``: its profile
    scaled by a log-normal factor per arm and per joint (``stiffness_log_sd``)."""
    drawn = draw_stiffnesses(truth.seed, {a: truth.stiffness_nmm_per_rad[a]
                                          for a in truth.arms}, truth.stiffness_log_sd)
    return {a: tuple(float(v) for v in k) for a, k in drawn.items()}


MASS_STREAM = 19  # the arms' true masses' own random stream: other draws stay as they were


def drawn_masses(truth: LinkedChainTruth) -> dict[str, np.ndarray]:
    """Each arm's true link masses (kg) for the rig of ``truth.seed``: the described masses
    scaled by exp(N(0, ``mass_log_sd``)) per arm and per link."""
    rng = np.random.default_rng([truth.seed, MASS_STREAM])
    m = np.asarray(truth.masses_kg, float)
    return {a: m * np.exp(truth.mass_log_sd * rng.normal(size=m.shape)) for a in truth.arms}


def simulate_linked_chain_rig(out_dir: str | Path, truth: LinkedChainTruth) -> Path:
    """Write a rig of two arm6 arms, ``left`` and ``right`` (or ``truth.arms``), into out_dir:
    rig.toml, arm6.urdf (nominal), measurements.csv and truth.toml.

    Each arm has single-arm train, validation and holdout rows at random poses (as
    :func:`simulate_chain_rig`, with its own true geometry, noise and compliance). Then each
    arm is calibrated on its train rows (``truth.calibration_groups``) and the ``left+right``
    (``+``-joined ``truth.arms``) test rows aim every arm at random targets in
    ``truth.target_box_mm`` through their calibrated models (position-only inverse
    kinematics); their observed point is where the joined markers really settle
    (:func:`linked_equilibrium`), plus measurement noise.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(truth.seed)
    chains = {a: urdf_chain(arm6_urdf_path(), "base_link", "tool0", a,
                            marker=truth.marker_nominal_mm,
                            instrument=truth.instrument_nominal[a]) for a in truth.arms}
    robot = Robot(chains, 3)
    x_true = _true_vector(robot, truth, rng)
    masses = drawn_masses(truth)
    # a copy: the caller's truth stays the profile, so simulating it again draws the same
    truth = replace(truth, stiffness_nmm_per_rad=drawn_stiffness(truth),
                    drawn_masses_kg={a: m.tolist() for a, m in masses.items()})
    stiffness = {a: np.asarray(truth.stiffness_nmm_per_rad[a], float) for a in truth.arms}
    lines = [",".join(["config", "set", "target_x", "target_y", "target_z",
                       *[f"{a}_u{k + 1}" for a in truth.arms for k in range(6)],
                       "x", "y", "z"])]
    sets = [(s, n) for s, n in (("train", truth.n_train), ("validation", truth.n_validation),
                                ("holdout", truth.n_holdout)) if n]
    for arm in truth.arms:
        q_cmd = _poses(rng, sum(n for _, n in sets))
        q = q_cmd + rng.normal(0, truth.joint_noise_rad, q_cmd.shape)
        if truth.compliance:
            # Frames in the instrument frame, so gravity is the instrument's -z. Eight steps:
            # the softer arm's fixed point contracts more slowly than four steps allow (they
            # leave up to 6e-6 rad).
            q = q + gravity_deflection(robot, x_true, arm, q, masses[arm], stiffness[arm],
                                       np.asarray(GRAVITY), iterations=8)
        p = np.asarray(robot.marker_points(jnp.asarray(x_true), arm, jnp.asarray(q)))
        p = p + rng.normal(0, truth.measurement_noise_mm, p.shape)
        names = [s for s, n in sets for _ in range(n)]
        lines += [_fmt_row(arm, s, None, {arm: qc}, pc, truth.arms)
                  for s, qc, pc in zip(names, q_cmd, p, strict=True)]
    shutil.copy(arm6_urdf_path(), out / ARM6_URDF)
    rig_doc = {"name": f"arm6-linked-seed{truth.seed}", "gravity": list(GRAVITY),
               "arms": {a: _arm_table(a, truth.marker_nominal_mm, truth.instrument_nominal[a])
                        for a in truth.arms}}
    (out / "rig.toml").write_text(dump_toml(rig_doc))
    (out / "measurements.csv").write_text("\n".join(lines) + "\n")

    linked: dict = {}
    if truth.n_linked:
        # Small dense solves throughout (the fit's rank analysis, pseudo-inverses, KKT
        # systems): BLAS threads only hand them between busy cores, several times slower.
        with threadpool_limits(limits=1, user_api="blas"):
            targets, commands, u0, eq = _aim_and_settle(out, robot, x_true, truth, rng)
        observed = eq.point + rng.normal(0, truth.measurement_noise_mm, eq.point.shape)
        first_line = len(lines) + 1
        lines += [_fmt_row("+".join(truth.arms), "test", t,
                           {a: commands[a][i] for a in truth.arms}, o, truth.arms)
                  for i, (t, o) in enumerate(zip(targets, observed, strict=True))]
        (out / "measurements.csv").write_text("\n".join(lines) + "\n")
        linked = {
            "line": list(range(first_line, first_line + truth.n_linked)),
            "target": targets.tolist(),
            "point": eq.point.tolist(),
            **{f"free_{a}": eq.free_points[a].tolist() for a in truth.arms},
            **{f"u0_{a}": u0[a].tolist() for a in truth.arms},
            "max_violation_mm": float(eq.violation_mm.max()),
        }
    truth.true_params = {name: float(v) for name, v in zip(robot.layout.names, x_true,
                                                            strict=True)}
    truth.linked_rows = linked
    (out / "truth.toml").write_text(dump_toml({"linked_chain_truth": asdict(truth)}))
    return out


def load_linked_truth(rig_dir: str | Path) -> dict:
    """The ``linked_chain_truth`` table of a rig written by :func:`simulate_linked_chain_rig`."""
    import tomllib

    return tomllib.loads((Path(rig_dir) / "truth.toml").read_text())["linked_chain_truth"]
