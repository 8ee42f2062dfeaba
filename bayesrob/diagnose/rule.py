"""The diagnosis's decision rule on the log densities of rows a candidate's fit did not see,
and its parameter guard (docs/diagnose.md): ``nats_per_parameter`` nats per added parameter (a
real 7-joint arm's 24-parameter encoder error at z 4.9 made validation worse, 1.01 -> 1.06 mm);
off in the rule and reported beside URDF/DH candidates, as it cost a true effect.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

# The usual two-sided 5% level: not tuned on any rig.
Z = 2.0
# The planar engine's floor since its tuning rigs (seeds 21-35): a gain of a few nats is what
# one lucky row can give.
MIN_GAIN_NATS = 4.0
# The guard as reported: AIC's price of a parameter, chosen on the tuning rigs (planar seeds
# 21-35, 6-joint seed 61: true effects gained 2.8-10.7 nats per parameter, the closest call
# among the rest 0.26); on report seed 76 it stops a true encoder error (9.2 nats, 11 params).
NATS_PER_PARAMETER = 1.0


@dataclass(frozen=True)
class DecisionRule:
    """When a candidate counts as missing (module docstring), read off its score:
    ``elpd_diff``, ``elpd_diff_se``, ``parameters`` (added), ``cv_error_*_mm`` (rows the fit did
    not see) and, where the rig repeats its training commands, ``heldout_error_*_mm``."""

    z: float = Z
    min_gain: float = MIN_GAIN_NATS
    nats_per_parameter: float = 0.0
    require_heldout: bool = True
    require_cv: bool = True

    def threshold(self, parameters: int) -> float:
        """The gain (nats) a candidate adding ``parameters`` must exceed."""
        return max(self.min_gain, self.nats_per_parameter * parameters)

    def passes(self, s: dict) -> bool:
        if "arms" in s and not s["arms"]:
            return False  # added to no arm: nothing to name
        diff = s["elpd_diff"]
        ok = diff > self.z * s["elpd_diff_se"] and diff > self.threshold(s.get("parameters", 0))
        if self.require_heldout and s.get("heldout_error_before_mm") is not None:
            ok &= s["heldout_error_after_mm"] < s["heldout_error_before_mm"]
        if self.require_cv:
            ok &= s["cv_error_after_mm"] < s["cv_error_before_mm"]
        return bool(ok)

    def best(self, passing: Sequence[dict]) -> dict:
        """The passing candidate named: the largest gain."""
        return max(passing, key=lambda s: s["elpd_diff"])

    def text(self) -> str:
        guard = (f" and > {self.nats_per_parameter:g} * added parameters"
                 if self.nats_per_parameter else "")
        parts = [f"cross-fitted elpd_diff > {self.z:g} * se and > {self.min_gain:g}{guard}"]
        if self.require_heldout:
            parts.append("validation error shrinks")
        if self.require_cv:
            parts.append("cross-validated error shrinks")
        return " AND ".join(parts) + " (holdout rows only report)"


def elpd_diff(before: np.ndarray, after: np.ndarray) -> tuple[float, float]:
    """The held-out elpd gain ``after - before`` (nats) and its standard error by
    ``arviz.compare`` of exact pointwise densities (refits, not PSIS: with 16 points and 8-14
    parameters Pareto k exceeded 1 on most points)."""
    import arviz as az

    from bayesrob.compare.comparison import elpd_data

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # stacking weights of two models: nothing to warn
        cmp = az.compare({"before": elpd_data(np.asarray(before), 0.0),
                          "after": elpd_data(np.asarray(after), 0.0)}, ic="loo")
    return (float(cmp.loc["after", "elpd_loo"] - cmp.loc["before", "elpd_loo"]),
            float(cmp["dse"].max()))
