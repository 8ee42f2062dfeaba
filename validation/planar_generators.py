"""Rig generators whose physics deliberately differs from ``bayesrob.sim``.

The diagnosis must recognise an effect in data it did not make: real sag does not come from
point masses on linear springs, real play does not sit exactly on the gravity side, real
servos are not bent by a sinusoid. So these generators write rig directories in the rig
format from other physics:

- ``gravity_sag``, ``sag="joints"``: uniform rods plus point masses on *hardening* springs
  (k d + k3 d^3 = torque, stiffness doubling by 0.1 rad; the torque taken at the deflected
  pose, solved by fixed point), plus link 2 bending like a cantilever under the load across
  it (an end-point shift, not a joint rotation).
- ``gravity_sag``, ``sag="links"``: stiff joints, and the compliance in the *links*: each link
  bends as a cantilever under its own weight and everything beyond it (tip deflection
  P L^3 / 3EI + w L^4 / 8EI across the link, and the slope that turns the next link).
- ``backlash``: play with *hysteresis*: a joint whose gravity torque exceeds its friction
  rests on the gravity side; below that, on the side it was approached from (the order the
  commands were sent in matters, as on hardware).
- ``servo_nonlinearity``: a saturating map, theta = g(u) + A tanh((u - u0) / w) with u0 off
  the centre of the commanded range: odd *and* even curvature, not a sinusoid.

Every rig also has ``holdout`` rows at new poses (the centres of the training grid's cells),
after its other rows, so that gaps are reported where no row was fitted.

Only numpy and the kinematics module are used; nothing reads ``truth.toml``.

Sweeps keep their rigs apart: :func:`tuning_cases` (seeds 21-35) are the rigs the decision
rule and the candidates' priors were chosen on; :func:`report_cases` (seeds 501-534, fixed
before any diagnosis was run on them) only report. The validation study
:mod:`bayesrob.validation.diagnosis` runs them.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from bayesrob import robot as kin
from bayesrob.data.rig import ArmSpec, dump_toml, format_row, measurement_header, rig_toml_dict
from bayesrob.sim.rigs import holdout_points

G_ACC = 9.81
EFFECTS = ("gravity_sag", "backlash", "servo_nonlinearity")


@dataclass(frozen=True)
class GenArm:
    name: str
    base: tuple[float, float]
    links: tuple[float, float]
    gain: tuple[float, float]
    elbow: int
    link_mass_kg: tuple[float, float] = (0.05, 0.04)
    elbow_mass_kg: float = 0.07
    end_mass_kg: float = 0.02
    stiffness: tuple[float, float] = (2500.0, 1800.0)  # N mm / rad
    hardening: tuple[float, float] = (2.5e5, 1.8e5)  # N mm / rad^3: stiffness x2 at 0.1 rad
    link2_flex_mm_per_n: float = 2.0  # end shift per N of load across link 2
    # bending stiffness E I of each link (N mm^2), for sag="links": printed plastic bars
    # (E about 3.5 GPa, a 10 x 7 mm section). Stiffer links (aluminium, 15x) sag a few mm,
    # which the geometric calibration takes up almost entirely (measured: strength 1.0).
    link_ei_nmm2: tuple[float, float] = (4.0e5, 3.0e5)
    play_rad: tuple[float, float] = (0.008, 0.008)  # half-width
    friction_nmm: tuple[float, float] = (8.0, 8.0)  # torque below which play follows approach
    tanh_amp_rad: tuple[float, float] = (0.04, 0.03)
    tanh_width_us: tuple[float, float] = (300.0, 350.0)
    tanh_shift_us: tuple[float, float] = (120.0, -90.0)  # u0 relative to the range centre
    limits: tuple[tuple[float, float], tuple[float, float]] = ((600.0, 2400.0),) * 2


@dataclass(frozen=True)
class GenRig:
    arms: tuple[GenArm, ...]
    effects: tuple[str, ...] = ()
    gravity: tuple[float, float] = (0.0, -1.0)
    workspace: tuple[tuple[float, float], tuple[float, float]] = ((80.0, 260.0), (100.0, 280.0))
    grid: int = 4
    seed: int = 0
    joint_noise_rad: float = 0.0008
    measurement_noise_mm: float = 0.35
    scale: dict = field(default_factory=dict)  # effect -> magnitude multiplier
    sag: str = "joints"  # where gravity_sag's compliance is: "joints" or "links"

    def with_effects(self, *effects: str, **scale: float) -> GenRig:
        for e in effects:
            if e not in EFFECTS:
                raise ValueError(e)
        return replace(self, effects=tuple(effects), scale=dict(scale))


def paper_like(grid: int = 4, seed: int = 0) -> GenRig:
    """Two arms as in the paper (one hung above, one standing below), own numbers."""
    return GenRig((
        GenArm("top", (25.0, 445.0), (235.0, 225.0), (0.00151, 0.00149), 1,
               link_mass_kg=(0.06, 0.035), elbow_mass_kg=0.06, end_mass_kg=0.025),
        GenArm("bottom", (15.0, -25.0), (225.0, 195.0), (0.00149, 0.00153), -1,
               link_mass_kg=(0.045, 0.025), elbow_mass_kg=0.095, end_mass_kg=0.012),
    ), grid=grid, seed=seed)


def tilted(grid: int = 4, seed: int = 0) -> GenRig:
    """Another geometry: arms on a plane tilted 20 degrees, bases left and right."""
    t = math.radians(20)
    return GenRig((
        GenArm("left", (-120.0, 120.0), (250.0, 210.0), (0.00150, 0.00152), -1,
               link_mass_kg=(0.05, 0.03), elbow_mass_kg=0.09, end_mass_kg=0.015,
               stiffness=(2000.0, 1600.0)),
        GenArm("right", (420.0, 140.0), (240.0, 220.0), (0.00152, 0.00148), 1,
               link_mass_kg=(0.05, 0.04), elbow_mass_kg=0.07, end_mass_kg=0.02,
               stiffness=(2000.0, 1600.0)),
    ), gravity=(math.sin(t), -math.cos(t)), workspace=((90.0, 230.0), (90.0, 250.0)),
        grid=grid, seed=seed)


# ------------------------------------------------------------------------------ physics


def _unit(a: np.ndarray) -> np.ndarray:
    return np.stack([np.cos(a), np.sin(a)], -1)


def _cross(a: np.ndarray, g: np.ndarray) -> float:
    return float(a[0] * g[1] - a[1] * g[0])


def _torques(arm: GenArm, theta: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Gravity torques (N mm) about shoulder and elbow: uniform rods and point masses."""
    l1, l2 = arm.links
    e1, e12 = _unit(theta[0]), _unit(theta[0] + theta[1])
    m1, m2 = arm.link_mass_kg
    # Moment of the distal masses about the elbow (kg mm), along link 2.
    elbow_moment = (m2 * l2 / 2 + arm.end_mass_kg * l2) * e12
    distal_mass = m2 + arm.end_mass_kg + arm.elbow_mass_kg
    shoulder_moment = m1 * l1 / 2 * e1 + distal_mass * l1 * e1 + elbow_moment
    return G_ACC * np.array([_cross(shoulder_moment, g), _cross(elbow_moment, g)])


def _bent_end(arm: GenArm, theta: np.ndarray, g: np.ndarray, scale: float) -> np.ndarray:
    """End point of an arm with rigid joints at ``theta`` whose links bend as cantilevers.

    Link 1 carries its own weight (spread), the elbow and everything beyond it (a force and
    the distal part's moment at its tip); link 2 its weight and the end mass. Each link's
    tip moves across it by the beam's deflection and turns by its slope, which turns the
    next link: small-deflection beam theory, loads taken at the unbent pose.
    """
    l1, l2 = arm.links
    m1, m2 = arm.link_mass_kg
    ei1, ei2 = (e / scale for e in arm.link_ei_nmm2)
    e1 = _unit(theta[0])
    n1 = np.array([-e1[1], e1[0]])
    w1 = G_ACC * m1 / l1 * float(n1 @ g)  # N per mm across link 1
    p1 = G_ACC * (arm.elbow_mass_kg + m2 + arm.end_mass_kg) * float(n1 @ g)
    moment1 = _torques(arm, theta, g)[1]  # the distal part's torque about the elbow
    defl1 = p1 * l1**3 / (3 * ei1) + w1 * l1**4 / (8 * ei1) + moment1 * l1**2 / (2 * ei1)
    slope1 = p1 * l1**2 / (2 * ei1) + w1 * l1**3 / (6 * ei1) + moment1 * l1 / ei1
    elbow = np.asarray(arm.base) + l1 * e1 + defl1 * n1
    e2 = _unit(theta[0] + theta[1] + slope1)
    n2 = np.array([-e2[1], e2[0]])
    w2 = G_ACC * m2 / l2 * float(n2 @ g)
    p2 = G_ACC * arm.end_mass_kg * float(n2 @ g)
    defl2 = p2 * l2**3 / (3 * ei2) + w2 * l2**4 / (8 * ei2)
    return elbow + l2 * e2 + defl2 * n2


def _solve_spring(k: float, k3: float, tau: float) -> float:
    """The deflection d with k d + k3 d^3 = tau (a hardening spring), by Newton."""
    d = tau / k
    for _ in range(20):
        d -= (k * d + k3 * d**3 - tau) / (k + 3 * k3 * d**2)
    return d


def _offsets(arm: GenArm, workspace) -> tuple[float, float]:
    centre = jnp.array([np.mean(workspace[0]), np.mean(workspace[1])])
    p = kin.ArmParams(jnp.array(arm.base), jnp.array(arm.links), jnp.array(arm.gain),
                      jnp.zeros(2))
    theta, ok = kin.inverse(p, centre, arm.elbow)
    if not bool(ok):
        raise ValueError(f"arm {arm.name}: workspace centre out of reach")
    mid = np.array([(lo + hi) / 2 for lo, hi in arm.limits])
    return tuple(float(t - g * m) for t, g, m in zip(np.asarray(theta), arm.gain, mid,
                                                      strict=True))


class _Plant:
    """One arm's hardware: remembers where its joints came from (for hysteresis)."""

    def __init__(self, arm: GenArm, rig: GenRig, rng: np.random.Generator):
        self.arm, self.rig, self.rng = arm, rig, rng
        self.offset = np.array(_offsets(arm, rig.workspace))
        self.g = np.asarray(rig.gravity, float) / np.linalg.norm(rig.gravity)
        self.prev_cmd: np.ndarray | None = None
        self.u_mid = np.array([(lo + hi) / 2 for lo, hi in arm.limits])

    def s(self, effect: str) -> float:
        return float(self.rig.scale.get(effect, 1.0))

    def commanded(self, u: np.ndarray) -> np.ndarray:
        a = self.arm
        theta = np.asarray(a.gain) * u + self.offset
        if "servo_nonlinearity" in self.rig.effects:
            u0 = self.u_mid + np.asarray(a.tanh_shift_us)
            theta = theta + self.s("servo_nonlinearity") * np.asarray(a.tanh_amp_rad) * \
                np.tanh((u - u0) / np.asarray(a.tanh_width_us))
        return theta

    def end_point(self, u: np.ndarray) -> np.ndarray:
        a, eff = self.arm, self.rig.effects
        cmd = self.commanded(np.asarray(u, float))
        cmd = cmd + self.rng.normal(0.0, self.rig.joint_noise_rad, 2)
        bent = "gravity_sag" in eff and self.rig.sag == "links"
        sag = "gravity_sag" in eff and not bent
        k = np.asarray(a.stiffness) / (self.s("gravity_sag") if sag else 1e-3)
        theta = cmd.copy()
        for _ in range(30):  # the torque depends on the pose it deflects: fixed point
            tau = _torques(a, theta, self.g)
            defl = np.array([_solve_spring(k[j], a.hardening[j] if sag else 0.0, tau[j])
                             for j in range(2)])
            new = cmd + defl
            if "backlash" in eff:
                play = self.s("backlash") * np.asarray(a.play_rad)
                approach = np.sign(cmd - (self.prev_cmd if self.prev_cmd is not None
                                          else cmd - 1e-3))
                # The gear trails the motion unless gravity is strong enough to pull the
                # joint across its play.
                side = np.where(np.abs(tau) > np.asarray(a.friction_nmm), np.sign(tau),
                                -approach)
                new = new + play * side
            if np.max(np.abs(new - theta)) < 1e-12:
                break
            theta = new
        self.prev_cmd = cmd
        e12 = _unit(theta[0] + theta[1])
        if bent:
            end = _bent_end(a, theta, self.g, self.s("gravity_sag"))
        else:
            end = np.asarray(kin.forward(kin.ArmParams(
                jnp.asarray(a.base), jnp.asarray(a.links), jnp.zeros(2), jnp.zeros(2)),
                jnp.asarray(theta)))
        if sag:
            # Link 2 bends under the load across it: a shift square to the link.
            normal = np.array([-e12[1], e12[0]])
            load = G_ACC * (a.end_mass_kg + 0.4 * a.link_mass_kg[1]) * float(normal @ self.g)
            end = end + self.s("gravity_sag") * a.link2_flex_mm_per_n * load * normal
        return end + self.rng.normal(0.0, self.rig.measurement_noise_mm, 2)


def _grid(workspace, n: int) -> np.ndarray:
    xs = np.linspace(*workspace[0], n)
    ys = np.linspace(*workspace[1], n)[::-1]
    return np.array([(x, y) for y in ys for x in xs])


def write_rig(out_dir: str | Path, rig: GenRig) -> Path:
    """Write rig.toml and measurements.csv (no truth file: the diagnosis must not need one)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(rig.seed)
    names = [a.name for a in rig.arms]
    specs = {}
    for a in rig.arms:
        off = _offsets(a, rig.workspace)
        specs[a.name] = ArmSpec(
            a.name, tuple(float(round(x + rng.normal(0, 2.0), 4)) for x in a.base),
            tuple(float(round(x + rng.normal(0, 1.5), 4)) for x in a.links),
            tuple(float(round(x * (1 + rng.normal(0, 0.02)), 7)) for x in a.gain),
            tuple(float(round(x + rng.normal(0, 0.02), 4)) for x in off), a.elbow, a.limits)
    plants = {a.name: _Plant(a, rig, rng) for a in rig.arms}
    grid = _grid(rig.workspace, rig.grid)
    rows = []
    commands = {}
    for a in rig.arms:
        nominal = kin.Arm.nominal(specs[a.name])
        u_all = np.round(np.asarray(nominal.command(jnp.asarray(grid))) * 4) / 4
        commands[a.name] = u_all
        for set_name in ("train", "validation"):
            for u in u_all:
                d = plants[a.name].end_point(u)
                rows.append(format_row(names, a.name, set_name, None, {a.name: u}, d))
    # Linked rows: the arms share the end point; a stiffness-free average is enough here
    # (the diagnosis uses single-arm rows only, the rows just keep the rig complete).
    for i, target in enumerate(grid):
        cmds = {n: commands[n][i] for n in names}
        d = np.mean([plants[n].end_point(cmds[n]) for n in names], axis=0)
        rows.append(format_row(names, "+".join(names), "test", target, cmds, d))
    # New poses, after everything else (the plants remember their last command, as hardware
    # does): each arm alone at the centres of the grid's cells, aimed by its nominal model.
    for a in rig.arms:
        nominal = kin.Arm.nominal(specs[a.name])
        hold = holdout_points(rig.workspace, rig.grid)
        for u in np.round(np.asarray(nominal.command(jnp.asarray(hold))) * 4) / 4:
            rows.append(format_row(names, a.name, "holdout", None, {a.name: u},
                                   plants[a.name].end_point(u)))
    (out / "rig.toml").write_text(dump_toml(rig_toml_dict(
        "generated", specs, tuple(float(x) for x in np.asarray(rig.gravity) /
                                  np.linalg.norm(rig.gravity)), rig.workspace)))
    with (out / "measurements.csv").open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(measurement_header(names))
        w.writerows(rows)
    return out


# ------------------------------------------------------------------------------ sweeps


@dataclass(frozen=True)
class Case:
    """One rig of a sweep: which physics made it and with what."""

    source: str  # "simulator" (bayesrob.sim) or "generator" (this module)
    geometry: str  # "paper" for the simulator; "paper_like" or "tilted" here
    effects: tuple[str, ...]
    grid: int = 4
    seed: int = 1
    scale: float = 1.0  # multiplies every effect's magnitude
    noise_mm: float | None = None  # measurement noise sd (None: the default 0.35)
    sag: str = "joints"  # generator only: gravity sag in the "joints" or in the "links"

    @property
    def label(self) -> str:
        return "+".join(self.effects) or "none"


def make_rig(case: Case, out_dir: str | Path) -> Path:
    """Write the case's rig directory."""
    if case.source == "simulator":
        from bayesrob.sim.rigs import simulate_rig
        from bayesrob.sim.truth import paper_truth

        truth = paper_truth(case.effects, seed=case.seed, grid=case.grid)
        s = case.scale
        arms = {n: replace(a, stiffness_nmm_per_rad=tuple(k / s for k in a.stiffness_nmm_per_rad),
                           backlash_rad=tuple(b * s for b in a.backlash_rad),
                           nonlinearity_rad=tuple(c * s for c in a.nonlinearity_rad))
                for n, a in truth.arms.items()}
        truth = replace(truth, arms=arms)
        if case.noise_mm is not None:
            truth = replace(truth, measurement_noise_mm=case.noise_mm)
        return simulate_rig(out_dir, truth)
    make = {"paper_like": paper_like, "tilted": tilted}[case.geometry]
    rig = replace(make(grid=case.grid, seed=case.seed).with_effects(
        *case.effects, **{e: case.scale for e in case.effects}), sag=case.sag)
    if case.noise_mm is not None:
        rig = replace(rig, measurement_noise_mm=case.noise_mm)
    return write_rig(out_dir, rig)


TRUTHS = [(), ("gravity_sag",), ("backlash",), ("servo_nonlinearity",),
          ("gravity_sag", "backlash")]


def clean_twin(case: Case) -> Case:
    """The same rig (geometry, grid, seed, noise) without its hidden effects."""
    return replace(case, effects=(), scale=1.0)


def tuning_cases() -> list[Case]:
    """The rigs the decision rule and the candidates' priors were chosen on: 40 rigs, two
    kinds of physics, 4x4 and 6x6 (seeds 21-35)."""
    cases = []
    for eff in TRUTHS:
        for grid, seed in ((4, 21), (4, 22), (6, 23)):
            cases.append(Case("simulator", "paper", eff, grid, seed))
        for geometry, grid, seed in (("paper_like", 4, 31), ("tilted", 4, 32),
                                     ("paper_like", 6, 33), ("tilted", 6, 34), ("tilted", 4, 35)):
            cases.append(Case("generator", geometry, eff, grid, seed))
    return cases


def report_cases() -> list[Case]:
    """The rigs that only report (seeds 501-534, fixed before any diagnosis ran on them): 52
    rigs. Every hidden truth on the simulator (4x4, 6x6) and on both generator geometries
    (4x4, 6x6); sag in the links as well as in the joints; each single effect also at half
    and at twice its size; and four more clean rigs for the false-alarm count."""
    cases = []
    for eff in TRUTHS:
        cases += [Case("simulator", "paper", eff, 4, 501), Case("simulator", "paper", eff, 4, 502),
                  Case("simulator", "paper", eff, 6, 503),
                  Case("generator", "paper_like", eff, 4, 511),
                  Case("generator", "paper_like", eff, 6, 512),
                  Case("generator", "tilted", eff, 4, 513),
                  Case("generator", "tilted", eff, 6, 514)]
        if "gravity_sag" in eff:
            cases += [Case("generator", "paper_like", eff, 4, 515, sag="links"),
                      Case("generator", "tilted", eff, 4, 516, sag="links")]
    for eff in TRUTHS[1:4]:
        cases += [Case("simulator", "paper", eff, 4, 521, scale=0.5),
                  Case("generator", "paper_like", eff, 4, 522, scale=0.5),
                  Case("generator", "tilted", eff, 4, 523, scale=2.0)]
    cases += [Case("simulator", "paper", (), 4, 531), Case("generator", "paper_like", (), 6, 532),
              Case("generator", "tilted", (), 4, 533), Case("generator", "tilted", (), 6, 534)]
    return cases


def base_holdout_error(rig) -> float:
    """Mean error of the base model (no effect) at the rig's holdout rows, arms pooled."""
    from bayesrob.diagnose.refits import ArmData, evaluate_arm

    errs = [evaluate_arm(ArmData.from_rig(rig, a), (), k_folds=2).hold_errors for a in rig.arms]
    return float(np.mean(np.concatenate(errs)))


# the rounds' figures a sweep keeps, per engine: what each decides by
ROUND_KEYS = {
    "refits": ("effect", "arms", "elpd_diff", "elpd_diff_se", "heldout_error_before_mm",
               "heldout_error_after_mm", "cv_error_before_mm", "cv_error_after_mm", "passes",
               "z", "parameters", "drop_per_parameter_mm"),
    "groups": ("effect", "parameters", "selection_error_before_mm", "selection_error_after_mm",
               "z", "drop_per_parameter_mm", "passes", "z_vs_alone", "elpd_diff", "guard_nats"),
}


def diagnose_case(case: Case, engine: str = "refits") -> dict:
    """Make the case's rig (and its clean twin), diagnose it from its files alone, and say
    what was named and how strong the hidden effects are.

    *Strength*: the base model's mean error at the holdout rows (new poses) over that of the
    clean twin (same geometry, seed and noise, no effect): 2 means the hidden effects double
    the gap that noise alone leaves. It is the planar base model's for either engine, so both
    count the same rigs as strong.

    ``engine="groups"`` diagnoses the rig with the chain engine instead
    (:func:`~bayesrob.diagnose.groups.diagnose_groups`, the arms as 2-joint chains, effects
    reported in the planar names): how far one engine for every robot is from the planar one,
    on the same rigs and the same counts. Its errors at new poses, the clean twin's included
    (which the gap ratio subtracts), are its own base model's and ladder's.
    """
    import tempfile
    import time
    from dataclasses import asdict

    from bayesrob.calibrate.least_squares import base_groups, calibrate
    from bayesrob.data.rig import load_rig
    from bayesrob.diagnose.groups import diagnose_groups
    from bayesrob.diagnose.refits import diagnose
    from bayesrob.robot.effects import ALIASES

    if engine not in ROUND_KEYS:
        raise ValueError(f"engine must be one of {', '.join(ROUND_KEYS)}, not {engine!r}")
    t0 = time.perf_counter()
    rivals: dict[str, list[str]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        rig = load_rig(make_rig(case, Path(tmp) / "rig"))
        twin_rig = (load_rig(make_rig(clean_twin(case), Path(tmp) / "twin")) if case.effects
                    else None)
        if engine == "refits":
            doc = diagnose(rig).to_json()
            base = doc["baseline_holdout_error_mm"]  # the planar base model's
            twin = clean = base if twin_rig is None else base_holdout_error(twin_rig)
        else:
            base = base_holdout_error(rig)
            twin = base if twin_rig is None else base_holdout_error(twin_rig)
            diag = diagnose_groups(rig)  # its own candidates for servo arms
            first, last = diag.baseline, (diag.steps[-1] if diag.steps else diag.baseline)
            doc = {"effects": [ALIASES.get(e, e) for e in diag.effects],
                   "rounds": [[{**s, "effect": "+".join(ALIASES.get(e, e)
                                                        for e in s["effect"].split("+"))}
                               for s in r] for r in diag.rounds],
                   "baseline_heldout_error_mm": first["heldout_error_mm"],
                   "final_heldout_error_mm": last["heldout_error_mm"],
                   "baseline_holdout_error_mm": first["holdout_error_mm"],
                   "final_holdout_error_mm": last["holdout_error_mm"]}
            rivals = {ALIASES.get(s["effect"], s["effect"]):
                      [ALIASES.get(e, e) for e in s["rivals"]] for s in diag.steps}
            # the chain base's clean twin: a clean rig is its own, its ladder's first step
            clean = (first["holdout_error_mm"] if twin_rig is None else
                     calibrate(twin_rig, base_groups(twin_rig.robot))
                     .errors["holdout"]["all"]["mean_mm"])
    keys = ROUND_KEYS[engine]
    return {"case": asdict(case), "truth": case.label,
            "named": "+".join(sorted(doc["effects"])) or "none",
            "order": doc["effects"], "seconds": round(time.perf_counter() - t0, 1),
            **{k: doc[k] for k in ("baseline_heldout_error_mm", "final_heldout_error_mm",
                                   "baseline_holdout_error_mm", "final_holdout_error_mm")},
            "clean_holdout_error_mm": clean,
            "strength": base / twin,
            **({"rivals": rivals} if engine == "groups" else {}),
            "rounds": [[{k: s[k] for k in keys if k in s} for s in r] for r in doc["rounds"]]}


def cases_for_seeds(seeds) -> list[Case]:
    """The report and tuning cases made with any of ``seeds``, in their lists' order; a seed
    no case uses is an error (a typo would otherwise run a smaller sweep silently)."""
    wanted = set(seeds)
    cases = [c for c in report_cases() + tuning_cases() if c.seed in wanted]
    unused = wanted - {c.seed for c in cases}
    if unused:
        raise ValueError(f"no planar case has seed(s) {sorted(unused)}")
    return cases
