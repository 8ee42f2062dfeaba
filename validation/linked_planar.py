"""Linked planar arms predicted before they are built: how often the measured linked end point
falls inside the predicted 50% / 90% regions, and the predicted against the observed mean
linked error (docs/fusion.md).

Three studies:

- :func:`run`: two arms (``top+bottom``) linked by the equilibrium rule on rigs with gravity
  sag and backlash, each arm's stiffnesses drawn per seed, every improved model scored at the
  rigs' linked test rows; the product of likelihoods is measured beside it.
- :func:`three_arms_kde`: three arms (``top+bottom+side``) predicted from the modules'
  single-arm rows only (``predict_assembly`` on a copy of the rig without linked rows), the
  eight-parameter fits and the KDE models ``ind`` and ``cond``.
- :func:`three_arms_physics`: the same three arms through their fitted physics (``predict
  --params ...,compliance,backlash``), the assembly measured at predict's own commands.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from pathlib import Path
from tempfile import TemporaryDirectory
from typing import Any

import numpy as np

IMPROVED = ("ind", "corr", "cond")
EFFECTS = ("gravity_sag", "backlash")
FUSIONS = ("equilibrium", "product")
# Two arms are not equally stiff: with one stiffness for every arm a prior that linked arms
# are alike would be right by construction (docs/fusion.md, "a trap").
STIFFNESS_LOG_SD = 0.3
THREE_ARMS = "top+bottom+side"
THREE_ARM_MODELS = ("ind", "cond")
# The three-arm study through the arms' fitted physics. Its groups were chosen on
# THREE_ARM_TUNING_SEEDS (ind: with compliance alone 0.625 / 0.958, error ratio 1.251; with
# backlash too 0.583 / 0.948, 1.077); its report seeds were fixed before any of them ran.
THREE_ARM_TUNING_SEEDS = tuple(range(101, 107))
THREE_ARM_REPORT_SEEDS = tuple(range(611, 617))
THREE_ARM_GROUPS = ("frames", "offsets", "geometric", "servo", "compliance", "backlash")
MASSES = (0.5, 0.9)


def single_arm_copy(rig_dir: Path, out: Path) -> Path:
    """The rig with every linked row removed: what a lab has before linking the arms."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "rig.toml").write_text((rig_dir / "rig.toml").read_text())
    lines = (rig_dir / "measurements.csv").read_text().splitlines()
    col = lines[0].split(",").index("config")
    kept = [ln for ln in lines[1:] if "+" not in ln.split(",")[col]]
    (out / "measurements.csv").write_text("\n".join([lines[0], *kept]) + "\n")
    return out


def fit_model(rig_dir: Path, model: str) -> tuple[Any, dict, dict]:
    """The rig, its arms calibrated on their train rows, and ``model`` fitted to each arm."""
    from bayesrob.calibrate.arms import calibrate_arms
    from bayesrob.data.rig import load_rig
    from bayesrob.errors.noise_models import discover_models, fit_noise_models

    rig = load_rig(rig_dir)
    arms = {n: c.arm for n, c in calibrate_arms(rig).items()}
    spec = [s for s in discover_models() if s.name == model]
    return rig, arms, fit_noise_models(rig, arms, spec)[model]


def linked_scores(rig: Any, arms: dict, fitted: dict, config: str, fusion_rule: str
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """HDR levels of the test rows of ``config`` under ``fusion_rule``, and per row the
    predicted mean distance from the target and the observed one."""
    from bayesrob.compare.comparison import score_points
    from bayesrob.predict.grid import setup_rows

    rows = setup_rows(rig, arms, config)
    members = config.split("+")
    scores, post = score_points([fitted[a] for a in members], [arms[a] for a in members],
                                [rows["commands"][a] for a in members], rows["targets"],
                                rows["observed"], fusion_rule)
    dist = np.linalg.norm(post.points() - rows["targets"][:, None, :], axis=-1)
    predicted = np.einsum("tm,tm->t", post.prob, dist)
    observed = np.linalg.norm(rows["observed"] - rows["targets"], axis=1)
    return scores.hdr_level, predicted, observed


def _tally(levels: np.ndarray, predicted: np.ndarray, observed: np.ndarray) -> dict[str, Any]:
    """One rig's counts, from which any set of rigs pools exactly (the docs' tables pool
    halves of the report rigs)."""
    return {"points": int(levels.size), "in50": int(np.sum(levels <= 0.5)),
            "in90": int(np.sum(levels <= 0.9)), "predicted_sum_mm": float(predicted.sum()),
            "observed_sum_mm": float(observed.sum())}


def _pooled(tallies: Sequence[dict[str, Any]]) -> dict[str, float]:
    n = sum(t["points"] for t in tallies)
    observed = sum(t["observed_sum_mm"] for t in tallies)
    return {"points": n, "coverage50": sum(t["in50"] for t in tallies) / n,
            "coverage90": sum(t["in90"] for t in tallies) / n,
            "error_ratio": sum(t["predicted_sum_mm"] for t in tallies) / observed,
            "observed_mean_error_mm": observed / n}


def run(seeds: list[int], *, quick: bool, say: Callable[[str], None]) -> dict[str, Any]:
    """Two arms linked on sag-and-backlash rigs, per improved model and fusion rule."""
    from bayesrob.sim.rigs import simulate_rig
    from bayesrob.sim.truth import paper_truth

    rigs: list[dict[str, Any]] = []
    with TemporaryDirectory(prefix="bayesrob-linked-") as tmp:
        for i, seed in enumerate(seeds, 1):
            rig_dir = simulate_rig(Path(tmp) / f"rig{seed}",
                                   paper_truth(EFFECTS, seed=seed,
                                               stiffness_log_sd=STIFFNESS_LOG_SD))
            row: dict[str, Any] = {"seed": seed}
            for model in IMPROVED:
                fit = fit_model(rig_dir, model)
                for fusion in FUSIONS:
                    row[f"{fusion}.{model}"] = _tally(*linked_scores(*fit, "top+bottom",
                                                                     fusion))
            rigs.append(row)
            eq = {m: _pooled([row[f"equilibrium.{m}"]]) for m in IMPROVED}
            say(f"rig {i}/{len(seeds)} (seed {seed}): equilibrium "
                + ", ".join(f"{m} {p['coverage50']:.2f} / {p['coverage90']:.2f} / "
                            f"{p['error_ratio']:.2f}" for m, p in eq.items()))
    figures: dict[str, Any] = {}
    for fusion in FUSIONS:
        for model in IMPROVED:
            pooled = _pooled([r[f"{fusion}.{model}"] for r in rigs])
            for key in ("points", "coverage50", "coverage90", "error_ratio"):
                figures[f"{fusion}.{model}.{key}"] = pooled[key]
    # the same rows for every model and rule
    figures["observed_mean_error_mm"] = _pooled(
        [r["equilibrium.ind"] for r in rigs])["observed_mean_error_mm"]
    return figures | {"details": {"study": "two_arms", "rigs": rigs}}


def three_arms_kde(seeds: list[int], *, quick: bool, say: Callable[[str], None]
                   ) -> dict[str, Any]:
    """Three arms predicted from single-arm rows (eight-parameter fits, KDE models): each
    point's HDR level under the equilibrium of the rig's own linked rows, and the mean error
    ``predict`` gives against the observed."""
    from bayesrob.data.rig import load_rig
    from bayesrob.predict.assembly import predict_assembly
    from bayesrob.sim.rigs import simulate_rig
    from bayesrob.sim.truth import three_arm_truth

    rigs: list[dict[str, Any]] = []
    with TemporaryDirectory(prefix="bayesrob-three-") as tmp:
        for i, seed in enumerate(seeds, 1):
            rig_dir = simulate_rig(Path(tmp) / f"three{seed}",
                                   three_arm_truth(EFFECTS, seed=seed,
                                                   stiffness_log_sd=STIFFNESS_LOG_SD))
            single = load_rig(single_arm_copy(rig_dir, Path(tmp) / f"single{seed}"))
            targets = load_rig(rig_dir).config_rows(THREE_ARMS, "test")["target"]
            row: dict[str, Any] = {"seed": seed}
            for model in THREE_ARM_MODELS:
                pred = predict_assembly(single, THREE_ARMS, targets, model)
                levels, _, observed = linked_scores(*fit_model(rig_dir, model), THREE_ARMS,
                                                    "equilibrium")
                row[model] = _tally(levels, pred.expected_error_mm, observed)
            rigs.append(row)
            say(f"rig {i}/{len(seeds)} (seed {seed}): " + ", ".join(
                f"{m} {p['coverage50']:.2f} / {p['coverage90']:.2f} / {p['error_ratio']:.2f}"
                for m, p in ((m, _pooled([row[m]])) for m in THREE_ARM_MODELS)))
    figures: dict[str, Any] = {}
    for model in THREE_ARM_MODELS:
        pooled = _pooled([r[model] for r in rigs])
        for key in ("points", "coverage50", "coverage90", "error_ratio"):
            figures[f"{model}.{key}"] = pooled[key]
    return figures | {"details": {"study": "three_arms_kde", "rigs": rigs}}


def three_arm_study(seeds: Sequence[int], groups: tuple[str, ...] = THREE_ARM_GROUPS,
                    model: str = "ind", where: Path | None = None,
                    say: Callable[[str], None] = print) -> dict[str, Any]:
    """Three arms through their fitted physics, pooled over ``seeds``: on each rig
    (``simulator.three_arm_truth``: sag and backlash, every arm's stiffnesses drawn)
    ``predict`` sees the single-arm rows only and gives, per linked target, the commands and
    the draws of the shared end point; the simulator then measures the assembly at exactly
    those commands (the rig's own linked rows were aimed through the eight-parameter fits, so
    they are not what ``predict`` would build). Returns the linked points, the share inside
    the 50% / 90% regions, the predicted / observed mean error, and per rig in ``rigs`` (each
    also said as a JSON line)."""
    from bayesrob.data.rig import load_rig
    from bayesrob.predict.assembly import predict_assembly
    from bayesrob.predict.regions import hdr_levels
    from bayesrob.sim.equilibrium import PhysicalRig
    from bayesrob.sim.rigs import round_pulse, simulate_rig
    from bayesrob.sim.truth import three_arm_truth

    levels, pred, obs, rigs = [], [], [], []
    with TemporaryDirectory(prefix="bayesrob-three-physics-") as tmp:
        root = Path(where or tmp)
        for seed in seeds:
            truth = three_arm_truth(EFFECTS, seed=seed, stiffness_log_sd=STIFFNESS_LOG_SD)
            full = root / f"three{seed}"
            if not (full / "truth.toml").is_file():
                simulate_rig(full, truth)
            rig = load_rig(single_arm_copy(full, root / f"single{seed}"))
            targets = load_rig(full).config_rows(THREE_ARMS, "test")["target"]
            p = predict_assembly(rig, THREE_ARMS, targets, model, groups=groups)
            # the assembly measured once at predict's commands, rounded to the servos' 0.25 us,
            # with noise from a stream of its own
            plant = PhysicalRig(truth, seed=10_000 + seed)
            seen = np.array([plant.end_point({a: round_pulse(u[t]) for a, u in
                                              p.commands.items()})
                             for t in range(len(targets))])
            lv = hdr_levels(p.draws, seen)
            o = np.linalg.norm(seen - targets, axis=1)
            levels.append(lv)
            pred.append(p.expected_error_mm)
            obs.append(o)
            rigs.append({"seed": seed, "coverage50": float(np.mean(lv < 0.5)),
                         "coverage90": float(np.mean(lv < 0.9)),
                         "error_ratio": float(p.expected_error_mm.mean() / o.mean()),
                         "observed_mean_error_mm": float(o.mean())})
            say(json.dumps(rigs[-1]))
    lv = np.concatenate(levels)
    return {"points": int(lv.size), "coverage50": float(np.mean(lv < 0.5)),
            "coverage90": float(np.mean(lv < 0.9)),
            "error_ratio": float(np.concatenate(pred).mean() / np.concatenate(obs).mean()),
            "observed_mean_error_mm": float(np.concatenate(obs).mean()),
            "groups": list(groups), "model": model, "rigs": rigs}


def three_arms_physics(seeds: list[int], *, quick: bool, say: Callable[[str], None]
                       ) -> dict[str, Any]:
    """:func:`three_arm_study` with the chosen groups and ``ind``."""
    got = three_arm_study(seeds, say=lambda line: say(f"rig {line}"))
    figures = {k: got[k] for k in ("points", "coverage50", "coverage90", "error_ratio",
                                   "observed_mean_error_mm")}
    return figures | {"details": {"study": "three_arms_physics", "groups": got["groups"],
                                  "model": got["model"], "rigs": got["rigs"]}}


def _seed_span(seeds: Sequence[int]) -> str:
    seeds = sorted(seeds)
    if len(seeds) > 1 and seeds == list(range(seeds[0], seeds[-1] + 1)):
        return f"{seeds[0]}-{seeds[-1]}"
    return ", ".join(map(str, seeds))


def _rigs(seeds: Sequence[int]) -> str:
    return f"rig{'s' if len(seeds) > 1 else ''} {_seed_span(seeds)}"


def _pair(p: dict[str, float]) -> str:
    return f"{p['coverage50']:.3f} / {p['coverage90']:.3f}"


def tables(entry: dict[str, Any]) -> dict[str, str]:
    details = entry.get("details") or {}
    f = entry["figures"]
    kind = details.get("study")
    if kind == "two_arms":
        rows = ["| model | linked product | linked equilibrium | predicted / observed linked "
                "error (product, equilibrium) |", "|---|---|---|---|"]
        for m in IMPROVED:
            rows.append(f"| {m} | {f[f'product.{m}.coverage50']:.2f} / "
                        f"{f[f'product.{m}.coverage90']:.2f} | "
                        f"{f[f'equilibrium.{m}.coverage50']:.2f} / "
                        f"{f[f'equilibrium.{m}.coverage90']:.2f} | "
                        f"{f[f'product.{m}.error_ratio']:.2f}, "
                        f"{f[f'equilibrium.{m}.error_ratio']:.2f} |")
        return {"coverage": "\n".join(rows)}
    if kind == "three_arms_kde":
        rigs = details["rigs"]
        seeds = [r["seed"] for r in rigs]
        half = len(rigs) // 2
        parts = [(f"{_rigs(seeds)} (report, {_pooled([r['ind'] for r in rigs])['points']}"
                  " points per model)", rigs)]
        if half:
            parts += [(f"{_rigs(seeds[:half])} alone", rigs[:half]),
                      (f"{_rigs(seeds[half:])} alone", rigs[half:])]
        rows = ["| | 50% / 90% regions | predicted / observed mean error |", "|---|---|---|"]
        for label, part in parts:
            pooled = {m: _pooled([r[m] for r in part]) for m in THREE_ARM_MODELS}
            rows.append(f"| {label} | "
                        + ", ".join(f"{m} {_pair(pooled[m])}" for m in THREE_ARM_MODELS)
                        + " | " + ", ".join(f"{m} {pooled[m]['error_ratio']:.3f}"
                                            for m in THREE_ARM_MODELS) + " |")
        return {"three_arms": "\n".join(rows)}
    if kind == "three_arms_physics":
        rigs = details["rigs"]
        extra = ",".join(g for g in details["groups"]
                         if g not in ("frames", "offsets", "geometric", "servo"))
        per_rig = ("| seed | 50% / 90% regions | predicted / observed mean error | observed "
                   "mean error (mm) |\n|---|---|---|---|\n" + "\n".join(
                       f"| {r['seed']} | {_pair(r)} | {r['error_ratio']:.3f} | "
                       f"{r['observed_mean_error_mm']:.3f} |" for r in rigs))
        summary = ("| groups (`frames,offsets,geometric,servo` +) | rigs | 50% / 90% regions |"
                   " predicted / observed mean error |\n|---|---|---|---|\n"
                   f"| `{extra}` | report {_seed_span([r['seed'] for r in rigs])} "
                   f"({f['points']} points) | {details['model']} {_pair(f)} | "
                   f"{details['model']} {f['error_ratio']:.3f} |")
        return {"physics": summary, "physics_rigs": per_rig}
    return {}
