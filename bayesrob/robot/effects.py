"""Physical effects that correct a planar arm's servo angles, for the model-criticism workflow.

An effect maps the angles ``theta = gain * u + offset`` to
``effect.apply(params, extra, u, theta)``, with ``extra`` its own unknowns, fitted with the
eight base parameters by least squares (so ``apply`` is JAX). The forms are deliberately
*not* the simulator's: the diagnosis must recognise an effect in data made by physics it does
not know, so each is the simplest family a physicist would write down. A ``@register``-ed
subclass of :class:`Effect` is all ``bayesrob diagnose`` needs; ``settings()`` gives values a
gradient cannot fit (which side of a sign change a point lies on), profiled over by the fit.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cache
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from bayesrob import robot as kin
from bayesrob.data.vocabulary import CHAIN_EFFECTS


@dataclass(frozen=True)
class EffectContext:
    """What an effect may know about an arm besides its parameters: fixed, not fitted. The
    commanded pulses' centre and half-width (us) normalise polynomial terms to [-1, 1], so
    their coefficients compare between arms and rigs."""

    gravity: tuple[float, float] = (0.0, -1.0)
    u_centre: tuple[float, float] = (1500.0, 1500.0)
    u_half_span: tuple[float, float] = (300.0, 300.0)

    def to_array(self) -> jax.Array:
        return jnp.asarray([*self.gravity, *self.u_centre, *self.u_half_span],
                           dtype=jnp.float64)

    @classmethod
    def from_array(cls, a: jax.Array) -> EffectContext:
        """The inverse of ``to_array``; inside jit the fields are traced arrays."""
        return cls(a[0:2], a[2:4], a[4:6])

    @classmethod
    def from_commands(cls, u: np.ndarray, gravity: tuple[float, float]) -> EffectContext:
        u = np.asarray(u, float)
        lo, hi = u.min(axis=0), u.max(axis=0)
        half = np.maximum((hi - lo) / 2, 1.0)  # one command only: avoid dividing by zero
        return cls(tuple(float(g) for g in gravity), tuple(float(c) for c in (lo + hi) / 2),
                   tuple(float(h) for h in half))


@dataclass(frozen=True)
class Effect:
    """Base class of a candidate effect (see the module docstring for the contract)."""

    name: ClassVar[str] = ""
    summary: ClassVar[str] = ""
    # applied in increasing stage: 0 on the servo map, 1 on the load path
    stage: ClassVar[int] = 1

    ctx: EffectContext = field(default_factory=EffectContext)
    # The structural setting in use (one row of ``settings()``); a JAX array while fitting.
    setting: object = None

    def param_names(self) -> tuple[str, ...]:
        raise NotImplementedError

    def scales(self) -> np.ndarray:
        """Typical size of each extra parameter (radians unless named otherwise)."""
        raise NotImplementedError

    def apply(self, params: kin.ArmParams, extra: jax.Array, u: jax.Array,
              theta: jax.Array) -> jax.Array:
        raise NotImplementedError

    def prior_sd(self) -> np.ndarray:
        """Width of the weak zero-centred penalty on the parameters: generous (ten typical
        sizes), as it only decides directions the data cannot see at all."""
        return 10.0 * self.scales()

    def initial(self) -> np.ndarray:
        return np.zeros(len(self.param_names()))

    def settings(self, params: kin.ArmParams, u: np.ndarray) -> np.ndarray | None:
        """Candidate structural settings (G, s) to profile over, or None; ``params`` and ``u``
        let an effect drop settings that make no difference on these commands."""
        return None

    def magnitudes(self, params: kin.ArmParams, extra: jax.Array) -> dict[str, jax.Array]:
        """Physical sizes (JAX scalars, keys ending in their unit), differentiable: their
        uncertainties come from the delta method on the fit's covariance."""
        return {}

    def describe(self, values: dict[str, tuple[float, float]]) -> str:
        """One line for people from ``{magnitude: (value, standard error)}``."""
        return ", ".join(f"{k} {v:.3g} +- {s:.2g}" for k, (v, s) in values.items())

    def magnitude_report(self, params: kin.ArmParams, extra: np.ndarray,
                         cov: np.ndarray | None) -> dict:
        """``{"values": {name: {"value", "se"}}, "text": str}``, standard errors from ``cov``
        (over the base 8 + extra parameters)."""
        v = jnp.concatenate([params.to_vector(), jnp.asarray(extra, dtype=jnp.float64)])
        setting = None if self.setting is None else jnp.asarray(self.setting)
        value_fn, jac_fn = _magnitude_fns(type(self))
        val = value_fn(v, self.ctx.to_array(), setting)
        if not val:
            return {"values": {}, "text": ""}
        if cov is None:
            se = {k: np.nan for k in val}
        else:
            jac = jac_fn(v, self.ctx.to_array(), setting)
            c = np.asarray(cov)
            se = {k: float(np.sqrt(max(np.asarray(jac[k]) @ c @ np.asarray(jac[k]), 0.0)))
                  for k in val}
        values = {k: (float(val[k]), se[k]) for k in val}
        return {"values": {k: {"value": a, "se": b} for k, (a, b) in values.items()},
                "text": self.describe(values)}


@cache
def _magnitude_fns(cls: type[Effect]):
    """Jitted magnitudes of an effect class and their gradient (compiled once per class)."""

    def mags(vec: jax.Array, ctx: jax.Array, setting) -> dict[str, jax.Array]:
        eff = cls(EffectContext.from_array(ctx), setting)
        return eff.magnitudes(kin.ArmParams.from_vector(vec[:8]), vec[8:])

    return jax.jit(mags), jax.jit(jax.jacfwd(mags))


REGISTRY: dict[str, type[Effect]] = {}


def register(cls: type[Effect]) -> type[Effect]:
    """Class decorator: make an effect a candidate of the diagnosis under ``cls.name``."""
    if not cls.name:
        raise ValueError(f"{cls.__name__} needs a non-empty class attribute 'name'")
    if cls.name in REGISTRY and REGISTRY[cls.name] is not cls:
        raise ValueError(f"an effect named {cls.name!r} is already registered")
    REGISTRY[cls.name] = cls
    return cls


# Chain effects with a planar instance (``gravity_sag`` deflects as the chain's compliance
# group does on ``planar_chain``: tests/test_diagnosis.py).
ALIASES = {"joint_compliance": "gravity_sag"}
# Chain effects with no planar instance, and why: what a planar rig can be asked instead.
CHAIN_ONLY = {
    "lateral_compliance": "gravity acts in the arm's plane, so it has no torque across the "
                          "joints' axes to bend them",
    "encoder_error": "a planar arm's angles come from its servo map, whose curve is "
                     "servo_nonlinearity",
}


# Chain effects of a servo's command map, candidates by default only where a robot has one
# (:attr:`~bayesrob.robot.chain.Robot.servo_mapped`): an encoder-read joint's error is
# encoder_error.
SERVO_EFFECTS = ("servo_nonlinearity",)
# Chain effects of a joint encoder, candidates by default only where no servo map is: a
# servo's angle comes from its map, whose curve is servo_nonlinearity (with both, on the
# planar tuning rigs as 2-joint chains the encoder sinusoid took the servo curve's misfit:
# 14 of 40 named exactly, 17 without it, no false alarm either way).
ENCODER_EFFECTS = ("encoder_error",)


def resolve_effects(names: Sequence[str] | None, *, chain: bool = False,
                    robot: kin.Robot | None = None) -> list[str]:
    """Candidate effect names (None: all; of a chain ``robot`` given, those it can have) of a
    planar rig or, with ``chain``, a URDF/DH chain, each once in that robot's words; a name
    it has no model for is a one-line ValueError."""
    known = CHAIN_EFFECTS if chain else REGISTRY
    aliases = {p: c for c, p in ALIASES.items()} if chain else ALIASES
    if names is None:
        if robot is None:
            return list(known)
        left_out = ENCODER_EFFECTS if robot.servo_mapped else SERVO_EFFECTS
        return [n for n in known if n not in left_out]
    out: list[str] = []
    for n in names:
        n = aliases.get(n, n)
        if n not in known:
            raise ValueError(
                f"effect {n!r} is not modelled for URDF/DH chains (choose from "
                f"{', '.join([*CHAIN_EFFECTS, *aliases])})" if chain else
                f"effect {n!r} is for URDF/DH chains: {CHAIN_ONLY[n]} (planar rigs: "
                f"{', '.join(REGISTRY)}; joint_compliance is gravity_sag)" if n in CHAIN_ONLY else
                f"unknown effect {n!r}; known: {', '.join(REGISTRY)}")
        if n not in out:
            out.append(n)
    return out


def apply_effects(effects: tuple[Effect, ...], params: kin.ArmParams, extras: list[jax.Array],
                  u: jax.Array) -> jax.Array:
    """Joint angles of the augmented model: g(u) corrected by each effect in stage order."""
    theta = kin.servo(params, u)
    order = sorted(range(len(effects)), key=lambda i: effects[i].stage)
    for i in order:
        theta = effects[i].apply(params, extras[i], u, theta)
    return theta


def _cross(a: jax.Array, g: jax.Array) -> jax.Array:
    # z of a x g: the torque per unit weight of a mass at lever a about the pivot
    return a[..., 0] * g[1] - a[..., 1] * g[0]


def lever_signatures(theta: jax.Array, gravity: tuple[float, float]) -> tuple[jax.Array, jax.Array]:
    """Gravity torque per unit (mass x lever) along link 1 and along link 2: any mass on
    straight links gives a shoulder torque ``A s1 + B s12`` and an elbow torque ``B' s12``."""
    g = jnp.asarray(gravity, dtype=jnp.float64)
    t1 = theta[..., 0]
    t12 = t1 + theta[..., 1]
    e1 = jnp.stack([jnp.cos(t1), jnp.sin(t1)], -1)
    e12 = jnp.stack([jnp.cos(t12), jnp.sin(t12)], -1)
    return _cross(e1, g), _cross(e12, g)


def _straight_reach_mm(params: kin.ArmParams) -> tuple[jax.Array, jax.Array]:
    return params.links[0] + params.links[1], params.links[1]


@register
@dataclass(frozen=True)
class GravitySag(Effect):
    """Joints give way in proportion to the gravity torque: deflections ``c11 s1 + c12 s12``
    and ``c22 s12`` (:func:`lever_signatures`; c = mass x lever x g / stiffness, rad), which
    cover any mass distribution along straight links."""

    name: ClassVar[str] = "gravity_sag"
    summary: ClassVar[str] = "joint deflection proportional to the gravity torque"
    ITERATIONS: ClassVar[int] = 3

    def param_names(self) -> tuple[str, ...]:
        return ("c11_rad", "c12_rad", "c22_rad")

    def scales(self) -> np.ndarray:
        return np.full(3, 0.01)

    def prior_sd(self) -> np.ndarray:
        # Effectively flat. Over a workspace the shoulder's sag is nearly a linear function
        # of its angle, so the servo gain takes most of it and the data pin c11 down only
        # loosely; any real pull towards zero would shrink the reported sag (a tenth of a
        # radian halved the default rig's shoulder sag).
        return np.full(3, 1.0)

    def _deflection(self, extra, theta):
        s1, s12 = lever_signatures(theta, self.ctx.gravity)
        return jnp.stack([extra[0] * s1 + extra[1] * s12, extra[2] * s12], -1)

    def apply(self, params, extra, u, theta):
        # The torque acts at the pose the arm sags into, not the commanded one: two
        # fixed-point steps catch that (it matters once the sag is a few degrees).
        out = theta
        for _ in range(self.ITERATIONS):
            out = theta + self._deflection(extra, out)
        return out

    def magnitudes(self, params, extra):
        reach, l2 = _straight_reach_mm(params)
        # Arm straight and square to gravity: both signatures are 1, the torque is largest.
        d1 = extra[0] + extra[1]
        d2 = extra[2]
        # And where the arm works: the largest end-point sag over the commanded pulses.
        g = jnp.linspace(-1.0, 1.0, 7)
        x = jnp.stack(jnp.meshgrid(g, g), -1).reshape(-1, 2)
        u = jnp.asarray(self.ctx.u_centre) + x * jnp.asarray(self.ctx.u_half_span)
        theta = kin.servo(params, u)
        shift = kin.forward(params, self.apply(params, extra, u, theta)) - \
            kin.forward(params, theta)
        return {"sag_full_reach_mm": reach * d1 + l2 * d2,
                "sag_workspace_max_mm": jnp.sqrt(jnp.max(jnp.sum(shift**2, -1)) + 1e-18),
                "shoulder_deflection_deg": jnp.rad2deg(d1),
                "elbow_deflection_deg": jnp.rad2deg(d2)}

    def describe(self, values):
        (s, se), (w, wse), (a, ase), (b, bse) = (values[k] for k in (
            "sag_full_reach_mm", "sag_workspace_max_mm", "shoulder_deflection_deg",
            "elbow_deflection_deg"))
        return (f"sag at full reach {s:.2f} +- {se:.2f} mm (arm straight and level: shoulder "
                f"{a:.2f} +- {ase:.2f} deg, elbow {b:.2f} +- {bse:.2f} deg); up to {w:.2f} +- "
                f"{wse:.2f} mm over the commanded workspace")


@register
@dataclass(frozen=True)
class Backlash(Effect):
    """Play in a joint, taken on the side gravity pulls to: ``beta_j sign(torque_j)``. The
    elbow's torque has the sign of s12, the shoulder's that of (1 - rho) s1 + rho s12, rho in
    [0, 1] where the mass sits: flat for a gradient, so a structural setting."""

    name: ClassVar[str] = "backlash"
    summary: ClassVar[str] = "joint offset whose sign follows the gravity torque"
    RHO_GRID: ClassVar[np.ndarray] = np.linspace(0.0, 1.0, 41)
    # lever signature over which the side of the play changes: about 3 degrees of rotation
    FLOAT_WIDTH: ClassVar[float] = 0.05

    def param_names(self) -> tuple[str, ...]:
        return ("beta1_rad", "beta2_rad")

    def scales(self) -> np.ndarray:
        return np.full(2, 0.005)

    def _rho(self) -> jax.Array:
        return jnp.asarray(0.3 if self.setting is None else jnp.reshape(self.setting, (-1,))[0])

    def signs(self, theta: jax.Array) -> jax.Array:
        """Which side of its play each joint rests on, -1..1: a smooth step, since near zero
        torque a joint floats in its play and a hard step would make the fit jump."""
        s1, s12 = lever_signatures(theta, self.ctx.gravity)
        rho = self._rho()
        lever = jnp.stack([(1 - rho) * s1 + rho * s12, s12], -1)
        return jnp.tanh(lever / self.FLOAT_WIDTH)

    def apply(self, params, extra, u, theta):
        return theta + extra * self.signs(theta)

    def settings(self, params, u):
        # Settings that sort the arm's commands into the same sign pattern fit identically:
        # keep one rho per distinct pattern (its middle one, robust to small refits).
        theta = kin.servo(params, jnp.asarray(u, dtype=jnp.float64))
        s1, s12 = (np.asarray(s) for s in lever_signatures(theta, self.ctx.gravity))
        rho = self.RHO_GRID[:, None]
        # Patterns compare the sides far from the line: floating points do not split them.
        signs = np.round(np.tanh(((1 - rho) * s1[None] + rho * s12[None]) / self.FLOAT_WIDTH),
                         1)  # (G, n)
        patterns: dict[bytes, list[float]] = {}
        for r, row in zip(self.RHO_GRID, signs, strict=True):
            patterns.setdefault(row.tobytes(), []).append(float(r))
        return np.array([[r[len(r) // 2]] for r in patterns.values()])

    def magnitudes(self, params, extra):
        reach, l2 = _straight_reach_mm(params)
        return {"shoulder_play_deg": jnp.rad2deg(extra[0]),
                "elbow_play_deg": jnp.rad2deg(extra[1]),
                # Crossing a sign change moves a joint across the whole play, 2 beta.
                "shoulder_jump_full_reach_mm": 2 * jnp.abs(extra[0]) * reach,
                "elbow_jump_full_reach_mm": 2 * jnp.abs(extra[1]) * l2}

    def describe(self, values):
        (a, ase), (b, bse), (ja, jase), (jb, jbse) = (values[k] for k in (
            "shoulder_play_deg", "elbow_play_deg", "shoulder_jump_full_reach_mm",
            "elbow_jump_full_reach_mm"))
        rho = float(self._rho())

        def play(v: float, se: float, jump: float, jse: float) -> str:
            if not se < abs(v):
                # The torque keeps its sign over the data: the play hides in the offset.
                return f"not resolved ({v:.2f} +- {se:.2f} deg)"
            return f"{v:.2f} +- {se:.2f} deg (jump {jump:.2f} +- {jse:.2f} mm at full reach)"

        return (f"play (half-width) shoulder {play(a, ase, ja, jase)}, elbow "
                f"{play(b, bse, jb, jbse)}; a joint jumps by twice its play where its gravity "
                f"torque flips (mass position rho {rho:.2f})")


@register
@dataclass(frozen=True)
class ServoNonlinearity(Effect):
    """A curved pulse-to-angle map: ``q_j x^2 + k_j x^3`` in the normalised pulse (constant
    and linear parts are the servo map's own)."""

    name: ClassVar[str] = "servo_nonlinearity"
    summary: ClassVar[str] = "quadratic + cubic terms in the pulse-to-angle map"
    stage: ClassVar[int] = 0

    def param_names(self) -> tuple[str, ...]:
        return ("q1_rad", "k1_rad", "q2_rad", "k2_rad")

    def scales(self) -> np.ndarray:
        return np.full(4, 0.005)

    def _x(self, u: jax.Array) -> jax.Array:
        return (u - jnp.asarray(self.ctx.u_centre)) / jnp.asarray(self.ctx.u_half_span)

    def apply(self, params, extra, u, theta):
        x = self._x(u)
        q = jnp.stack([extra[0], extra[2]])
        k = jnp.stack([extra[1], extra[3]])
        return theta + q * x**2 + k * x**3

    def magnitudes(self, params, extra):
        # The part a straight line cannot take: deviation from the best line over [-1, 1].
        x = jnp.linspace(-1.0, 1.0, 41)
        basis = jnp.stack([jnp.ones_like(x), x], -1)
        proj = basis @ jnp.linalg.pinv(basis)
        reach, l2 = _straight_reach_mm(params)
        out = {}
        for j, (q, k) in enumerate(((extra[0], extra[1]), (extra[2], extra[3]))):
            curve = q * x**2 + k * x**3
            dev = curve - proj @ curve
            # A smooth maximum keeps the delta method's derivative defined.
            peak = jnp.sqrt(jnp.max(dev**2) + 1e-18)
            out[f"joint{j + 1}_bend_deg"] = jnp.rad2deg(peak)
            out[f"joint{j + 1}_bend_mm"] = peak * (reach if j == 0 else l2)
        return out

    def describe(self, values):
        parts = []
        for j in (1, 2):
            d, dse = values[f"joint{j}_bend_deg"]
            m, mse = values[f"joint{j}_bend_mm"]
            parts.append(f"joint {j} {d:.2f} +- {dse:.2f} deg ({m:.2f} +- {mse:.2f} mm)")
        return "pulse-to-angle map departs from a straight line by " + ", ".join(parts) + \
            " at most over the commanded range"
