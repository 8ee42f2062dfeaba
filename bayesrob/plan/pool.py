"""The candidate poses a plan chooses from, and the rig it plans for (measured or not yet).
A pool is a CSV of safe commands (``<arm>_u1..N``, ``config`` naming the measured arm), or
samples inside the joint limits (rig.toml ``limits``, a URDF's ``<limit>``, ``pulse_limits``).
"""

from __future__ import annotations

import csv
import io
import math
import tomllib
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bayesrob.data.rig import (
    MEASUREMENTS_FILE,
    RIG_FILE,
    Measurements,
    Rig,
    RigError,
    load_rig,
    load_rig_toml,
    parse_number,
)
from bayesrob.robot import Chain, Robot

M_TO_MM = 1000.0


@dataclass
class Pool:
    """Candidate poses: which arm's marker each measures, every chain's command columns
    (NaN where a row leaves a chain out), and the rows as the pool file wrote them."""

    config: np.ndarray  # (N,) str: the measured arm
    commands: dict[str, np.ndarray]  # chain -> (N, m)
    header: list[str]  # the pool file's columns (sampled pools: config and the commands)
    cells: list[list[str]]  # each row's cells as written, in ``header`` order
    source: str  # the file, or "M samples" (for messages)

    def __len__(self) -> int:
        return len(self.config)

    def columns(self, robot: Robot, arm: str, rows: np.ndarray) -> np.ndarray:
        """``arm``'s path columns (n, c) at ``rows``: what its marker depends on."""
        return np.concatenate([self.commands[c.name][rows] for c in robot.path(arm)], axis=1)

    def side(self, robot: Robot, arm: str, rows: np.ndarray) -> dict[str, np.ndarray] | None:
        """The other measured arms' path columns at ``rows`` where every row carries them
        (their weight bends the chains they share with ``arm``), else None."""
        side = {b: self.columns(robot, b, rows) for b in robot.side_arms(arm)}
        if not side or any(np.isnan(u).any() for u in side.values()):
            return None
        return side


def load_plan_rig(directory: str | Path) -> Rig:
    """The rig to plan for: :func:`~bayesrob.data.rig.load_rig`, but a rig with no
    ``measurements.csv`` yet, or one with a header only, loads with no rows."""
    directory = Path(directory)
    if not directory.is_dir():
        raise RigError(f"{directory}: rig directory not found")
    path = directory / MEASUREMENTS_FILE
    if path.is_file() and any(line.strip(" ,\r\n") for line in
                              path.read_text(encoding="utf-8-sig").splitlines()[1:]):
        return load_rig(directory, min_train_rows=0)
    meta = load_rig_toml(directory / RIG_FILE)
    chains = meta.pop("chains")
    dim = len(meta["gravity"])  # 2 for planar arms, 3 for URDF/DH chains
    robot = Robot(chains, dim)
    empty = Measurements(np.array([], str), np.array([], str), np.zeros((0, dim)),
                         {c: np.zeros((0, ch.n_columns)) for c, ch in chains.items()},
                         np.zeros((0, dim)), np.zeros(0, int))
    return Rig(measurements=empty, path=directory, robot=robot, **meta)


def command_limits(rig: Rig) -> dict[str, np.ndarray | None]:
    """Per chain, its columns' (lo, hi) limits (m, 2) in command units, or None unknown."""
    raw: dict = {}
    if rig.path is not None and (rig.path / RIG_FILE).is_file():
        raw = tomllib.loads((rig.path / RIG_FILE).read_text(encoding="utf-8-sig")).get(
            "arms", {})
    out: dict[str, np.ndarray | None] = {}
    for name, chain in rig.robot.chains.items():
        table = raw.get(name, {}) if isinstance(raw.get(name), dict) else {}
        spec = rig.arms.get(name)
        if "limits" in table:
            out[name] = _toml_limits(table["limits"], chain, f"{rig.path / RIG_FILE}: "
                                     f"arms.{name}.limits")
        elif hasattr(spec, "pulse_limits"):
            out[name] = np.asarray(spec.pulse_limits, float)
        else:
            out[name] = _urdf_limits(chain)
    return out


def _toml_limits(value: object, chain: Chain, where: str) -> np.ndarray:
    m = chain.n_columns
    try:
        lim = np.asarray(value, float)
    except (TypeError, ValueError):
        lim = np.zeros(0)
    if lim.shape != (m, 2) or not np.all(np.isfinite(lim)) or np.any(lim[:, 0] >= lim[:, 1]):
        raise RigError(f"{where}: expected {m} pairs [lo, hi] with lo < hi (command units), "
                       f"got {value!r}")
    return lim


def _urdf_limits(chain: Chain) -> np.ndarray | None:
    """A URDF chain's <limit lower upper> in command units, where every actuated joint has
    them and each column drives one joint (identity coupling); else None."""
    src = chain.source
    if src.get("kind") != "urdf" or not np.allclose(chain.coupling, np.eye(chain.n_joints)):
        return None
    text = src.get("text") or Path(src["path"]).read_text()
    joints = {j.get("name"): j for j in ET.fromstring(text).iter("joint")}
    lim = []
    for name, kind, gain, offset in zip(chain.joint_names, chain.kinds, chain.gain,
                                        chain.offset, strict=True):
        el = joints[name].find("limit")
        if el is None or el.get("lower") is None or el.get("upper") is None:
            return None
        scale = M_TO_MM if kind == "prismatic" else 1.0
        q = np.array([float(el.get("lower")), float(el.get("upper"))]) * scale
        lim.append(np.sort((q - offset) / gain))
    return np.array(lim)


def read_text(path: Path, what: str) -> str:
    try:
        return path.read_text(encoding="utf-8-sig")
    except OSError as exc:
        raise RigError(f"{path}: cannot read the {what} file: {exc.strerror}") from None


def read_pool(path: str | Path, rig: Rig, limits: dict[str, np.ndarray | None],
              what: str = "pool", text: str | None = None) -> Pool:
    """A pool (or task) file checked against the rig: its command columns, config, numbers
    and limits."""
    path = Path(path)
    text = read_text(path, what) if text is None else text
    rows = [r for r in csv.reader(io.StringIO(text, newline=""))]
    if not rows:
        raise RigError(f"{path}: empty {what} file (a header row is required)")
    header = [h.strip() for h in rows[0]]
    robot = rig.robot
    measured = robot.measured_arms()
    if len(measured) > 1 and "config" not in header:
        raise RigError(f"{path}: missing column 'config' (the rig measures "
                       f"{', '.join(measured)}: each row names its arm)")
    idx = {h: i for i, h in enumerate(header)}
    body = [(k + 2, r) for k, r in enumerate(rows[1:]) if any(c.strip() for c in r)]
    if not body:
        raise RigError(f"{path}: no rows in the {what} file")
    for line, row in body:
        if len(row) != len(header):
            raise RigError(f"{path}: line {line}: expected {len(header)} fields, found "
                           f"{len(row)}")
    lines = [line for line, _ in body]
    config = (np.array([r[idx["config"]].strip() for _, r in body]) if "config" in idx
              else np.full(len(body), measured[0]))
    for line, arm in zip(lines, config.tolist(), strict=True):
        if arm not in measured:
            raise RigError(f"{path}: line {line}: column 'config' = {arm!r} is not a measured "
                           f"arm of the rig ({', '.join(measured)})")
    # column by column (pools of thousands of rows); parse_number names a bad cell row by row
    commands = {c: np.full((len(body), ch.n_columns), np.nan) for c, ch in robot.chains.items()}
    for c, ch in robot.chains.items():
        on = np.isin(config, [a for a in measured if c in {x.name for x in robot.path(a)}])
        for k in range(ch.n_columns):
            col = f"{c}_u{k + 1}"
            if col not in idx:
                if on.any():
                    raise RigError(f"{path}: missing column {col!r} (the commands of arm "
                                   f"{str(config[on][0])!r})")
                continue
            cells = [r[idx[col]].strip() for _, r in body]
            filled = np.array([v != "" for v in cells])
            try:
                values = np.array([float(v) if v else np.nan for v in cells])
            except ValueError:
                values = np.full(len(cells), np.inf)
            if (on & ~filled).any() or not np.isfinite(values[filled]).all():
                for line, v, need in zip(lines, cells, on, strict=True):
                    parse_number(v, f"{path}: line {line}", col, allow_empty=not need)
            commands[c][:, k] = values
        lim = limits.get(c)
        if lim is not None:
            u = commands[c]
            bad = (u < lim[:, 0]) | (u > lim[:, 1])
            if bad.any():
                r, k = (int(v[0]) for v in np.nonzero(bad))
                raise RigError(f"{path}: line {lines[r]}: column '{c}_u{k + 1}' = {u[r, k]:g} "
                               f"is outside arm {c!r}'s limits [{lim[k, 0]:g}, {lim[k, 1]:g}]")
    return Pool(config.astype(str), commands, header, [list(r) for _, r in body], str(path))


def sample_pool(rig: Rig, limits: dict[str, np.ndarray | None], m: int,
                rng: np.random.Generator) -> Pool:
    """``m`` poses drawn uniformly inside the limits, measured arms in turn; planar arms with a
    ``workspace`` are aimed at points drawn in it instead (most of a servo's range points
    outside the workspace)."""
    robot = rig.robot
    measured = robot.measured_arms()
    config = np.array([measured[i % len(measured)] for i in range(m)])
    if rig.workspace is not None and not rig.is_chain:
        commands = {a: np.full((m, 2), np.nan) for a in robot.chains}
        for a in measured:
            rows = np.flatnonzero(config == a)
            commands[a][rows] = _aimed_samples(rig, a, len(rows), rng)
    else:
        for c, lim in limits.items():
            if lim is None:
                raise RigError(f"arm {c!r} has no joint limits (rig.toml arms.{c}.limits in "
                               "command units, or a URDF <limit lower upper> on every joint): "
                               "give a pool of safe poses with --pool")
        commands = {c: rng.uniform(lim[:, 0], lim[:, 1], size=(m, len(lim)))
                    for c, lim in limits.items()}
        for a in measured:
            # a row carries its arm's path and the arms whose weight bends it, nothing else
            own = {c.name for c in robot.path(a)}
            used = own | {c.name for b in robot.side_arms(a) if own & {c.name for c in
                          robot.path(b)} for c in robot.path(b)}
            for c in set(robot.chains) - used:
                commands[c][config == a] = np.nan
    cols = [f"{c}_u{k + 1}" for c, ch in robot.chains.items() for k in range(ch.n_columns)]
    header = (["config"] if len(measured) > 1 else []) + cols
    cells = [([str(config[i])] if len(measured) > 1 else [])
             + [_num(commands[c][i, k]) for c, ch in robot.chains.items()
                for k in range(ch.n_columns)] for i in range(m)]
    return Pool(config, commands, header, cells, f"{m} samples")


def _aimed_samples(rig: Rig, arm: str, n: int, rng: np.random.Generator) -> np.ndarray:
    """Pulses (n, 2) aiming planar ``arm``'s nominal model at points drawn in the workspace."""
    import jax.numpy as jnp

    from bayesrob.robot import Arm

    model = Arm.nominal(rig.arms[arm])
    ws = np.asarray(rig.workspace)
    lim = np.asarray(model.pulse_limits)
    out = np.zeros((0, 2))
    for _ in range(50):
        d = rng.uniform(ws[:, 0], ws[:, 1], size=(max(n, 16), 2))
        ok = np.asarray(model.reachable(jnp.asarray(d)))
        u = np.asarray(model.command(jnp.asarray(d[ok])))
        u = u[np.all((u >= lim[:, 0]) & (u <= lim[:, 1]), axis=1)]
        out = np.vstack([out, u])
        if len(out) >= n:
            return out[:n]
    raise RigError(f"arm {arm!r}: too few points of the workspace are reachable within its "
                   "pulse_limits to draw a pool: give one with --pool")


def _num(v: float) -> str:
    return "" if math.isnan(v) else f"{v:.10g}"
