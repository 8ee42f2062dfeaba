"""The rig format: ``rig.toml`` (nominal arm values) and ``measurements.csv`` (observed end points).

A rig directory is the only input of the pipeline. Everything is validated here, once, so
nothing downstream re-parses or re-checks files. Every problem a person can make in these
files raises :class:`RigError` with one line naming the file, the row or key and what is
wrong; the command line turns it into that line and exit code 2.
"""

from __future__ import annotations

import csv
import difflib
import io
import json
import math
import re
import tomllib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from bayesrob.robot import Chain, KinematicsError, Robot, dh_chain, planar_chain, urdf_chain
from bayesrob.robot import transforms as tf
from bayesrob.robot.chain import APPROACH as APPROACH_KEY
from bayesrob.robot.planar import ArmGeometry

RIG_FILE = "rig.toml"
MEASUREMENTS_FILE = "measurements.csv"
SETS = ("train", "validation", "test", "holdout")
ARM_KEYS = ("base", "links", "gain", "offset", "elbow", "pulse_limits", "stiffness", "meta")
# Keys of an arm described as a 3-D chain (a URDF or a DH table); see _parse_urdf_dh_arm.
CHAIN_KEYS = ("urdf", "root", "tip", "dh", "convention", "joint_types", "marker", "instrument",
              "gain", "offset", "mount", "origin", "tool", "coupling", "stiffness", "limits",
              "meta")
TOP_KEYS = ("name", "gravity", "workspace", "arms", "meta")
N_ARM_PARAMS = 8
# ``<arm>_d<k>``: the sign of joint k's last move before the row (+1, -1; 0: none or unknown),
# which decides the side of its play the joint rests on; kept in Measurements.extra
APPROACH = re.compile(r"(.+)_d(\d+)")
# A target a little outside the nominal reach is still accepted: nominal lengths are a
# person's measurements, and the calibrated arm may reach what the nominal one does not.
REACH_MARGIN = 0.02


class RigError(ValueError):
    """A rig file is missing or malformed; the message names the file, row or key."""


# Gravity when the rig does not say: straight down, -y in the plane, -z in 3-D
DOWN = {2: (0.0, -1.0), 3: (0.0, 0.0, -1.0)}


def _unit_gravity(g: tuple[float, ...], message: str) -> tuple[float, ...]:
    """Gravity's direction as a unit vector; ``message`` refuses a zero one."""
    norm = math.hypot(*g)
    if norm == 0:
        raise RigError(message)
    return tuple(float(v) / norm for v in g)


@dataclass(frozen=True)
class ArmSpec(ArmGeometry):
    """Nominal values of one arm as a person measured them (calibration's starting point)."""

    # Joint stiffnesses (N mm / rad) when known: linked arms settle where these balance
    # (bayesrob.predict.fusion); None: a prior over them is used instead.
    stiffness: tuple[float, float] | None = None

    @property
    def reach_mm(self) -> tuple[float, float]:
        l1, l2 = self.links
        return abs(l1 - l2), l1 + l2

    def reaches(self, point: Iterable[float], margin: float = REACH_MARGIN) -> bool:
        lo, hi = self.reach_mm
        r = math.dist(point, self.base)
        return lo * (1 - margin) - 1e-9 <= r <= hi * (1 + margin) + 1e-9



@dataclass(frozen=True)
class ChainSpec:
    """An arm described as a chain (a URDF or a DH table): its nominal chain in mm and rad."""

    name: str
    chain: Chain
    # each joint's stiffness (N mm / rad; N / mm if prismatic), when known: it decides where
    # linked arms settle (bayesrob.predict.draws)
    stiffness: np.ndarray | None = None


@dataclass
class Measurements:
    """Column arrays of ``measurements.csv``; NaN where a cell is legitimately empty."""

    config: np.ndarray  # (N,) str
    set: np.ndarray  # (N,) str
    target: np.ndarray  # (N, dim) mm, NaN where not given
    # arm -> (N, columns): pulse widths (us) of a planar arm, or a chain's command columns;
    # NaN where the row does not use the arm
    commands: dict[str, np.ndarray]
    observed: np.ndarray  # (N, dim) mm
    line: np.ndarray  # (N,) line number in the file, for messages
    extra: dict[str, list[str]] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.config)

    @classmethod
    def from_arrays(cls, config: Sequence[str], set: Sequence[str], observed: Any,
                    commands: dict[str, Any], target: Any | None = None) -> Measurements:
        """Rows built in memory, as ``measurements.csv`` would give them: ``config`` (the arm
        measured, or arms joined by '+') and ``set`` (train, validation, test, holdout) per
        row, ``observed`` (N, 2 or 3) mm, ``commands`` arm -> (N, columns) (NaN where a row
        does not use the arm), ``target`` (N, dim) or None. A malformed argument is refused
        with one line naming it (row numbers count from 0)."""
        config = np.asarray(config, dtype=str).reshape(-1)
        sets = np.asarray(set, dtype=str).reshape(-1)
        obs = np.asarray(observed, float)
        n = len(config)
        if obs.ndim != 2 or obs.shape[1] not in (2, 3) or len(obs) != n:
            raise RigError(f"observed: expected ({n}, 2) or ({n}, 3) mm, got {obs.shape}")
        if len(sets) != n:
            raise RigError(f"set: expected {n} values (one per row), got {len(sets)}")
        bad = [i for i, v in enumerate(sets) if v not in SETS]
        if bad:
            raise RigError(f"set: row {bad[0]}: {str(sets[bad[0]])!r} is not one of "
                           f"{', '.join(SETS)}")
        bad = np.flatnonzero(~np.isfinite(obs).all(axis=1))
        if len(bad):
            raise RigError(f"observed: row {bad[0]} is not finite")
        cmds = {}
        for arm, u in commands.items():
            u = np.asarray(u, float)
            if u.ndim != 2 or len(u) != n:
                raise RigError(f"commands[{arm!r}]: expected ({n}, columns), got {u.shape}")
            cmds[arm] = u
        tgt = np.full_like(obs, np.nan) if target is None else np.asarray(target, float)
        if tgt.shape != obs.shape:
            raise RigError(f"target: expected {obs.shape}, got {tgt.shape}")
        return cls(config, sets, tgt, cmds, obs, np.arange(n))

    @classmethod
    def blank(cls, n: int, dim: int, widths: dict[str, int],
              extra_cols: Sequence[str]) -> Measurements:
        """``n`` rows for a loader to fill: NaN numbers, and no extra cells until it keeps a
        row."""
        return cls(config=np.empty(n, dtype=object), set=np.empty(n, dtype=object),
                   target=np.full((n, dim), np.nan),
                   commands={a: np.full((n, w), np.nan) for a, w in widths.items()},
                   observed=np.full((n, dim), np.nan), line=np.zeros(n, int),
                   extra={h: [] for h in extra_cols})

    def kept(self, keep: np.ndarray, path: Path) -> Measurements:
        """The rows in ``keep`` of a filled :meth:`blank`; a file with none is refused."""
        meas = Measurements(config=self.config[keep].astype(str),
                            set=self.set[keep].astype(str), target=self.target[keep],
                            commands={a: c[keep] for a, c in self.commands.items()},
                            observed=self.observed[keep], line=self.line[keep],
                            extra=self.extra)
        if len(meas) == 0:
            raise RigError(f"{path}: no measurement rows")
        return meas

    def approach(self, chains: Sequence[tuple[str, int]], mask: np.ndarray) -> np.ndarray | None:
        """The approach sides (+1, -1; 0: unknown) of ``chains``' joints ((name, joints) in
        path order) in the rows of ``mask``, (rows, joints) side by side, or None where the
        file records none of them."""
        cols = [f"{c}_d{k + 1}" for c, n in chains for k in range(n)]
        if not any(h in self.extra for h in cols):
            return None
        out = np.zeros((len(self), len(cols)))
        for j, h in enumerate(cols):
            if h in self.extra:  # checked +1, -1, 0 or empty when loaded
                out[:, j] = [float(v) if v.strip() else 0.0 for v in self.extra[h]]
        return out[mask]

    def mask(self, config: str | None = None, set: str | None = None) -> np.ndarray:
        m = np.ones(len(self), bool)
        if config is not None:
            m &= self.config == config
        if set is not None:
            m &= self.set == set
        return m


@dataclass
class Rig:
    """A validated rig: nominal arms plus measurements."""

    name: str
    arms: dict[str, ArmSpec | ChainSpec]
    measurements: Measurements
    gravity: tuple[float, ...] = (0.0, -1.0)
    workspace: tuple[tuple[float, float], tuple[float, float]] | None = None
    path: Path | None = None
    # The kinematic model of every arm: planar arms as 2-joint planar chains, or the rig's
    # URDF/DH chains (a tree when arms are mounted on each other).
    robot: Robot | None = None

    @classmethod
    def from_arrays(cls, arms: dict[str, ArmSpec | Chain], measurements: Measurements,
                    name: str = "rig", gravity: Sequence[float] | None = None,
                    stiffness: dict[str, Sequence[float]] | None = None) -> Rig:
        """A rig built in memory, no directory needed: ``arms`` the paper's planar arms
        (:class:`ArmSpec`) or chains (:func:`bayesrob.robot.urdf_chain` with a file or
        ``text=``, :func:`~bayesrob.robot.dh_chain`), and their rows
        (:meth:`Measurements.from_arrays`). ``gravity`` as rig.toml's (default straight down:
        -y in the plane, -z in 3-D); ``stiffness``: joint stiffnesses per chain, where known.
        Checked as :func:`load_rig` checks a directory: every config names arms of the rig,
        every arm has its command columns, every measured arm train rows."""
        chain_arms = [n for n, a in arms.items() if isinstance(a, Chain)]
        if chain_arms and len(chain_arms) != len(arms):
            raise RigError("arms: planar arms (ArmSpec) and chains cannot share a rig")
        dim = measurements.observed.shape[1]
        if chain_arms:
            specs = {n: ChainSpec(n, c, None if not stiffness or n not in stiffness
                                  else np.asarray(stiffness[n], float))
                     for n, c in arms.items()}
            chains = _ordered_chains(specs, "arms")
            specs = {n: specs[n] for n in chains}
            robot = Robot(chains, dim)
        else:
            specs = dict(arms)
            robot = Robot({n: planar_chain(n, a) for n, a in arms.items()}, 2)
        for n, c in robot.chains.items():
            u = measurements.commands.get(n)
            if u is None or u.shape[1] != c.n_columns:
                raise RigError(f"commands[{n!r}]: arm {n!r} needs {c.n_columns} command "
                               "columns")
        known = robot.measured_arms()
        for cfg in sorted(str(c) for c in set(measurements.config)):
            for a in cfg.split("+"):
                if a not in known:
                    raise RigError(f"config {cfg!r} names {a!r}, not a measured arm of the rig "
                                   f"({', '.join(known)})")
        down = tuple(gravity) if gravity is not None else DOWN[dim]
        bad = f"gravity: expected a non-zero {dim}-vector, got {list(down)}"
        if len(down) != dim:
            raise RigError(bad)
        rig = cls(name, specs, measurements, _unit_gravity(down, bad), None, None, robot)
        for a in known:
            if not measurements.mask(a, "train").any():
                raise RigError(f"arm {a!r} has no train rows")
        return rig

    @property
    def is_chain(self) -> bool:
        """True when the arms are URDF/DH chains rather than the paper's planar arms."""
        return any(isinstance(a, ChainSpec) for a in self.arms.values())

    def rows(self, arm: str, set: str) -> tuple[np.ndarray, np.ndarray]:
        """A measured arm's single-arm rows in a set: the columns of its path (N, c; a planar
        arm's two pulse widths, a mounted arm's mounts' columns first) and the observed points
        (N, dim)."""
        meas = self.measurements
        m = meas.mask(arm, set)
        cols = [meas.commands[c.name][m] for c in self.robot.path(arm)]
        return np.concatenate(cols, axis=1), meas.observed[m]

    def side_rows(self, arm: str, set: str) -> dict[str, np.ndarray] | None:
        """The other measured arms' path columns in ``arm``'s rows of a set (the rest of each
        pose, whose weight bends shared chains), or None unless every such row carries them."""
        meas = self.measurements
        m = meas.mask(arm, set)
        side = {b: np.concatenate([meas.commands[c.name][m] for c in self.robot.path(b)],
                                  axis=1) for b in self.robot.side_arms(arm)}
        if not m.any() or any(np.isnan(u).any() for u in side.values()):
            side = {}
        approach = meas.approach([(c.name, c.n_joints) for c in self.robot.path(arm)], m)
        if approach is not None and m.any():
            side[APPROACH_KEY] = approach
        return side or None

    @property
    def configs(self) -> list[str]:
        """Configs in order of first appearance."""
        return list(dict.fromkeys(self.measurements.config.tolist()))

    @property
    def linked_configs(self) -> list[str]:
        return [c for c in self.configs if "+" in c]

    def config_rows(self, config: str, set: str) -> dict[str, np.ndarray]:
        """Rows of a config and set: ``commands`` per arm, ``target`` and ``observed``."""
        meas = self.measurements
        m = meas.mask(config, set)
        return {
            "commands": {a: meas.commands[a][m] for a in config.split("+")},
            "target": meas.target[m],
            "observed": meas.observed[m],
        }


# ----------------------------------------------------------------------------- rig.toml


def _read_text(path: Path) -> str:
    """A rig file's text: UTF-8 whatever the locale, a leading BOM (Excel, Notepad) dropped."""
    if not path.is_file():
        raise RigError(f"{path}: file not found")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise RigError(f"{path}: cannot read: {exc.strerror or exc}") from None
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = data[: exc.start].count(b"\n") + 1
        raise RigError(f"{path}: line {line}: not UTF-8 text (byte {data[exc.start]:#04x})"
                       ) from None


def _pair(value: object, where: str, positive: bool = False) -> tuple[float, float]:
    if not isinstance(value, list | tuple) or len(value) != 2:
        raise RigError(f"{where}: expected a list of two numbers, got {value!r}")
    a, b = _numbers(value, 2, where)
    if positive and min(a, b) <= 0:
        raise RigError(f"{where}: values must be positive, got {value!r}")
    return float(a), float(b)


def _check_keys(table: dict, known: Iterable[str], where: str, what: str) -> None:
    """Refuse unknown keys: a typo (say 'gravty') would otherwise silently fall back to a
    default. Other tools' data belongs in a ``meta`` table, which is never read."""
    known = tuple(known)
    for key in table:
        if key not in known:
            near = difflib.get_close_matches(key, known, n=1, cutoff=0.6)
            hint = f"; did you mean {near[0]!r}?" if near else \
                f" (known keys: {', '.join(known)}; put other tools' data in a 'meta' table)"
            raise RigError(f"{where}: {what} has unknown key {key!r}{hint}")


def _parse_arm(name: str, table: dict, where: str) -> ArmSpec:
    _check_keys(table, ARM_KEYS, where, f"[arms.{name}]")
    key = f"{where}: arms.{name}"
    for k in ("base", "links", "gain", "offset"):
        if k not in table:
            raise RigError(f"{where}: [arms.{name}] is missing key '{k}'")
    base, links, gain = (_pair(table[k], f"{key}.{k}", positive=k == "links")
                         for k in ("base", "links", "gain"))
    if 0.0 in gain:
        raise RigError(f"{key}.gain must be non-zero, got {list(gain)}")
    offset = _pair(table["offset"], f"{key}.offset")
    elbow = table.get("elbow", 1)
    if elbow not in (1, -1) or isinstance(elbow, bool):
        raise RigError(f"{key}.elbow must be +1 or -1, got {elbow!r}")
    limits_raw = table.get("pulse_limits", [[500.0, 2500.0], [500.0, 2500.0]])
    if not isinstance(limits_raw, list) or len(limits_raw) != 2:
        raise RigError(f"{key}.pulse_limits must be [[lo, hi], [lo, hi]], got {limits_raw!r}")
    limits = tuple(_pair(lim, f"{key}.pulse_limits[{j}]") for j, lim in enumerate(limits_raw))
    for j, (lo, hi) in enumerate(limits):
        if lo >= hi:
            raise RigError(f"{key}.pulse_limits[{j}] needs lo < hi, got {[lo, hi]}")
    stiffness = (_pair(table["stiffness"], f"{key}.stiffness", positive=True)
                 if "stiffness" in table else None)
    return ArmSpec(name, base, links, gain, offset, int(elbow), limits,  # type: ignore[arg-type]
                   stiffness)


def _numbers(value: object, n: int, where: str) -> np.ndarray:
    """A list of n finite numbers (a single number stands for n equal ones when n > 1)."""
    if isinstance(value, int | float) and not isinstance(value, bool) and n > 1:
        value = [value] * n
    if not isinstance(value, list | tuple) or len(value) != n:
        raise RigError(f"{where}: expected a list of {n} numbers, got {value!r}")
    for v in value:
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise RigError(f"{where}: expected finite numbers, got {value!r}")
    return np.asarray(value, float)


def _parse_urdf_dh_arm(name: str, table: dict, where: str, directory: Path) -> ChainSpec:
    """An arm given by ``urdf`` (+ ``root``, ``tip``) or ``dh`` (+ ``convention``)."""
    _check_keys(table, CHAIN_KEYS, where, f"[arms.{name}]")
    key = f"{where}: arms.{name}"
    if ("urdf" in table) == ("dh" in table):
        raise RigError(f"{key}: give either 'urdf' (with 'root' and 'tip') or 'dh', not both")
    if "mount" in table and not isinstance(table["mount"], str):
        raise RigError(f"{key}.mount: expected an arm name, got {table['mount']!r}")
    marker = _numbers(table.get("marker", [0.0, 0.0, 0.0]), 3, f"{key}.marker")
    if "instrument" in table and "mount" in table:
        raise RigError(f"{key}: a mounted arm has no 'instrument' pose of its own (its root "
                       "arm's is used)")
    instrument = _numbers(table.get("instrument", [0.0] * 6), 6, f"{key}.instrument")
    common = {"marker": marker, "mount": table.get("mount"), "instrument": instrument}
    try:
        if "urdf" in table:
            for k in ("root", "tip"):
                if not isinstance(table.get(k), str):
                    raise RigError(f"{key}: a URDF arm needs '{k}' (a link name)")
            if not isinstance(table["urdf"], str):
                raise RigError(f"{key}.urdf: expected a file name, got {table['urdf']!r}")
            chain = urdf_chain(directory / table["urdf"], table["root"], table["tip"], name,
                               **common)
        else:
            rows = table["dh"]
            if not isinstance(rows, list) or not rows:
                raise RigError(f"{key}.dh: expected a list of [d, theta, a, alpha] rows")
            for i, r in enumerate(rows):
                if not isinstance(r, list) or len(r) != 4:
                    raise RigError(f"{key}.dh[{i}]: a DH row is [d, theta, a, alpha] (4 "
                                   f"numbers), got {r!r}")
                _numbers(r, 4, f"{key}.dh[{i}]")
            convention = table.get("convention", "modified")
            if convention not in ("modified", "standard"):
                raise RigError(f"{key}.convention: must be 'modified' or 'standard', got "
                               f"{convention!r}")
            kinds = table.get("joint_types", ["revolute"] * len(rows))
            if not isinstance(kinds, list) or len(kinds) != len(rows) or any(
                    k not in ("revolute", "prismatic") for k in kinds):
                raise RigError(f"{key}.joint_types: expected {len(rows)} of 'revolute' or "
                               f"'prismatic', got {kinds!r}")
            chain = dh_chain(name, rows, convention, kinds, **common)
    except KinematicsError as exc:
        raise RigError(f"{key}: {exc}") from None
    n = chain.n_joints
    changes: dict = {}
    if "coupling" in table:
        c = table["coupling"]
        if not isinstance(c, list) or len(c) != n or not all(isinstance(r, list) for r in c):
            raise RigError(f"{key}.coupling: expected {n} rows (one per joint) of weights on "
                           f"the arm's columns, got {c!r}")
        m = len(c[0]) if c else 0
        changes["coupling"] = np.array([_numbers(r, m, f"{key}.coupling[{i}]")
                                        for i, r in enumerate(c)])
    m = changes.get("coupling", chain.coupling).shape[1]
    changes["gain"] = _numbers(table.get("gain", [1.0] * m), m, f"{key}.gain")
    if np.any(changes["gain"] == 0):
        raise RigError(f"{key}.gain: must be non-zero, got {changes['gain'].tolist()}")
    changes["offset"] = _numbers(table.get("offset", [0.0] * m), m, f"{key}.offset")
    origins = chain.origins.copy()
    if "origin" in table:
        t = tf.np_pose_matrix(_numbers(table["origin"], 6, f"{key}.origin"))
        origins[0] = tf.matrix_to_pose(t @ tf.np_pose_matrix(origins[0]))
    if "tool" in table:
        t = tf.np_pose_matrix(_numbers(table["tool"], 6, f"{key}.tool"))
        origins[-1] = tf.matrix_to_pose(tf.np_pose_matrix(origins[-1]) @ t)
    changes["origins"] = origins
    stiffness = None
    if "stiffness" in table:
        stiffness = _numbers(table["stiffness"], n, f"{key}.stiffness")
        if np.any(stiffness <= 0):
            raise RigError(f"{key}.stiffness: must be positive (N mm / rad per joint), got "
                           f"{stiffness.tolist()}")
    return ChainSpec(name, replace(chain, **changes), stiffness)


def _ordered_chains(specs: dict[str, ChainSpec], where: str) -> dict[str, Chain]:
    """Chains with every mount before the arms on it; unknown mounts and cycles refused."""
    out: dict[str, Chain] = {}
    pending = dict(specs)
    while pending:
        ready = [n for n, s in pending.items()
                 if s.chain.mount is None or s.chain.mount in out]
        if not ready:
            for n, s in pending.items():
                if s.chain.mount not in specs:
                    raise RigError(f"{where}: arms.{n}.mount: {s.chain.mount!r} is not an arm "
                                   f"of this rig ({', '.join(specs)})")
            raise RigError(f"{where}: arms {', '.join(pending)} are mounted on each other in "
                           "a loop")
        for n in ready:
            out[n] = pending.pop(n).chain
    return out


def load_rig_toml(path: Path) -> dict:
    """Parse and validate ``rig.toml``; returns the pieces of a :class:`Rig` but its rows."""
    text = _read_text(path)
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        # Duplicate [arms.x] tables surface here: TOML forbids declaring a table twice.
        dup = re.match(r"Cannot declare \('arms', '(.*)'\) twice \(at (line \d+)", str(exc))
        if dup:
            raise RigError(f"{path}: {dup[2]}: duplicate arm name {dup[1]!r} "
                           f"([arms.{dup[1]}] declared twice)") from None
        raise RigError(f"{path}: invalid TOML: {exc}") from None
    _check_keys(doc, TOP_KEYS, str(path), "rig.toml")
    arms_raw = doc.get("arms")
    if "arms" not in doc:
        raise RigError(f"{path}: missing key 'arms' (at least one [arms.<name>] table)")
    if not isinstance(arms_raw, dict) or not arms_raw:
        what = "an empty table" if arms_raw == {} else f"a {type(arms_raw).__name__}"
        raise RigError(f"{path}: key 'arms' must hold one [arms.<name>] table per arm, "
                       f"got {what}")
    lowered = [a.lower() for a in arms_raw]
    for a in arms_raw:
        if lowered.count(a.lower()) > 1:
            raise RigError(f"{path}: duplicate arm name {a!r} (names differ only by case)")
    chain_arms = [n for n, t in arms_raw.items()
                  if isinstance(t, dict) and ("urdf" in t or "dh" in t)]
    if chain_arms and len(chain_arms) != len(arms_raw):
        planar = [n for n in arms_raw if n not in chain_arms]
        raise RigError(f"{path}: arms {', '.join(chain_arms)} are chains (urdf/dh) but "
                       f"{', '.join(planar)} planar (base/links): describe all arms one way "
                       "(a planar arm is a 2-row DH table)")
    for name in arms_raw:
        if "+" in name or "," in name or not name.strip() or name != name.strip():
            raise RigError(f"{path}: arm name {name!r} may not be empty, contain '+' or ',', "
                           "or start or end with a space")
        if not isinstance(arms_raw[name], dict):
            raise RigError(f"{path}: [arms.{name}] must be a table")
    if chain_arms:
        arms: dict = {name: _parse_urdf_dh_arm(name, tbl, str(path), path.parent)
                      for name, tbl in arms_raw.items()}
        chains = _ordered_chains(arms, str(path))
        arms = {n: arms[n] for n in chains}
    else:
        arms = {name: _parse_arm(name, tbl, str(path)) for name, tbl in arms_raw.items()}
        chains = {n: planar_chain(n, a) for n, a in arms.items()}
    dim = 3 if chain_arms else 2
    gravity = doc.get("gravity", list(DOWN[dim]))
    gravity = tuple(float(g) for g in _numbers(gravity, dim, f"{path}: gravity")) \
        if chain_arms else _pair(gravity, f"{path}: gravity")
    gravity = _unit_gravity(gravity, f"{path}: gravity must be a non-zero vector")
    workspace = doc.get("workspace")
    if workspace is not None:
        if not isinstance(workspace, list) or len(workspace) not in (2, 3):
            raise RigError(f"{path}: workspace must be [[x0, x1], [y0, y1]] (with [z0, z1] "
                           f"for a 3-D rig), got {workspace!r}")
        workspace = tuple(_pair(r, f"{path}: workspace") for r in workspace)
    name = doc.get("name", path.parent.name)
    if not isinstance(name, str):
        raise RigError(f"{path}: name must be a string, got {name!r}")
    return {"name": name, "arms": arms, "gravity": gravity, "workspace": workspace,
            "chains": chains}


# ----------------------------------------------------------------------------- measurements


def parse_number(text: str, where: str, column: str, allow_empty: bool = False) -> float:
    """A finite number from a CSV cell, or a RigError naming the place and column."""
    text = text.strip()
    if text == "":
        if allow_empty:
            return math.nan
        raise RigError(f"{where}: column '{column}' is empty")
    try:
        value = float(text)
    except ValueError:
        raise RigError(f"{where}: column '{column}' is not a number: {text!r}") from None
    if not math.isfinite(value):
        raise RigError(f"{where}: column '{column}' is not a finite number: {text!r}")
    return value


def _read_csv(path: Path) -> tuple[list[str], list[list[str]], list[int]]:
    """Header (stripped, unique), rows, and the line each row starts on."""
    text = _read_text(path)
    reader = csv.reader(io.StringIO(text, newline=""))
    rows: list[list[str]] = []
    starts: list[int] = []  # line each record starts on: a quoted field may span lines
    try:
        header = next(reader, None)
        end = reader.line_num
        for row in reader:
            rows.append(row)
            starts.append(end + 1)
            end = reader.line_num
    except csv.Error as exc:
        raise RigError(f"{path}: line {reader.line_num}: malformed CSV: {exc}") from None
    if not header:
        raise RigError(f"{path}: empty file (a header row is required)")
    header = [h.strip() for h in header]
    dup = {h for h in header if header.count(h) > 1}
    if dup:
        raise RigError(f"{path}: duplicate column {sorted(dup)[0]!r} in header")
    return header, rows, starts


def csv_records(path: Path, header: list[str], rows: Sequence[list[str]],
                starts: Sequence[int]):
    """The rows that carry a measurement: (index, line, place to name in messages, fields).
    Blank lines are skipped; a row whose field count differs from the header's is an error."""
    for r, row in enumerate(rows):
        if not row or all(not c.strip() for c in row):
            continue
        where = f"{path}: line {starts[r]}"
        if len(row) != len(header):
            raise RigError(f"{where}: expected {len(header)} fields, found {len(row)}")
        yield r, starts[r], where, row


def _config_members(row: list[str], idx: dict, arms: Iterable[str], where: str) -> list[str]:
    members = [m.strip() for m in row[idx["config"]].split("+")]
    cfg = "+".join(members)  # 'top + bottom' is 'top+bottom'
    if not cfg or any(not m for m in members):
        raise RigError(f"{where}: column 'config' is empty or malformed: {cfg!r}")
    for m in members:
        if m not in arms:
            raise RigError(f"{where}: config {cfg!r} names unknown arm {m!r} (rig.toml has "
                           f"{', '.join(arms)})")
    if len(set(members)) != len(members):
        raise RigError(f"{where}: config {cfg!r} names the same arm twice")
    return members


def row_set(row: list[str], idx: dict, where: str) -> str:
    st = row[idx["set"]].strip()
    if st not in SETS:
        raise RigError(f"{where}: column 'set' must be one of {', '.join(SETS)}, got {st!r}")
    return st


def is_planned(row: list[str], idx: dict[str, int]) -> bool:
    """A row with commands but every coordinate (x, y and, where the file has it, z) empty:
    planned, not measured yet (``bayesrob design`` writes such rows; ``simulate --planned``
    fills them; loading skips them)."""
    return all(not row[idx[a]].strip() for a in "xyz" if a in idx)


def _load_rows(path: Path, table: tuple, required: list[str], optional: list[str], dim: int,
               widths: dict[str, int], arms: Iterable[str], cells: Any) -> Measurements:
    """The measured rows of ``measurements.csv`` (``table``: its :func:`_read_csv`), one
    loader for every robot: ``cells(m, r, where, row, idx, members)`` reads and checks a row's
    commands and target against its arms; a planned row (commands, no coordinates) is then
    dropped."""
    header, rows, starts = table
    for col in required:
        if col not in header:
            raise RigError(f"{path}: missing column '{col}'")
    idx = {h: i for i, h in enumerate(header)}
    extra_cols = [h for h in header if h not in {*required, *optional}]
    sides = [h for h in extra_cols if (d := APPROACH.fullmatch(h)) and d[1] in widths]
    m = Measurements.blank(len(rows), dim, widths, extra_cols)
    keep = np.zeros(len(rows), bool)
    for r, lineno, where, row in csv_records(path, header, rows, starts):
        members = _config_members(row, idx, arms, where)
        st = row_set(row, idx, where)
        cells(m, r, where, row, idx, members)
        for h in sides:
            side = parse_number(row[idx[h]], where, h, allow_empty=True)
            if not (math.isnan(side) or side in (-1, 0, 1)):
                raise RigError(f"{where}: column '{h}' must be +1, -1 or 0 (the side the joint "
                               f"approached its command from) or empty, got {row[idx[h]]!r}")
        if is_planned(row, idx):
            continue  # planned by ``bayesrob design``, not measured yet
        m.observed[r] = [parse_number(row[idx[a]], where, a) for a in "xyz"[:dim]]
        m.config[r], m.set[r], m.line[r], keep[r] = "+".join(members), st, lineno, True
        for h in extra_cols:
            m.extra[h].append(row[idx[h]])
    return m.kept(keep, path)


def load_measurements(path: Path, arms: dict[str, ArmSpec]) -> Measurements:
    """Parse and validate a planar rig's ``measurements.csv`` against its arms."""

    def cells(m: Measurements, r: int, where: str, row: list[str], idx: dict,
              members: list[str]) -> None:
        cfg = "+".join(members)
        for a in members:
            spec = arms[a]
            u = []
            for j in (1, 2):
                col = f"{a}_u{j}"
                if row[idx[col]].strip() == "":
                    what = "a linked row" if len(members) > 1 else "the row"
                    raise RigError(f"{where}: {what} for {cfg!r} is missing arm {a!r}'s '{col}'")
                u.append(parse_number(row[idx[col]], where, col))
            for j, (p, (lo, hi)) in enumerate(zip(u, spec.pulse_limits, strict=True)):
                if not lo <= p <= hi:
                    raise RigError(f"{where}: column '{a}_u{j + 1}' = {p:g} us is outside arm "
                                   f"{a!r}'s pulse_limits [{lo:g}, {hi:g}]")
            m.commands[a][r] = u
        for a in arms:
            if a not in members:
                for j in (1, 2):
                    # Cells of arms outside the config are ignored, but must not be garbage
                    # that hides a mistyped config.
                    parse_number(row[idx[f"{a}_u{j}"]], where, f"{a}_u{j}", allow_empty=True)
        tx = parse_number(row[idx["target_x"]], where, "target_x", allow_empty=True)
        ty = parse_number(row[idx["target_y"]], where, "target_y", allow_empty=True)
        if math.isnan(tx) != math.isnan(ty):
            raise RigError(f"{where}: target_x and target_y must both be given or both empty")
        if len(members) > 1 and math.isnan(tx):
            raise RigError(f"{where}: linked row {cfg!r} needs target_x and target_y")
        if not math.isnan(tx):
            for a in members:
                if not arms[a].reaches((tx, ty)):
                    lo, hi = arms[a].reach_mm
                    raise RigError(f"{where}: target ({tx:g}, {ty:g}) is outside arm {a!r}'s "
                                   f"reach ({lo:g} to {hi:g} mm from its base)")
        m.target[r] = tx, ty

    required = ["config", "set", "target_x", "target_y", "x", "y",
                *(f"{a}_u{j}" for a in arms for j in (1, 2))]
    return _load_rows(path, _read_csv(path), required, [], 2, dict.fromkeys(arms, 2), arms,
                      cells)


def load_robot_measurements(path: Path, chains: dict[str, Chain]) -> tuple[Measurements, Robot]:
    """``measurements.csv`` of a chain rig: ``x,y`` or ``x,y,z`` (mm) and each chain's
    ``<arm>_u1..<arm>_uN``; a row's ``config`` names the arm whose marker was measured, and the
    row carries that arm's columns and its mounts' (targets are optional).

    A linked row (``config`` = ``left+right``) measures the one point where the named arms'
    markers are joined: every member must carry a marker (a measured arm), and the row carries
    the columns of every member's path. Calibration reads single-arm rows only
    (:meth:`Rig.rows` matches ``config`` exactly), so linked rows never enter a fit."""
    table = _read_csv(path)
    dim = 3 if "z" in table[0] else 2
    robot = Robot(chains, dim)
    if dim == 2:
        flat = [n for n, c in chains.items() if not c.is_planar()]
        if flat:
            raise RigError(f"{path}: 2-D data (no 'z' column) for 3-D arm {flat[0]!r}: a chain "
                           "that leaves the plane needs x, y and z")
    axes = "xyz"[:dim]
    targets = [f"target_{a}" for a in axes]
    measured = robot.measured_arms()

    def cells(m: Measurements, r: int, where: str, row: list[str], idx: dict,
              members: list[str]) -> None:
        cfg = "+".join(members)
        for arm in members:
            if arm in measured:
                continue
            if len(members) == 1:
                raise RigError(f"{where}: config {arm!r} names an arm other arms are mounted "
                               f"on; a marker is measured on an arm's tip ({', '.join(measured)})")
            raise RigError(f"{where}: linked config {cfg!r} names {arm!r}, an arm other arms "
                           "are mounted on; arms are linked at the markers on their tips "
                           f"({', '.join(measured)})")
        # Members may share chains (two hands on one torso): each chain's columns once.
        owner = {c.name: a for a in members for c in robot.path(a)}
        for c in chains.values():
            uses = c.name in owner
            for k in range(c.n_columns):
                col = f"{c.name}_u{k + 1}"
                if uses and len(members) > 1 and row[idx[col]].strip() == "":
                    raise RigError(f"{where}: a linked row for {cfg!r} is missing arm "
                                   f"{owner[c.name]!r}'s {col!r}")
                # a chain off the row's path may carry the rest of the pose: the other arms'
                # weight on the chains they share with this one
                m.commands[c.name][r, k] = parse_number(row[idx[col]], where, col,
                                                        allow_empty=not uses)
        if all(t in idx for t in targets):
            m.target[r] = [parse_number(row[idx[t]], where, t, allow_empty=True)
                           for t in targets]

    required = ["config", "set", *axes,
                *(f"{c.name}_u{k + 1}" for c in chains.values() for k in range(c.n_columns))]
    return _load_rows(path, table, required, targets, dim,
                      {c: chains[c].n_columns for c in chains}, chains, cells), robot


def load_rig(directory: str | Path, min_train_rows: int = N_ARM_PARAMS) -> Rig:
    """Load and validate a rig directory.

    ``min_train_rows``: each planar arm needs at least this many single-arm ``train`` rows (by
    default as many as it has parameters); pass 0 for rigs still being collected. A chain rig's
    measured arms need at least one (calibration checks rows against the parameters it frees).
    """
    directory = Path(directory)
    if not directory.is_dir():
        raise RigError(f"{directory}: rig directory not found")
    meta = load_rig_toml(directory / RIG_FILE)
    chains = meta.pop("chains")
    if any(isinstance(a, ChainSpec) for a in meta["arms"].values()):
        meas, robot = load_robot_measurements(directory / MEASUREMENTS_FILE, chains)
        rig = Rig(measurements=meas, path=directory, robot=robot, **meta)
        for a in robot.measured_arms():
            if min_train_rows and not meas.mask(a, "train").any():
                raise RigError(f"{directory / MEASUREMENTS_FILE}: arm {a!r} has no train rows")
        return rig
    meas = load_measurements(directory / MEASUREMENTS_FILE, meta["arms"])
    rig = Rig(measurements=meas, path=directory, robot=Robot(chains, 2), **meta)
    for a in rig.arms:
        n_train = int(meas.mask(a, "train").sum())
        if n_train < min_train_rows:
            raise RigError(f"{directory / MEASUREMENTS_FILE}: arm {a!r} has {n_train} train "
                           f"rows, fewer than its {N_ARM_PARAMS} parameters")
    return rig


# ----------------------------------------------------------------------------- writing


def measurement_header(arm_names: Iterable[str], approach: bool = False) -> list[str]:
    """The columns of a planar rig's ``measurements.csv``; ``approach`` adds each arm's
    ``<arm>_d1``, ``<arm>_d2`` after x, y."""
    arm_names = list(arm_names)
    cols = ["config", "set", "target_x", "target_y"]
    cols += [f"{a}_u{j}" for a in arm_names for j in (1, 2)]
    return cols + ["x", "y"] + [f"{a}_d{j}" for a in arm_names for j in (1, 2) if approach]


def format_row(
    arm_names: Iterable[str],
    config: str,
    set: str,
    target: Iterable[float] | None,
    commands: dict[str, Iterable[float]],
    observed: Iterable[float],
    approach: dict[str, Iterable[float]] | None = None,
) -> list[str]:
    """One CSV row in :func:`measurement_header` order; pulse widths are written as given.
    ``approach``: each arm's approach sides, for a header with them (empty for other arms)."""

    def num(v: float) -> str:
        return "" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.6g}"

    row = [config, set]
    row += [num(float(v)) for v in target] if target is not None else ["", ""]
    for a in arm_names:
        row += [num(float(v)) for v in commands[a]] if a in commands else ["", ""]
    # a planned row (not measured yet) leaves x, y empty
    row += ["" if v is None or math.isnan(float(v)) else f"{float(v):.4f}" for v in observed]
    for a in arm_names if approach is not None else ():
        row += [f"{int(v):d}" for v in approach[a]] if a in approach else ["", ""]
    return row


def _toml_value(v: object) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int | float):
        if isinstance(v, float) and not math.isfinite(v):
            raise ValueError(f"cannot write non-finite number {v!r} to TOML")
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)  # a JSON string literal is a valid TOML basic string
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def dump_toml(doc: dict, _prefix: str = "") -> str:
    """TOML text with arrays on one line, so rig files stay readable and hand-editable."""
    lines = [f"{_bare(k)} = {_toml_value(v)}" for k, v in doc.items() if not isinstance(v, dict)]
    for k, v in doc.items():
        if isinstance(v, dict):
            name = f"{_prefix}{_bare(k)}"
            scalars = {kk: vv for kk, vv in v.items() if not isinstance(vv, dict)}
            if scalars or not v:
                lines += ["", f"[{name}]"]
            body = dump_toml(v, name + ".")
            if body:
                lines.append(body)
    return "\n".join(lines).strip("\n") + ("\n" if not _prefix else "")


def _bare(key: str) -> str:
    ok = key and all(c.isalnum() or c in "_-" for c in key)
    return key if ok else json.dumps(key)


def rig_toml_dict(
    name: str,
    arms: dict[str, ArmSpec],
    gravity: tuple[float, float] = (0.0, -1.0),
    workspace: tuple[tuple[float, float], tuple[float, float]] | None = None,
) -> dict:
    doc: dict = {"name": name, "gravity": list(gravity)}
    if workspace is not None:
        doc["workspace"] = [list(r) for r in workspace]
    doc["arms"] = {
        a.name: {
            "base": list(a.base),
            "links": list(a.links),
            "gain": list(a.gain),
            "offset": list(a.offset),
            "elbow": a.elbow,
            "pulse_limits": [list(p) for p in a.pulse_limits],
            **({"stiffness": list(a.stiffness)} if a.stiffness is not None else {}),
        }
        for a in arms.values()
    }
    return doc


def default_rig_dir() -> Path:
    """The embedded default rig (simulated; see its README for the command that regenerates it)."""
    from importlib.resources import files

    return Path(str(files("bayesrob.data") / "default_rig"))
