"""The diagnosis's one decision rule, for every robot (docs/diagnose.md): the evidence is each
row's marker error at rows no fit of the candidate saw (a planar arm's train rows by
cross-fitted leave-one-out refits, :mod:`~bayesrob.diagnose.refits`; a chain's selection
poses, :mod:`~bayesrob.diagnose.groups`). A candidate passes when its paired error drop there
exceeds ``Z`` standard errors; of those that pass, the one dropping the mean error most per
added parameter is named. A pair tried because nothing passed alone must also beat each member
alone by ``Z`` and clear the parameter guard: ``NATS_PER_PARAMETER`` nats of log predictive
density per added parameter (a real 7-joint arm's 24-parameter encoder error at z 4.9 made
validation worse, 1.01 -> 1.06 mm), reported beside every single candidate, deciding none.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

# The usual two-sided 5% level: not tuned on any rig.
Z = 2.0
# The guard's floor: a gain of a few nats is what one lucky row can give (the planar
# engine's tuning rigs, seeds 21-35).
MIN_GAIN_NATS = 4.0
# AIC's price of a parameter, chosen on the tuning rigs (planar seeds 21-35, 6-joint seed 61:
# true effects gained 2.8-10.7 nats per parameter, the closest call among the rest 0.26).
NATS_PER_PARAMETER = 1.0


def paired_z(before: np.ndarray, after: np.ndarray) -> float:
    """How many standard errors the per-row error drop ``before - after`` is above zero."""
    d = np.asarray(before) - np.asarray(after)
    sd = float(d.std(ddof=1)) if len(d) > 1 else 0.0
    # no spread: a candidate that moved no row (nothing identifiable to fit) is no drop, not
    # the NaN of 0/0 that a JSON document cannot hold
    return float(d.mean() / (sd / np.sqrt(len(d)))) if sd > 0 else 0.0


def public_scores(scores: Sequence[dict]) -> list[dict]:
    """A round's candidate scores as the JSON has them: the engines' own ``_`` entries (arrays
    kept for later comparisons) left out."""
    return [{k: v for k, v in s.items() if not k.startswith("_")} for s in scores]


@dataclass(frozen=True)
class DecisionRule:
    """When a candidate counts as missing (module docstring), read off its score: ``z`` (its
    paired error drop's), ``drop_per_parameter_mm``, ``elpd_diff`` and ``parameters``
    (added); ``arms``, where the engine gives an effect to some arms only."""

    z: float = Z
    min_gain: float = MIN_GAIN_NATS
    nats_per_parameter: float = NATS_PER_PARAMETER

    def threshold(self, parameters: int) -> float:
        """The parameter guard: the gain (nats) a candidate adding ``parameters`` must
        exceed where the guard decides (pairs)."""
        return max(self.min_gain, self.nats_per_parameter * parameters)

    def guard_passes(self, s: dict) -> bool:
        return bool(s["elpd_diff"] > self.threshold(s.get("parameters", 0)))

    def passes(self, s: dict) -> bool:
        if "arms" in s and not s["arms"]:
            return False  # added to no arm: nothing to name
        return bool(s["z"] > self.z)

    def pair_passes(self, s: dict, z_over_members: Sequence[float]) -> bool:
        """A pair tried because nothing passed alone: each member needed (the pair's errors
        below each member's alone by ``z``) and the guard cleared."""
        return bool(self.passes(s) and all(z > self.z for z in z_over_members)
                    and self.guard_passes(s))

    def best(self, passing: Sequence[dict]) -> dict:
        """The passing candidate named: the largest drop of the mean error per added
        parameter (so compliance goes before an encoder sinusoid that mimics part of it)."""
        return max(passing, key=lambda s: s["drop_per_parameter_mm"])

    def text(self) -> str:
        return (f"of the candidates whose paired error drop on rows their fits did not see "
                f"exceeds {self.z:g} standard errors, name the one with the largest drop per "
                f"added parameter; a pair, tried where nothing passes alone, also beats each "
                f"member alone by {self.z:g} standard errors and gains more than "
                f"max({self.min_gain:g}, {self.nats_per_parameter:g} * added parameters) "
                "nats; validation and holdout rows only report")


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
