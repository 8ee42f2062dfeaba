"""A 3-D two-arm linked prediction at 16 targets: two 6-joint arms (``bayesrob simulate
--robot arm6 --linked``, seed 0) linked at their tool points, equilibrium fusion.

    python benchmarks/bench_predict_3d.py [--repeats 2]
    python benchmarks/bench_predict_3d.py --coverage tuning|report [--variants]
    python benchmarks/bench_predict_3d.py --coverage tuning|report --masses description \
        --mass-spread 0.1 [--sag-steps N]
    python benchmarks/bench_predict_3d.py --coverage report --many-rigs [--masses ...]
    python benchmarks/bench_predict_3d.py --coverage tuning --many-rigs [--variants]
    python benchmarks/bench_predict_3d.py --coverage tuning [--many-rigs] --sag-variants
    python benchmarks/bench_predict_3d.py --coverage report --many-rigs --sag-report
    python benchmarks/bench_predict_3d.py --coverage tuning|report --three-arms

Prints one JSON line: the whole ``predict_assembly`` warm (calibration, both arms' latent
joint-error fits by NUTS, aiming, 4000 draws per target, regions), and its prediction step alone
(aiming, draws and regions from fitted modules). Target (2 cores): the whole prediction under
60 s warm; the single-arm prediction's time in the same run is printed beside it.

Coverage (a line per rig, then the pooled figures): two arm6 arms with gravity sag, each
seed's stiffnesses drawn about the simulator's profile (``LinkedChainTruth.stiffness_log_sd``),
calibrated with joint compliance on their single-arm rows, predicted at the rig's 24 linked
targets and commands with the stiffness prior (the rig gives no stiffness) and compared with the
simulated measurements of the linked assembly: the share inside the predicted 50% / 90%
regions and predicted / observed mean error. ``tuning`` (seeds TUNING_SEEDS) with
``--variants`` tries every prior in VARIANTS (centre, per-joint sd, the shared per-arm term's
centre and sd) and ``--sag-variants`` those of SAG_VARIANTS; ``report``
(seeds REPORT_SEEDS, fixed before any run) runs the chosen prior once. With ``--masses
description`` the arms are calibrated with their link masses held at the URDF's, their
stiffnesses read from the fitted compliances (``chain_prediction._stiffness_prior``), each
simulated arm's true masses drawn ``--mass-spread`` (log sd) about the URDF's; its report rigs
are DESCRIPTION_REPORT_SEEDS.

``--many-rigs`` reports on twelve rigs of 8 linked points each (MANY_REPORT_SEEDS, or
MANY_DESCRIPTION_REPORT_SEEDS with ``--masses description``; fixed before their first run)
instead of four of 24: the same 96 points, but a rig's points share one pair of arms and
their stiffness ratio, so they miss or hit together, and four rigs leave the pooled coverage
far noisier than the binomial range the targets assume (docs/fusion.md). With ``--coverage
tuning`` it runs the twelve tuning rigs MANY_TUNING_SEEDS; ``--rechosen`` reports the prior
chosen on them (and on TUNING_SEEDS) on MANY_RECHOSEN_REPORT_SEEDS, and ``--sag-report``
the prior whose arm term is centred on the arms' fitted sags
(``chain_prediction.sag_scaled_priors``) on MANY_SAG_REPORT_SEEDS.

``--three-arms`` runs the same study on three arms joined at one point (left and right as
above, and a third, front, facing the targets from the side:
``chain_simulator.three_linked_chain_truth``), MANY_LINKED points per rig, with the prior
``predict`` uses as it stands: THREE_TUNING_SEEDS checked that it runs, THREE_REPORT_SEEDS
(fixed before any of them ran) report it.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from bayesrob.kinematics import MASS_SOURCES

WARM_TARGET_S = 60.0
TUNING_SEEDS = (201, 202, 203, 204, 205, 206)
REPORT_SEEDS = (211, 212, 213, 214)
# The report rigs of --masses description (stiffnesses from compliances fitted under the URDF's
# masses), fixed before its first report run: 211-214 had been run with a variant of it
# (docs/fusion.md), so they no longer report it untouched.
DESCRIPTION_REPORT_SEEDS = (221, 222, 223, 224)
# The same 96 points spread over twelve rigs (--many-rigs), fixed before their first run.
MANY_REPORT_SEEDS = tuple(range(231, 243))
MANY_DESCRIPTION_REPORT_SEEDS = tuple(range(251, 263))
# The prior chosen again in that design (--coverage tuning --many-rigs): its tuning rigs, and
# the rigs that report the choice (--coverage report --many-rigs --rechosen), both fixed before
# their first run; 231-242 had shown the previous prior's error ratio, so they cannot report a
# prior chosen after it.
MANY_TUNING_SEEDS = tuple(range(271, 283))
MANY_RECHOSEN_REPORT_SEEDS = tuple(range(291, 303))
# The rigs that report the arm term centred on the fitted sags (--coverage report --many-rigs
# --sag-report), fixed before their first run: 291-302 led to it (their worst rigs were read
# arm by arm), so they cannot report it.
MANY_SAG_REPORT_SEEDS = tuple(range(311, 323))
MANY_LINKED = 8
# Three arms joined at one point (``chain_simulator.three_linked_chain_truth``: left, right and
# front), predicted with the prior ``predict`` uses, chosen on the two-arm tuning rigs; nothing
# is chosen on these. THREE_TUNING_SEEDS only checked that the study runs (its figures are
# printed, not published); THREE_REPORT_SEEDS were fixed before any of them ran.
THREE_TUNING_SEEDS = (901, 902, 903, 904, 905, 906)
THREE_REPORT_SEEDS = tuple(range(341, 353))
GROUPS = ("frames", "offsets", "geometric", "compliance")
# (centre, per-joint log sd, arm term's centre, arm term's log sd), as chosen_prior() names them
VARIANTS = [(c, j, "equal", a) for c in ("equal", "effort") for j in (0.25, 0.5, 0.75)
            for a in (0.0, 0.25, 0.5)]
# the arm term centred on the arms' fitted sags (--sag-variants), beside the prior it would
# replace (per-joint sds 0.35-0.45 were added after 0.25 and 0.5 had bracketed the rates on
# tuning rigs 271-282)
SAG_VARIANTS = [("effort", 0.5, "equal", 0.25)] + [
    ("effort", j, "sags", a) for j in (0.25, 0.35, 0.4, 0.45, 0.5)
    for a in (0.0, 0.15, 0.25, 0.35, 0.5)]


def _fitted(seed: int, where: Path, masses: str = "fitted", mass_log_sd: float = 0.0,
            sag_steps: int = 1, n_linked: int | None = None, three: bool = False):
    """The rig of ``seed`` and its modules fitted on single-arm rows, kept in ``where`` so a
    second sweep of priors skips the fits (the fits do not depend on the prior). ``masses``:
    the calibration's (fitted, or held at the description's); ``mass_log_sd``: how far each
    simulated arm's true link masses stray from the description's; ``sag_steps``: the
    calibration's steps of the sag's torques; ``n_linked``: the rig's linked points (None: the
    simulator's default); ``three``: three arms joined (left, right and front)."""
    import pickle

    import bayesrob.chain_prediction as cp
    from bayesrob.chain_simulator import (
        LinkedChainTruth,
        simulate_linked_chain_rig,
        three_linked_chain_truth,
    )
    from bayesrob.rig import load_rig

    if n_linked is None:
        n_linked = LinkedChainTruth.n_linked
    # rigs of the default size keep the names their caches were written under
    linked = "" if n_linked == LinkedChainTruth.n_linked else f"-linked{n_linked}"
    tag = f"{'three-' if three else ''}{seed}-{masses}-{mass_log_sd:g}{linked}"
    rig_dir = where / f"rig-{tag}"
    kept = where / f"modules-{tag}{'' if sag_steps == 1 else f'-steps{sag_steps}'}.pkl"
    if kept.is_file():
        return load_rig(rig_dir), pickle.loads(kept.read_bytes())
    truth = (three_linked_chain_truth if three else LinkedChainTruth)(
        seed=seed, mass_log_sd=mass_log_sd, n_linked=n_linked)
    rig = load_rig(simulate_linked_chain_rig(rig_dir, truth))
    mods = cp.fit_chain_modules(rig, list(truth.arms), "ind", groups=GROUPS, seed=seed,
                                masses=masses, sag_steps=sag_steps)
    kept.write_bytes(pickle.dumps(mods))
    return rig, mods


_PRIOR_CONSTANTS = ("CHAIN_STIFFNESS_CENTRE", "CHAIN_STIFFNESS_LOG_SD",
                    "CHAIN_STIFFNESS_ARM_CENTRE", "CHAIN_STIFFNESS_ARM_LOG_SD",
                    "SAG_SCALED_LOG_SD", "SAG_SCALED_ARM_LOG_SD")


def chosen_prior() -> tuple[str, float, str, float]:
    """The prior ``predict`` draws stiffnesses from: (centre, per-joint log sd, arm term's
    centre, arm term's log sd), as VARIANTS names them (the sds the arms' fitted sags
    bring with them where the arm term is centred on them)."""
    import bayesrob.chain_prediction as cp

    if cp.CHAIN_STIFFNESS_ARM_CENTRE == "sags":
        return cp.CHAIN_STIFFNESS_CENTRE, cp.SAG_SCALED_LOG_SD, "sags", cp.SAG_SCALED_ARM_LOG_SD
    return (cp.CHAIN_STIFFNESS_CENTRE, cp.CHAIN_STIFFNESS_LOG_SD,
            cp.CHAIN_STIFFNESS_ARM_CENTRE, cp.CHAIN_STIFFNESS_ARM_LOG_SD)


@contextlib.contextmanager
def _prior(centre: str, joint_sd: float, arm_centre: str, arm_sd: float) -> Iterator[None]:
    """The module's prior set to a variant for the block, and put back after it: a sweep
    must not leave its last variant behind for whatever runs next in the process."""
    import bayesrob.chain_prediction as cp

    before = {name: getattr(cp, name) for name in _PRIOR_CONSTANTS}
    cp.CHAIN_STIFFNESS_CENTRE, cp.CHAIN_STIFFNESS_ARM_CENTRE = centre, arm_centre
    if arm_centre == "sags":
        cp.SAG_SCALED_LOG_SD, cp.SAG_SCALED_ARM_LOG_SD = joint_sd, arm_sd
    else:
        cp.CHAIN_STIFFNESS_LOG_SD, cp.CHAIN_STIFFNESS_ARM_LOG_SD = joint_sd, arm_sd
    try:
        yield
    finally:
        for name, value in before.items():
            setattr(cp, name, value)


def coverage(seeds: tuple[int, ...], variants: list[tuple[str, float, str, float]],
             cache: Path | None = None, masses: str = "fitted", mass_log_sd: float = 0.0,
             sag_steps: int = 1, n_linked: int | None = None, three: bool = False) -> dict:
    import jax

    import bayesrob.chain_prediction as cp

    pooled: dict = {v: {"in50": [], "in90": [], "pred": [], "obs": []} for v in variants}
    with tempfile.TemporaryDirectory() as tmp:
        where = cache if cache is not None else Path(tmp)
        where.mkdir(parents=True, exist_ok=True)
        for seed in seeds:
            rig, mods = _fitted(seed, where, masses, mass_log_sd, sag_steps, n_linked, three)
            arms = rig.robot.measured_arms()
            m = rig.measurements.mask("+".join(arms), "test")
            commands = [rig.measurements.commands[a][m] for a in arms]
            seen, target = rig.measurements.observed[m], rig.measurements.target[m]
            obs = np.linalg.norm(seen - target, axis=1)
            row: dict = {"seed": seed}
            for variant in variants:
                # the prior is read when the stiffnesses are set and again when drawn
                with _prior(*variant):
                    mods.stiffness = cp.stiffness_priors(rig, arms, mods.calibration)
                    draws = cp.chain_draws(mods, arms, commands, seed=seed)
                level = cp.hdr_levels(draws, seen)
                pred = np.linalg.norm(draws - target[None], axis=-1).mean(axis=0)
                p = pooled[variant]
                p["in50"] += (level < 0.5).tolist()
                p["in90"] += (level < 0.9).tolist()
                p["pred"] += pred.tolist()
                p["obs"] += obs.tolist()
                row["/".join(map(str, variant))] = [
                    float(np.mean(level < 0.5)), float(np.mean(level < 0.9)),
                    float(pred.mean() / obs.mean())]
            row["observed_mean_error_mm"] = float(obs.mean())
            print(json.dumps(row), flush=True)
            # each variant's draws compile programs of their own, whose code stays mapped until
            # released: a sweep of 26 variants ran the process out of memory maps on its sixth
            # rig (LLVM: cannot allocate memory)
            jax.clear_caches()
    return {"/".join(map(str, v)): {
        "points": len(p["in50"]), "coverage50": float(np.mean(p["in50"])),
        "coverage90": float(np.mean(p["in90"])),
        "error_ratio": float(np.mean(p["pred"]) / np.mean(p["obs"]))}
            for v, p in pooled.items()}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--coverage", choices=("tuning", "report"),
                   help="the linked coverage study instead of the timing")
    p.add_argument("--variants", action="store_true",
                   help="with --coverage: every prior in VARIANTS, not only the chosen one")
    p.add_argument("--cache", metavar="DIR",
                   help="with --coverage: keep the rigs and fitted modules here for a rerun")
    p.add_argument("--masses", choices=MASS_SOURCES, default=MASS_SOURCES[0],
                   help="with --coverage: the links' masses fitted, or held at the URDF's "
                        "(then the stiffnesses come from the fitted compliances)")
    p.add_argument("--mass-spread", type=float, default=0.0, metavar="SD",
                   help="with --coverage: log sd of the simulated arms' true link masses "
                        "about the URDF's (0)")
    p.add_argument("--sag-steps", type=int, default=1, metavar="N",
                   help="with --coverage: the calibration's steps of the sag's torques (1)")
    p.add_argument("--many-rigs", action="store_true",
                   help=f"with --coverage: {len(MANY_REPORT_SEEDS)} rigs of "
                        f"{MANY_LINKED} linked points instead of {len(REPORT_SEEDS)} of the "
                        "simulator's default number")
    p.add_argument("--rechosen", action="store_true",
                   help="with --coverage report --many-rigs: the rigs that report the prior "
                        "chosen on the many-rig tuning rigs")
    p.add_argument("--sag-variants", action="store_true",
                   help="with --coverage: every prior in SAG_VARIANTS (the arm term centred "
                        "on the arms' fitted sags)")
    p.add_argument("--three-arms", action="store_true",
                   help="with --coverage: three arms joined at one point (left, right, front), "
                        f"{MANY_LINKED} linked points per rig, with the chosen prior "
                        "(THREE_TUNING_SEEDS or THREE_REPORT_SEEDS)")
    p.add_argument("--sag-report", action="store_true",
                   help="with --coverage report --many-rigs: the rigs that report the arm "
                        "term centred on the arms' fitted sags")
    args = p.parse_args()
    if args.many_rigs and not args.coverage:
        p.error("--many-rigs needs --coverage")
    for flag in ("rechosen", "sag_report"):
        if getattr(args, flag) and not (args.many_rigs and args.coverage == "report"):
            p.error(f"--{flag.replace('_', '-')} needs --coverage report --many-rigs")
    if (args.rechosen or args.sag_report) and args.masses == "description":
        # the described-masses route has its own report rigs; these report the prior
        p.error("--rechosen and --sag-report report the stiffness prior: drop --masses "
                "description")
    if args.variants and args.sag_variants:
        p.error("give --variants or --sag-variants, not both")
    if args.three_arms and (not args.coverage or args.many_rigs or args.rechosen
                            or args.sag_report or args.variants or args.sag_variants
                            or args.masses == "description" or args.mass_spread
                            or args.sag_steps != 1):
        p.error("--three-arms takes --coverage tuning|report (and --cache) only: it reports "
                "the chosen prior")
    if args.three_arms:
        seeds = THREE_TUNING_SEEDS if args.coverage == "tuning" else THREE_REPORT_SEEDS
        print(json.dumps(coverage(seeds, [chosen_prior()],
                                  Path(args.cache) if args.cache else None,
                                  n_linked=MANY_LINKED, three=True)))
        return
    if args.coverage:
        described = args.masses == "description"
        if args.many_rigs and args.coverage == "tuning":
            seeds = MANY_TUNING_SEEDS
        elif args.rechosen:
            seeds = MANY_RECHOSEN_REPORT_SEEDS
        elif args.sag_report:
            seeds = MANY_SAG_REPORT_SEEDS
        elif args.many_rigs:
            seeds = MANY_DESCRIPTION_REPORT_SEEDS if described else MANY_REPORT_SEEDS
        else:
            seeds = (TUNING_SEEDS if args.coverage == "tuning"
                     else DESCRIPTION_REPORT_SEEDS if described else REPORT_SEEDS)
        print(json.dumps(coverage(seeds, VARIANTS if args.variants
                                  else SAG_VARIANTS if args.sag_variants else [chosen_prior()],
                                  Path(args.cache) if args.cache else None, args.masses,
                                  args.mass_spread, args.sag_steps,
                                  MANY_LINKED if args.many_rigs else None)))
        return

    from bayesrob.assembly import predict_assembly
    from bayesrob.chain_prediction import fit_chain_modules, hdr_sizes, predict_chain_points
    from bayesrob.chain_simulator import LinkedChainTruth, simulate_linked_chain_rig
    from bayesrob.rig import load_rig

    with tempfile.TemporaryDirectory() as tmp:
        rig = load_rig(simulate_linked_chain_rig(Path(tmp) / "rig", LinkedChainTruth(seed=0)))
        targets = rig.measurements.target[rig.measurements.mask("left+right", "test")][:16]
        whole, step, single = [], [], []
        for k in range(args.repeats + 1):  # the first run compiles
            t0 = time.perf_counter()
            predict_assembly(rig, "left+right", targets, seed=k)
            t1 = time.perf_counter()
            predict_assembly(rig, "left", targets, seed=k)
            if k:
                whole.append(t1 - t0)
                single.append(time.perf_counter() - t1)
        mods = fit_chain_modules(rig, ["left", "right"])
        for k in range(args.repeats + 1):
            t0 = time.perf_counter()
            _, draws = predict_chain_points(mods, rig, ["left", "right"], targets,
                                               "equilibrium", seed=k)
            hdr_sizes(draws)
            if k:
                step.append(time.perf_counter() - t0)
    w = float(np.median(whole))
    print(json.dumps({"targets": len(targets), "arms": 2, "joints_per_arm": 6,
                      "predict_warm_s": w, "prediction_step_warm_s": float(np.median(step)),
                      "single_arm_predict_warm_s": float(np.median(single)),
                      "target_s": WARM_TARGET_S, "met": w < WARM_TARGET_S}))


if __name__ == "__main__":
    main()
