"""Coverage of every joint-error model's 50% and 90% regions on simulated two-arm rigs with
gravity sag and backlash (the paper's setup): at the validation and linked test rows, which
repeat the training commands, and at the holdout rows, new poses between the training grid's.
The paper-faithful variants are measured beside the improved ones: the paper found its models
conservative, and their over-coverage is a figure here.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from tempfile import TemporaryDirectory
from typing import Any

import numpy as np

from bayesrob.calibrate.arms import calibrate_arms, predicted_points
from bayesrob.compare.comparison import PointScores, heldout_scores, score_points
from bayesrob.data.rig import Rig, load_rig
from bayesrob.errors.noise_models import discover_models, fit_noise_models
from bayesrob.sim.rigs import simulate_rig
from bayesrob.sim.truth import paper_truth

MASSES = (0.5, 0.9)
IMPROVED = ("ind", "corr", "cond")
EFFECTS = ("gravity_sag", "backlash")


def holdout_scores(rig: Rig, specs) -> dict[str, dict[str, PointScores]]:
    """Scores {model: {config: scores}} of every config's holdout rows, models fitted on the
    train rows as for the held-out scores; each row's prediction is centred where the
    calibrated model says it lands (f(g(u)) for one arm, the aimed-at target when linked)."""
    arms = {n: c.arm for n, c in calibrate_arms(rig).items()}
    configs = [c for c in rig.configs if rig.measurements.mask(c, "holdout").any()]
    out: dict[str, dict[str, PointScores]] = {}
    for spec in specs:
        fitted = fit_noise_models(rig, arms, [spec])[spec.name]
        out[spec.name] = {}
        for config in configs:
            rows = rig.config_rows(config, "holdout")
            members = config.split("+")
            out[spec.name][config], _ = score_points(
                [fitted[a] for a in members], [arms[a] for a in members],
                [rows["commands"][a] for a in members],
                predicted_points(rig, arms, config, "holdout"), rows["observed"])
    return out


def levels(scores: list[dict[str, dict[str, PointScores]]], model: str, kind: str
           ) -> np.ndarray:
    """HDR levels pooled over rigs: kind "single" (one arm's rows) or "linked"."""
    return np.concatenate([s.hdr_level for by_setup in scores
                           for config, s in by_setup[model].items()
                           if ("+" in config) == (kind == "linked")])


def coverage_figures(scores: list, prefix: str, models: Sequence[str]) -> dict[str, float]:
    out: dict[str, float] = {}
    for model in models:
        for kind in ("single", "linked"):
            lv = levels(scores, model, kind)
            out[f"{prefix}.{model}.{kind}.points"] = int(lv.size)
            for m in MASSES:
                out[f"{prefix}.{model}.{kind}.coverage{int(m * 100)}"] = float(np.mean(lv <= m))
    return out


def run(seeds: list[int], *, quick: bool, say: Callable[[str], None]) -> dict[str, Any]:
    specs = discover_models()
    validation, holdout = [], []
    with TemporaryDirectory(prefix="bayesrob-coverage-") as tmp:
        for i, seed in enumerate(seeds, 1):
            rig = load_rig(simulate_rig(Path(tmp) / f"rig{seed}",
                                        paper_truth(EFFECTS, seed=seed)))
            validation.append(heldout_scores(rig, specs))
            holdout.append(holdout_scores(rig, [s for s in specs if s.name in IMPROVED]))
            say(f"rig {i}/{len(seeds)} (seed {seed}) scored")
    figures = coverage_figures(validation, "validation", [s.name for s in specs])
    figures |= coverage_figures(holdout, "holdout", IMPROVED)
    for fam in IMPROVED:
        lv = np.concatenate([levels(validation, f"{fam}_paper", k) for k in ("single", "linked")])
        figures[f"validation.{fam}_paper.pooled.coverage50"] = float(np.mean(lv <= 0.5))
    return figures


def tables(entry: dict[str, Any]) -> dict[str, str]:
    f = entry["figures"]

    def pair(prefix: str, model: str, kind: str) -> str:
        return (f"{f[f'{prefix}.{model}.{kind}.coverage50']:.3f} / "
                f"{f[f'{prefix}.{model}.{kind}.coverage90']:.3f}")

    rows = ["| model | validation, single | validation, linked | new poses, single | "
            "new poses, linked |", "| --- | --- | --- | --- | --- |"]
    for model in IMPROVED:
        rows.append(f"| {model} | {pair('validation', model, 'single')} | "
                    f"{pair('validation', model, 'linked')} | {pair('holdout', model, 'single')}"
                    f" | {pair('holdout', model, 'linked')} |")
    for model in (f"{m}_paper" for m in IMPROVED):
        rows.append(f"| {model} | {pair('validation', model, 'single')} | "
                    f"{pair('validation', model, 'linked')} | - | - |")
    return {"coverage": "\n".join(rows)}
