"""Observed accuracy of calibrated planar arms: the error of each setup's rows with the
Student-t 95 % interval of its mean (``accuracy.json``'s ``observed``)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import scipy.stats

from bayesrob import kinematics as kin
from bayesrob.rig import SETS, Rig


def mean_ci95(errors: np.ndarray) -> dict:
    """Mean with the Student-t 95% confidence interval of the mean."""
    e = np.asarray(errors, float)
    n = len(e)
    mean = float(np.mean(e)) if n else float("nan")
    if n < 2:
        return {"mean_mm": mean, "ci95_mm": [float("nan"), float("nan")], "n": n}
    half = float(scipy.stats.t.ppf(0.975, n - 1) * np.std(e, ddof=1) / np.sqrt(n))
    return {"mean_mm": mean, "ci95_mm": [mean - half, mean + half], "n": n}


def predicted_points(rig: Rig, arms: dict[str, kin.Arm], config: str, set: str) -> np.ndarray:
    """Where the model says the rows of a config ended up.

    A single arm: f(g(u)) of the commands sent. Linked arms: the target the commands aimed at,
    as the paper did (the commands came from the arms' own inverse models).
    """
    rows = rig.config_rows(config, set)
    members = config.split("+")
    if len(members) == 1:
        return np.asarray(arms[config].forward_u(jnp.asarray(rows["commands"][config])))
    target = rows["target"]
    if np.isnan(target).any():
        # No target recorded: fall back to the mean of the arms' forward predictions.
        return np.mean([np.asarray(arms[a].forward_u(jnp.asarray(rows["commands"][a])))
                        for a in members], axis=0)
    return target


def observed_errors(rig: Rig, arms: dict[str, kin.Arm], config: str, set: str) -> np.ndarray:
    """Euclidean distance (mm) between predicted and observed end point, row by row."""
    rows = rig.config_rows(config, set)
    pred = predicted_points(rig, arms, config, set)
    return np.linalg.norm(pred - rows["observed"], axis=-1)


def observed_accuracy(rig: Rig, arms: dict[str, kin.Arm]) -> dict[str, dict[str, dict]]:
    """Mean error with 95% CI per config and set, for every config and set present."""
    out: dict[str, dict[str, dict]] = {}
    for config in rig.configs:
        for s in SETS:
            if rig.measurements.mask(config, s).any():
                out.setdefault(config, {})[s] = mean_ci95(observed_errors(rig, arms, config, s))
    return out
