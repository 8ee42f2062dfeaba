"""Where simulated arms settle: the least energy of their springs and weights (linked arms: a
tug of war between their stiffnesses), under one physics: each arm's energy is
:func:`bayesrob.sim.physics.arm_energy`. :class:`PhysicalRig`: the paper's planar arms, as
2-joint chains, by BFGS (the dead band's kink needs no Hessian); :class:`ChainPlant`: a chain
arm alone, by fixed-point steps; :func:`linked_equilibrium`: 3-D arms joined, by Newton.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import scipy.optimize

from bayesrob import robot as kin
from bayesrob.robot import Robot, RobotStructure, on_row_buckets
from bayesrob.sim import physics
from bayesrob.sim.physics import (
    G_N_PER_KG,
    STIFF_FACTOR,
    arm_energy,
    link_weights,
    servo_ripple,
)
from bayesrob.sim.truth import GRAVITY, TRUTH_FILE, ArmTruth, Truth


def commanded_angles(arm: ArmTruth, u: jax.Array, effects: Sequence[str]) -> jax.Array:
    ripple = (arm.u_mid, arm.nonlinearity_rad, arm.nonlinearity_period_us)
    return _commanded(arm.params, u, *(np.asarray(v, float) for v in ripple),
                      "servo_nonlinearity" in effects)


@partial(jax.jit, static_argnames=("ripple",))
def _commanded(params: kin.ArmParams, u: jax.Array, u_mid: jax.Array, amplitude: jax.Array,
               period: jax.Array, ripple: bool) -> jax.Array:
    theta = kin.servo(params, u)
    return theta + servo_ripple(u, u_mid, amplitude, period) if ripple else theta


class _ArmArrays(NamedTuple):
    """What :func:`~bayesrob.sim.physics.arm_energy` takes of a planar arm besides its
    structure, in its argument order (a pytree: traced, not compiled in)."""

    values: dict  # the 2-joint chain's nominal values
    x: jax.Array  # its parameters (nominal)
    stiffness: jax.Array  # (2,) N mm / rad, already scaled for the effects in force
    weight: jax.Array  # (2, 3) N: each link with what it carries (elbow servo, end mass)
    centre: jax.Array  # (2,) where along its link that weight acts
    backlash: jax.Array  # (2,) rad half-width, zero without the effect


class _ArmPhysics(NamedTuple):
    """A planar arm as one configuration of the chains' physics: its 2-joint chain (columns
    the joint angles) and its arrays, so its programs are compiled once per arm name and
    shared by every rig."""

    structure: RobotStructure
    name: str
    arrays: _ArmArrays


def _arm_physics(arm: ArmTruth, effects: Sequence[str], gravity: Sequence[float]
                 ) -> _ArmPhysics:
    k = np.asarray(arm.stiffness_nmm_per_rad, float)
    if "gravity_sag" not in effects:
        k = k * STIFF_FACTOR
    b = np.asarray(arm.backlash_rad, float) if "backlash" in effects else np.zeros(2)
    mass, centre = arm.link_masses
    weight = mass[:, None] * (G_N_PER_KG * np.r_[np.asarray(gravity, float), 0.0])[None]
    robot = arm.robot()
    _arm_program(robot, arm.name)  # its checks: revolute joints, standing on its own
    return _ArmPhysics(robot.structure, arm.name, _ArmArrays(
        robot.nominal_values, jnp.asarray(robot.layout.nominal),
        *(jnp.asarray(v) for v in (k, weight, centre, b))))


def _terms(structure: RobotStructure, arm: str, a: _ArmArrays, theta: jax.Array,
           theta_cmd: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    s = arm_energy(structure, arm, a.values, a.x, theta[None], theta_cmd[None], a.stiffness,
                   a.weight, a.centre, a.backlash, periodic=True)
    return s["energy"][0], s["grad"][0], s["jac"][0, :2]


@partial(jax.jit, static_argnames=("structure", "arm"))
def _at_angles(structure: RobotStructure, arm: str, arrays: _ArmArrays, theta: jax.Array,
               theta_cmd: jax.Array) -> jax.Array:
    # energy (N mm) and its gradient in the joint angles, in one array: one transfer
    energy, grad, _ = _terms(structure, arm, arrays, theta, theta_cmd)
    return jnp.concatenate([energy[None], grad])


@partial(jax.jit, static_argnames=("structures", "arms", "elbows"))
def _at_point(structures: tuple, arms: tuple, elbows: tuple, arrays: tuple, params: tuple,
              d: jax.Array, theta_cmds: tuple) -> jax.Array:
    # the arms' total at their shared end point d, each arm's joints by its closed-form
    # inverse: the gradient in d is J^-T times the gradient in the joints
    out = jnp.zeros(3)
    for structure, arm, elbow, a, p, tc in zip(structures, arms, elbows, arrays, params,
                                               theta_cmds, strict=True):
        theta, _ = kin.inverse(p, d, elbow)
        energy, grad, jac = _terms(structure, arm, a, theta, tc)
        out = out + jnp.concatenate([energy[None], jnp.linalg.solve(jac.T, grad)])
    return out


def _least_energy(value_and_grad: Callable, x0: np.ndarray, scale: float) -> np.ndarray:
    # ``scale`` divides the energy so the tolerances mean the same for stiff and soft servos

    def obj(x: np.ndarray) -> tuple[float, np.ndarray]:
        v, gr = value_and_grad(jnp.asarray(x))
        return float(v) / scale, np.asarray(gr) / scale

    return scipy.optimize.minimize(obj, x0, jac=True, method="BFGS",
                                   options={"gtol": 1e-12, "maxiter": 500}).x


class PhysicalRig:
    """The simulated hardware: pulse widths in, settled end points out (for ``bayesrob
    simulate`` and the simulated serial device alike)."""

    def __init__(self, truth: Truth, seed: int | None = None):
        self.truth = truth
        self.rng = np.random.default_rng(truth.seed if seed is None else seed)
        self._physics = {n: _arm_physics(a, truth.effects, truth.gravity)
                         for n, a in truth.arms.items()}

    @classmethod
    def from_rig_dir(cls, directory: str | Path, seed: int | None = None) -> PhysicalRig:
        return cls(Truth.from_toml(Path(directory) / TRUTH_FILE), seed)

    def _k_scale(self, name: str) -> float:
        # the softest spring: what an arm's energy is divided by (_least_energy)
        return float(jnp.min(self._physics[name].arrays.stiffness))

    def settle_arm(self, name: str, theta_cmd: np.ndarray) -> np.ndarray:
        a, tc = self._physics[name], jnp.asarray(theta_cmd, float)

        def value_and_grad(theta: jax.Array) -> tuple[float, np.ndarray]:
            out = np.asarray(_at_angles(a.structure, a.name, a.arrays, theta, tc))
            return out[0], out[1:]

        return _least_energy(value_and_grad, np.asarray(theta_cmd, float), self._k_scale(name))

    def settle_linked(self, theta_cmds: dict[str, np.ndarray]) -> np.ndarray:
        names = tuple(theta_cmds)
        phys = [self._physics[n] for n in names]
        arms = {"structures": tuple(a.structure for a in phys),
                "arms": tuple(a.name for a in phys),
                "elbows": tuple(int(self.truth.arms[n].elbow) for n in names),
                "arrays": tuple(a.arrays for a in phys),
                "params": tuple(self.truth.arms[n].params for n in names),
                "theta_cmds": tuple(jnp.asarray(theta_cmds[n], float) for n in names)}

        def value_and_grad(d: jax.Array) -> tuple[float, np.ndarray]:
            out = np.asarray(_at_point(d=d, **arms))
            return out[0], out[1:]

        free = [kin.forward(self.truth.arms[n].params, self.settle_arm(n, theta_cmds[n]))
                for n in names]
        return _least_energy(value_and_grad, np.mean(np.asarray(free), axis=0),
                             sum(self._k_scale(n) for n in names))

    def end_point(self, commands: dict[str, Sequence[float]], noise: bool = True) -> np.ndarray:
        """Observed end point (mm) for pulse widths per arm; several arms means linked."""
        theta_cmds = {}
        for name, u in commands.items():
            arm = self.truth.arms[name]
            tc = np.asarray(commanded_angles(arm, jnp.asarray(u, float), self.truth.effects))
            if noise:
                tc = tc + self.rng.normal(0.0, self.truth.joint_noise_rad, 2)
            theta_cmds[name] = tc
        if len(theta_cmds) == 1:
            (name, tc), = theta_cmds.items()
            arm = self.truth.arms[name]
            d = np.asarray(kin.forward(arm.params, jnp.asarray(self.settle_arm(name, tc))))
        else:
            d = self.settle_linked(theta_cmds)
        if noise:
            d = d + self.rng.normal(0.0, self.truth.measurement_noise_mm, 2)
        return d



@dataclass(frozen=True, eq=False)
class ChainPlant:
    """A simulated chain robot as it really is, measured one arm at a time: joint commands in,
    marker points out (for ``bayesrob simulate --robot arm6``, its linked rigs' single-arm rows
    and planned poses alike). A row's draws, in order: the joint noise; the encoders'
    eccentricity (no draw); the side of each joint's play (``approach_rng``, where neither its
    gravity torque nor a recorded approach decides it); where gravity against the springs
    settles it (:func:`gravity_settled`, the Newton steps of linked equilibria's arms); the
    tracker's noise. Gravity
    acts along ``gravity`` in the frames of ``torque_robot`` at ``torque_x``: a single arm6's
    base at the identity, so gravity is its -z; a linked rig's instrument frame."""

    robot: Robot  # the robot the rows are written for, instrument pose included
    x_true: np.ndarray
    joint_noise_rad: float
    measurement_noise_mm: float
    torque_robot: Robot
    torque_x: np.ndarray
    masses_kg: Mapping[str, np.ndarray]  # per arm: each link's mass, halfway along it
    stiffness: Mapping[str, np.ndarray] | None = None  # per arm, N mm / rad; None: rigid
    gravity: Sequence[float] = GRAVITY
    encoder_eccentricity: float = 0.0
    encoder_phase: np.ndarray | None = None  # (n,) rad, where eccentric
    play_rad: float = 0.0  # each joint's play, whole width
    stick_nmm: float = 0.0  # the gravity torque below which friction holds a joint's side

    def measure(self, arm: str, q_cmd: np.ndarray, rng: np.random.Generator,
                approach_rng: np.random.Generator | None = None,
                approach: np.ndarray | None = None) -> np.ndarray:
        """Marker points (N, 3) mm of ``arm`` at the commanded joint values ``q_cmd`` (N, n);
        each joint's ``approach`` side (N, n; +1, -1, 0: unknown) where the rows record it."""
        q = q_cmd + rng.normal(0, self.joint_noise_rad, q_cmd.shape)
        if self.encoder_eccentricity:
            q = q + physics.encoder_error(q_cmd, self.encoder_eccentricity, self.encoder_phase)
        on_torques = (self.torque_robot, self.torque_x, arm)
        gravity = np.asarray(self.gravity, float)
        if self.play_rad:
            tau = physics.gravity_torques(*on_torques, q, self.masses_kg[arm], gravity)
            q = q + physics.play_offsets(tau, self.play_rad, self.stick_nmm,
                                         approach_rng if approach_rng is not None else rng,
                                         approach)
        if self.stiffness is not None:
            q = gravity_settled(*on_torques, q, self.masses_kg[arm], self.stiffness[arm],
                                gravity)
        p = np.asarray(self.robot.compiled_points(arm)(jnp.asarray(self.x_true),
                                                       jnp.asarray(q)))
        return p + rng.normal(0, self.measurement_noise_mm, p.shape)


class LinkedSimulationError(RuntimeError):
    """A linked row cannot be made: no joint solution reaches a target within the working
    range, or the joined arms' equilibrium did not settle."""



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


def _arm_program(robot: Robot, arm: str) -> Callable:
    """:func:`~bayesrob.sim.physics.arm_energy` of ``robot``'s ``arm``, as ``(x, u, u0, k,
    weight, centre, backlash, periodic=False) -> dict``, once the arm is one it can take."""
    chain = robot.chains[arm]
    if len(robot.path(arm)) != 1 or any(k != "revolute" for k in chain.kinds):
        raise ValueError(f"arm {arm!r}: linked equilibria are computed for arms of revolute "
                         "joints standing on their own (not mounted on another arm)")
    return partial(arm_energy, robot.structure, arm, robot.nominal_values)


def _arm_states(robot: Robot, arms: Sequence[str], x: jax.Array, us: Sequence[np.ndarray],
                u0s: Sequence[np.ndarray], ks: Sequence[jax.Array],
                weights: Sequence[jax.Array]) -> list[dict[str, np.ndarray]]:
    out = []
    for a, u, u0, k, w in zip(arms, us, u0s, ks, weights, strict=True):
        program, middles = _arm_program(robot, a), _middles(robot, a)

        def rows(x: jax.Array, u: jax.Array, side: dict, program=program, k=k, w=w,
                 middles=middles) -> dict:
            return program(x, u, side["u0"], k, w, *middles)
        # row buckets: one compiled program serves every row count of its bucket
        out.append(on_row_buckets(rows, x, np.asarray(u, float),
                                  {"u0": np.asarray(u0, float)}))
    return out


def _free_equilibria(robot: Robot, arms: Sequence[str], x: jax.Array,
                     u0s: Sequence[np.ndarray], ks: Sequence[jax.Array],
                     weights: Sequence[jax.Array], max_iter: int = 40) -> list[np.ndarray]:
    """Each arm's own equilibrium (N, n), springs holding it at ``u0s``, by Newton steps."""
    us = [u.copy() for u in u0s]
    for _ in range(max_iter):
        steps = [-np.linalg.solve(s["hess"], s["grad"][..., None])[..., 0]
                 for s in _arm_states(robot, arms, x, us, u0s, ks, weights)]
        us = [u + d for u, d in zip(us, steps, strict=True)]
        if max(np.abs(d).max() for d in steps) < 1e-12:
            return us
    raise LinkedSimulationError(f"free equilibrium did not converge in {max_iter} Newton steps")


def gravity_settled(robot: Robot, x: np.ndarray, arm: str, q: np.ndarray,
                    masses_kg: np.ndarray, stiffness: np.ndarray,
                    gravity: Sequence[float] = GRAVITY) -> np.ndarray:
    """Where an arm's joints (N, n) settle from their commands ``q`` under its links' weights
    (``masses_kg`` at their middles, ``gravity`` in the frames of ``robot`` at ``x``)."""
    ks, weights = _physics_arguments(robot, [arm], {arm: stiffness}, {arm: masses_kg}, gravity)
    return _free_equilibria(robot, [arm], jnp.asarray(x, float),
                            [np.atleast_2d(np.asarray(q, float))], ks, weights)[0]


def _middles(robot: Robot, arm: str) -> tuple[jax.Array, jax.Array]:
    # arm6's physics: centres of mass at the links' middles, no dead band
    n = robot.chains[arm].n_joints
    return jnp.full(n, 0.5), jnp.zeros(n)


def _physics_arguments(robot: Robot, arms: Sequence[str], stiffness: Mapping[str, np.ndarray],
                       masses_kg: Mapping[str, np.ndarray] | None,
                       gravity: Sequence[float] | None) -> tuple[list, list]:
    ks = [jnp.asarray(np.asarray(stiffness[a], float)) for a in arms]
    weights = [jnp.asarray(link_weights(None if masses_kg is None else masses_kg[a],
                                           gravity, robot.chains[a].n_joints)) for a in arms]
    return ks, weights


def linked_energy(robot: Robot, x: np.ndarray, u: Mapping[str, np.ndarray],
                  u0: Mapping[str, np.ndarray], stiffness: Mapping[str, np.ndarray],
                  masses_kg: Mapping[str, np.ndarray] | None = None,
                  gravity: Sequence[float] | None = GRAVITY) -> np.ndarray:
    """Total potential energy (N mm) per row of the arms at columns ``u[arm]`` (N, n), as
    :func:`linked_equilibrium` weighs it; the markers need not meet."""
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
    """The exact equilibrium of arms whose markers are joined by a ball joint, row by row:
    springs (``stiffness[arm]``, N mm/rad) hold the columns at ``u0[arm]`` (N, n) and link
    masses (kg) hang under ``gravity`` (None: none). LinkedSimulationError when the markers
    stay over ``tol_mm`` (at most 1e-6 mm) apart or the point is no constrained minimum."""
    arms = tuple(u0)
    if len(arms) < 2:
        raise ValueError("a linked equilibrium needs two arms or more")
    xj = jnp.asarray(x, float)
    ks, weights = _physics_arguments(robot, arms, stiffness, masses_kg, gravity)
    u0s = [np.atleast_2d(np.asarray(u0[a], float)) for a in arms]

    def states(us):
        return _arm_states(robot, arms, xj, us, u0s, ks, weights)

    us = _free_equilibria(robot, arms, xj, u0s, ks, weights, max_iter)
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
