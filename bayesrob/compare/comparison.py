"""Model comparison: every joint-error model scored on end points it was not fitted on.

A point's score is the log of the model's predicted density (per mm^2, normalised over the grid
box like every grid prediction) at the observed end point, for:

- held-out rows: each arm's ``validation`` rows and the linked ``test`` rows, and, reported
  beside them and never pooled, ``holdout`` rows (single-arm rows at new poses, linked rows at
  new targets);
- leave-one-out over the training rows, exact: row i scored with everything fitted on it
  refitted without it, the arm's calibration included (a row's leverage on the 8 parameters
  is about 0.25 with 16 rows, so keeping it would flatter every model), the bandwidths kept
  from all rows (re-selecting them would cost minutes for COND; it flatters the LOO-ML
  variants a little). A KDE has no posterior draws to importance-weight, but dropping one of
  its points is cheap.

Both go through ``arviz.compare`` (``ELPDData`` built from the exact pointwise values): elpd
differences, ``dse = sqrt(n) sd(pointwise differences)`` and stacking weights. Alongside, each
model's HDR levels of the held-out points (uniform on (0, 1) when calibrated) and coverage.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import arviz as az
import jax.numpy as jnp
import numpy as np
import scipy.stats
import xarray as xr

from bayesrob import robot as kin
from bayesrob.calibrate.arms import calibrate_arm, calibrate_arms, predicted_points
from bayesrob.calibrate.least_squares import calibrate, side_rows
from bayesrob.data.rig import Rig
from bayesrob.data.vocabulary import EQUILIBRIUM
from bayesrob.errors.marker_density import fit_marker_model, loo_marker_scores, marker_model_kind
from bayesrob.errors.noise_models import (
    FittedNoiseModel,
    ModelSpec,
    discover_models,
    fit_noise_models,
    joint_errors,
)
from bayesrob.predict.fusion import fused_posterior
from bayesrob.predict.grid import (
    GridPosterior,
    grid_posterior,
    point_log_density,
    setup_set,
    setups,
)
from bayesrob.predict.regions import kde_log_density
from bayesrob.progress import progress as progress_report

__all__ = ["PointScores", "ModelComparison", "score_points", "score_setup", "holdout_setups",
           "refit_at_bandwidths", "loo_training_scores", "loo_calibrations", "compare_models",
           "elpd_rows"]

MASSES = (0.5, 0.9)

# Rows taken where no training, validation or test row was: single-arm rows at new poses and
# linked rows at new targets. Scored beside the validation/test rows, never fitted on.
HOLDOUT = "holdout"


@dataclass
class PointScores:
    """Scores of observed end points under one model's predictions."""

    lpd: np.ndarray  # (n,) log density per mm^2 at the observed end point
    hdr_level: np.ndarray  # (n,) predicted mass denser than the observation, in [0, 1]
    grid: GridPosterior | None = field(default=None, repr=False)
    observed: np.ndarray | None = field(default=None, repr=False)

    def coverage(self, mass: float) -> float:
        """Fraction of points inside the ``mass`` highest-density region."""
        return float(np.mean(self.hdr_level <= mass)) if self.lpd.size else float("nan")

    def ppc(self, draws: int = 4000, seed: int = 0) -> dict:
        """Posterior predictive check of the points, jointly over the targets: the HDR levels
        (a 2-D PIT, Kolmogorov-Smirnov against uniform), and the paper's mean distance of the
        end points from their targets against ``draws`` replicated sets from the grid
        prediction; ``ppp`` = P(replicated >= observed), near 1 when conservative."""
        post = self.grid
        rep = post.sample(seed, draws)  # (draws, T, 2)
        pred = np.linalg.norm(rep - post.targets[None], axis=-1).mean(axis=1)
        obs = float(np.linalg.norm(self.observed - post.targets, axis=-1).mean())
        return {
            "n": int(self.lpd.size),
            "hdr_levels": [float(x) for x in self.hdr_level],
            "ks_pvalue": float(scipy.stats.kstest(self.hdr_level, "uniform").pvalue),
            "mean_error_obs_mm": obs,
            "mean_error_pred_mm": {"q05": float(np.quantile(pred, 0.05)),
                                   "median": float(np.median(pred)),
                                   "q95": float(np.quantile(pred, 0.95))},
            "ppp": float(np.mean(pred >= obs)),
        }


def score_points(models: Sequence[FittedNoiseModel], arms: Sequence[kin.Arm],
                 commands: Sequence[np.ndarray], targets: np.ndarray, observed: np.ndarray,
                 fusion: str = "product", stiffness: Sequence[Any] | None = None,
                 **grid_kw: Any) -> tuple[PointScores, GridPosterior]:
    """Log predictive density and HDR level of ``observed`` (T, 2), one point per target
    (row t's prediction centred at ``targets[t]``), for one arm or arms linked at their end
    point, fused by ``fusion`` (:mod:`bayesrob.predict.fusion`)."""
    observed = np.asarray(observed, float)
    if fusion != "product" and len(arms) > 1:
        post, draws = fused_posterior(models, arms, commands, targets, fusion, stiffness)
        lpd = kde_log_density(draws, observed)
        return PointScores(lpd, post.hdr_level(lpd), post, observed), post
    post = grid_posterior(models, arms, commands, targets, **grid_kw)
    lpd = point_log_density(post, models, arms, commands, observed)
    return PointScores(lpd, post.hdr_level(lpd), post, observed), post


def score_setup(rig: Rig, arms: dict[str, kin.Arm], fitted: dict[str, FittedNoiseModel],
                config: str, fusion: str = "product", set: str | None = None) -> PointScores:
    """Scores of a setup's rows of ``set``: by default its judged rows (validation for one arm,
    test for linked arms); ``holdout``: new poses for one arm, new targets when linked."""
    set = set or setup_set(config)
    rows = rig.config_rows(config, set)
    members = config.split("+")
    scores, _ = score_points([fitted[a] for a in members], [arms[a] for a in members],
                             [rows["commands"][a] for a in members],
                             predicted_points(rig, arms, config, set), rows["observed"],
                             fusion, rig_stiffness(rig, members))
    return scores


def holdout_setups(rig: Rig) -> list[str]:
    """Every single arm, then every linked config, that has ``holdout`` rows."""
    single = [a for a in rig.arms if rig.measurements.mask(a, HOLDOUT).any()]
    linked = [c for c in rig.linked_configs if rig.measurements.mask(c, HOLDOUT).any()]
    return single + linked


def rig_stiffness(rig: Rig, members: Sequence[str]) -> list | None:
    """The rig's joint stiffnesses of the members (None for an arm without; None if none)."""
    known = [rig.arms[a].stiffness for a in members]
    return known if any(k is not None for k in known) else None


def refit_at_bandwidths(model: FittedNoiseModel, theta_err: np.ndarray, u: np.ndarray
                        ) -> FittedNoiseModel:
    """``model``'s density refitted to other joint errors and commands at its bandwidths,
    all else (the histogram COND's grid included) re-derived from the new rows: a grid
    carried over would put the scored row off the histogram, where only the floor is."""
    return model.spec.fit(theta_err, u, model.widths)


def refit_without(model: FittedNoiseModel, keep: np.ndarray) -> FittedNoiseModel:
    """The model refitted on the rows ``keep`` (boolean mask) at its current bandwidths."""
    return refit_at_bandwidths(model, model.theta_err[keep], model.u[keep])


def loo_calibrations(rig: Rig, arm: str) -> list[kin.Arm]:
    """The arm calibrated (least squares, as :func:`calibrate_arms`) without each training row."""
    u, d = rig.rows(arm, "train")
    uv, dv = rig.rows(arm, "validation")
    spec = rig.arms[arm]
    return [calibrate_arm(spec, u[np.arange(len(u)) != i], d[np.arange(len(u)) != i],
                          "least-squares", uv, dv).arm for i in range(len(u))]


def loo_training_scores(rig: Rig, arm: kin.Arm, model: FittedNoiseModel,
                        recalibrate: bool = True,
                        calibrations: Sequence[kin.Arm] | None = None) -> np.ndarray:
    """Exact leave-one-out log predictive density of each of an arm's training rows: row i
    scored with the calibration (if ``recalibrate``; ``calibrations`` when already computed),
    the joint errors and the density (at the full fit's bandwidths) refitted without it."""
    u, d = rig.rows(arm.name, "train")
    if recalibrate and calibrations is None:
        calibrations = loo_calibrations(rig, arm.name)
    out = np.empty(len(u))
    for i in range(len(u)):
        keep = np.arange(len(u)) != i
        if recalibrate:
            arm_i = calibrations[i]
            m = refit_at_bandwidths(model, joint_errors(arm_i, u[keep], d[keep]), u[keep])
        else:
            arm_i, m = arm, refit_without(model, keep)
        target = np.asarray(arm_i.forward_u(jnp.asarray(u[i:i + 1])))
        scores, _ = score_points([m], [arm_i], [u[i:i + 1]], target, d[i:i + 1])
        out[i] = scores.lpd[0]
    return out


def _in_sample_scores(rig: Rig, arm: kin.Arm, model: FittedNoiseModel) -> np.ndarray:
    u, d = rig.rows(arm.name, "train")
    target = np.asarray(arm.forward_u(jnp.asarray(u)))
    scores, _ = score_points([model], [arm], [u], target, d)
    return scores.lpd


def elpd_data(pointwise: np.ndarray, p: float) -> Any:
    """An arviz ``ELPDData`` (kind loo) holding exact pointwise values, for ``az.compare``."""
    n = pointwise.size
    return az.ELPDData(
        data=[float(pointwise.sum()), float(np.sqrt(n * np.var(pointwise))), p, n, n, False,
              xr.DataArray(pointwise, dims=["obs"]), "log"],
        index=["elpd_loo", "se", "p_loo", "n_samples", "n_data_points", "warning", "loo_i",
               "scale"],
    )


def _elpd_tables(specs: Sequence[ModelSpec], heldout: dict[str, dict[str, PointScores]],
                 loo: dict[str, np.ndarray], in_sample: dict[str, np.ndarray],
                 holdout: dict[str, dict[str, PointScores]]) -> tuple[Any, Any, Any]:
    """arviz's stacking comparisons of every model's held-out, leave-one-out (p: in-sample
    minus LOO) and holdout elpd (None without holdout rows)."""
    def table(pointwise: dict[str, np.ndarray], p: dict[str, float] | None = None) -> Any:
        return az.compare({s.name: elpd_data(pointwise[s.name],
                                              float("nan") if p is None else p[s.name])
                           for s in specs}, method="stacking")

    def pooled(scores: dict[str, dict[str, PointScores]]) -> dict[str, np.ndarray]:
        return {n: np.concatenate([x.lpd for x in by_setup.values()])
                for n, by_setup in scores.items()}

    with warnings.catch_warnings():
        # arviz 0.23 calls a pandas sort_values(inplace=True) that pandas deprecates.
        warnings.filterwarnings("ignore", message="The inplace keyword")
        return (table(pooled(heldout)),
                table(loo, {n: float(in_sample[n].sum() - loo[n].sum()) for n in loo}),
                table(pooled(holdout)) if holdout else None)


def elpd_rows(compared: Any) -> list[dict]:
    """An ``arviz.compare`` table as the JSON's rows, best first."""
    return [{"model": str(name), "rank": int(r["rank"]), "elpd": float(r["elpd_loo"]),
             "se": float(r["se"]), "elpd_diff": float(r["elpd_diff"]), "dse": float(r["dse"]),
             "weight": float(r["weight"]), "p": float(r["p_loo"])}
            for name, r in compared.iterrows()]


def _score_summary(by_config: dict[str, PointScores]) -> dict:
    """elpd, its SE and per-setup calibration of one model's scores over a set of rows."""
    by_setup = {}
    for config, s in by_config.items():
        by_setup[config] = {
            "n": int(s.lpd.size), "elpd": float(s.lpd.sum()),
            "mean_lpd": float(s.lpd.mean()),
            "coverage50": s.coverage(0.5), "coverage90": s.coverage(0.9),
            "mean_hdr_level": float(s.hdr_level.mean()),
        }
        if "+" in config:
            by_setup[config]["ppc"] = {k: v for k, v in s.ppc().items() if k != "hdr_levels"}
    pw = np.concatenate([s.lpd for s in by_config.values()])
    return {"n": int(pw.size), "elpd": float(pw.sum()),
            "se": float(np.sqrt(pw.size * np.var(pw))),
            "mean_lpd": float(pw.mean()), "by_setup": by_setup}


@dataclass
class ModelComparison:
    """Held-out and leave-one-out scores of every model, with arviz's comparison tables."""

    rig: Rig
    specs: list[ModelSpec]
    heldout: dict[str, dict[str, PointScores]]  # model -> setup -> scores
    loo: dict[str, np.ndarray]  # model -> pointwise LOO lpd over all arms' training rows
    in_sample: dict[str, np.ndarray]
    heldout_compare: Any  # az.compare DataFrame
    loo_compare: Any
    seconds: float
    notes: list[str] = field(default_factory=list)
    holdout: dict[str, dict[str, PointScores]] = field(default_factory=dict)  # empty: none
    holdout_compare: Any = None  # az.compare DataFrame when the rig has holdout rows
    loo_recalibrated: bool = True  # whether LOO refitted the calibration without the row too
    # the same setups with linked ones fused by the equilibrium rule (model -> setup -> scores)
    fused: dict[str, dict[str, PointScores]] = field(default_factory=dict)
    fused_holdout: dict[str, dict[str, PointScores]] = field(default_factory=dict)
    # URDF/DH rigs: what each model is on their arms (bayesrob.errors.marker_density), and the score
    kinds: dict[str, str] = field(default_factory=dict)
    score: str = ("log predictive density per mm^2 of the observed end point, normalised "
                  "over the grid box; elpd = sum over points")

    def heldout_pointwise(self, model: str) -> np.ndarray:
        return np.concatenate([s.lpd for s in self.heldout[model].values()])

    def document(self) -> dict:
        """The ``bayesrob compare --json`` document."""
        models = {}
        for spec in self.specs:
            name = spec.name
            loo = self.loo[name]
            models[name] = {
                "description": spec.description, "paper": spec.paper,
                "heldout": _score_summary(self.heldout[name]),
                "loo_train": {"n": int(loo.size), "elpd": float(loo.sum()),
                              "se": float(np.sqrt(loo.size * np.var(loo))),
                              "p_loo": float(self.in_sample[name].sum() - loo.sum())},
                "holdout": _score_summary(self.holdout[name]) if self.holdout else None,
                "fusion": "product",
            }
            if name in self.kinds:
                models[name]["marker_model"] = self.kinds[name]
            if self.fused.get(name) and any("+" in c for c in self.fused[name]):
                models[f"{name}:{EQUILIBRIUM}"] = {
                    "model": name, "fusion": EQUILIBRIUM,
                    "description": spec.description, "paper": spec.paper,
                    "heldout": _score_summary(self.fused[name]),
                    "holdout": (_score_summary(self.fused_holdout[name])
                                if self.fused_holdout else None),
                }
        held = elpd_rows(self.heldout_compare)
        loo = elpd_rows(self.loo_compare)
        winner = held[0]
        runner_up = held[1] if len(held) > 1 else None
        return {
            "rig": self.rig.name,
            "score": self.score,
            "heldout_rows": {c: int(s.lpd.size) for c, s in
                             self.heldout[self.specs[0].name].items()},
            "models": models,
            "heldout_compare": held,
            "loo_compare": loo,
            "holdout_rows": ({c: int(s.lpd.size) for c, s in
                              self.holdout[self.specs[0].name].items()} if self.holdout else {}),
            "holdout_compare": (elpd_rows(self.holdout_compare)
                                if self.holdout_compare is not None else []),
            "loo_recalibrated": self.loo_recalibrated,
            "winner": {
                "model": winner["model"],
                "over": runner_up["model"] if runner_up else None,
                "elpd_diff": runner_up["elpd_diff"] if runner_up else None,
                "dse": runner_up["dse"] if runner_up else None,
            },
            "notes": self.notes,
            "seconds": self.seconds,
        }

    to_dict = document  # the name every result's JSON goes by (bayesrob.__all__)


def heldout_scores(rig: Rig, specs: Sequence[ModelSpec], arms: dict[str, kin.Arm] | None = None
                   ) -> dict[str, dict[str, PointScores]]:
    """Held-out scores {model: {setup: scores}} of every model, fitted on the train rows."""
    arms = arms if arms is not None else {n: c.arm for n, c in calibrate_arms(rig).items()}
    out = {}
    for spec in specs:
        fitted = fit_noise_models(rig, arms, [spec])[spec.name]
        out[spec.name] = {c: score_setup(rig, arms, fitted, c) for c in setups(rig)}
    return out


def compare_models(rig: Rig, models: Sequence[str] | None = None,
                   models_dir: str | Path | None = None, progress: bool = False,
                   recalibrate: bool = True, groups: tuple[str, ...] | None = None
                   ) -> ModelComparison:
    """Fit every model on the training rows and score it on held-out and LOO points
    (``recalibrate``: LOO refits the calibration too). A rig of URDF/DH arms, or a planar rig
    given ``groups``, is calibrated over ``groups`` (default :data:`bayesrob.robot.GROUPS`)
    and scored by its markers' densities (:func:`_compare_marker_models`)."""
    if rig.is_chain or groups is not None:
        return _compare_marker_models(rig, models, models_dir, progress, groups)
    t0 = time.perf_counter()
    specs = discover_models(models_dir, models)
    bar = progress_report(len(specs), "compare", "models", enabled=progress,
                          postfix="calibrating")
    arms = {n: c.arm for n, c in calibrate_arms(rig).items()}
    configs = setups(rig)
    hold_configs = holdout_setups(rig)
    bar.set_postfix("calibrating without each training row")
    loo_arms = {a: loo_calibrations(rig, a) for a in arms} if recalibrate else {}
    # model -> setup -> scores, under the product and the equilibrium fusion
    heldout, holdout, fused, fused_holdout = {}, {}, {}, {}
    loo, in_sample = {}, {}  # model -> pointwise scores over every arm's training rows
    for spec in specs:
        bar.set_postfix_str(spec.name)
        fitted = fit_noise_models(rig, arms, [spec])[spec.name]
        for set_, cfgs, product, other in ((None, configs, heldout, fused),
                                           (HOLDOUT, hold_configs, holdout, fused_holdout)):
            if cfgs or set_ is None:
                product[spec.name] = {c: score_setup(rig, arms, fitted, c, set=set_)
                                      for c in cfgs}
                # the other fusion rule: single arms are the same prediction under both
                other[spec.name] = {c: (score_setup(rig, arms, fitted, c, EQUILIBRIUM, set_)
                                        if "+" in c else product[spec.name][c]) for c in cfgs}
        loo[spec.name] = np.concatenate(
            [loo_training_scores(rig, arms[a], fitted[a], recalibrate, loo_arms.get(a))
             for a in arms])
        in_sample[spec.name] = np.concatenate(
            [_in_sample_scores(rig, arms[a], fitted[a]) for a in arms])
        bar.update()
    bar.close()
    notes = [
        "held out: validation rows of each arm + linked test rows; models fitted on train rows",
        "loo_train: exact leave-one-out over each arm's train rows: "
        + ("calibration, joint errors and density refitted without the row"
           if recalibrate else "density refitted without the row, calibration kept")
        + "; bandwidths kept from the full fit (flatters the LOO-ML variants slightly)",
        "weights: arviz stacking; dse: sqrt(n) * sd of pointwise differences to the best model",
    ]
    held_table, loo_table, hold_table = _elpd_tables(specs, heldout, loo, in_sample, holdout)
    if hold_configs:
        notes.append("holdout: rows at poses and targets no other set has; models fitted "
                     "on train rows, scored like the held-out rows")
    if any("+" in c for c in configs):
        notes.append(f"linked setups are scored under both fusion rules: models.<name> by the "
                     f"product of likelihoods (the paper's), models.<name>:{EQUILIBRIUM} by the "
                     "arms' stiffness balance (bayesrob.predict.fusion); elpd tables use the "
                     "product")
    return ModelComparison(rig, list(specs), heldout, loo, in_sample, held_table, loo_table,
                           time.perf_counter() - t0, notes, holdout, hold_table, recalibrate,
                           fused, fused_holdout)


def _compare_marker_models(rig: Rig, models: Sequence[str] | None,
                           models_dir: str | Path | None, progress: bool,
                           groups: tuple[str, ...] | None) -> ModelComparison:
    """:func:`compare_models` on a rig of URDF/DH arms: every measured arm's validation rows
    (and holdout rows) scored by :class:`bayesrob.errors.marker_density.MarkerDensity`, and
    leave-one-out over its train rows with the calibration kept."""
    t0 = time.perf_counter()
    if models:
        specs = discover_models(models_dir, models)
    else:  # the paper's estimators are planar: a URDF/DH rig compares the improved ones
        specs = [s for s in discover_models(models_dir) if not s.paper]
    kinds = {s.name: marker_model_kind(s) for s in specs}
    bar = progress_report(len(specs), "compare", "models", enabled=progress,
                          postfix="calibrating")
    cal = calibrate(rig, groups if groups is not None else kin.GROUPS)
    arms = [a for a in cal.robot.measured_arms() if rig.measurements.mask(a, "train").any()]
    hold_arms = [a for a in arms if rig.measurements.mask(a, HOLDOUT).any()]

    def scored(model, arm: str, set: str) -> PointScores:
        u, d = rig.rows(arm, set)
        density = model.density(u, side_rows(rig, cal.robot, arm, set))
        return PointScores(density.logpdf(d), density.hdr_level(d), observed=d)

    heldout, holdout, loo, in_sample = {}, {}, {}, {}
    for spec in specs:
        bar.set_postfix_str(spec.name)
        fitted = {a: fit_marker_model(rig, cal, a, spec, seed=i) for i, a in enumerate(arms)}
        heldout[spec.name] = {a: scored(fitted[a], a, "validation") for a in arms}
        if hold_arms:
            holdout[spec.name] = {a: scored(fitted[a], a, HOLDOUT) for a in hold_arms}
        pairs = [loo_marker_scores(rig, fitted[a]) for a in arms]
        loo[spec.name] = np.concatenate([p[0] for p in pairs])
        in_sample[spec.name] = np.concatenate([p[1] for p in pairs])
        bar.update()
    bar.close()
    notes = [
        "held out: validation rows of each measured arm; models fitted on train rows",
        "score: log density per mm^3 (per mm^2 on a 2-D rig) of the observed marker under the "
        "arm's marker density at its commands (bayesrob.errors.marker_density): ind and corr the "
        "latent joint-error population, cond the kernel conditional of the marker residuals "
        "given the commands",
        "loo_train: leave-one-out over each arm's train residuals (scaled for the calibration's "
        "degrees of freedom), calibration kept: exact for cond, Pareto-smoothed importance "
        "sampling (arviz loo) over the population's posterior draws for ind and corr",
        "weights: arviz stacking; dse: sqrt(n) * sd of pointwise differences to the best model",
        f"calibrated with --params {','.join(cal.groups)}",
    ]
    held, loos, hold_table = _elpd_tables(specs, heldout, loo, in_sample, holdout)
    if hold_arms:
        notes.append("holdout: rows at poses no other set has, scored like the held-out rows")
    linked = [c for c in rig.linked_configs if rig.measurements.mask(c).any()]
    if linked:
        notes.append(f"linked rows ({', '.join(linked)}) are not scored by the marker "
                     "densities: 'bayesrob predict' gives their coverage")
    dim = rig.robot.dim
    return ModelComparison(rig, list(specs), heldout, loo, in_sample, held, loos,
                           time.perf_counter() - t0, notes, holdout, hold_table, False,
                           kinds=kinds, score=(
                               f"log predictive density per mm^{dim} of the observed marker "
                               "under the arm's marker density; elpd = sum over points"))
