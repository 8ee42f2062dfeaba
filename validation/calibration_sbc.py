"""Simulation-based calibration (Talts et al. 2018) of the planar arm's Bayesian calibration.

The data sets are drawn from the model's own prior and Gaussian likelihood at the top arm's 16
training commands of the clean rig (grid 4, seed 0: the tests' session rig), not from the
physical simulator: only then must the rank of each true value among its posterior draws be
uniform, whatever the data. A wrong likelihood, prior or parameter transform, or a sampler
that has not converged, shows as non-uniform ranks. The sampler settings are the
calibration's (500 warm-up + 500 draws, dense mass), one chain per data set thinned to 49
draws (ranks 0..49).

Each seed draws a batch of 25 data sets; the ranks of every batch run are pooled, so the
report seeds' eight batches are the 200 data sets of the uniformity test: 10 bins of 5 rank
values (20 expected per bin), a chi-square test per quantity (the eight parameters and the
noise sd), Bonferroni-combined. Its power is a figure too: the same ranks under posteriors
shrunk to 70% of their width about their mean must be rejected.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from tempfile import TemporaryDirectory
from typing import Any

import numpy as np

from bayesrob.calibrate import bayes as bc
from bayesrob.data.rig import load_rig
from bayesrob.sim.rigs import simulate_rig
from bayesrob.sim.truth import paper_truth

BATCH = 25  # data sets per seed
DRAWS = 49  # thinned posterior draws per data set: ranks 0..49, 50 values
NARROW = 0.7  # the power check's posterior width, as a share of the true one


def narrowed_ranks(res: bc.SBCResult, factor: float) -> np.ndarray:
    """Ranks under a posterior shrunk about its mean (sd x factor): what SBC must catch."""
    m = res.draws.mean(axis=1, keepdims=True)
    return np.sum(m + factor * (res.draws - m) < res.truth[:, None, :], axis=1)


def bins_for(n_datasets: int) -> int:
    """10 bins (5 rank values each) from 100 data sets on, else 5: at least 10 expected per
    bin, where the chi-square approximation holds."""
    return 10 if n_datasets >= 100 else 5


def run(seeds: list[int], *, quick: bool, say: Callable[[str], None]) -> dict[str, Any]:
    with TemporaryDirectory(prefix="bayesrob-sbc-") as tmp:
        rig = load_rig(simulate_rig(Path(tmp) / "clean", paper_truth((), seed=0, grid=4),
                                    holdout=False))
    u, _ = rig.rows("top", "train")
    batches = []
    for i, seed in enumerate(seeds, 1):
        batches.append(bc.sbc(rig.arms["top"], u, BATCH, n_draws=DRAWS, seed=seed))
        say(f"batch {i}/{len(seeds)} (seed {seed}): {BATCH} data sets in "
            f"{batches[-1].seconds:.0f} s")
    res = bc.SBCResult(np.concatenate([b.truth for b in batches]),
                       np.concatenate([b.draws for b in batches]),
                       np.concatenate([b.divergences for b in batches]),
                       sum(b.seconds for b in batches))
    n = len(res.truth)
    bins = bins_for(n)
    un = res.uniformity(bins)
    narrow = res.uniformity(bins, narrowed_ranks(res, NARROW))
    transitions = n * bc.SamplerSettings().num_samples
    figures: dict[str, Any] = {
        "datasets": n,
        "p_bonferroni": un["p_bonferroni"],
        "p_min": un["p_min"],
        **{f"p.{name}": float(p) for name, p in zip(res.names, un["p"], strict=True)},
        "narrow70.p_bonferroni": narrow["p_bonferroni"],
        "divergence_share": float(res.divergences.sum() / transitions),
    }
    figures["details"] = {"bins": bins, "quantities": list(res.names),
                          "counts": un["counts"].tolist(),
                          "narrow70_counts": narrow["counts"].tolist(),
                          "divergences": int(res.divergences.sum()), "transitions": transitions,
                          "sampling_seconds": round(res.seconds, 1)}
    return figures


def tables(entry: dict[str, Any]) -> dict[str, str]:
    f, d = entry["figures"], entry["details"]
    names = d["quantities"]
    worst = min(names, key=lambda q: f[f"p.{q}"])
    rows = ["| data sets | bins | smallest p (quantity) | Bonferroni p | posteriors 30% too "
            "narrow: Bonferroni p | divergent transitions |", "|---|---|---|---|---|---|",
            f"| {f['datasets']} | {d['bins']} | {f['p_min']:.2g} ({worst}) | "
            f"{f['p_bonferroni']:.2g} | {f['narrow70.p_bonferroni']:.1g} | "
            f"{d['divergences']} of {d['transitions']} |"]
    return {"sbc": "\n".join(rows)}
