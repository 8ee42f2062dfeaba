"""Calibration of the simulator's 6-joint arm (arm6) through the general kinematic model: two
studies, one rig per seed.

``run_bayes``: NUTS over the identifiable parameters (``calibrate --method bayes``) on a truth
the model can express (frames and joint offsets perturbed, geometry exact, 30 train poses):
converged, as wide as the least-squares standard errors (the prior is weak against 90
coordinates), and the true marker points at the 20 validation poses inside the posterior's 99%
ellipsoids. The poses share one parameter error, so they miss together or not at all: a
posterior too narrow by half puts most of them outside.

``run_compliance``: an arm whose joints give way under gravity (the simulator's point masses
and stiffnesses): the geometric calibration cannot express it, the compliance group (masses
unknown, fitted with the compliances) brings the held-out error to the noise floor, what joint
and measurement noise leave against the true sagging arm.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from tempfile import TemporaryDirectory
from typing import Any

import numpy as np

from bayesrob import robot as kin
from bayesrob.data.rig import Rig, load_rig
from bayesrob.sim.equilibrium import gravity_settled
from bayesrob.sim.rigs import simulate_arm6_rig
from bayesrob.sim.truth import Arm6Truth, arm6_urdf_path, load_true_params

CHI2_3_99 = 11.34  # chi-square with 3 degrees of freedom at 0.99


def true_vector(rig_dir: Path, rig: Rig) -> np.ndarray:
    """The simulated truth's parameters in the rig's layout."""
    truth = load_true_params(rig_dir)
    return np.array([truth[n] for n in rig.robot.layout.names])


def bayes_rig(rig_dir: Path, seed: int) -> dict[str, Any]:
    """One rig's figures of the NUTS posterior against least squares and the truth."""
    from bayesrob.calibrate.bayes import SamplerSettings, calibrate_bayes
    from bayesrob.calibrate.least_squares import calibrate

    d = simulate_arm6_rig(rig_dir, Arm6Truth(seed=seed, n_train=30, n_validation=20,
                                               n_holdout=0, origin_sd_mm=0.0,
                                               origin_sd_rad=0.0))
    rig = load_rig(d)
    groups = ("frames", "offsets")
    post = calibrate_bayes(rig, groups, settings=SamplerSettings(num_warmup=300, num_samples=400),
                           seed=seed)
    ls = calibrate(rig, groups)
    p = post.extra["posterior"]
    free = post.ident.free
    u, _ = rig.rows("arm", "validation")
    true_points = np.asarray(rig.robot.marker_points(true_vector(d, rig), "arm", u))
    points = np.stack([np.asarray(rig.robot.marker_points(x, "arm", u))
                       for x in post.draws[::4]])  # (200, poses, 3)
    inside = []
    for k in range(len(u)):
        diff = true_points[k] - points[:, k].mean(axis=0)
        inside.append(diff @ np.linalg.solve(np.cov(points[:, k].T), diff) < CHI2_3_99)
    return {"seed": seed, "r_hat_max": p["r_hat_max"], "ess_bulk_min": p["ess_bulk_min"],
            "divergences": p["divergences"],
            "se_ratio": float(np.median(post.se[free] / ls.se[free])),
            "inside99": float(np.mean(inside)), "poses": len(u)}


def run_bayes(seeds: list[int], *, quick: bool, say: Callable[[str], None]) -> dict[str, Any]:
    rows = []
    with TemporaryDirectory(prefix="bayesrob-chain-bayes-") as tmp:
        for i, seed in enumerate(seeds, 1):
            rows.append(bayes_rig(Path(tmp) / f"rig{seed}", seed))
            say(f"rig {i}/{len(seeds)} (seed {seed}): r_hat {rows[-1]['r_hat_max']:.3f}, "
                f"inside {rows[-1]['inside99']:.2f}")
    return {
        "r_hat_max": max(r["r_hat_max"] for r in rows),
        "ess_bulk_min": min(r["ess_bulk_min"] for r in rows),
        "divergences": sum(r["divergences"] for r in rows),
        "se_ratio_min": min(r["se_ratio"] for r in rows),
        "se_ratio_max": max(r["se_ratio"] for r in rows),
        "inside99_min": min(r["inside99"] for r in rows),
        "inside99_mean": float(np.mean([r["inside99"] for r in rows])),
        "details": {"rigs": rows},
    }


def noise_floor(rig: Rig, x_true: np.ndarray, truth: Arm6Truth, u: np.ndarray,
                obs: np.ndarray) -> float:
    """Mean distance of the observed points from the true sagging arm's."""
    base = kin.Robot({"arm": kin.urdf_chain(arm6_urdf_path(), "base_link", "tool0", "arm")})
    x_base = x_true.copy()
    # the sag is computed in the robot's own frame: the instrument's pose plays no part
    x_base[base.layout.slices[("arm", "instrument")]] = 0.0
    q = gravity_settled(base, x_base, "arm", u, np.asarray(truth.masses_kg),
                        np.asarray(truth.stiffness_nmm_per_rad), (0.0, 0.0, -1.0))
    # the compiled program: an eager call compiles its loop anew for every rig
    points = rig.robot.compiled_points("arm")(x_true, q)
    return float(np.linalg.norm(np.asarray(points) - obs, axis=1).mean())


def compliance_rig(rig_dir: Path, seed: int) -> dict[str, Any]:
    from bayesrob.calibrate.least_squares import calibrate

    truth = Arm6Truth(seed=seed, compliance=True)
    d = simulate_arm6_rig(rig_dir, truth)
    rig = load_rig(d)
    geometric = calibrate(rig, ("frames", "geometric"))
    compliant = calibrate(rig, ("frames", "geometric", "compliance"))
    u, obs = rig.rows("arm", "validation")
    floor = noise_floor(rig, true_vector(d, rig), truth, u, obs)
    doc = compliant.to_json()
    return {"seed": seed, "floor_mm": floor,
            "geometric_mm": geometric.errors["validation"]["all"]["mean_mm"],
            "compliance_mm": compliant.errors["validation"]["all"]["mean_mm"],
            "free_added": int(compliant.ident.free.sum() - geometric.ident.free.sum()),
            "sag_steps": doc["sag_steps"], "sag_next_step_mm": doc["sag_next_step_mm"],
            "notes": len(doc.get("notes", []))}


def run_compliance(seeds: list[int], *, quick: bool,
                   say: Callable[[str], None]) -> dict[str, Any]:
    rows = []
    with TemporaryDirectory(prefix="bayesrob-chain-compliance-") as tmp:
        for i, seed in enumerate(seeds, 1):
            r = compliance_rig(Path(tmp) / f"rig{seed}", seed)
            rows.append(r)
            say(f"rig {i}/{len(seeds)} (seed {seed}): geometric {r['geometric_mm']:.2f} mm, "
                f"compliance {r['compliance_mm']:.2f} mm, floor {r['floor_mm']:.2f} mm")
    return {
        "geometric_over_floor_min": min(r["geometric_mm"] / r["floor_mm"] for r in rows),
        "compliance_over_floor_max": max(r["compliance_mm"] / r["floor_mm"] for r in rows),
        "free_added_min": min(r["free_added"] for r in rows),
        "sag_steps_max": max(r["sag_steps"] for r in rows),
        "sag_next_step_mm_min": min(r["sag_next_step_mm"] for r in rows),
        "sag_next_step_mm_max": max(r["sag_next_step_mm"] for r in rows),
        "notes": sum(r["notes"] for r in rows),
        "details": {"rigs": rows},
    }


def tables(entry: dict[str, Any]) -> dict[str, str]:
    rigs = entry["details"]["rigs"]
    if "floor_mm" in rigs[0]:
        rows = ["| seed | geometric (mm) | with compliance (mm) | noise floor (mm) | "
                "one more torque step moves a marker (mm) |", "|---|---|---|---|---|"]
        rows += [f"| {r['seed']} | {r['geometric_mm']:.2f} | {r['compliance_mm']:.2f} | "
                 f"{r['floor_mm']:.2f} | {r['sag_next_step_mm']:.2f} |" for r in rigs]
        return {"compliance": "\n".join(rows)}
    rows = ["| seed | r_hat | bulk ESS | divergences | posterior / least-squares sd | true "
            "points inside the 99% ellipsoids |", "|---|---|---|---|---|---|"]
    rows += [f"| {r['seed']} | {r['r_hat_max']:.2f} | {r['ess_bulk_min']:.0f} | "
             f"{r['divergences']} | {r['se_ratio']:.2f} | {r['inside99']:.2f} |" for r in rigs]
    return {"bayes": "\n".join(rows)}
