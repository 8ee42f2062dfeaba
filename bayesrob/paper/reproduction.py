"""``bayesrob reproduce``: the paper's whole pipeline on a rig, with its figures and numbers.

rig -> calibrated arms -> every joint-error model in ``models/`` -> grid predictions for each
arm alone and for the linked arms -> accuracy.json, Figures 3-8, a terminal table.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bayesrob import robot as kin
from bayesrob.calibrate.arms import Method, calibrate_arms
from bayesrob.data.rig import Rig, RigError
from bayesrob.errors.noise_models import (
    FittedNoiseModel,
    ModelSpec,
    discover_models,
    fit_noise_models,
    joint_errors,
)
from bayesrob.predict.grid import Grid, Prediction, accuracy_document, predict, setup_rows, setups

FIGURES = (
    "fig3_workspace_errors.png",
    "fig4_accuracy.png",
    "fig5_ind_densities.png",
    "fig6_corr_densities.png",
    "fig7_cond_grid.png",
    "fig8_error_densities.png",
)


@dataclass
class Reproduction:
    """Everything a reproduction computed, for reports and figures."""

    rig: Rig
    arms: dict[str, kin.Arm]
    specs: list[ModelSpec]
    fitted: dict[str, dict[str, FittedNoiseModel]]
    predictions: dict[str, dict[str, Prediction]]  # model -> setup -> prediction
    rows: dict[str, dict]  # setup -> commands, targets, observed
    accuracy: dict
    seconds: float

    def training_errors(self, arm: str) -> tuple[np.ndarray, np.ndarray]:
        """Joint errors (N, 2) and commands (N, 2) of an arm's training rows."""
        u, d = self.rig.rows(arm, "train")
        return joint_errors(self.arms[arm], u, d), u


def run_reproduction(rig: Rig, models: Sequence[str] | None = None,
                     models_dir: str | Path | None = None, grid: Grid | None = None,
                     calibration: Method = "least-squares", progress: bool = False
                     ) -> Reproduction:
    """Calibrate, fit every model, predict every setup; no files written."""
    from bayesrob.progress import progress as progress_report

    t0 = time.perf_counter()
    grid = grid if grid is not None else Grid()
    if not rig.linked_configs:
        raise RigError(f"{rig.path}: no linked config (e.g. 'a+b' rows in set 'test') to "
                       "reproduce the paper with")
    specs = discover_models(models_dir, models)
    configs = setups(rig)
    steps = 1 + len(specs) * (len(rig.arms) + len(configs))
    bar = progress_report(steps, "reproduce", "steps", enabled=progress,
                          postfix=f"calibrating ({calibration})")
    arms = {n: c.arm for n, c in calibrate_arms(rig, calibration).items()}
    bar.update()

    def fitted_one(model: str, arm: str) -> None:
        bar.set_postfix(f"fitting {model}")
        bar.update()

    fitted = fit_noise_models(rig, arms, specs, on_fit=fitted_one)
    rows = {c: setup_rows(rig, arms, c) for c in configs}
    predictions: dict[str, dict[str, Prediction]] = {}
    for spec in specs:
        predictions[spec.name] = {}
        for c in configs:
            r = rows[c]
            bar.set_postfix(f"predicting {spec.name}")
            predictions[spec.name][c] = predict(c, fitted[spec.name], arms, r["commands"],
                                                r["targets"], grid, spec.name)
            bar.update()
    bar.close()
    accuracy = accuracy_document(rig, arms, predictions)
    accuracy["rig"] = rig.name
    accuracy["calibration"] = calibration
    accuracy["grid"] = {"half_width_mm": grid.half_width_mm, "n": grid.n}
    accuracy["models"] = {s.name: {"family": s.family, "paper": s.paper,
                                   "description": s.description,
                                   "bandwidth_on_bound": any(f.on_bound for f in
                                                             fitted[s.name].values())}
                          for s in specs}
    return Reproduction(rig, arms, specs, fitted, predictions, rows, accuracy,
                        time.perf_counter() - t0)


EDGE_MASS_WARN = 0.01


def grid_warnings(rep: Reproduction) -> list[str]:
    """One line per setup and model whose predicted mass reaches the edge of the grid."""
    out = []
    for model, by_setup in rep.predictions.items():
        for config, p in by_setup.items():
            bad = int(np.sum(p.edge_mass > EDGE_MASS_WARN))
            if bad:
                out.append(
                    f"warning: {config} / {model}: up to {100 * p.edge_mass.max():.0f}% of the "
                    f"predicted mass lies on the +-{p.grid.half_width_mm:g} mm grid edge at {bad} "
                    f"of {len(p.edge_mass)} targets; the expected error is clipped (do the "
                    "commands aim at the targets? else widen --grid-half-width)")
    return out


def bound_notes(rep: Reproduction) -> list[str]:
    """Models whose bandwidth search ended on its bound (the paper's J_LOO always does)."""
    out = []
    for spec in rep.specs:
        for arm, fitted in rep.fitted[spec.name].items():
            if fitted.on_bound:
                lo, hi = fitted.search_range or (float("nan"), float("nan"))
                why = (" (J_LOO decreases monotonically in h, see docs/paper-notes.md)"
                       if spec.bandwidth == "paper" else
                       " (a width at the upper bound means the data show no structure along "
                       "that dimension)")
                out.append(f"note: {spec.name} / {arm}: bandwidth on the bound of its search "
                           f"range [{lo:g}, {hi:g}] (in data standard deviations){why}")
    return out
