"""One kinematic model for every robot: serial chains of revolute and prismatic joints in 3-D,
mounted on each other to form trees, measured by an instrument (mm and rad).

A :class:`Chain` is data: each joint's *origin* (a URDF-style xyz/rpy pose in the previous
frame), axis and kind, then a *tool* transform; joint values are ``C @ (gain * u + offset)``
of the measured columns, so a passive joint can follow others. A chain may be ``mount``-ed on
another's tip, making a tree. A :class:`Robot`'s calibration parameters are one flat vector
with a name and group per entry (:class:`ParamLayout`); forward kinematics is a pure JAX
function of it and the rows' columns.
"""

from __future__ import annotations

import functools
import hashlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, fields, replace
from functools import cached_property

import jax
import jax.numpy as jnp
import numpy as np

import bayesrob.robot.transforms as tf

# The parameter groups and the links' mass sources are names the command line checks before
# it imports this module: they are defined there.
from bayesrob.data.vocabulary import ALL_GROUPS, GROUPS, MASS_SOURCES, OPTIONAL_GROUPS  # noqa: F401

JOINT_KINDS = ("revolute", "prismatic")
SAG_GROUPS = ("compliance", "lateral", "backlash")  # the groups gravity's torques drive
G_N_PER_KG = 9.81  # weight per kg: torques in N mm with lever arms in mm
LINK_MASS_GUESS_KG = 1.0  # where a compliance fit starts: 1 kg at each link's middle
POSE_AXES = ("x", "y", "z", "rx", "ry", "rz")
# A joint's play is taken on the side its gravity deflection points to, as
# tanh(deflection / PLAY_SIDE_RAD): 0.1 mrad, the joints' repeatability on the arms seen so
# far, puts three quarters of it there; smaller deflections leave the joint mid-play. Where
# the rows record the side each joint approached its command from (+1, -1), friction holds
# the joint on that side unless its gravity deflection is larger than the arm's fitted stick
# deflection (``<chain>.stick``): the side is tanh((deflection + stick * approach) /
# PLAY_SIDE_RAD).
PLAY_SIDE_RAD = 1e-4
STICK_NOMINAL_RAD = 1e-3  # where a stick fit starts (mrad-scale friction over the stiffness)
# the key under which a rows' context dict (``side``) carries the arm's approach sides
# (N, path joints), beside the other arms' columns; not a valid arm name
APPROACH = "@approach"
# A compiled program of rows is built for at least this many, else for the next quarter
# octave (80, 96, 112, 128, 160, ...; at most a quarter more rows): XLA compiles a program per
# shape, so three arms' train, validation and holdout rows, a prediction's targets and a
# test's few rows took a program each (six of the _compiled_points compiles of the
# linked_chain_three quick study, 5 s); the padded rows cost microseconds.
MIN_ROW_BUCKET = 64
# chains off a path, per chain: (path elements it weighs on, its first element, its links'
# frames (E_c, N, 4, 4), its name), as Robot.side_frames gives them
Hanging = tuple[tuple[int, int, jax.Array, str], ...]


class KinematicsError(ValueError):
    """A robot description is inconsistent; the message says where and what."""


def _canonical(v: object, ordered: bool = False) -> object:
    """A hashable, comparable form of a field's value: arrays by dtype, shape and bytes (what
    a traced program bakes in), dicts as item tuples (sorted unless ``ordered``)."""
    if isinstance(v, np.ndarray):
        return ("ndarray", v.dtype.str, v.shape, v.tobytes())
    if isinstance(v, dict):
        items = tuple((repr(k), _canonical(x)) for k, x in v.items())
        return ("dict", items if ordered else tuple(sorted(items)))
    if isinstance(v, (list, tuple)):
        return (type(v).__name__, tuple(_canonical(x) for x in v))
    if isinstance(v, _ByValue):
        return v._value
    if v is None or isinstance(v, (str, bool, int, float, np.generic)):
        return (type(v).__name__, repr(v))
    raise TypeError(f"no canonical form for a {type(v).__name__}")


def _digest(value: object) -> int:
    # from the canonical form's repr, not hash(): str hashes differ between processes, and a
    # robot shipped to a Dask worker keeps the hash it cached where it was computed
    return int.from_bytes(hashlib.blake2b(repr(value).encode(), digest_size=8).digest(), "big")


class _ByValue:
    """Equality and hash from every dataclass field's canonical form, so a
    :class:`RobotStructure` can be ``jax.jit``'s static argument (one program per design).
    The fields are taken as immutable: the form and its hash are cached on first use."""

    _ordered_fields: tuple[str, ...] = ()  # dict fields whose order is part of the value

    @cached_property
    def _value(self) -> tuple:
        return (type(self).__name__,
                tuple(_canonical(getattr(self, f.name), f.name in self._ordered_fields)
                      for f in fields(self)))

    @cached_property
    def _hash(self) -> int:
        return _digest(self._value)

    def __eq__(self, other: object) -> bool:
        if other is self:
            return True
        if type(other) is not type(self):
            return NotImplemented
        return self._hash == other._hash and self._value == other._value

    def __hash__(self) -> int:
        return self._hash


@dataclass(frozen=True, eq=False)
class Chain(_ByValue):
    """A serial chain's structure and nominal values (mm, rad). ``source`` counts in equality:
    the masses and limits read from it enter fits, and a calibrated URDF is written from it."""

    name: str
    joint_names: tuple[str, ...]
    kinds: tuple[str, ...]
    axes: np.ndarray  # (n, 3) unit axes, each in its joint's frame
    origins: np.ndarray  # (n + 1, 6) poses: joint i's frame in the previous one; last: the tool
    coupling: np.ndarray  # (n, m): joint values = coupling @ (gain * u + offset)
    gain: np.ndarray  # (m,)
    offset: np.ndarray  # (m,)
    marker: np.ndarray = field(default_factory=lambda: np.zeros(3))  # mm, in the tip frame
    mount: str | None = None
    # A root chain's base pose in the instrument frame [x, y, z, roll, pitch, yaw] (mm, rad):
    # every robot standing on its own has one, and it is always calibrated.
    instrument: np.ndarray = field(default_factory=lambda: np.zeros(6))
    source: dict = field(default_factory=dict)  # how it was described (for writing URDF)

    def __post_init__(self) -> None:
        n, m = self.n_joints, self.n_columns
        if self.axes.shape != (n, 3) or self.origins.shape != (n + 1, 6):
            raise KinematicsError(f"chain {self.name!r}: {n} joints need {n} axes and "
                                  f"{n + 1} origins")
        if self.coupling.shape != (n, m) or self.gain.shape != (m,) or self.offset.shape != (m,):
            raise KinematicsError(f"chain {self.name!r}: coupling must be {n} x {m}")
        for k in self.kinds:
            if k not in JOINT_KINDS:
                raise KinematicsError(f"chain {self.name!r}: unknown joint kind {k!r}")
        norms = np.linalg.norm(self.axes, axis=1)
        if np.any(norms < 1e-12):
            raise KinematicsError(f"chain {self.name!r}: a joint axis is zero")

    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

    @property
    def n_columns(self) -> int:
        return self.coupling.shape[1]

    @property
    def weighed(self) -> bool:
        """Whether the description gives every moving link a mass and first moment."""
        return (self.source.get("link_masses_kg") is not None
                and self.source.get("link_moments_kg_mm") is not None)

    @classmethod
    def build(cls, name: str, joint_names: Sequence[str], kinds: Sequence[str],
              axes: np.ndarray, origins: np.ndarray, coupling: np.ndarray | None = None,
              gain: np.ndarray | None = None, offset: np.ndarray | None = None,
              marker: Sequence[float] = (0.0, 0.0, 0.0), mount: str | None = None,
              source: dict | None = None, instrument: Sequence[float] | None = None) -> Chain:
        """A chain with identity coupling and command map unless given."""
        n = len(joint_names)
        axes = np.asarray(axes, float).reshape(n, 3)
        axes = axes / np.maximum(np.linalg.norm(axes, axis=1, keepdims=True), 1e-300)
        coupling = np.eye(n) if coupling is None else np.asarray(coupling, float)
        m = coupling.shape[1] if coupling.ndim == 2 else 0
        gain = np.ones(m) if gain is None else np.asarray(gain, float)
        offset = np.zeros(m) if offset is None else np.asarray(offset, float)
        return cls(name, tuple(joint_names), tuple(kinds), axes,
                   np.asarray(origins, float).reshape(n + 1, 6), coupling, gain, offset,
                   np.asarray(marker, float), mount,
                   np.zeros(6) if instrument is None else np.asarray(instrument, float),
                   dict(source or {}))

    def is_planar(self) -> bool:
        """Every joint turns about z and no origin leaves the xy plane: a planar chain."""
        flat = np.allclose(self.origins[:, 2:5], 0.0, atol=1e-12)
        about_z = all(k == "revolute" for k in self.kinds) and np.allclose(
            np.abs(self.axes[:, 2]), 1.0, atol=1e-12)
        return bool(flat and about_z and abs(self.marker[2]) < 1e-12)


@dataclass(frozen=True)
class Param:
    """One calibration parameter: its name, group and nominal value."""

    name: str
    group: str
    nominal: float
    scale: float  # a typical size: 1 mm for lengths, 1 mrad for angles, 0.1% for gains


@dataclass(frozen=True, eq=False)
class ParamLayout:
    """Names, groups and slices of the flat parameter vector of a robot."""

    params: tuple[Param, ...]
    slices: dict  # (chain or "instrument", part) -> slice

    @property
    def names(self) -> list[str]:
        return [p.name for p in self.params]

    @property
    def nominal(self) -> np.ndarray:
        return np.array([p.nominal for p in self.params])

    @property
    def scales(self) -> np.ndarray:
        return np.array([p.scale for p in self.params])

    def group_mask(self, groups: Sequence[str]) -> np.ndarray:
        return np.array([p.group in groups for p in self.params])


def _layout(chains: dict[str, Chain]) -> ParamLayout:
    params: list[Param] = []
    slices: dict = {}

    def add(key, names, group, nominal, scale):
        start = len(params)
        params.extend(Param(n, group, float(v), float(s))
                      for n, v, s in zip(names, nominal, scale, strict=True))
        slices[key] = slice(start, len(params))

    for c in chains.values():
        if c.mount is None:
            add((c.name, "instrument"), [f"{c.name}.instrument.{a}" for a in POSE_AXES],
                "frames", np.zeros(6), [1.0, 1.0, 1.0, 1e-3, 1e-3, 1e-3])
    parents = {c.mount for c in chains.values()}
    for c in chains.values():
        if c.name in parents:
            continue  # a chain other chains are mounted on carries no marker of its own
        add((c.name, "marker"), [f"{c.name}.marker.{a}" for a in "xyz"], "frames", c.marker,
            [1.0] * 3)
    for c in chains.values():
        add((c.name, "offset"), [f"{c.name}.{j}.offset" for j in c.joint_names], "offsets",
            np.zeros(c.n_joints),
            [1e-3 if k == "revolute" else 1.0 for k in c.kinds])
    for c in chains.values():
        names = [f"{c.name}.{j}.origin.{a}" for j in (*c.joint_names, "tool") for a in POSE_AXES]
        add((c.name, "origins"), names, "geometric", np.zeros(6 * (c.n_joints + 1)),
            [1.0, 1.0, 1.0, 1e-3, 1e-3, 1e-3] * (c.n_joints + 1))
    for c in chains.values():
        add((c.name, "gain"), [f"{c.name}.u{k + 1}.gain" for k in range(c.n_columns)], "servo",
            c.gain, np.maximum(np.abs(c.gain) * 1e-3, 1e-12))
    for c in chains.values():
        # compliance (rad per N mm) of each joint first: of a mass and a compliance only their
        # product is seen, so the rank analysis keeps the compliance and drops a mass
        add((c.name, "compliance"), [f"{c.name}.{j}.compliance" for j in c.joint_names],
            "compliance", np.zeros(c.n_joints), [1e-7] * c.n_joints)
    for c in chains.values():
        # bending of each joint's bearing and link about the two axes across its own (rad per
        # N mm), under the same gravity torques
        add((c.name, "lateral"), [f"{c.name}.{j}.lateral.{k}" for j in c.joint_names
                                  for k in (1, 2)],
            "lateral", np.zeros(2 * c.n_joints), [1e-7] * (2 * c.n_joints))
    for c in chains.values():
        half = 0.5 * c.origins[1:, :3]  # each link's middle: half way to the next origin
        names, nominal, scale = [], [], []
        for j, h in zip(c.joint_names, half, strict=True):
            names += [f"{c.name}.{j}.mass", *(f"{c.name}.{j}.moment.{a}" for a in "xyz")]
            nominal += [LINK_MASS_GUESS_KG, *(LINK_MASS_GUESS_KG * h)]
            scale += [1.0, 100.0, 100.0, 100.0]
        add((c.name, "links"), names, "compliance", nominal, scale)
    for c in chains.values():
        # an eccentric encoder: a once-per-revolution error a sin q + b cos q in each revolute
        # joint's angle (the prismatic joints' pairs stay zero: the rank analysis drops them)
        add((c.name, "encoder"), [f"{c.name}.{j}.encoder.{k}" for j in c.joint_names
                                  for k in ("sin", "cos")],
            "encoder", np.zeros(2 * c.n_joints), [1e-3] * (2 * c.n_joints))
    for c in chains.values():
        # half the play of each joint (rad, mm if prismatic): how far gravity moves it to one
        # side of the middle (last in the vector, so earlier groups keep their indices)
        add((c.name, "backlash"), [*(f"{c.name}.{j}.play" for j in c.joint_names),
                                   f"{c.name}.stick"], "backlash",
            [*np.zeros(c.n_joints), STICK_NOMINAL_RAD],
            [*(1e-3 if k == "revolute" else 1.0 for k in c.kinds), 1e-3])
    for c in chains.values():
        # a curved command map: c2 q^2 + c3 q^3 added to each joint's commanded value (a
        # servo's potentiometer track and gear train; the line is the gains' and offsets')
        add((c.name, "curve"), [f"{c.name}.{j}.curve.{k}" for j in c.joint_names
                                for k in (2, 3)],
            "servo_curve", np.zeros(2 * c.n_joints), [1e-3] * (2 * c.n_joints))
    return ParamLayout(tuple(params), slices)


def _across(axis: np.ndarray) -> np.ndarray:
    """Two unit vectors (2, 3) across a joint axis, completing it to a right-handed frame."""
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    b1 = np.cross(a, np.eye(3)[int(np.argmin(np.abs(a)))])
    b1 /= np.linalg.norm(b1)
    return np.stack([b1, np.cross(a, b1)])


def _bend(phi: jax.Array) -> jax.Array:
    # a small rotation (..., 3) about a joint's own axes, as a 4x4 transform
    return tf.perturbation(jnp.concatenate([jnp.zeros_like(phi), phi], axis=-1))


def _revolute(chain: Chain) -> np.ndarray:
    """1.0 for each revolute joint of the chain, 0.0 for each prismatic one."""
    return np.array([k == "revolute" for k in chain.kinds], dtype=float)


def _times_rigid(nominal: jax.Array, t: jax.Array) -> jax.Array:
    """``nominal @ t`` for a rigid transform t, split at t's constant row as XLA computes it
    for a constant ``nominal``, so an argument gives the bits a constant gave."""
    return nominal[:, :3] @ t[:3, :] + nominal[:, 3:] * jnp.array([0.0, 0.0, 0.0, 1.0])


def _joint_motion(kind: str, axis: np.ndarray, q: jax.Array) -> jax.Array:
    if kind == "revolute":
        rot = tf.rot_axis(axis, q)
        return tf.homogeneous(rot, jnp.zeros(q.shape + (3,)))
    rot = jnp.broadcast_to(jnp.eye(3), q.shape + (3, 3))
    return tf.homogeneous(rot, q[..., None] * jnp.asarray(axis))


@dataclass(frozen=True, eq=False)
class Robot(_ByValue):
    """Chains (parents first, the parameter vector's order) and the dimension of the measured
    points (2 or 3). Compiled programs take its :attr:`structure` as their static argument
    and its :attr:`nominal_values` as arrays, so robots of one design share them."""

    _ordered_fields = ("chains",)  # their order is the parameter vector's

    chains: dict[str, Chain]
    dim: int = 3
    # Unit gravity in the robot base frame: joints give way under it when the compliance
    # parameters are non-zero (None: no gravity model).
    gravity: np.ndarray | None = None
    # How many times the sag's gravity torques are taken: at the commanded pose, then at the
    # pose each step sagged into (a fixed-point iteration, contracting by about 1e-3 on a few
    # mrad of sag). Agile Justin's fits (sag up to 0.2 rad) land where it does not converge,
    # so one step is the default (docs/robots.md).
    sag_steps: int = 1

    def __post_init__(self) -> None:
        seen: set[str] = set()
        for c in self.chains.values():
            if c.mount is not None and c.mount not in seen:
                known = c.mount in self.chains
                raise KinematicsError(
                    f"chain {c.name!r} is mounted on {c.mount!r}, which "
                    + ("must come before it" if known else "is not a chain of this robot"))
            seen.add(c.name)
        if self.dim not in (2, 3):
            raise KinematicsError(f"measurements must be 2-D or 3-D, not {self.dim}-D")

    @cached_property
    def layout(self) -> ParamLayout:
        return _layout(self.chains)

    def path(self, arm: str) -> list[Chain]:
        """The chains from the robot base to ``arm``'s tip, base first."""
        out = []
        name: str | None = arm
        while name is not None:
            out.append(self.chains[name])
            name = self.chains[name].mount
        return out[::-1]

    def columns(self, arm: str) -> list[str]:
        """The measurement columns a row of ``arm`` carries: its ancestors' and its own."""
        return [f"{c.name}_u{k + 1}" for c in self.path(arm) for k in range(c.n_columns)]

    def joint_values(self, x: jax.Array, chain: Chain, u: jax.Array) -> jax.Array:
        """Joint values (N, n) of ``chain`` for its columns u (N, m): q = C (gain u + offset) +
        zero offset, then a revolute joint's encoder eccentricity and the command map's
        curve, q + a sin q + b cos q + c2 q^2 + c3 q^3."""
        q = self._commanded_values(x, chain, u)
        a, b = self._encoder(x, chain)
        c2, c3 = self._curve(x, chain)
        return q + a * jnp.sin(q) + b * jnp.cos(q) + (c2 + c3 * q) * q * q

    def _commanded_values(self, x: jax.Array, chain: Chain, u: jax.Array) -> jax.Array:
        sl = self.layout.slices
        gain = x[sl[(chain.name, "gain")]]
        q_act = gain * u + jnp.asarray(chain.offset)
        return q_act @ jnp.asarray(chain.coupling).T + x[sl[(chain.name, "offset")]]

    def _encoder(self, x: jax.Array, chain: Chain) -> tuple[jax.Array, jax.Array]:
        ab = x[self.layout.slices[(chain.name, "encoder")]].reshape(chain.n_joints, 2)
        revolute = _revolute(chain)
        return ab[:, 0] * revolute, ab[:, 1] * revolute

    def _curve(self, x: jax.Array, chain: Chain) -> tuple[jax.Array, jax.Array]:
        c = x[self.layout.slices[(chain.name, "curve")]].reshape(chain.n_joints, 2)
        return c[:, 0], c[:, 1]

    def _elements(self, arm: str) -> dict[str, np.ndarray]:
        """The path to ``arm`` as one sequence of elements (an origin, then a joint's motion;
        a tool's motion is nothing) for one ``lax.scan``, which compiles once however many
        joints there are. Indices and axes are the structure's, ``nominal`` this robot's."""
        parts = [self._matrices["origins"][c.name] for c in self.path(arm)]
        concrete = all(isinstance(p, np.ndarray) for p in parts)
        return {**_element_table(self.structure, arm),
                "nominal": np.concatenate(parts) if concrete else jnp.concatenate(parts)}

    def _element_values(self, x: jax.Array, arm: str, u: jax.Array) -> jax.Array:
        qs, col = [], 0
        for chain in self.path(arm):
            qs.append(self.joint_values(x, chain, u[:, col:col + chain.n_columns]))
            col += chain.n_columns
        q = jnp.concatenate([*qs, jnp.zeros((u.shape[0], 1))], axis=1)
        return q[:, self._elements(arm)["q_idx"]]

    def instrument_pose(self, x: jax.Array, arm: str) -> jax.Array:
        """The 4x4 pose of ``arm``'s root in the instrument frame under parameters x."""
        root = self.path(arm)[0]
        return _times_rigid(self._matrices["instrument"][root.name], tf.perturbation(
            x[self.layout.slices[(root.name, "instrument")]]))

    def element_frames(self, x: jax.Array, arm: str, u: jax.Array,
                       deflection: jax.Array | None = None, bend: jax.Array | None = None
                       ) -> tuple[jax.Array, jax.Array]:
        """Frames along the path to ``arm`` (instrument frame), each (E, N, 4, 4): ``joints``,
        where each element's motion happens, and ``links``, the frame after it. ``deflection``
        (N, E) adds to the joint values; ``bend`` (N, E, 3) rotates about each joint's own
        axes before its motion (lateral compliance)."""
        x = jnp.asarray(x)
        u = jnp.atleast_2d(jnp.asarray(u))
        el = self._elements(arm)
        t0 = jnp.broadcast_to(self.instrument_pose(x, arm), (u.shape[0], 4, 4))

        def step(t, e):
            nominal, delta, axis, prismatic, qe, phi = e
            turn = tf.rot_axis(axis, qe * (1.0 - prismatic))
            motion = _bend(phi) @ tf.homogeneous(turn, (qe * prismatic)[:, None] * axis)
            joint = t @ (nominal @ tf.perturbation(delta))
            return joint @ motion, (joint, joint @ motion)

        qe = self._element_values(x, arm, u)
        if deflection is not None:
            qe = qe + deflection
        phi = (jnp.zeros(qe.shape + (3,)) if bend is None else bend)
        xs = (jnp.asarray(el["nominal"]), x[el["delta_idx"]], jnp.asarray(el["axes"]),
              jnp.asarray(el["prismatic"]), qe.T, jnp.swapaxes(phi, 0, 1))
        _, (joints, links) = jax.lax.scan(step, t0, xs)
        return joints, links

    def side_arms(self, arm: str) -> list[str]:
        """Measured arms whose path leaves ``arm``'s: their links hang on the chains the two
        share (a torso carries both hands), and weigh on those joints too."""
        return [b for b in self.measured_arms() if b != arm]

    def side_frames(self, x: jax.Array, arm: str, side: dict[str, jax.Array]
                    ) -> Hanging:
        """For each chain off ``arm``'s path, in the pose of ``side`` (a side arm's path columns):
        (how many of ``arm``'s path elements it hangs beyond, its first element on the side
        arm's path, its links' frames (E_c, N, 4, 4), that side arm)."""
        on_path = {c.name for c in self.path(arm)}
        done: set[str] = set()
        out = []
        for b, ub in side.items():
            _, links = self.element_frames(x, b, ub)
            start, shared = 0, 0
            for c in self.path(b):
                n = c.n_joints + 1
                if c.name in on_path:
                    shared = start + n
                elif c.name not in done:
                    done.add(c.name)
                    out.append((shared, start, links[start:start + n], b))
                start += n
        return tuple(out)

    def deflections(self, x: jax.Array, arm: str, u: jax.Array,
                    side: dict[str, jax.Array] | None = None) -> jax.Array:
        """How far each joint on the path gives way under gravity, (N, E) rad (mm if prismatic):
        its compliance times tau_e = a_e . (sum_k (m_k (p_k - o_e)) x g) of the links beyond it
        (masses and first moments fitted with the compliances), at the commanded pose, plus
        its half play p_e tanh(deflection_e / PLAY_SIDE_RAD)."""
        return self.sag(x, arm, u, side)[0]

    def sag(self, x: jax.Array, arm: str, u: jax.Array,
            side: dict[str, jax.Array] | None = None) -> tuple[jax.Array, jax.Array]:
        """The joints' deflections (N, E) of :meth:`deflections` and the bending (N, E, 3), lateral
        compliances times the torque about the two axes across each joint's own."""
        x = jnp.asarray(x)
        return self._sag_at(x, arm, *self._sag_frames(x, arm, u, side),
                            self._approach(arm, side))

    def _sag_frames(self, x: jax.Array, arm: str, u: jax.Array,
                    side: dict[str, jax.Array] | None) -> tuple:
        # the frames the sag's torques are taken in: the path's joints and links as commanded
        # (or, with sag_steps > 1, as the previous step sagged them), and what hangs off it.
        # What hangs off the path keeps its commanded frames: the path's sag turns it as a
        # whole, which moves its torque on the shared joints only at second order.
        arms = {b: v for b, v in (side or {}).items() if b != APPROACH}
        hanging = self.side_frames(x, arm, arms) if arms else ()
        approach = self._approach(arm, side)
        frames = (*self.element_frames(x, arm, u), hanging)
        # a loop unrolled into the program (not a while loop), so that reverse mode (NUTS
        # through a chain with sag) still differentiates it
        for _ in range(self.sag_steps - 1):
            frames = (*self.element_frames(x, arm, u,
                                           *self._sag_at(x, arm, *frames, approach)), hanging)
        return frames

    def _approach(self, arm: str, side: dict[str, jax.Array] | None) -> jax.Array | None:
        # the rows' approach sides per element (E, N), tools 0, or None where not recorded
        if not side or APPROACH not in side:
            return None
        a = jnp.asarray(side[APPROACH])
        a = jnp.concatenate([a, jnp.zeros((a.shape[0], 1))], axis=1)
        return a[:, self._elements(arm)["q_idx"]].T

    def _weights(self, xz: jax.Array, link_idx: np.ndarray, links: jax.Array
                 ) -> tuple[jax.Array, jax.Array]:
        # each element's first moment about the instrument origin, (E, N, 3), and its mass
        link = xz[link_idx]  # (E, 4): mass, first moment in the link's frame
        mass, moment = link[:, 0], link[:, 1:]
        weight = mass[:, None, None] * links[:, :, :3, 3] + jnp.einsum(
            "enij,ej->eni", links[:, :, :3, :3], moment)
        return weight, mass

    def _torques(self, x: jax.Array, arm: str, joints: jax.Array, links: jax.Array,
                 hanging: Hanging = ()) -> tuple[jax.Array, jax.Array]:
        """The gravity torques of sag() in frames already computed: each element's torque in
        its joint's frame (E, N, 3) and about its axis (E, N); the sag and its written-out
        derivative must take the same ones."""
        el = self._elements(arm)
        xz = jnp.concatenate([x, jnp.zeros(1)])
        weight, mass = self._weights(xz, el["link_idx"], links)
        beyond = jnp.cumsum(weight[::-1], axis=0)[::-1]
        mass_beyond = jnp.cumsum(mass[::-1], axis=0)[::-1][:, None]
        for shared, start, frames, b in hanging:
            # a chain off the path weighs on the path's elements before where it hangs
            idx = self._elements(b)["link_idx"][start:start + frames.shape[0]]
            w, m = self._weights(xz, idx, frames)
            on = (jnp.arange(beyond.shape[0]) < shared)[:, None]
            beyond = beyond + jnp.where(on[..., None], w.sum(axis=0)[None], 0.0)
            mass_beyond = mass_beyond + jnp.where(on, m.sum(), 0.0)
        g = self._gravity_force(x, arm)
        origin = joints[:, :, :3, 3]
        rot = joints[:, :, :3, :3]
        lever = beyond - mass_beyond[:, :, None] * origin
        torque = jnp.einsum("enji,enj->eni", rot, jnp.cross(lever, g))  # in the joint's frame
        tau = jnp.sum(torque * jnp.asarray(el["axes"])[:, None, :], axis=-1)  # (E, N)
        return torque, tau

    def _gravity_force(self, x: jax.Array, arm: str) -> jax.Array:
        # weight per kg in the instrument frame, where the frames are
        return self.instrument_pose(x, arm)[:3, :3] @ jnp.asarray(self.gravity, float) * G_N_PER_KG

    def _sag_at(self, x: jax.Array, arm: str, joints: jax.Array, links: jax.Array,
                hanging: Hanging = (), approach: jax.Array | None = None
                ) -> tuple[jax.Array, jax.Array]:
        # the deflections and bending linear in the compliances (plus the play), from the
        # torques in frames already computed
        return self._sag_from_torques(x, arm, *self._torques(x, arm, joints, links, hanging),
                                      approach)

    def _play_side(self, x: jax.Array, arm: str, defl: jax.Array,
                   approach: jax.Array | None) -> jax.Array:
        # which side of its play each joint rests on, -1..1 (E, N): its deflection's, or
        # the approach's where friction holds it against a weaker deflection
        if approach is None:
            return jnp.tanh(defl / PLAY_SIDE_RAD)
        stick = jnp.concatenate([x, jnp.zeros(1)])[self._elements(arm)["stick_idx"]]
        return jnp.tanh((defl + stick[:, None] * approach) / PLAY_SIDE_RAD)

    def _sag_from_torques(self, x: jax.Array, arm: str, torque: jax.Array, tau: jax.Array,
                          approach: jax.Array | None = None) -> tuple[jax.Array, jax.Array]:
        # apart from _sag_at so that the marker Jacobian, which needs the torques for the
        # sag's derivative too, takes them once
        el = self._elements(arm)
        s, lateral, play = self._sag_coefficients(x, arm)
        across = jnp.asarray(el["across"])  # (E, 2, 3)
        bend = jnp.einsum("ek,enk,ekj->enj", lateral,
                          jnp.einsum("enj,ekj->enk", torque, across), across)
        defl = s[:, None] * tau
        # play taken on the side the joint gives way to: the deflection's sign is identified
        # where the torque itself is not (only compliance x mass is), and it is zero, so is
        # the play's effect, until a compliance is fitted
        taken = play[:, None] * self._play_side(x, arm, defl, approach)
        return (defl + taken).T, jnp.swapaxes(bend, 0, 1)

    def _sag_coefficients(self, x: jax.Array, arm: str
                          ) -> tuple[jax.Array, jax.Array, jax.Array]:
        """Each element's compliance (E,), lateral compliances (E, 2) and half play (E,)."""
        el = self._elements(arm)
        xz = jnp.concatenate([x, jnp.zeros(1)])
        return xz[el["compliance_idx"]], xz[el["lateral_idx"]], xz[el["play_idx"]]

    def _sag_marker_jacobian(self, x: jax.Array, arm: str, joints: jax.Array,
                             links: jax.Array, hanging: Hanging, idx: np.ndarray,
                             w_q: jax.Array, w_phi: jax.Array,
                             torques: tuple[jax.Array, jax.Array],
                             approach: jax.Array | None = None) -> jax.Array:
        """The sag's part of the marker Jacobian, (N, 3, C) over x[idx], in the frames given
        held fixed (``w_q``, ``w_phi``: d marker / d joint value and / d bend; tested equal to
        ``jax.jacfwd``), written out since every torque is linear in the masses and moments: a
        few passes, where forward mode pushes C (Justin: 144) tangents through every torque."""
        el = self._elements(arm)
        n = joints.shape[1]
        zero = len(self.layout.params)
        s, lateral, play = self._sag_coefficients(x, arm)
        play = play[:, None]
        torque, tau = torques
        origin = joints[:, :, :3, 3]  # (E, N, 3)
        rot = joints[:, :, :3, :3]
        g = self._gravity_force(x, arm)
        axes = jnp.asarray(el["axes"])
        side = self._play_side(x, arm, s[:, None] * tau, approach)
        # d (deflection + play) / d deflection: the play's smooth step turns with it
        gain = 1.0 + play * (1.0 - side ** 2) / PLAY_SIDE_RAD
        across = jnp.asarray(el["across"])  # (E, 2, 3)
        phi_across = jnp.einsum("enji,ekj->enik", w_phi, across)  # (E, N, 3, 2)
        # the marker's weight on each torque component in the joint's frame, then on the
        # lever arm in the instrument frame: w . R^T (dlever x g) = dlever . (g x R w)
        on_torque = ((w_q * (s[:, None] * gain)[:, :, None])[..., None] * axes[:, None, None]
                     + jnp.einsum("enik,ek,ekm->enim", phi_across, lateral, across))
        v = jnp.cross(g, jnp.einsum("enim,enjm->enij", on_torque, rot))  # (E, N, 3, 3)
        v_origin = jnp.einsum("enia,ena->eni", v, origin)

        def links_block(frames, v_sum, o_sum):
            # a link's weight moves by its frame's origin per unit mass and its frame's axes
            # per unit first moment; its mass also moves every lever by minus that element's
            # origin: (N, 3, L * 4), the link's four parameters inner
            d_w = jnp.concatenate([frames[:, :, :3, 3:4], frames[:, :, :3, :3]], axis=-1)
            out = jnp.einsum("lnia,lnak->nilk", v_sum, d_w)
            return out.at[:, :, :, 0].add(-jnp.transpose(o_sum, (1, 2, 0))).reshape(n, 3, -1)

        # a link on the path weighs on the elements up to its own: cumulative sums
        sources = [links_block(links, jnp.cumsum(v, axis=0), jnp.cumsum(v_origin, axis=0))]
        keys = [np.asarray(el["link_idx"]).ravel()]
        for shared, start, frames, b in hanging:
            # a chain off the path weighs on the path's elements before where it hangs
            h = frames.shape[0]
            sources.append(links_block(
                frames, jnp.broadcast_to(v[:shared].sum(axis=0), (h, n, 3, 3)),
                jnp.broadcast_to(v_origin[:shared].sum(axis=0), (h, n, 3))))
            keys.append(np.asarray(self._elements(b)["link_idx"][start:start + h]).ravel())
        along = jnp.einsum("eni,eki->enk", torque, across)  # (E, N, 2)
        sources += [jnp.transpose(w_q * (tau * gain)[:, :, None], (1, 2, 0)),  # compliances
                    jnp.transpose(w_q * side[:, :, None], (1, 2, 0)),  # play
                    jnp.transpose(phi_across * along[:, :, None, :], (1, 2, 0, 3)).reshape(
                        n, 3, -1)]  # lateral compliances
        keys += [el["compliance_idx"], el["play_idx"], np.asarray(el["lateral_idx"]).ravel()]
        # every source's columns side by side, then one gather into idx's order: each sag
        # parameter is one source's column (a tool's zero index aside), so nothing is summed
        keys = np.concatenate([np.asarray(k) for k in keys])
        real = keys != zero
        if len(set(keys[real].tolist())) != int(real.sum()):
            raise AssertionError("a sag parameter enters two elements")  # the gather's premise
        pos = np.full(zero + 1, len(keys))  # a parameter no source has: the zero column
        pos[keys[real]] = np.flatnonzero(real)
        out = jnp.concatenate([*sources, jnp.zeros((n, 3, 1))], axis=-1)[..., pos[np.asarray(idx)]]
        if approach is None:
            return out
        # a chain's stick deflection enters each of its joints: summed over its elements
        stick = np.asarray(el["stick_idx"])
        onto = (stick[:, None] == np.asarray(idx)[None]) & (stick[:, None] != zero)  # (E, C)
        coef = play * (1.0 - side ** 2) / PLAY_SIDE_RAD * approach  # (E, N)
        return out + jnp.einsum("eni,en,ec->nic", w_q, coef, jnp.asarray(onto, float))

    def n_path_joints(self, arm: str) -> int:
        return sum(c.n_joints for c in self.path(arm))

    def tip_transforms(self, x: jax.Array, arm: str, u: jax.Array,
                       joint_errors: jax.Array | None = None,
                       side: dict[str, jax.Array] | None = None) -> jax.Array:
        """Tip frames (N, 4, 4) of ``arm`` in the instrument frame, for rows u (N, columns);
        ``joint_errors`` (N, n_path_joints) add to the path's joint values, base first;
        ``side``: the other arms' columns (:meth:`side_arms`), whose weight bends shared chains.
        """
        u = jnp.atleast_2d(jnp.asarray(u))
        deflection = None
        if joint_errors is not None:
            # elements index the joints, tools the zero column appended after them
            err = jnp.concatenate([jnp.asarray(joint_errors), jnp.zeros((u.shape[0], 1))], axis=1)
            deflection = err[:, self._elements(arm)["q_idx"]]
        bend = None
        if self.gravity is not None:
            sag, bend = self.sag(x, arm, u, side)
            deflection = sag if deflection is None else deflection + sag
        return self.element_frames(x, arm, u, deflection, bend)[1][-1]

    def marker_jacobian(self, x: jax.Array, arm: str, u: jax.Array,
                        side: dict[str, jax.Array] | None = None) -> jax.Array:
        """d marker_points / d x, (N, dim, P): each parameter is one factor of the product of
        transforms, so one pass forward and one back give every derivative (tested equal to
        ``jax.jacfwd``, which pushes each tangent through the whole chain).
        """
        x = jnp.asarray(x)
        u = jnp.atleast_2d(jnp.asarray(u))
        n_rows = u.shape[0]
        sl = self.layout.slices
        path = self.path(arm)
        el = self._elements(arm)
        q = self._element_values(x, arm, u).T  # (E, N)
        if self.gravity is not None:
            frames = self._sag_frames(x, arm, u, side)
            torques = self._torques(x, arm, *frames)
            approach = self._approach(arm, side)
            defl, bend = self._sag_from_torques(x, arm, *torques, approach)
            q = q + defl.T
        deltas = x[el["delta_idx"]]  # (E, 6)
        axes = jnp.asarray(el["axes"])
        prismatic = jnp.asarray(el["prismatic"])
        factors = jnp.asarray(el["nominal"]) @ tf.perturbation(deltas)  # (E, 4, 4)
        turn = jax.vmap(tf.rot_axis)(axes, q * (1.0 - prismatic)[:, None])  # (E, N, 3, 3)
        motions = tf.homogeneous(turn, (q * prismatic[:, None])[..., None] * axes[:, None, :])
        if self.gravity is not None:
            motions = _bend(jnp.swapaxes(bend, 0, 1)) @ motions
        inst_nominal = self._matrices["instrument"][path[0].name]
        inst_delta = x[sl[(path[0].name, "instrument")]]
        t0 = jnp.broadcast_to(self.instrument_pose(x, arm), (n_rows, 4, 4))

        def forward(t, fm):
            f, m = fm
            before = t @ f  # frame after the origin's correction, before the motion
            return before @ m, (t, before @ m)

        tip, (prefix, after) = jax.lax.scan(forward, t0, (factors, motions))
        marker = x[sl[(arm, "marker")]]
        point = jnp.concatenate([marker, jnp.ones(1)])

        def backward(b, fm):
            f, m = fm
            inner = jnp.einsum("nij,nj->ni", m, b)  # the motion applied to what follows
            return jnp.einsum("ij,nj->ni", f, inner), (b, inner)

        _, (suffix, inner) = jax.lax.scan(backward, jnp.broadcast_to(point, (n_rows, 4)),
                                          (factors, motions), reverse=True)
        # suffix[k]: the marker in the frame after element k's motion; inner[k]: after its
        # origin, before its motion.
        d_deltas = jax.vmap(jax.jacfwd(tf.perturbation))(deltas)  # (E, 4, 4, 6)
        nominal = jnp.asarray(el["nominal"])
        j_delta = jnp.einsum("enij,ejk,eklp,enl->enip", prefix, nominal, d_deltas, inner)
        skew = jnp.stack([jnp.cross(jnp.eye(3), a) for a in axes])  # row i: e_i x a, so K v = a x v
        gen = jnp.zeros((axes.shape[0], 4, 4))
        gen = gen.at[:, :3, :3].set(skew * (1.0 - prismatic)[:, None, None])
        gen = gen.at[:, :3, 3].set(axes * prismatic[:, None])
        j_q = jnp.einsum("enij,ejk,enk->eni", after, gen, suffix)  # (E, N, 4)
        jac = jnp.zeros((n_rows, 3, len(self.layout.params)))
        jac = jac.at[:, :, jnp.asarray(el["delta_idx"]).ravel()].add(
            jnp.transpose(j_delta[:, :, :3, :], (1, 2, 0, 3)).reshape(n_rows, 3, -1))
        d_inst = jax.jacfwd(tf.perturbation)(inst_delta)
        first = jnp.einsum("ij,jkl,nk->nil", inst_nominal, d_inst,
                           jnp.einsum("ij,nj->ni", factors[0], inner[0]))
        jac = jac.at[:, :, sl[(path[0].name, "instrument")]].set(first[:, :3, :])
        jac = jac.at[:, :, sl[(arm, "marker")]].set(tip[:, :3, :3])
        # joint values -> zero offsets, gains, encoder and curve terms, chain by chain
        # (q = C (gain u + offset) + off, then q + a sin q + b cos q + c2 q^2 + c3 q^3)
        start, col = 0, 0
        for chain in path:
            k = chain.n_joints
            dq = jnp.transpose(j_q[start:start + k, :, :3], (1, 2, 0))  # (N, 3, k)
            uc = u[:, col:col + chain.n_columns]
            q0 = self._commanded_values(x, chain, uc)  # (N, k)
            a, b = self._encoder(x, chain)
            ecc = jnp.stack([jnp.sin(q0), jnp.cos(q0)], axis=-1) * _revolute(chain)[:, None]
            jac = jac.at[:, :, sl[(chain.name, "encoder")]].set(
                jnp.einsum("nik,nkj->nikj", dq, ecc).reshape(n_rows, 3, 2 * k))
            jac = jac.at[:, :, sl[(chain.name, "curve")]].set(
                jnp.einsum("nik,nkj->nikj", dq, jnp.stack([q0 ** 2, q0 ** 3], axis=-1))
                .reshape(n_rows, 3, 2 * k))
            c2, c3 = self._curve(x, chain)
            dq = dq * (1.0 + a * jnp.cos(q0) - b * jnp.sin(q0)
                       + (2.0 * c2 + 3.0 * c3 * q0) * q0)[:, None, :]  # d q / d q0
            jac = jac.at[:, :, sl[(chain.name, "offset")]].set(dq)
            d_gain = jnp.einsum("nik,kc,nc->nic", dq, jnp.asarray(chain.coupling), uc)
            jac = jac.at[:, :, sl[(chain.name, "gain")]].set(d_gain)
            start += k + 1
            col += chain.n_columns
        if self.gravity is not None:
            # The sag's derivative in its torques' frames held fixed: how they move with the
            # sag, its dependence on geometry, offsets and gains, and the bend's beyond zero
            # are left out (relative 1e-3 on a few mrad, tests/test_chain.py); where the sag
            # is large (Agile Justin) the calibration finishes with the exact Jacobian.
            idx = np.flatnonzero(self.layout.group_mask(SAG_GROUPS))
            gens = jnp.stack([jnp.zeros((4, 4)).at[:3, :3].set(jnp.cross(jnp.eye(3), e))
                              for e in jnp.eye(3)])  # about the joint's own x, y, z
            before = jnp.einsum("enij,ejk->enik", prefix, factors)
            j_phi = jnp.einsum("enij,kjl,enl->enki", before, gens, inner)  # (E, N, 3, 4)
            jac = jac.at[:, :, idx].add(self._sag_marker_jacobian(
                x, arm, *frames, idx, j_q[:, :, :3], j_phi[..., :3], torques, approach))
        return jac[:, : self.dim, :]

    def marker_points(self, x: jax.Array, arm: str, u: jax.Array,
                      joint_errors: jax.Array | None = None,
                      side: dict[str, jax.Array] | None = None) -> jax.Array:
        """Where the instrument sees ``arm``'s marker: (N, dim) in mm (``joint_errors`` and
        ``side`` as :meth:`tip_transforms`)."""
        t = self.tip_transforms(x, arm, u, joint_errors, side)
        m = jnp.asarray(x)[self.layout.slices[(arm, "marker")]]
        p = t[:, :3, :3] @ m + t[:, :3, 3]
        return p[:, : self.dim]

    def compiled_points(self, arm: str) -> Callable[..., jax.Array]:
        """A jitted ``(x, u, side=None) -> marker points`` for one arm, compiled once per
        process for all robots of this one's structure (its nominal values are arguments)
        and for any number of rows up to a bucket (:func:`on_row_buckets`)."""
        return functools.partial(on_row_buckets, functools.partial(
            _compiled_points, self.structure, arm, self.nominal_values))

    @cached_property
    def structure(self) -> RobotStructure:
        return RobotStructure(
            tuple(ChainStructure(c.name, c.joint_names, c.kinds, np.asarray(c.axes),
                                 np.asarray(c.coupling), c.mount)
                  for c in self.chains.values()),
            self.dim, self.gravity is not None, self.sag_steps)

    @cached_property
    def _matrices(self) -> dict[str, dict[str, np.ndarray]]:
        # the nominal transforms, taken on the host in numpy as they were when they were
        # constants of the programs, so that the programs compute the same numbers
        return {"origins": {c.name: np.stack([tf.np_pose_matrix(o) for o in c.origins])
                            for c in self.chains.values()},
                "instrument": {c.name: tf.np_pose_matrix(c.instrument)
                               for c in self.chains.values()}}

    @cached_property
    def nominal_values(self) -> dict:
        """The robot's numbers apart from its structure, a pytree a compiled program takes
        beside the parameter vector; on the device once, not copied at every call."""
        chains = {c.name: {"origins": c.origins, "gain": c.gain, "offset": c.offset,
                           "marker": c.marker, "instrument": c.instrument}
                  for c in self.chains.values()}
        return jax.device_put({
            "chains": chains, "matrices": self._matrices,
            "gravity": None if self.gravity is None else np.asarray(self.gravity, float)})

    def with_values(self, x: np.ndarray) -> Robot:
        """A robot whose nominal values are those of the parameter vector x (deltas folded in):
        what a calibrated URDF / rig file holds."""
        x = np.asarray(x, float)
        sl = self.layout.slices
        chains = {}
        for c in self.chains.values():
            instrument = c.instrument
            if c.mount is None:
                instrument = tf.matrix_to_pose(tf.np_pose_matrix(c.instrument) @ np.asarray(
                    tf.perturbation(x[sl[(c.name, "instrument")]])))
            deltas = x[sl[(c.name, "origins")]].reshape(c.n_joints + 1, 6)
            offsets = x[sl[(c.name, "offset")]]
            origins = []
            for i in range(c.n_joints + 1):
                t = tf.np_pose_matrix(c.origins[i]) @ np.asarray(tf.perturbation(deltas[i]))
                origins.append(tf.matrix_to_pose(t))
            # A joint's zero offset is folded into its origin: a turn (or shift) about its own
            # axis commutes with the joint's motion, so Origin @ M(q + dq) = (Origin @ M(dq)) M(q).
            for i in range(c.n_joints):
                t = tf.np_pose_matrix(origins[i]) @ np.asarray(
                    _joint_motion(c.kinds[i], c.axes[i], jnp.asarray(offsets[i])))
                origins[i] = tf.matrix_to_pose(t)
            chains[c.name] = Chain(
                c.name, c.joint_names, c.kinds, c.axes, np.array(origins), c.coupling,
                x[sl[(c.name, "gain")]].copy(), c.offset.copy(),
                x[sl[(c.name, "marker")]].copy() if (c.name, "marker") in sl else c.marker,
                c.mount, instrument, c.source)
        return Robot(chains, self.dim, self.gravity, self.sag_steps)

    def measured_arms(self) -> list[str]:
        """Chains that carry a marker (the leaves of the tree)."""
        parents = {c.mount for c in self.chains.values()}
        return [c for c in self.chains if c not in parents]

    @property
    def servo_mapped(self) -> bool:
        """Whether a chain's commands reach its joints through a servo map (a gain other than
        1: a planar arm's pulse widths), whose gain and curve are the servo's; a robot whose
        columns are its joint values (read by encoders) has none."""
        return any(bool(np.any(c.gain != 1.0)) for c in self.chains.values())


@dataclass(frozen=True, eq=False)
class ChainStructure(_ByValue):
    """A chain's part of a :class:`RobotStructure`. The axes are structure: no group corrects
    them, and the frames across each axis (an argmin) are taken from them on the host."""

    name: str
    joint_names: tuple[str, ...]
    kinds: tuple[str, ...]
    axes: np.ndarray
    coupling: np.ndarray
    mount: str | None


@dataclass(frozen=True, eq=False)
class RobotStructure(_ByValue):
    """The static part of a robot, the key of its compiled programs (and so the parameter
    layout); the numbers are :attr:`Robot.nominal_values`, and ``source`` is in neither."""

    chains: tuple[ChainStructure, ...]
    dim: int
    gravity: bool
    sag_steps: int

    @cached_property
    def skeleton(self) -> Robot:
        """A robot of this structure with placeholder numbers, for what depends on the
        structure alone (paths, slices, element indices)."""
        chains = {c.name: Chain(c.name, c.joint_names, c.kinds, c.axes,
                                np.zeros((len(c.joint_names) + 1, 6)), c.coupling,
                                np.ones(c.coupling.shape[1]), np.zeros(c.coupling.shape[1]),
                                mount=c.mount)
                  for c in self.chains}
        return Robot(chains, self.dim, np.zeros(3) if self.gravity else None, self.sag_steps)

    @cached_property
    def layout(self) -> ParamLayout:
        """The parameter layout, its nominal values and scales NaN: a program takes those
        from its arguments."""
        sk = self.skeleton.layout
        return ParamLayout(tuple(replace(p, nominal=np.nan, scale=np.nan) for p in sk.params),
                           sk.slices)

    def robot(self, values: dict) -> Robot:
        """The robot of this structure with ``values`` (:attr:`Robot.nominal_values`, maybe
        tracers): it computes as the original does, but is no value to hash or compare."""
        chains = {}
        for c in self.chains:
            v = values["chains"][c.name]
            chains[c.name] = Chain(c.name, c.joint_names, c.kinds, c.axes, v["origins"],
                                   c.coupling, v["gain"], v["offset"], v["marker"], c.mount,
                                   v["instrument"], {})
        robot = Robot(chains, self.dim, values["gravity"], self.sag_steps)
        robot.__dict__.update(structure=self, layout=self.layout,
                              _matrices=values["matrices"])
        return robot


@functools.lru_cache(maxsize=256)
def _element_table(structure: RobotStructure, arm: str) -> dict[str, np.ndarray]:
    # Robot._elements but the nominal transforms, shared by robots of one structure; bounded,
    # as a sweep may build structure after structure
    robot = structure.skeleton
    sl = robot.layout.slices
    zero = len(robot.layout.params)  # index of a zero appended to x: tools have no mass
    delta_idx, axes, prismatic, q_idx = [], [], [], []
    compliance_idx, link_idx, lateral_idx, across, play_idx, stick_idx = [], [], [], [], [], []
    n_q = 0
    for chain in robot.path(arm):
        start = sl[(chain.name, "origins")].start
        c0, l0 = sl[(chain.name, "compliance")].start, sl[(chain.name, "links")].start
        b0 = sl[(chain.name, "lateral")].start
        p0 = sl[(chain.name, "backlash")].start
        for i in range(chain.n_joints + 1):
            delta_idx.append(np.arange(start + 6 * i, start + 6 * i + 6))
            last = i == chain.n_joints
            axes.append(np.zeros(3) if last else chain.axes[i])
            prismatic.append(0.0 if last else float(chain.kinds[i] == "prismatic"))
            q_idx.append(-1 if last else n_q + i)
            compliance_idx.append(zero if last else c0 + i)
            play_idx.append(zero if last else p0 + i)
            stick_idx.append(zero if last else p0 + chain.n_joints)
            link_idx.append([zero] * 4 if last else list(range(l0 + 4 * i, l0 + 4 * i + 4)))
            lateral_idx.append([zero] * 2 if last else [b0 + 2 * i, b0 + 2 * i + 1])
            across.append(np.zeros((2, 3)) if last else _across(chain.axes[i]))
        n_q += chain.n_joints
    q_idx = [n_q if k < 0 else k for k in q_idx]  # a zero column appended after the joints
    return {"delta_idx": np.stack(delta_idx),
            "axes": np.stack(axes), "prismatic": np.array(prismatic),
            "q_idx": np.array(q_idx), "compliance_idx": np.array(compliance_idx),
            "link_idx": np.array(link_idx), "lateral_idx": np.array(lateral_idx),
            "across": np.stack(across), "play_idx": np.array(play_idx),
            "stick_idx": np.array(stick_idx)}


def row_bucket(n: int) -> int:
    """The number of rows a compiled program for n rows is built for (:data:`MIN_ROW_BUCKET`)."""
    if n <= MIN_ROW_BUCKET:
        return MIN_ROW_BUCKET
    step = 1 << ((n - 1).bit_length() - 3)
    return -(-n // step) * step


def pad_rows(rows: object, size: int) -> object:
    """Every array of ``rows`` (a pytree of (N, ...) arrays: the commands, their side
    arrays, None) with its last row repeated to ``size`` rows, as numpy arrays (a real pose:
    no row of zeros that a servo map or a sag would take somewhere odd)."""
    def padded(a: object) -> np.ndarray:
        a = np.asarray(a)
        return np.concatenate([a, np.repeat(a[-1:], size - len(a), axis=0)]) if len(a) else a
    return jax.tree_util.tree_map(padded, rows)


def on_row_buckets(program: Callable, x: jax.Array, u: jax.Array,
                   side: dict[str, jax.Array] | None = None) -> object:
    """``program(x, u, side)``, a compiled function of rows u (N, c) and their ``side``
    arrays (N, ...) whose outputs are per row, run on the rows padded to their
    :func:`row_bucket` and cut back to N, so that a program serves every row count of its
    bucket. Outputs come back as numpy arrays; traced arguments (inside another
    transformation) run unpadded."""
    leaves = [x, u, *jax.tree_util.tree_leaves(side)]
    if any(isinstance(a, jax.core.Tracer) for a in leaves):
        return program(x, u, side)
    u = np.atleast_2d(np.asarray(u))
    n, size = len(u), row_bucket(len(u))
    out = program(x, *pad_rows((u, side), size))
    return jax.tree_util.tree_map(lambda a: np.asarray(a)[:n], out)


@functools.partial(jax.jit, static_argnames=("structure", "arm"))
def _compiled_points(structure: RobotStructure, arm: str, values: dict, x: jax.Array,
                     u: jax.Array, side: dict[str, jax.Array] | None = None) -> jax.Array:
    return structure.robot(values).marker_points(x, arm, u, side=side)
