"""A study of the validation suite: its targets file, and the check of its figures.

Each study is a function ``run(seeds, *, quick, say) -> dict`` in a module of this package and a
targets file ``targets/<name>.toml`` beside it, committed before the study's report seeds
first ran. The targets file says which seeds are tuning seeds (choices were made on them;
never reported), which are report seeds (run after the targets were fixed), which few a
``--quick`` run uses, and each figure's target range::

    title = "linked coverage of two planar arms"
    module = "linked_planar"          # validation/linked_planar.py
    function = "run"                  # optional, default "run"
    fixed = "targets of issue 13, committed before seeds 601-606 first ran (26cfebc)"

    [seeds]
    tuning = [101, 102]
    report = [601, 602, 603]
    quick = [601]

    [figures."ind.coverage50"]
    min = 0.40
    max = 0.60
    why = "a 50% region within binomial error of nominal at 96 points"

    [figures."ind.strong_right"]
    min = 0.9
    known_miss = "10 of 13: the tilted plane's play is too weak to be seen"

A figure with neither ``min`` nor ``max`` is measured and recorded only. A figure with
``known_miss`` is a target the project has not met yet: a miss is reported as known (the run
still passes), and meeting it is reported as news ("met, was a known miss") so the file is
updated. A ``--quick`` run checks that the figures it produces are finite (a study may leave
its costly part out: those are "not run"), and only the ranges given as ``quick_min`` /
``quick_max`` (a study on one or two seeds cannot hold
targets set for its report seeds).

The function returns its figures by name (numbers), and may add ``"details"``: anything
JSON can hold (per-rig rows, a confusion matrix) for the report and the docs' tables.
"""

from __future__ import annotations

import importlib
import math
import tomllib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

TARGETS_DIR = Path(__file__).resolve().parent / "targets"


def repository() -> Path:
    """The repository whose files a study reads (``examples/``, ``../shared/data``): the one
    this package lies in, else the current directory, as when an installed copy is run from a
    checkout (CI runs ``bayesrob validate`` so)."""
    for root in (Path(__file__).resolve().parents[1], Path.cwd()):
        if (root / "examples").is_dir() and (root / "pyproject.toml").is_file():
            return root
    return Path.cwd()


# The outcome of one figure against its target.
PASS, FAIL, KNOWN_MISS, NEWLY_MET = "pass", "fail", "known miss", "met, was a known miss"
RECORDED, NOT_JUDGED, NOT_RUN = "recorded", "not judged (quick)", "not run (quick)"


class StudyError(ValueError):
    """A targets file is malformed, or a study did not produce what its file promises."""


@dataclass(frozen=True)
class Target:
    name: str
    min: float | None = None
    max: float | None = None
    quick_min: float | None = None
    quick_max: float | None = None
    why: str = ""
    known_miss: str = ""

    def check(self, value: Any, quick: bool) -> str:
        if value is None and quick:
            return NOT_RUN  # a quick run may leave out the costly part of a study
        if not isinstance(value, int | float) or not math.isfinite(value):
            return FAIL
        low, high = (self.quick_min, self.quick_max) if quick else (self.min, self.max)
        if low is None and high is None:
            return NOT_JUDGED if quick and (self.min, self.max) != (None, None) else RECORDED
        inside = (low is None or value >= low) and (high is None or value <= high)
        if quick:
            return PASS if inside else FAIL
        if self.known_miss:
            return NEWLY_MET if inside else KNOWN_MISS
        return PASS if inside else FAIL

    def range_text(self) -> str:
        if self.min is not None and self.max is not None:
            return f"{self.min:g} to {self.max:g}"
        if self.min is not None:
            return f">= {self.min:g}"
        if self.max is not None:
            return f"<= {self.max:g}"
        return "recorded"


@dataclass(frozen=True)
class Study:
    name: str
    title: str
    module: str
    function: str
    fixed: str
    tuning_seeds: tuple[int, ...]
    report_seeds: tuple[int, ...]
    quick_seeds: tuple[int, ...]
    targets: tuple[Target, ...] = field(default=())
    path: Path | None = None

    def seeds(self, quick: bool) -> tuple[int, ...]:
        return self.quick_seeds if quick else self.report_seeds

    def runner(self) -> Callable[..., dict]:
        module = importlib.import_module(f"bayesrob.validation.{self.module}")
        try:
            return getattr(module, self.function)
        except AttributeError:
            raise StudyError(f"{self.path}: module {self.module} has no function "
                             f"{self.function!r}") from None

    def check(self, figures: dict[str, Any], quick: bool) -> dict[str, str]:
        """Each target's outcome; a promised figure the study did not produce fails."""
        return {t.name: t.check(figures.get(t.name), quick) for t in self.targets}


_NUMBER_KEYS = ("min", "max", "quick_min", "quick_max")


def _seeds(doc: dict, key: str, path: Path) -> tuple[int, ...]:
    value = doc.get(key, [])
    if not isinstance(value, list) or not all(isinstance(s, int) for s in value):
        raise StudyError(f"{path}: seeds.{key} must be a list of integers, not {value!r}")
    return tuple(value)


def load_study(path: Path) -> Study:
    """Read one targets file; a wrong key or value is a one-line error naming it."""
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise StudyError(f"{path}: {exc}") from None
    for key in ("title", "module", "fixed"):
        if not isinstance(doc.get(key), str) or not doc[key].strip():
            raise StudyError(f"{path}: '{key}' must be a non-empty string")
    seeds = doc.get("seeds", {})
    report = _seeds(seeds, "report", path)
    tuning = _seeds(seeds, "tuning", path)
    quick = _seeds(seeds, "quick", path)
    if set(tuning) & set(report):
        raise StudyError(f"{path}: seeds {sorted(set(tuning) & set(report))} are both tuning "
                         "and report seeds")
    if set(quick) & set(tuning):
        raise StudyError(f"{path}: quick seeds {sorted(set(quick) & set(tuning))} are tuning "
                         "seeds")
    targets = []
    for name, spec in doc.get("figures", {}).items():
        if not isinstance(spec, dict):
            raise StudyError(f"{path}: figures.{name} must be a table")
        unknown = set(spec) - {*_NUMBER_KEYS, "why", "known_miss"}
        if unknown:
            raise StudyError(f"{path}: figures.{name} has unknown key(s) {sorted(unknown)}")
        for key in _NUMBER_KEYS:
            if key in spec and not isinstance(spec[key], int | float):
                raise StudyError(f"{path}: figures.{name}.{key} must be a number")
        targets.append(Target(name, **{k: spec[k] for k in spec}))
    return Study(name=path.stem, title=doc["title"], module=doc["module"],
                 function=doc.get("function", "run"), fixed=doc["fixed"], tuning_seeds=tuning,
                 report_seeds=report, quick_seeds=quick, targets=tuple(targets), path=path)


def discover_studies(names: list[str] | None = None,
                     directory: Path = TARGETS_DIR) -> list[Study]:
    """Every study with a targets file, in name order; ``names`` picks some (unknown: error)."""
    studies = {p.stem: p for p in sorted(directory.glob("*.toml"))}
    if names:
        unknown = [n for n in names if n not in studies]
        if unknown:
            raise StudyError(f"no study named {', '.join(unknown)} (studies: "
                             f"{', '.join(studies)})")
        return [load_study(studies[n]) for n in names]
    return [load_study(p) for p in studies.values()]
