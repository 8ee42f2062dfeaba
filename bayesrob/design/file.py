"""The design file (``bayesrob design DESIGN.toml``, docs/design.md), read and checked in full
apart from the search, so a mistake in it is one line before the numerical stack is imported.
"""

from __future__ import annotations

import itertools
import math
import tomllib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from bayesrob.data.vocabulary import ALL_GROUPS, DEFAULT_FUSION, FUSIONS, MASS_SOURCES

__all__ = ["DesignError", "DesignSpec", "ModuleSpec", "load_design", "DRAWS", "DEFAULT_MODEL"]

DRAWS = 2000  # per candidate: the 0.95 quantile over 16 targets pools 32,000 draws
DEFAULT_MODEL = "ind"  # holds its linked coverage with equilibrium fusion (docs/fusion.md)
TOP_KEYS = ("fusion", "seed", "draws", "tracker_noise_mm", "modules", "mounts", "task",
            "requirement", "limits")


class DesignError(ValueError):
    """A design file, a module or the search itself is unusable; the message is one line."""


@dataclass(frozen=True)
class ModuleSpec:
    """One module of the inventory: arm ``arm`` of the rig directory ``rig``."""

    name: str
    rig: Path
    arm: str
    model: str = DEFAULT_MODEL
    # a chain module's calibration groups (None: the chain default; a planar module: refused)
    params: tuple[str, ...] | None = None
    # a chain module's link masses with a compliance group: "fitted", or held at its URDF's
    # ("description"), so that its fitted compliances give its joint stiffnesses
    masses: str = "fitted"


@dataclass(frozen=True)
class DesignSpec:
    """A parsed design file."""

    path: Path
    modules: dict[str, ModuleSpec]
    mounts: np.ndarray  # (P, dim) mm
    # (V, 2) polygon vertices, counter-clockwise or not (a box: 4 corners); in 3-D the
    # box's 8 corners
    region: np.ndarray
    n_targets: int
    error_mm: float
    quantile: float
    confidence: float = 0.9
    max_arms: int = 3
    min_arms: int = 1
    linked: bool = True
    fusion: str = DEFAULT_FUSION
    seed: int = 0
    draws: int = DRAWS
    tracker_noise_mm: float = 0.0

    @property
    def requirement(self) -> dict:
        return {"error_mm": self.error_mm, "quantile": self.quantile,
                "confidence": self.confidence}

    @property
    def dim(self) -> int:
        return int(self.mounts.shape[1])


def _table(doc: dict, key: str, where: str) -> dict:
    value = doc.get(key)
    if not isinstance(value, dict):
        raise DesignError(f"{where}: needs a [{key}] table")
    return value


def _unknown(table: dict, known: Sequence[str], where: str) -> None:
    for k in table:
        if k not in known:
            raise DesignError(f"{where}: unknown key {k!r} (known: {', '.join(known)})")


def _points(value: Any, where: str, min_rows: int = 1, dims: tuple[int, ...] = (2,)
            ) -> np.ndarray:
    try:
        arr = np.asarray(value, float)
    except (TypeError, ValueError):
        arr = np.zeros((0, 0))
    if (arr.ndim != 2 or arr.shape[1] not in dims or len(arr) < min_rows
            or not np.isfinite(arr).all()):
        what = " or ".join("[x, y]" if d == 2 else "[x, y, z]" for d in dims)
        raise DesignError(f"{where}: expected a list of at least {min_rows} {what} points in "
                          f"mm, got {value!r}")
    return arr


def _number(table: dict, key: str, where: str, kind: type = float, default: Any = None,
            lo: float | None = None, hi: float | None = None) -> Any:
    if key not in table:
        if default is None:
            raise DesignError(f"{where}: missing {key!r}")
        return default
    v = table[key]
    ok = isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
    if kind is int:
        ok = ok and float(v).is_integer()
    if not ok or (lo is not None and v <= lo) or (hi is not None and v >= hi):
        bounds = (f" (must be above {lo:g}" + (f" and below {hi:g})" if hi is not None else ")")
                  if lo is not None else "")
        what = "an integer" if kind is int else "a number"
        raise DesignError(f"{where}: {key} = {v!r} must be {what}{bounds}")
    return kind(v)


def _mount_grid(grid: Any, where: str) -> np.ndarray:
    if not isinstance(grid, dict) or set(grid) not in ({"x", "y"}, {"x", "y", "z"}):
        raise DesignError(f"{where}: grid must be {{ x = [lo, hi, n], y = [lo, hi, n] }} "
                          "(and z = [lo, hi, n] in 3-D)")
    axes = []
    for k in sorted(grid):
        v = grid[k]
        if (not isinstance(v, list) or len(v) != 3 or not all(isinstance(t, int | float)
                                                               for t in v)
                or not float(v[2]).is_integer() or v[2] < 1):
            raise DesignError(f"{where}: grid.{k} must be [lo, hi, n] with n a positive "
                              f"integer, got {v!r}")
        axes.append(np.linspace(float(v[0]), float(v[1]), int(v[2])))
    # x runs fastest, then y (then z)
    return np.array([p[::-1] for p in itertools.product(*axes[::-1])])


def load_design(path: str | Path) -> DesignSpec:
    """Parse and check a design file; every problem is one :class:`DesignError` line."""
    path = Path(path)
    if not path.is_file():
        raise DesignError(f"{path}: design file not found")
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise DesignError(f"{path}: not valid TOML ({e})") from None
    _unknown(doc, TOP_KEYS, str(path))
    fusion = doc.get("fusion", DEFAULT_FUSION)
    if fusion not in FUSIONS:
        raise DesignError(f"{path}: fusion = {fusion!r}; choose from {', '.join(FUSIONS)}")
    mods = _table(doc, "modules", str(path))
    if not mods:
        raise DesignError(f"{path}: [modules] names no module")
    modules = {}
    for name, t in mods.items():
        where = f"{path}: [modules.{name}]"
        if not isinstance(t, dict):
            raise DesignError(f"{where}: must be a table with rig, arm, model")
        _unknown(t, ("rig", "arm", "model", "params", "masses"), where)
        masses = t.get("masses", MASS_SOURCES[0])
        if masses not in MASS_SOURCES:
            raise DesignError(f"{where}: masses = {masses!r} must be "
                              + " or ".join(f'"{m}"' for m in MASS_SOURCES))
        if not isinstance(t.get("rig"), str):
            raise DesignError(f"{where}: needs rig = \"DIR\" (a rig directory)")
        rig = (path.parent / t["rig"]).resolve()
        modules[name] = ModuleSpec(name, rig, str(t.get("arm", name)),
                                   str(t.get("model", DEFAULT_MODEL)),
                                   _groups(t["params"], where) if "params" in t else None,
                                   masses)
    mt = _table(doc, "mounts", str(path))
    _unknown(mt, ("points", "grid"), f"{path}: [mounts]")
    if ("points" in mt) == ("grid" in mt):
        raise DesignError(f"{path}: [mounts] needs exactly one of points or grid")
    mounts = (_points(mt["points"], f"{path}: [mounts] points", dims=(2, 3)) if "points" in mt
              else _mount_grid(mt["grid"], f"{path}: [mounts] grid"))
    task = _table(doc, "task", str(path))
    _unknown(task, ("box", "polygon", "targets"), f"{path}: [task]")
    if ("box" in task) == ("polygon" in task):
        raise DesignError(f"{path}: [task] needs exactly one of box or polygon")
    dim = mounts.shape[1]
    if "box" in task:
        region = _box(task["box"], dim, f"{path}: [task] box")
    elif dim == 3:
        raise DesignError(f"{path}: [task] polygon is a region of the plane but the mounts are "
                          "3-D points; give box = [[x0, x1], [y0, y1], [z0, z1]]")
    else:
        region = _points(task["polygon"], f"{path}: [task] polygon", 3)
    req = _table(doc, "requirement", str(path))
    _unknown(req, ("error_mm", "quantile", "confidence"), f"{path}: [requirement]")
    lim = doc.get("limits", {})
    _unknown(lim, ("max_arms", "min_arms", "linked"), f"{path}: [limits]")
    linked = lim.get("linked", True)
    if not isinstance(linked, bool):
        raise DesignError(f"{path}: [limits] linked must be true or false, got {linked!r}")
    max_arms = _number(lim, "max_arms", f"{path}: [limits]", int, 3, lo=0)
    min_arms = _number(lim, "min_arms", f"{path}: [limits]", int, 1, lo=0)
    if min_arms > (max_arms if linked else 1):
        # no assembly has that many arms: the search would run and rank nothing
        raise DesignError(f"{path}: [limits] min_arms = {min_arms} is more than "
                          + (f"max_arms = {max_arms}" if linked else
                             "1, the most arms an assembly has with linked = false"))
    return DesignSpec(
        path=path, modules=modules, mounts=mounts, region=region,
        n_targets=_number(task, "targets", f"{path}: [task]", int, 16, lo=0),
        error_mm=_number(req, "error_mm", f"{path}: [requirement]", lo=0),
        quantile=_number(req, "quantile", f"{path}: [requirement]", lo=0, hi=1),
        confidence=_number(req, "confidence", f"{path}: [requirement]", float, 0.9, lo=0, hi=1),
        max_arms=max_arms, min_arms=min_arms,
        linked=linked, fusion=fusion,
        seed=_number(doc, "seed", str(path), int, 0, lo=-1),
        draws=_number(doc, "draws", str(path), int, DRAWS, lo=99),
        tracker_noise_mm=_tracker_noise(doc, str(path)))


def _groups(value: Any, where: str) -> tuple[str, ...]:
    names = value.split(",") if isinstance(value, str) else value
    if not isinstance(names, list | tuple) or not names or not all(
            isinstance(n, str) and n.strip() in ALL_GROUPS for n in names):
        raise DesignError(f"{where}: params = {value!r} must name calibration groups among "
                          f"{', '.join(ALL_GROUPS)}")
    return tuple(dict.fromkeys(["frames", *(n.strip() for n in names)]))


def _box(value: Any, dim: int, where: str) -> np.ndarray:
    # a task box's corners: (4, 2) counter-clockwise in the plane, (8, 3) in space
    shape = "[[x0, x1], [y0, y1]]" if dim == 2 else "[[x0, x1], [y0, y1], [z0, z1]]"
    try:
        box = np.asarray(value, float)
    except (TypeError, ValueError):
        box = np.zeros((0, 0))
    if box.shape != (dim, 2) or not np.isfinite(box).all() or not (box[:, 0] < box[:, 1]).all():
        raise DesignError(f"{where} must be {shape} with each low below its high (the mounts "
                          f"are {dim}-D), got {value!r}")
    if dim == 2:
        (x0, x1), (y0, y1) = box
        return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
    return np.array([[box[0, i], box[1, j], box[2, k]]
                     for k in range(2) for j in range(2) for i in range(2)])


def _tracker_noise(doc: dict, where: str) -> float:
    v = _number(doc, "tracker_noise_mm", where, float, 0.0)
    if v < 0:  # zero is allowed (no tracker noise known), a negative sd is a typo
        raise DesignError(f"{where}: tracker_noise_mm = {v!r} must be 0 or more")
    return v
