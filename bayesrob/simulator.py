"""A physical simulator of servo-driven planar arms: the test bed of the whole project.

Physics, not curve fitting. Each joint is a position servo: a torsional spring of
stiffness ``k`` (N mm / rad) pulling the joint towards its commanded angle, with an
optional dead band (backlash) of half-width ``b`` in which the spring exerts nothing.
Gravity acts in the arm plane on point masses (link masses at mid-link, the elbow servo,
an end mass). An arm settles where its potential energy

    U(theta) = sum_j 1/2 k_j deadzone(theta_j - theta_cmd_j, b_j)^2 + sum_m m g_acc h_m(theta)

is least (h_m: height of mass m against the gravity direction). Linked arms share their end
point d and settle at the d that minimises the summed energy of both arms, each arm's joint
angles being its inverse kinematics at d: a tug of war between the servos' stiffnesses, not
an average.

Effects (names are a contract, see ``EFFECTS``):
- ``gravity_sag``: gravity loads the joints with the servos' real stiffness. Without it the
  servos are treated as ``STIFF_FACTOR`` times stiffer, so gravity still decides which side of
  a dead band a joint rests on but no longer deflects it measurably.
- ``backlash``: the dead band; where the gravity torque on a joint changes sign the joint
  crosses its band and the end point jumps (the paper's bottom-arm discontinuity).
- ``servo_nonlinearity``: the pulse-to-angle map gets a smooth ripple
  ``c * sin(2 pi (u - u_mid) / period)``, as a feedback potentiometer's track and the gear
  train give; over the few hundred microseconds a workspace uses it bends the map visibly.
Always on: joint repeatability noise (on the commanded angle) and measurement noise on the
observed end point.

All randomness flows from one seed, so a rig is reproducible from its ``truth.toml``.
"""

from __future__ import annotations

import tomllib
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import scipy.optimize

from bayesrob import kinematics as kin
from bayesrob.rig import (
    MEASUREMENTS_FILE,
    RIG_FILE,
    ArmSpec,
    RigError,
    dump_toml,
    format_row,
    is_planned,
    measurement_header,
    rig_toml_dict,
)
from bayesrob.vocabulary import EFFECTS

TRUTH_FILE = "truth.toml"
G_ACC = 9.81  # m/s^2: with masses in kg and lengths in mm, energies come out in N mm
STIFF_FACTOR = 1000.0
HOLDOUT_STREAM = 1  # spawn key of the holdout rows' noise (see holdout_seed)


@dataclass(frozen=True)
class ArmTruth:
    """True physical parameters of one arm (what ``truth.toml`` records)."""

    name: str
    base: tuple[float, float]
    links: tuple[float, float]
    gain: tuple[float, float]
    offset: tuple[float, float]
    elbow: int
    pulse_limits: tuple[tuple[float, float], tuple[float, float]]
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
        return kin.ArmParams(*(jnp.asarray(x, dtype=jnp.float64)
                               for x in (self.base, self.links, self.gain, self.offset)))

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

    # -- file round trip ---------------------------------------------------------------
    def to_toml(self) -> str:
        doc = asdict(self)
        doc["effects"] = list(self.effects)
        return "# True parameters of a simulated rig. Only tests read this file.\n" + \
            dump_toml(_lists(doc))

    @classmethod
    def from_toml(cls, path: str | Path) -> Truth:
        doc = tomllib.loads(Path(path).read_text())
        arms = {n: ArmTruth(**_tuples(a)) for n, a in doc.pop("arms").items()}
        doc = _tuples(doc)
        return cls(arms=arms, **doc)


def _lists(x):
    if isinstance(x, dict):
        return {k: _lists(v) for k, v in x.items()}
    if isinstance(x, tuple | list):
        return [_lists(v) for v in x]
    return x


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
    """The paper's setup: a top arm hung from a strut, a bottom arm standing on the base.

    The bottom arm carries most of its mobile mass in the elbow servo and bends its elbow to
    the left, so across the workspace the gravity torque on its shoulder changes sign and the
    shoulder's backlash makes the end point jump, as the paper saw.

    ``stiffness_log_sd`` > 0 draws each arm's joint stiffnesses for this seed
    (:func:`with_drawn_stiffness`); 0 keeps every arm at the same (2500, 1800) N mm/rad.
    """
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
    """The truth with each arm's joint stiffnesses drawn for its seed: the arm's own ones
    scaled by exp(N(0, sd) per arm + N(0, sd) per joint), as the 3-D simulator draws them.

    Two servos of one model are not equally stiff, and neither are two arms' mountings and
    links. With one stiffness for every arm, a prior that linked arms are alike is right by
    construction, so predictions judged on such rigs flatter it. The draws come from a stream
    of their own: the rest of the rig is what the seed always gave. 0 leaves the truth as is.
    """
    if not (np.isfinite(log_sd) and log_sd >= 0):
        raise ValueError(f"stiffness_log_sd must be a finite number >= 0, got {log_sd}")
    if log_sd == 0:
        return truth
    drawn = draw_stiffnesses(truth.seed, {n: a.stiffness_nmm_per_rad
                                          for n, a in truth.arms.items()}, log_sd)
    return replace(truth, arms={
        n: replace(a, stiffness_nmm_per_rad=tuple(float(round(v, 1)) for v in drawn[n]))
        for n, a in truth.arms.items()})


def draw_stiffnesses(seed: int, profiles: Mapping[str, Sequence[float]], log_sd: float
                     ) -> dict[str, np.ndarray]:
    """Each arm's joint stiffnesses for a seed: its profile times exp(N(0, sd) per arm +
    N(0, sd) per joint), arms in the order given, from the seed's stream 17 (planar and 3-D
    simulators alike)."""
    rng = np.random.default_rng([seed, 17])
    out = {}
    for name, profile in profiles.items():
        k = np.asarray(profile, float)
        out[name] = k * np.exp(log_sd * rng.normal() + log_sd * rng.normal(size=k.shape))
    return out


def three_arm_truth(effects: Iterable[str] = (), seed: int = 0, grid: int = 4,
                    stiffness_log_sd: float = 0.0) -> Truth:
    """The paper's two arms and a third standing to the left of the workspace (``side``):
    three arms linked at one end point, for predictions of assemblies of more than two.

    With ``stiffness_log_sd`` the top and bottom arms get the stiffnesses :func:`paper_truth`
    draws for the seed, and the side arm the next draws of the same stream."""
    pair = paper_truth(effects, seed, grid)
    base, links, gain = (-170.0, 190.0), (260.0, 240.0), (0.00151, 0.00149)
    limits = ((600.0, 2400.0), (600.0, 2400.0))
    offset = _offsets_for(base, links, gain, -1, limits, pair.workspace)
    side = ArmTruth("side", base, links, gain, offset, -1, limits, link_mass_kg=(0.045, 0.035),
                    elbow_mass_kg=0.07, end_mass_kg=0.015)
    truth = replace(pair, name="three-arm-rig", arms={**pair.arms, "side": side})
    return with_drawn_stiffness(truth, stiffness_log_sd)


# ------------------------------------------------------------------------------ physics


def commanded_angles(arm: ArmTruth, u: jax.Array, effects: Sequence[str]) -> jax.Array:
    """The angle each servo tries to hold for pulse widths u (..., 2)."""
    theta = kin.servo(arm.params, u)
    if "servo_nonlinearity" in effects:
        phase = 2 * jnp.pi * (u - arm.u_mid) / jnp.asarray(arm.nonlinearity_period_us)
        theta = theta + jnp.asarray(arm.nonlinearity_rad) * jnp.sin(phase)
    return theta


class _ArmArrays(NamedTuple):
    """An arm's physics as arrays, so one compiled energy serves every arm and every rig."""

    params: kin.ArmParams
    masses: jax.Array  # (4,) kg: link 1, elbow servo, link 2, end
    stiffness: jax.Array  # (2,) N mm / rad, already scaled for the effects in force
    backlash: jax.Array  # (2,) rad half-width, zero without the effect


def _arm_arrays(arm: ArmTruth, effects: Sequence[str]) -> _ArmArrays:
    k = jnp.asarray(arm.stiffness_nmm_per_rad, dtype=jnp.float64)
    if "gravity_sag" not in effects:
        k = k * STIFF_FACTOR
    b = jnp.asarray(arm.backlash_rad, dtype=jnp.float64) if "backlash" in effects else jnp.zeros(2)
    m = jnp.array([arm.link_mass_kg[0], arm.elbow_mass_kg, arm.link_mass_kg[1], arm.end_mass_kg])
    return _ArmArrays(arm.params, m, k, b)


def _mass_points(params: kin.ArmParams, theta: jax.Array) -> jax.Array:
    """Positions (4, 2) of the point masses: mid link 1, elbow, mid link 2, end."""
    elbow = kin.elbow_point(params, theta)
    end = kin.forward(params, theta)
    return jnp.stack([(params.base + elbow) / 2, elbow, (elbow + end) / 2, end])


def _deadzone(x: jax.Array, b: jax.Array) -> jax.Array:
    return jnp.sign(x) * jnp.maximum(jnp.abs(x) - b, 0.0)


def _energy(theta: jax.Array, theta_cmd: jax.Array, a: _ArmArrays, gravity: jax.Array
            ) -> jax.Array:
    spring = 0.5 * jnp.sum(a.stiffness * _deadzone(kin.wrap_angle(theta - theta_cmd),
                                                   a.backlash) ** 2)
    # Potential of a mass in a field along unit vector g_dir is -m g (g_dir . r).
    grav = -G_ACC * jnp.sum(a.masses * (_mass_points(a.params, theta) @ gravity))
    return spring + grav


_arm_energy_vg = jax.jit(jax.value_and_grad(_energy))


@partial(jax.jit, static_argnames="elbows")
def _linked_energy_vg(d: jax.Array, theta_cmds: tuple, arms: tuple, gravity: jax.Array,
                      elbows: tuple[int, ...]) -> tuple[jax.Array, jax.Array]:
    def total(d):
        out = 0.0
        for a, tc, e in zip(arms, theta_cmds, elbows, strict=True):
            theta, _ = kin.inverse(a.params, d, e)
            out = out + _energy(theta, tc, a, gravity)
        return out

    return jax.value_and_grad(total)(d)


class PhysicalRig:
    """The simulated hardware: pulse widths in, settled end points out.

    Used by ``bayesrob simulate`` and by the simulated serial device, so the files and the
    pseudo-terminal answer with the same physics.
    """

    def __init__(self, truth: Truth, seed: int | None = None):
        self.truth = truth
        self.rng = np.random.default_rng(truth.seed if seed is None else seed)
        self._gravity = jnp.asarray(truth.gravity, dtype=jnp.float64)
        self._arrays = {n: _arm_arrays(a, truth.effects) for n, a in truth.arms.items()}

    @classmethod
    def from_rig_dir(cls, directory: str | Path, seed: int | None = None) -> PhysicalRig:
        return cls(Truth.from_toml(Path(directory) / TRUTH_FILE), seed)

    def _k_scale(self, name: str) -> float:
        # Energies are divided by the softest spring so the optimiser's tolerances mean the
        # same for stiff and soft servos.
        return float(jnp.min(self._arrays[name].stiffness))

    def settle_arm(self, name: str, theta_cmd: np.ndarray) -> np.ndarray:
        """Equilibrium joint angles of a free arm holding commanded angles theta_cmd."""
        a = self._arrays[name]
        scale = self._k_scale(name)
        tc = jnp.asarray(theta_cmd, dtype=jnp.float64)

        def obj(t):
            v, gr = _arm_energy_vg(jnp.asarray(t), tc, a, self._gravity)
            return float(v) / scale, np.asarray(gr) / scale

        res = scipy.optimize.minimize(obj, np.asarray(theta_cmd, float), jac=True,
                                      method="BFGS", options={"gtol": 1e-12, "maxiter": 500})
        return res.x

    def settle_linked(self, theta_cmds: dict[str, np.ndarray]) -> np.ndarray:
        """Common end point of arms linked at their end points (least total energy)."""
        names = tuple(theta_cmds)
        arrays = tuple(self._arrays[n] for n in names)
        elbows = tuple(int(self.truth.arms[n].elbow) for n in names)
        tc = tuple(jnp.asarray(theta_cmds[n], dtype=jnp.float64) for n in names)
        free = [kin.forward(self.truth.arms[n].params, self.settle_arm(n, theta_cmds[n]))
                for n in names]
        d0 = np.mean(np.asarray(free), axis=0)
        scale = sum(self._k_scale(n) for n in names)

        def obj(d):
            v, gr = _linked_energy_vg(jnp.asarray(d), tc, arrays, self._gravity, elbows)
            return float(v) / scale, np.asarray(gr) / scale

        res = scipy.optimize.minimize(obj, d0, jac=True, method="BFGS",
                                      options={"gtol": 1e-12, "maxiter": 500})
        return res.x

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


# ------------------------------------------------------------------------------ rig files


def grid_points(workspace, n: int) -> np.ndarray:
    """An n x n grid over the workspace, row by row from the top left."""
    xs = np.linspace(*workspace[0], n)
    ys = np.linspace(*workspace[1], n)[::-1]
    return np.array([(x, y) for y in ys for x in xs])


def holdout_points(workspace, n: int) -> np.ndarray:
    """The centres of the n x n grid's (n - 1) x (n - 1) cells, row by row from the top left.

    The training grid shifted by half a cell, keeping the points inside the workspace: each
    is as far from the training poses as the grid allows, so errors there measure accuracy at
    new poses, where the paper's ``validation`` repeats only measure repeatability.
    """
    if n < 2:
        return np.zeros((0, 2))
    g = grid_points(workspace, n)
    half = np.array([(workspace[0][1] - workspace[0][0]) / (n - 1),
                     -(workspace[1][1] - workspace[1][0]) / (n - 1)]) / 2
    corners = g.reshape(n, n, 2)[:-1, :-1].reshape(-1, 2)  # drop the last row and column
    return corners + half


def nominal_specs(truth: Truth, rng: np.random.Generator) -> dict[str, ArmSpec]:
    """Nominal values as a person would measure them: the truth plus measuring error."""
    err = truth.nominal_error
    specs = {}
    for name, a in truth.arms.items():
        def r(x, sd, rel=False):
            x = np.asarray(x, float)
            return tuple(float(round(v, 5)) for v in
                         (x * (1 + rng.normal(0, sd, x.shape)) if rel else
                          x + rng.normal(0, sd, x.shape)))
        specs[name] = ArmSpec(
            name, r(a.base, err["base_mm"]), r(a.links, err["links_mm"]),
            r(a.gain, err["gain_rel"], rel=True), r(a.offset, err["offset_rad"]),
            a.elbow, a.pulse_limits)
    return specs


def round_pulse(u: np.ndarray) -> np.ndarray:
    """Controllers resolve a quarter microsecond (the Maestro's unit)."""
    return np.round(np.asarray(u, float) * 4) / 4


def simulate_rig(out_dir: str | Path, truth: Truth, progress: bool = False,
                 holdout: bool = True) -> Path:
    """Write a rig directory (rig.toml, measurements.csv, truth.toml) from the truth.

    Training commands aim at the grid through each arm's *nominal* inverse model (a person
    aiming approximately); validation repeats them; the linked ``test`` rows aim both arms at
    each grid point through their own inverse models calibrated on the train rows. Then the
    ``holdout`` rows, at new poses (:func:`holdout_points`, between the grid points): each
    arm alone aimed through its nominal model, then the arms linked and aimed through their
    calibrated models. Their noise comes from a stream of its own, so the rows before them
    are those a run without holdout rows (``holdout=False``) writes, byte for byte.
    """
    from bayesrob.calibrate.arms import calibrate_arm  # calibration needs rig types only

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(truth.seed)
    specs = nominal_specs(truth, rng)
    plant = PhysicalRig(truth, seed=int(rng.integers(2**31)))
    names = list(truth.arms)
    grid = grid_points(truth.workspace, truth.grid)
    rows = []
    hold = holdout_points(truth.workspace, truth.grid) if holdout else np.zeros((0, 2))
    steps = (2 * len(names) + 1) * len(grid) + (len(names) + (len(names) > 1)) * len(hold)
    bar = _progress(steps, progress, "simulate")
    train: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    nominals = {name: kin.Arm.nominal(specs[name]) for name in names}
    for name in names:
        nominal = nominals[name]
        u_all = round_pulse(np.asarray(nominal.command(jnp.asarray(grid))))
        _check_limits(name, u_all, truth.arms[name].pulse_limits)
        for set_name in ("train", "validation"):
            obs = []
            for u in u_all:
                d = plant.end_point({name: u})
                obs.append(d)
                rows.append(format_row(names, name, set_name, None, {name: u}, d))
                bar.update()
            if set_name == "train":
                train[name] = (u_all, np.asarray(obs))
    calibrated = {}
    for name in names:
        u, d = train[name]
        calibrated[name] = calibrate_arm(specs[name], u, d).arm
    linked = "+".join(names)

    def aim(target: np.ndarray) -> dict[str, np.ndarray]:
        cmds = {}
        for name in names:
            u = round_pulse(np.asarray(calibrated[name].command(jnp.asarray(target))))
            _check_limits(name, u[None], truth.arms[name].pulse_limits)
            cmds[name] = u
        return cmds

    for target in grid:
        cmds = aim(target)
        d = plant.end_point(cmds)
        rows.append(format_row(names, linked, "test", target, cmds, d))
        bar.update()
    plant.rng = np.random.default_rng(holdout_seed(truth.seed))
    for name in names if len(hold) else ():
        u_all = round_pulse(np.asarray(nominals[name].command(jnp.asarray(hold))))
        _check_limits(name, u_all, truth.arms[name].pulse_limits)
        for u in u_all:
            rows.append(format_row(names, name, "holdout", None, {name: u},
                                   plant.end_point({name: u})))
            bar.update()
    if len(names) > 1:  # a single arm's test rows are its only ones: nothing is linked
        for target in hold:
            cmds = aim(target)
            rows.append(format_row(names, linked, "holdout", target, cmds,
                                   plant.end_point(cmds)))
            bar.update()
    bar.close()

    (out / RIG_FILE).write_text(dump_toml(rig_toml_dict(
        truth.name, specs, truth.gravity, truth.workspace)))
    import csv
    with (out / MEASUREMENTS_FILE).open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(measurement_header(names))
        w.writerows(rows)
    (out / TRUTH_FILE).write_text(truth.to_toml())
    return out


def holdout_seed(seed: int) -> np.random.SeedSequence:
    """The holdout rows' noise stream: derived from the rig's seed, apart from the main one."""
    return np.random.SeedSequence([seed, HOLDOUT_STREAM])


def _check_limits(name: str, u: np.ndarray, limits) -> None:
    lim = np.asarray(limits)
    bad = ~np.all((u >= lim[:, 0]) & (u <= lim[:, 1]), axis=-1)
    if bad.any():
        raise ValueError(f"simulated arm {name!r}: a grid point needs pulses "
                         f"{u[bad][0].tolist()} outside its limits {limits}")


def _progress(total: int, enabled: bool, desc: str):
    from bayesrob.progress import progress
    return progress(total, desc, "pt", enabled=enabled)


def measure_planned(directory: str | Path, seed: int = 0, progress: bool = False
                    ) -> tuple[int, int]:
    """Measure a rig's planned rows (commands given, x and y empty) with the physics of its
    ``truth.toml``: how a candidate written by ``bayesrob design`` is tried in simulation.

    Rows already measured are kept as they are; the file is replaced in one step at the end,
    so an interrupted run leaves it unchanged. Returns (rows measured, rows in the file).
    """
    import csv
    import io
    import os

    directory = Path(directory)
    truth_path = directory / TRUTH_FILE
    if not truth_path.is_file():
        raise RigError(f"{truth_path}: file not found (only a rig with the simulator's truth "
                       "can be measured in simulation; use bayesrob collect on hardware)")
    truth = Truth.from_toml(truth_path)
    path = directory / MEASUREMENTS_FILE
    if not path.is_file():
        raise RigError(f"{path}: file not found")
    with path.open(newline="", encoding="utf-8") as fh:
        rows = list(csv.reader(fh))
    if not rows:
        raise RigError(f"{path}: empty file (a header row is required)")
    header, body = rows[0], rows[1:]
    idx = {h: i for i, h in enumerate(header)}
    for col in ("config", "x", "y"):
        if col not in idx:
            raise RigError(f"{path}: missing column '{col}'")
    plant = PhysicalRig(truth, seed=seed)
    planned = [r for r, row in enumerate(body) if len(row) == len(header)
               and is_planned(row, idx)]
    bar = _progress(len(planned), progress, "measure")
    for r in planned:
        row, where = body[r], f"{path}: line {r + 2}"
        members = row[idx["config"]].split("+")
        cmds = {}
        for a in members:
            if a not in truth.arms:
                raise RigError(f"{where}: arm {a!r} is not in {truth_path}")
            try:
                cmds[a] = [float(row[idx[f"{a}_u{j}"]]) for j in (1, 2)]
            except (KeyError, ValueError):
                raise RigError(f"{where}: arm {a!r} needs numbers in {a}_u1 and {a}_u2") \
                    from None
        d = plant.end_point(cmds)
        row[idx["x"]], row[idx["y"]] = (f"{v:.6g}" for v in d)
        bar.update()
    bar.close()
    buf = io.StringIO()
    csv.writer(buf).writerows([header, *body])
    tmp = path.with_suffix(".csv.tmp")
    tmp.write_text(buf.getvalue())
    os.replace(tmp, path)
    return len(planned), len(body)
