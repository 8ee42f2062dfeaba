"""Checks of the linked chain prediction's pieces on a rig of two 6-joint arms linked at their
tool points (``LinkedArm6Truth``, calibrated with joint compliance on the single-arm rows
only), each too long for the tests (the fits and the product's NUTS take minutes):

- **known stiffness**: given each arm's true joint stiffnesses, the predicted linked point
  lands where the simulator's assembly does, within 0.35 mm on average over the 24 linked rows
  (0.17 mm on tuning rig 201), where the linked points lie 2-5 mm from their targets: the
  linearised balance with the compliance-calibrated arms is the physics, not a fit;
- **the product rule** (every arm's joint errors and the shared point sampled by NUTS)
  against the Gaussian product of the arms' free-point draws (exact for Gaussian joint errors
  through a linearised arm; errors of a few mrad make the arm linear to parts in a thousand):
  means within 0.1 mm and 0.25 of the product's sd, the variances within 20%. The reference
  takes 8000 free-point draws per arm: the linked point lies several of their sds from each
  arm's centre, so the reference's own Monte Carlo error in the tails counts (with 4000 its
  gap came out at 0.30 sd, with 8000 0.22-0.23 sd for 1000 and for 4000 NUTS draws alike);
- **stiffnesses read from the URDF's masses** (what ``predict --masses description`` draws
  the balance from, the rig's masses the URDF's): each arm's shoulder and elbow stiffnesses
  within 15% of the simulator's (the tuning rigs' fits: 1-8%).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from tempfile import TemporaryDirectory
from typing import Any

import numpy as np

ARMS = ("left", "right")
GROUPS = ("frames", "offsets", "geometric", "compliance")
PRODUCT_ROWS = 3


def _known_stiffness(mods: Any, rows: dict, stiffness: dict) -> dict[str, float]:
    import bayesrob.predict.draws as cp
    import bayesrob.predict.stiffness as st

    guessed = dict(mods.stiffness)
    try:
        mods.stiffness = {a: st.StiffnessPrior(np.log(np.asarray(stiffness[a], float)),
                                               np.zeros(6), np.zeros(6, bool), "the rig")
                          for a in ARMS}
        draws = cp.assembly_draws(mods, list(ARMS), rows["commands"], seed=2)
    finally:
        mods.stiffness = guessed
    gap = float(np.linalg.norm(draws.mean(0) - rows["observed"], axis=1).mean())
    miss = float(np.linalg.norm(rows["observed"] - rows["target"], axis=1).mean())
    return {"known_stiffness.gap_mm": gap, "known_stiffness.miss_over_gap": miss / gap}


def _product(mods: Any, rows: dict) -> dict[str, float]:
    import bayesrob.predict.draws as cp

    cmds = [u[:PRODUCT_ROWS] for u in rows["commands"]]
    nuts = cp.assembly_draws(mods, list(ARMS), cmds, "product", num_samples=1000, seed=4)
    prec, pull = 0.0, 0.0
    for a, u in zip(ARMS, cmds, strict=True):
        free = cp.assembly_draws(mods, [a], [u], num_samples=8000, seed=5)
        cov = np.einsum("sti,stj->tij", free - free.mean(0), free - free.mean(0)) / len(free)
        p = np.linalg.inv(cov)
        prec, pull = prec + p, pull + np.einsum("tij,tj->ti", p, free.mean(0))
    ref_cov = np.linalg.inv(prec)
    ref_mean = np.einsum("tij,tj->ti", ref_cov, pull)
    sd = np.sqrt(np.einsum("tii->ti", ref_cov))
    gap = np.abs(nuts.mean(0) - ref_mean)
    return {"product.max_mean_gap_mm": float(gap.max()),
            "product.max_gap_over_sd": float((gap / sd).max()),
            "product.max_variance_error": float(np.abs(nuts.var(0) / sd**2 - 1).max())}


def _described(rig: Any, stiffness: dict) -> dict[str, Any]:
    """The stiffnesses ``predict --masses description`` draws linked arms' balance from: the
    priors of the calibration with the links' masses held at the URDF's (what
    ``fit_modules`` keeps; its joint-error fits do not touch them)."""
    import bayesrob.predict.stiffness as st
    from bayesrob.calibrate.least_squares import calibrate

    cal = calibrate(rig, GROUPS, masses="description")
    priors = st.stiffness_priors(rig, list(ARMS), cal)
    errors = {}
    for a in ARMS:
        record = priors[a].record()
        if record["from"] != st.STIFFNESS_SOURCES[1]:
            # the route did not read the masses: there is nothing to measure
            raise RuntimeError(f"with the URDF's masses held, {a}'s stiffnesses came from "
                               f"{record['from']}")
        got = np.asarray(record["nmm_per_rad"][1:3], float)
        true = np.asarray(stiffness[a][1:3], float)
        errors[a] = (got / true - 1).tolist()
    worst = max(abs(e) for v in errors.values() for e in v)
    return {"described.max_stiffness_error": float(worst), "details": errors}


def run(seeds: list[int], *, quick: bool, say: Callable[[str], None]) -> dict[str, Any]:
    """The three checks on each rig of ``seeds`` (one rig each, the worst over them)."""
    from bayesrob.data.rig import load_rig
    from bayesrob.predict.draws import fit_modules
    from bayesrob.sim.rigs import simulate_linked_arm6_rig
    from bayesrob.sim.truth import LinkedArm6Truth, load_linked_truth

    per_rig: list[dict[str, Any]] = []
    with TemporaryDirectory(prefix="bayesrob-linked-checks-") as tmp:
        for i, seed in enumerate(seeds, 1):
            d = simulate_linked_arm6_rig(Path(tmp) / f"rig{seed}", LinkedArm6Truth(seed=seed))
            rig = load_rig(d)
            stiffness = load_linked_truth(d)["stiffness_nmm_per_rad"]
            mods = fit_modules(rig, list(ARMS), "ind", groups=GROUPS)
            m = rig.measurements.mask("+".join(ARMS), "test")
            rows = {"commands": [rig.measurements.commands[a][m] for a in ARMS],
                    "observed": rig.measurements.observed[m],
                    "target": rig.measurements.target[m]}
            row: dict[str, Any] = {"seed": seed}
            row |= _known_stiffness(mods, rows, stiffness)
            say(f"rig {i}/{len(seeds)} (seed {seed}): known stiffness, mean gap "
                f"{row['known_stiffness.gap_mm']:.3f} mm")
            if quick:  # the first check runs the route; the others' NUTS fits are "not run"
                per_rig.append(row)
                continue
            row |= _product(mods, rows)
            say(f"rig {i}/{len(seeds)}: product rule, mean gap "
                f"{row['product.max_mean_gap_mm']:.3f} mm at most")
            described = _described(rig, stiffness)
            row["described_errors"] = described.pop("details")
            row |= described
            say(f"rig {i}/{len(seeds)}: stiffnesses from the URDF's masses, worst error "
                f"{row['described.max_stiffness_error']:.3f}")
            per_rig.append(row)
    worst = {"known_stiffness.gap_mm": max, "known_stiffness.miss_over_gap": min,
             "product.max_mean_gap_mm": max, "product.max_gap_over_sd": max,
             "product.max_variance_error": max, "described.max_stiffness_error": max}
    figures = {k: pick(r[k] for r in per_rig) for k, pick in worst.items()
               if all(k in r for r in per_rig)}
    return figures | {"details": {"rigs": per_rig}}


def tables(entry: dict[str, Any]) -> dict[str, str]:
    f = entry["figures"]
    rows = ["| check | figure | value |", "|---|---|---|",
            f"| known stiffness | mean gap, predicted to measured linked point (mm) | "
            f"{f['known_stiffness.gap_mm']:.3f} |",
            f"| | mean linked error over that gap | {f['known_stiffness.miss_over_gap']:.1f} |",
            f"| product rule against the Gaussian product | largest mean gap (mm) | "
            f"{f['product.max_mean_gap_mm']:.3f} |",
            f"| | largest mean gap in the product's sds | {f['product.max_gap_over_sd']:.3f} |",
            f"| | largest variance error | {f['product.max_variance_error']:.3f} |",
            f"| stiffnesses from the URDF's masses | worst shoulder or elbow error | "
            f"{f['described.max_stiffness_error']:.3f} |"]
    return {"checks": "\n".join(rows)}
