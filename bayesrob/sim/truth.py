"""What a simulated rig really is, as written to ``truth.toml`` (only tests and studies read
it); all randomness flows from the seed. Two configurations of one physics:

- the paper's servo-driven planar arms (:func:`paper_truth`), springs pulling to the commanded
  angles under point masses, aimed on a grid. Effects (``vocabulary.EFFECTS``): ``gravity_sag``
  gives the servos their real stiffness (without it they are ``STIFF_FACTOR`` times stiffer,
  so gravity still picks the side of a dead band), ``backlash`` a dead band (the paper's
  bottom-arm jump), ``servo_nonlinearity`` a ripple on the pulse-to-angle map;
- arm6 (:class:`Arm6Truth`, :class:`LinkedArm6Truth`): a 6-joint URDF arm off its nominal
  geometry at random poses, with sag, eccentric encoders and play; linked arms share a marker.
"""

from __future__ import annotations

import tomllib
from collections.abc import Iterable
from dataclasses import asdict, dataclass, field, replace
from importlib.resources import files
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np

from bayesrob import robot as kin
from bayesrob.data.rig import RigError, dump_toml
from bayesrob.data.vocabulary import EFFECTS
from bayesrob.robot.planar import ArmGeometry
from bayesrob.sim.physics import draw_stiffnesses

TRUTH_FILE = "truth.toml"
ARM6_URDF = "arm6.urdf"
GRAVITY = (0.0, 0.0, -1.0)  # arm6: unit gravity in the instrument frame
# The working range of arm6's joints (rad): the shoulder lift keeps the arm off its own base.
POSE_LO = np.array([-2.8, -2.2, -2.4, -2.8, -2.8, -3.0])
POSE_HI = np.array([2.8, -0.6, 2.4, 2.8, 2.8, 3.0])
MASS_STREAM = 19  # the arms' drawn masses' own random stream


@dataclass(frozen=True)
class ArmTruth(ArmGeometry):
    """True physical parameters of one arm (what ``truth.toml`` records)."""

    link_mass_kg: tuple[float, float] = (0.05, 0.04)
    elbow_mass_kg: float = 0.065  # the elbow servo
    end_mass_kg: float = 0.02
    # One spring stands in for every compliance between command and end point (the servo's
    # position loop, horn, mounting, link bending), so it is softer than a servo alone: soft
    # enough that calibration cannot absorb all of the sag into gains and offsets.
    stiffness_nmm_per_rad: tuple[float, float] = (2500.0, 1800.0)
    backlash_rad: tuple[float, float] = (0.008, 0.008)  # half-width of the dead band
    nonlinearity_rad: tuple[float, float] = (0.01, 0.008)  # amplitude of the ripple
    nonlinearity_period_us: tuple[float, float] = (900.0, 1100.0)

    @property
    def params(self) -> kin.ArmParams:
        return kin.ArmParams.from_spec(self)

    def robot(self) -> kin.Robot:
        """The arm as a 2-joint chain whose columns are the joint angles (servo map outside)."""
        angles = kin.ArmParams(*(jnp.asarray(v, dtype=jnp.float64)
                                 for v in (self.base, self.links, (1.0, 1.0), (0.0, 0.0))))
        return kin.Robot({self.name: kin.planar_chain(self.name, angles)}, 2)

    @property
    def link_masses(self) -> tuple[np.ndarray, np.ndarray]:
        """Each link's mass (kg) with what it carries (elbow servo, end mass) and where along
        the link (fraction of its length) their centre of mass sits."""
        link = np.asarray(self.link_mass_kg, float)
        carried = np.array([self.elbow_mass_kg, self.end_mass_kg])
        mass = link + carried
        return mass, (0.5 * link + carried) / mass

    @property
    def u_mid(self) -> np.ndarray:
        return np.array([(lo + hi) / 2 for lo, hi in self.pulse_limits])

    @property
    def u_half_span(self) -> np.ndarray:
        return np.array([(hi - lo) / 2 for lo, hi in self.pulse_limits])


@dataclass(frozen=True)
class Truth:
    """Everything the simulator knows and the rig files do not."""

    name: str
    arms: dict[str, ArmTruth]
    effects: tuple[str, ...] = ()
    gravity: tuple[float, float] = (0.0, -1.0)
    workspace: tuple[tuple[float, float], tuple[float, float]] = ((80.0, 260.0), (100.0, 280.0))
    joint_noise_rad: float = 0.0008
    measurement_noise_mm: float = 0.35
    seed: int = 0
    grid: int = 4
    nominal_error: dict[str, float] = field(
        default_factory=lambda: {"base_mm": 2.0, "links_mm": 1.5, "gain_rel": 0.02,
                                 "offset_rad": 0.02}
    )

    def with_effects(self, effects: Iterable[str]) -> Truth:
        effects = tuple(effects)
        for e in effects:
            if e not in EFFECTS:
                raise ValueError(f"unknown effect {e!r}; known: {', '.join(EFFECTS)}")
        return replace(self, effects=effects)

    def to_toml(self) -> str:
        return "# True parameters of a simulated rig. Only tests read this file.\n" + \
            dump_toml(asdict(self))

    @classmethod
    def from_toml(cls, path: str | Path) -> Truth:
        """A planar rig's truth.toml; RigError (one line, naming the file) where it is none."""
        try:
            doc = tomllib.loads(Path(path).read_text())
        except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as e:
            raise RigError(f"{path}: cannot read the simulated rig's truth: {e}") from None
        if not isinstance(doc.get("arms"), dict):
            kind = ("a 6-joint arm's" if {"chain_truth", "linked_chain_truth"} & set(doc)
                    else "no planar rig's")
            raise RigError(f"{path}: is {kind} truth (no [arms] tables); this needs the "
                           "paper's planar arms, simulated by 'bayesrob simulate'")
        try:
            arms = {n: ArmTruth(**_tuples(a)) for n, a in doc.pop("arms").items()}
            return cls(arms=arms, **_tuples(doc))
        except (TypeError, ValueError) as e:
            raise RigError(f"{path}: not a simulated rig's truth as written: {e}") from None


def _tuples(x):
    if isinstance(x, dict):
        return {k: _tuples(v) if k != "nominal_error" else v for k, v in x.items()}
    if isinstance(x, list):
        return tuple(_tuples(v) for v in x)
    return x


def _offsets_for(base, links, gain, elbow, limits, workspace) -> tuple[float, float]:
    """Servo offsets that put the workspace centre at mid pulse: how a person mounts horns."""
    centre = jnp.array([np.mean(workspace[0]), np.mean(workspace[1])])
    p = kin.ArmParams(jnp.array(base), jnp.array(links), jnp.array(gain), jnp.zeros(2))
    theta, ok = kin.inverse(p, centre, elbow)
    assert bool(ok)
    mid = np.array([(lo + hi) / 2 for lo, hi in limits])
    return tuple(float(round(t - g * m, 4)) for t, g, m in zip(np.asarray(theta), gain, mid,
                                                                strict=True))


def paper_truth(effects: Iterable[str] = (), seed: int = 0, grid: int = 4,
                stiffness_log_sd: float = 0.0) -> Truth:
    """The paper's setup: a top arm hung from a strut, a bottom arm standing on the base,
    whose elbow-heavy left-bent pose flips its shoulder's gravity torque across the workspace
    (backlash then makes the jump the paper saw). ``stiffness_log_sd``: see
    :func:`with_drawn_stiffness`."""
    workspace = ((80.0, 260.0), (100.0, 280.0))
    limits = ((600.0, 2400.0), (600.0, 2400.0))
    arms = {}
    for name, base, links, gain, elbow, masses in (
        ("top", (20.0, 440.0), (240.0, 220.0), (0.00152, 0.00148), 1,
         dict(link_mass_kg=(0.05, 0.04), elbow_mass_kg=0.065, end_mass_kg=0.02)),
        ("bottom", (20.0, -20.0), (220.0, 200.0), (0.00150, 0.00155), -1,
         dict(link_mass_kg=(0.04, 0.03), elbow_mass_kg=0.09, end_mass_kg=0.01)),
    ):
        offset = _offsets_for(base, links, gain, elbow, limits, workspace)
        arms[name] = ArmTruth(name, base, links, gain, offset, elbow, limits, **masses)
    truth = Truth("paper-rig", arms, seed=seed, grid=grid, workspace=workspace).with_effects(
        effects)
    return with_drawn_stiffness(truth, stiffness_log_sd)


def with_drawn_stiffness(truth: Truth, log_sd: float) -> Truth:
    """The truth with each arm's stiffnesses scaled by exp(N(0, sd) per arm + N(0, sd) per
    joint) for its seed, from a stream of their own (0: as is). With one stiffness for every
    arm, a prior that linked arms are alike would be right by construction."""
    if not (np.isfinite(log_sd) and log_sd >= 0):
        raise ValueError(f"stiffness_log_sd must be a finite number >= 0, got {log_sd}")
    if log_sd == 0:
        return truth
    drawn = draw_stiffnesses(truth.seed, {n: a.stiffness_nmm_per_rad
                                          for n, a in truth.arms.items()}, log_sd)
    return replace(truth, arms={
        n: replace(a, stiffness_nmm_per_rad=tuple(float(round(v, 1)) for v in drawn[n]))
        for n, a in truth.arms.items()})


def three_arm_truth(effects: Iterable[str] = (), seed: int = 0, grid: int = 4,
                    stiffness_log_sd: float = 0.0) -> Truth:
    """The paper's two arms and a third (``side``) standing left of the workspace, for
    assemblies of more than two; stiffnesses drawn as :func:`paper_truth` does."""
    pair = paper_truth(effects, seed, grid)
    base, links, gain = (-170.0, 190.0), (260.0, 240.0), (0.00151, 0.00149)
    limits = ((600.0, 2400.0), (600.0, 2400.0))
    offset = _offsets_for(base, links, gain, -1, limits, pair.workspace)
    side = ArmTruth("side", base, links, gain, offset, -1, limits, link_mass_kg=(0.045, 0.035),
                    elbow_mass_kg=0.07, end_mass_kg=0.015)
    truth = replace(pair, name="three-arm-rig", arms={**pair.arms, "side": side})
    return with_drawn_stiffness(truth, stiffness_log_sd)


def arm6_urdf_path() -> Path:
    return Path(str(files("bayesrob.data") / "arm6" / ARM6_URDF))


@dataclass
class _ArmErrors:
    """How far a simulated arm6 is from its nominal URDF and how noisy its rows are."""

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
class Arm6Truth(_ArmErrors):
    """What a simulated chain rig really is (written to truth.toml)."""

    instrument_nominal: tuple[float, ...] = (1200.0, -300.0, 150.0, 0.0, 0.0, 0.4)
    compliance: bool = False
    stiffness_nmm_per_rad: tuple[float, ...] = (4e6, 4e6, 2e6, 6e5, 6e5, 6e5)
    # each joint's encoder disk sits off its axis by this fraction of its radius (0: none),
    # at a phase drawn per joint: the angle read is off by atan2(e sin, 1 + e cos), a
    # sinusoid once per revolution and its harmonics
    encoder_eccentricity: float = 0.0
    encoder_phase_rad: tuple[float, ...] = ()  # filled by simulate_arm6_rig
    # each joint's play (rad, whole width; 0: none): the joint rests against the side its
    # gravity torque pushes it to; where that torque is weaker than the friction that holds
    # it (play_stick_nmm), on the side it was approached from, drawn per row
    joint_play_rad: float = 0.0
    play_stick_nmm: float = 2000.0
    true_params: dict = field(default_factory=dict)  # filled by simulate_arm6_rig


def load_true_params(rig_dir: str | Path) -> dict[str, float]:
    """The true parameter values a simulated arm6 rig (one arm or linked) was made with."""
    doc = tomllib.loads((Path(rig_dir) / TRUTH_FILE).read_text())
    return doc.get("chain_truth", doc.get("linked_chain_truth"))["true_params"]


# Arm6 arms facing each other, markers joined by a ball joint for the linked rows. The joined
# point is the exact constrained energy minimum: prediction balances linearised stiffnesses,
# so the simulator must not.

LINKED_ARMS = ("left", "right")
# A third arm for assemblies of three: facing the targets from the side (its base 450 mm from
# the box's middle line, turned a quarter turn), so the box lies where it lies for the left
# arm in the arm's own frame; stiffer than the right arm, softer than the left.
THIRD_ARM = "front"
THIRD_ARM_INSTRUMENT = (450.0, -450.0, 0.0, 0.0, 0.0, np.pi / 2)
THIRD_ARM_STIFFNESS_SCALE = 0.8


@dataclass
class LinkedArm6Truth(_ArmErrors):
    """What a simulated rig of linked arm6 arms (``arms``, in order) really is (truth.toml):
    per-arm tables keyed by arm name; ``true_params`` under full names (``left.marker.x``) and
    ``linked_rows`` filled by :func:`simulate_linked_arm6_rig`."""

    n_linked: int = 24
    arms: tuple[str, ...] = LINKED_ARMS
    # Bases 900 mm apart on the x axis, facing each other (the right one turned half a turn).
    instrument_nominal: dict[str, tuple[float, ...]] = field(default_factory=lambda: {
        "left": (0.0, 0.0, 0.0, 0.0, 0.0, 0.0), "right": (900.0, 0.0, 0.0, 0.0, 0.0, np.pi)})
    compliance: bool = True
    # The right arm is the softer one (0.6 of the left's stiffness): where the linked point
    # settles between the arms depends on the ratio.
    stiffness_nmm_per_rad: dict[str, tuple[float, ...]] = field(default_factory=lambda: {
        "left": Arm6Truth.stiffness_nmm_per_rad,
        "right": tuple(0.6 * k for k in Arm6Truth.stiffness_nmm_per_rad)})
    # Each seed draws its arms' stiffnesses about the profile above, log k = log(profile) +
    # N(0, sd) per arm + N(0, sd) per joint, from a stream of its own (0: the profile).
    stiffness_log_sd: float = 0.3
    # True link masses: the description's times a log-normal factor per arm and per link, from
    # a stream of their own (0: as described); ``drawn_masses_kg`` records them.
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
                raise ValueError(f"LinkedArm6Truth.{table} has no entry for "
                                 f"{', '.join(missing)}")


def three_arm6_truth(**kwargs: Any) -> LinkedArm6Truth:
    """:class:`LinkedArm6Truth` (``kwargs``) with a third arm, ``front``, facing the targets
    from the side, its stiffness the left arm's times :data:`THIRD_ARM_STIFFNESS_SCALE`."""
    base = LinkedArm6Truth()
    instrument = {**base.instrument_nominal, THIRD_ARM: THIRD_ARM_INSTRUMENT}
    stiffness = {**base.stiffness_nmm_per_rad,
                 THIRD_ARM: tuple(THIRD_ARM_STIFFNESS_SCALE * k
                                  for k in base.stiffness_nmm_per_rad["left"])}
    return LinkedArm6Truth(**{"arms": (*LINKED_ARMS, THIRD_ARM),
                               "instrument_nominal": instrument,
                               "stiffness_nmm_per_rad": stiffness, **kwargs})


def drawn_stiffness(truth: LinkedArm6Truth) -> dict[str, tuple[float, ...]]:
    """Each arm's joint stiffnesses (N mm/rad) drawn about its profile for ``truth.seed``."""
    drawn = draw_stiffnesses(truth.seed, {a: truth.stiffness_nmm_per_rad[a]
                                          for a in truth.arms}, truth.stiffness_log_sd)
    return {a: tuple(float(v) for v in k) for a, k in drawn.items()}


def drawn_masses(truth: LinkedArm6Truth) -> dict[str, np.ndarray]:
    """Each arm's true link masses (kg) for ``truth.seed``: the described ones scaled by
    exp(N(0, ``mass_log_sd``)) per arm and per link."""
    rng = np.random.default_rng([truth.seed, MASS_STREAM])
    m = np.asarray(truth.masses_kg, float)
    return {a: m * np.exp(truth.mass_log_sd * rng.normal(size=m.shape)) for a in truth.arms}


def load_linked_truth(rig_dir: str | Path) -> dict:
    """The ``linked_chain_truth`` table of a simulated linked arm6 rig."""
    return tomllib.loads((Path(rig_dir) / TRUTH_FILE).read_text())["linked_chain_truth"]
