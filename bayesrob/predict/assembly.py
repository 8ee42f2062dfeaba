"""The accuracy of an assembly predicted before it is built (``bayesrob predict``).

An assembly is one arm or several linked at their end point (``top+bottom+side``), predicted
from the modules' single-arm ``train`` rows alone (a rig without any linked row works: that is
the point) as draws of the end point at each target (:mod:`.draws`), fused by a rule
(:mod:`.fusion`). Per target: the expected end point and distance from the target, and the
areas (volumes in 3-D) of the 50% / 90% regions of the draws' KDE (:mod:`.regions`).
"""

from __future__ import annotations

import csv
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from bayesrob import robot as kin
from bayesrob.data.rig import Rig, RigError
from bayesrob.errors.latent_errors import LATENT_MODELS
from bayesrob.errors.noise_models import joint_errors_observed
from bayesrob.predict.draws import fit_modules, fit_paper_modules
from bayesrob.predict.fusion import DEFAULT_FUSION, DRAWS, FUSIONS
from bayesrob.predict.regions import hdr_sizes
from bayesrob.predict.stiffness import STIFFNESS_SOURCES

__all__ = ["AssemblyPrediction", "predict_assembly", "grid_targets", "read_targets",
           "beyond_train_range", "stiffness_note"]


@dataclass
class AssemblyPrediction:
    """Predicted accuracy of one assembly at its targets."""

    rig: str
    config: str
    model: str
    fusion: str
    targets: np.ndarray  # (T, dim) mm
    commands: dict[str, np.ndarray]  # arm -> (T, c) pulses or chain columns
    expected_point: np.ndarray  # (T, dim)
    expected_error_mm: np.ndarray  # (T,)
    hdr50: np.ndarray  # (T,) area (mm^2) or, in 3-D, volume (mm^3) of the 50% region
    hdr90: np.ndarray  # (T,)
    seconds: float
    draws: np.ndarray  # (S, T, dim): the draws the prediction is
    # arm -> (T, c): how far each target's commands lie beyond that arm's train range, per
    # column (0 inside), set with the two fields after it by :func:`_with_command_ranges`
    beyond_train: dict[str, np.ndarray] = field(default_factory=dict)
    columns: dict[str, list[str]] = field(default_factory=dict)  # arm -> its command columns
    command_unit: str = " us"  # of the command columns in the note ("" for joint values)
    # linked chain arms under equilibrium fusion: arm -> StiffnessPrior.record()
    stiffness: dict[str, dict] = field(default_factory=dict)
    stiffness_note: str | None = None

    @property
    def size_key(self) -> str:
        """Unit of the region sizes: ``mm2`` (areas) or ``mm3`` (volumes)."""
        return f"mm{self.targets.shape[1]}"

    def to_dict(self) -> dict:
        """The ``bayesrob predict --json`` document."""
        e = self.expected_error_mm
        u = self.size_key
        return {
            "rig": self.rig, "config": self.config, "model": self.model, "fusion": self.fusion,
            "rows_used": "train rows of each arm alone (no linked row is read)",
            "targets": [
                {"target": [float(x) for x in t],
                 "commands": {a: [float(v) for v in u[i]] for a, u in self.commands.items()},
                 "expected_point": [float(x) for x in self.expected_point[i]],
                 "expected_error_mm": float(e[i]),
                 f"hdr50_{u}": float(self.hdr50[i]), f"hdr90_{u}": float(self.hdr90[i]),
                 "beyond_train_range": {a: [float(v) for v in b[i]]
                                        for a, b in self.beyond_train.items()}}
                for i, t in enumerate(self.targets)],
            "summary": {"n_targets": int(e.size), "mean_expected_error_mm": float(e.mean()),
                        "max_expected_error_mm": float(e.max()),
                        f"mean_hdr50_{u}": float(self.hdr50.mean()),
                        f"mean_hdr90_{u}": float(self.hdr90.mean()),
                        "targets_beyond_train_range": int(self.extrapolated.sum())},
            **({"stiffness": self.stiffness} if self.stiffness else {}),
            "seconds": self.seconds,
        }

    document = property(to_dict)

    @property
    def extrapolated(self) -> np.ndarray:
        """(T,) True where some arm's commands leave the range of its train rows."""
        out = np.zeros(len(self.targets), bool)
        for b in self.beyond_train.values():
            out |= np.any(b > 0, axis=1)
        return out

    def extrapolation_note(self) -> str | None:
        """One line on the targets whose commands leave an arm's calibrated range, or None:
        there a misfit the train rows did not show can grow (docs/fusion.md)."""
        n = int(self.extrapolated.sum())
        if not n:
            return None
        parts = []
        for a, b in self.beyond_train.items():
            hit = np.any(b > 0, axis=1)
            if hit.any():
                col = int(np.argmax(b.max(axis=0)))
                parts.append(f"{a} at {int(hit.sum())}, by up to {b.max():.3g}"
                             f"{self.command_unit} in {self.columns[a][col]}")
        return (f"note: {n} of {len(self.targets)} targets need commands beyond the range of "
                f"the train rows ({'; '.join(parts)}): the calibration extrapolates there, and "
                "the prediction may be too narrow")


def grid_targets(rig: Rig, n: int) -> np.ndarray:
    """n^dim targets over the rig's workspace (cell centres, x fastest)."""
    if rig.workspace is None:
        raise RigError(f"{rig.path}: no 'workspace' in rig.toml to lay a --grid over; give "
                       "--targets FILE instead")
    axes = [lo + (hi - lo) * (np.arange(n) + 0.5) / n for lo, hi in rig.workspace]
    mesh = np.meshgrid(*axes[::-1], indexing="ij")  # last axis x: x runs fastest
    return np.column_stack([m.ravel() for m in mesh[::-1]])


def read_targets(path: str | Path, dim: int = 2) -> np.ndarray:
    """Targets (T, dim) from a CSV file with columns ``x,y`` (and ``z`` in 3-D; mm)."""
    path = Path(path)
    if not path.is_file():
        raise RigError(f"{path}: file not found")
    names = list("xyz"[:dim])
    with path.open(newline="", encoding="utf-8-sig") as fh:
        reader = csv.DictReader(fh)
        if not reader.fieldnames or not set(names) <= set(reader.fieldnames):
            raise RigError(f"{path}: needs a header with columns {','.join(names)}, got "
                           f"{reader.fieldnames}")
        if dim == 2 and "z" in reader.fieldnames:
            raise RigError(f"{path}: column z: this rig's arms are planar (x, y); a 3-D "
                           "target cannot be reached or predicted here")
        out = []
        for i, row in enumerate(reader, start=2):
            try:
                xy = [float(row[c]) for c in names]
            except (TypeError, ValueError):
                raise RigError(f"{path}: line {i}: {', '.join(names)} must be numbers, got "
                               f"{', '.join(repr(row.get(c)) for c in names)}") from None
            if not np.all(np.isfinite(xy)):
                raise RigError(f"{path}: line {i}: {', '.join(names)} must be finite, got {xy}")
            out.append(xy)
    if not out:
        raise RigError(f"{path}: no targets")
    return np.asarray(out, float)


def beyond_train_range(rig: Rig, arm: str, commands: np.ndarray) -> np.ndarray:
    """(T, c): how far each row of ``commands`` lies beyond ``arm``'s train range, per column."""
    u = rig.rows(arm, "train")[0]
    lo, hi = u.min(axis=0), u.max(axis=0)
    c = np.asarray(commands, float)
    return np.maximum(lo - c, 0.0) + np.maximum(c - hi, 0.0)


def _with_command_ranges(pred: AssemblyPrediction, rig: Rig) -> AssemblyPrediction:
    return replace(pred, beyond_train={a: beyond_train_range(rig, a, u)
                                       for a, u in pred.commands.items()},
                   columns={a: rig.robot.columns(a) for a in pred.commands},
                   # servo-driven arms are commanded in pulse widths, joints in their values
                   command_unit=" us" if all(getattr(rig.arms[a], "pulse_limits", None)
                                             is not None for a in pred.commands) else "")


def predict_assembly(rig: Rig, config: str, targets: np.ndarray, model: str | None = None,
                     fusion: str = DEFAULT_FUSION, models_dir: Any = None, seed: int = 0,
                     groups: tuple[str, ...] | None = None, masses: str = "fitted"
                     ) -> AssemblyPrediction:
    """Predict ``config`` (arms joined by '+') at ``targets`` (T, dim) from single-arm rows.

    ``model``: default ``cond`` where the rows observe the joint errors, else ``ind``.
    ``groups``: the calibration groups (default ``GROUPS``); given for a planar rig, its arms
    are predicted as 2-joint chains through their fitted physics. ``masses``: "fitted" or
    "description" (then sagging arms' stiffnesses come from their fitted compliances).
    """
    t0 = time.perf_counter()
    if fusion not in FUSIONS:
        raise RigError(f"unknown fusion {fusion!r}; choose from {', '.join(FUSIONS)}")
    members = config.split("+")
    unknown = [a for a in members if a not in rig.arms]
    if unknown or len(set(members)) != len(members):
        raise RigError(f"config {config!r}: " + (f"no arm {unknown[0]!r} in the rig (arms: "
                       f"{', '.join(rig.arms)})" if unknown else "an arm appears twice"))
    for a in members:
        if not rig.measurements.mask(a, "train").any():
            raise RigError(f"{rig.path}: arm {a!r} has no train rows of its own to calibrate "
                           "and fit its joint-error model on")
    targets = np.atleast_2d(np.asarray(targets, float))
    dim = rig.robot.dim
    if targets.shape[1] != dim:
        raise RigError(f"{rig.path}: the rig measures {dim}-D points but the targets have "
                       f"{targets.shape[1]} coordinates")
    # The one choice between joint-error models: a Parzen density of the joint errors where
    # the rows observe them (as many joints as measured coordinates), else the latent
    # population; calibration ``groups`` asked for take the population on every robot (the
    # physics-fitted prediction of planar arms is measured so). The paper's planar arms take
    # their closed-form specialisation (eight parameters, closed-form inverse, exact grid).
    kernel = groups is None and joint_errors_observed(rig.robot, members)
    paper = kernel and not rig.is_chain
    if masses != "fitted" and not rig.is_chain:
        raise RigError(f"{rig.path}: planar arms have no link masses to hold (masses "
                       f"{masses!r} is for URDF rigs)")
    model = model or ("cond" if kernel else LATENT_MODELS[0])
    try:
        mods = (fit_paper_modules(rig, members, model, models_dir, targets) if paper
                else fit_modules(rig, members, model, groups or kin.GROUPS, seed=seed,
                                 masses=masses, targets=targets, models_dir=models_dir,
                                 latent=not kernel, linked=len(members) > 1))
    except RigError:
        raise
    except ValueError as e:
        if paper:
            raise
        raise RigError(f"{rig.path}: {e}") from None
    commands = mods.commands
    draws = mods.draws(members, [commands[a] for a in members], targets, fusion, DRAWS, seed)
    sizes = hdr_sizes(draws)
    pred = AssemblyPrediction(
        rig.name, config, model, fusion, targets, commands, draws.mean(axis=0),
        np.linalg.norm(draws - targets[None], axis=-1).mean(axis=0), sizes[0], sizes[1],
        time.perf_counter() - t0, draws)
    priors = getattr(mods, "stiffness", None)
    if fusion == "equilibrium" and len(members) > 1 and isinstance(priors, dict):
        pred.stiffness = {a: priors[a].record() for a in members}
        pred.stiffness_note = stiffness_note(rig.robot, {a: priors[a].source for a in members})
    return _with_command_ranges(pred, rig)


def stiffness_note(robot: kin.Robot, sources: dict[str, str]) -> str | None:
    """``predict``'s note where linked arms took their stiffnesses from the prior (``sources``:
    arm -> one of STIFFNESS_SOURCES) though every chain weighs its links: how to read them
    from those masses instead."""
    guessed = [a for a, src in sources.items() if src in STIFFNESS_SOURCES[2:]]
    if not guessed or not all(c.weighed for c in robot.chains.values()):
        return None
    return (f"note: the description weighs every link, yet {', '.join(guessed)} took "
            "their stiffnesses from the prior: add compliance to --params and give "
            "--masses description to read them from compliances fitted under those masses "
            "(each joint's own, where the prior gives the arms' profile; on the simulated "
            "report rigs that route met every coverage target: docs/fusion.md)")
