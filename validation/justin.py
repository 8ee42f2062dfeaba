"""DLR's Agile Justin (torso and two 7-joint arms, 300 train / 200 validation poses, two hand
markers): real data nobody here produced. Two studies on it:

``run_ladder``: the calibration ladder (``--params frames``, ``frames,offsets``,
``frames,geometric``, the four rigid groups, ``frames,geometric,compliance``, ``...,lateral``,
and the last with its torques at equilibrium, ``--sag-steps 6``), each fitted on the 300 train
poses and scored on the 400 validation marker positions, beside the authors' published ladder.

``run_coverage``: with the model the diagnosis names (``frames,geometric,compliance,lateral``),
each hand's predicted 50% / 90% regions at its 200 validation poses, and its predicted mean
error against the observed one. Nothing here is tuned on the validation rows.

The data carries no licence: it is read from ``../shared/data/agile-justin/measurements.csv``
beside the checkout and never copied into the project; without it a study fails with one line
naming the path. The examples in ``examples/agile_justin/`` run the same code.
"""

from __future__ import annotations

import csv
import shutil
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from tempfile import TemporaryDirectory
from typing import Any

import numpy as np
from bayesrob.validation.study import repository

CHECKOUT = repository()
DATA = CHECKOUT.parent / "shared" / "data" / "agile-justin" / "measurements.csv"
# the rig description from the published nominal values (the examples' own)
RIG_TOML = CHECKOUT / "examples" / "agile_justin" / "rig.toml"
TORSO, RIGHT, LEFT = slice(0, 3), slice(3, 10), slice(10, 17)
HANDS = ("right", "left")


def justin_data(path: Path = DATA) -> Path:
    """The authors' file; a one-line error naming where it was looked for when absent."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: the Agile Justin data is not there (it is read from "
                                "../shared/data/ beside the checkout, never shipped)")
    return path


# ------------------------------------------------------------------------------ conversion


def _array(text: str, shape: tuple[int, ...], where: str) -> np.ndarray:
    try:
        values = np.array(text.replace("[", " ").replace("]", " ").split(), float)
    except ValueError:
        raise SystemExit(f"{where}: not a numeric array: {text[:40]!r}...") from None
    if values.size != int(np.prod(shape)) or not np.all(np.isfinite(values)):
        raise SystemExit(f"{where}: expected {np.prod(shape)} finite numbers, got {values.size}")
    return values.reshape(shape)


def convert(src: Path, out: Path, split: int = 300, rig_toml: Path = RIG_TOML) -> int:
    """Write the authors' ``measurements.csv`` (an index, ``joints``: 19 joint angles in rad,
    ``markers``: 2 x 3 in metres, right hand then left) into the rig directory ``out``; returns
    the number of poses. Rows keep the file's order (the authors shuffled it): the first
    ``split`` poses are ``train``, the rest ``validation``, as in the authors' scripts. Each pose
    becomes two rows, one per hand marker (config ``right`` / ``left``), in mm, each with the
    whole pose; ``rig_toml`` is copied beside it."""
    with open(src, newline="") as f:
        rows = list(csv.reader(f))
    header = [h.strip() for h in rows[0]]
    if header[1:] != ["joints", "markers"]:
        raise SystemExit(f"{src}: header must be ',joints,markers', got {','.join(header)!r}")
    out.mkdir(parents=True, exist_ok=True)
    cols = ([f"torso_u{k + 1}" for k in range(3)] + [f"right_u{k + 1}" for k in range(7)]
            + [f"left_u{k + 1}" for k in range(7)])
    lines = [["config", "set", *cols, "x", "y", "z", "pose"]]
    for i, row in enumerate(rows[1:]):
        where = f"{src}: line {i + 2}"
        q = _array(row[1], (19,), where + ": joints")
        markers = _array(row[2], (2, 3), where + ": markers") * 1000.0  # m -> mm
        st = "train" if i < split else "validation"
        # every row carries the whole pose: the other arm's weight bends the shared torso
        u = [f"{v:.10g}" for v in (*q[TORSO], *q[RIGHT], *q[LEFT])]
        for arm, m in (("right", markers[0]), ("left", markers[1])):
            lines.append([arm, st, *u, *(f"{v:.4f}" for v in m), row[0]])
    with open(out / "measurements.csv", "w", newline="") as f:
        csv.writer(f).writerows(lines)
    shutil.copy(rig_toml, out / "rig.toml")
    return len(rows) - 1


# ------------------------------------------------------------------------------ the ladder

# A quick run fits as the diagnosis's selection fits do, without the exact-Jacobian polish and
# with 140 evaluations a least-squares stage: the same steps in a fraction of the time, their
# errors within about 0.1 mm of the full fits'. The gravity steps still take minutes.
QUICK_FIT = {"polish": False, "max_nfev": 140}
# and takes the rigid steps only (seconds each): the conversion, the calibration and the
# scoring all run; the gravity steps' figures need the full run
QUICK_STEPS = 3

PUBLISHED = {  # mean / sd / max, mm (the authors' table)
    "frames": (21.33, 9.71, 63.41),
    "frames,offsets": (18.18, 7.8, 45.9),
    "frames,geometric": (10.5, 5.74, 36.37),
    # theirs with CAD masses; ours fits the masses' products with the compliances
    "frames,geometric,compliance": (5.64, 2.57, 12.83),
    "frames,geometric,compliance,lateral": (3.12, None, None),  # their full calibration
    "frames,geometric,compliance,lateral --sag-steps 6": (3.12, None, None),
}
# each step's name among the study's figures
STEP_KEYS = {
    "frames": "frames",
    "frames,offsets": "offsets",
    "frames,geometric": "geometric",
    "frames,offsets,geometric,servo": "rigid",
    "frames,geometric,compliance": "compliance",
    "frames,geometric,compliance,lateral": "lateral",
    # the same model with its torques taken six times, each at the pose the last sagged
    # into: a fixed point (a seventh step moves no train marker by 0.01 mm; the row's
    # sag_next_step_mm says so), chosen on two inner splits of the train poses
    # (docs/robots.md)
    "frames,geometric,compliance,lateral --sag-steps 6": "equilibrium",
}
STEPS = list(STEP_KEYS)
# the README's names of the steps
README_LABELS = {
    "frames,offsets,geometric,servo": "all four groups",
    "frames,geometric,compliance,lateral": "... ,lateral",
    "frames,geometric,compliance,lateral --sag-steps 6":
        "... at torque equilibrium (`--sag-steps 6`)",
}


def ladder(rig_dir: Path, steps: Sequence[str] = STEPS,
           say: Callable[[str], None] | None = None, polish: bool = True,
           max_nfev: int = 300) -> list[dict]:
    """One row per step: its fitted parameter count and train / validation marker errors.
    ``polish`` and ``max_nfev``: as :func:`~bayesrob.calibrate.least_squares.calibrate`'s."""
    from bayesrob import robot as kin
    from bayesrob.calibrate.least_squares import calibrate, sag_convergence
    from bayesrob.data.rig import load_rig

    rig = load_rig(rig_dir)
    out = []
    for i, step in enumerate(steps, 1):
        params, _, n_steps = step.partition(" --sag-steps ")
        groups = tuple(params.split(","))
        cal = calibrate(rig, groups, sag_steps=int(n_steps or 1), polish=polish,
                              max_nfev=max_nfev)
        extra = cal.extra
        if not polish and set(groups) & set(kin.SAG_GROUPS):
            # the fit reports its sag's convergence only after the polish
            extra = sag_convergence(rig, cal.x, int(n_steps or 1))
        out.append({"params": step, "n_free": int(cal.ident.free.sum()),
                    "train": cal.errors["train"]["all"],
                    "validation": cal.errors["validation"]["all"], "seconds": cal.seconds,
                    **{k: v for k, v in extra.items() if k.startswith("sag_")}})
        if say:
            say(f"step {i}/{len(steps)} ({step}): validation "
                f"{out[-1]['validation']['mean_mm']:.2f} mm in {cal.seconds:.0f} s")
    return out


def ladder_table(rows: list[dict]) -> str:
    """The ladder beside the published one, as the example prints it."""
    lines = ["| `--params` | fitted | train mean | validation mean / sd / max (ours) | "
             "published mean / sd / max |", "|---|---|---|---|---|"]
    for r in rows:
        v = r["validation"]
        pub = PUBLISHED.get(r["params"])
        pub_text = " / ".join("-" if p is None else f"{p:g}" for p in pub) if pub else "-"
        lines.append(f"| {r['params']} | {r['n_free']} | {r['train']['mean_mm']:.2f} | "
                     f"{v['mean_mm']:.2f} / {v['sd_mm']:.2f} / {v['max_mm']:.2f} | {pub_text} |")
    return "\n".join(lines)


def run_ladder(seeds: list[int], *, quick: bool, say: Callable[[str], None]) -> dict[str, Any]:
    # least squares from fixed starts: the seed picks nothing, the ladder is one run
    with TemporaryDirectory(prefix="bayesrob-justin-") as tmp:
        convert(justin_data(), Path(tmp) / "rig")
        rows = ladder(Path(tmp) / "rig", STEPS[:QUICK_STEPS] if quick else STEPS, say=say,
                      **(QUICK_FIT if quick else {}))
    figures: dict[str, Any] = {}
    for r in rows:
        key, v = STEP_KEYS[r["params"]], r["validation"]
        figures |= {f"{key}.mean_mm": v["mean_mm"], f"{key}.sd_mm": v["sd_mm"],
                    f"{key}.max_mm": v["max_mm"], f"{key}.train_mean_mm": r["train"]["mean_mm"],
                    f"{key}.fitted": r["n_free"]}
    points = [r["validation"]["n"] for r in rows]
    figures |= {"validation_points_min": min(points), "validation_points_max": max(points)}
    eq = [r for r in rows if STEP_KEYS[r["params"]] == "equilibrium"]
    if eq:  # the full run
        figures |= {
            "lateral_gain_mm": figures["compliance.mean_mm"] - figures["lateral.mean_mm"],
            "equilibrium.sag_steps": eq[0]["sag_steps"],
            "equilibrium.sag_next_step_mm": eq[0]["sag_next_step_mm"]}
    figures |= {
        "details": {"steps": [{k: r[k] for k in ("params", "n_free", "train", "validation",
                                                 "seconds")} for r in rows]},
    }
    return figures


# ------------------------------------------------------------------------------ coverage

COVERAGE_GROUPS = ("frames", "geometric", "compliance", "lateral")


def coverage(rig_dir: Path, groups: tuple[str, ...], model: str = "ind", seed: int = 0,
             sag_steps: int = 1, say: Callable[[str], None] | None = None,
             polish: bool = True, max_nfev: int = 300,
             hands: Sequence[str] = HANDS) -> list[dict]:
    """Per hand: the share of its validation points inside the predicted 50% and 90% regions
    and the predicted / observed mean error (observed: distance from the predicted mean
    point). The other arm's pose is given: its weight bends the torso. ``polish`` and
    ``max_nfev``: the calibration's, as :func:`~bayesrob.calibrate.least_squares.calibrate`'s."""
    from bayesrob.calibrate.least_squares import calibrate
    from bayesrob.data.rig import load_rig
    from bayesrob.predict.draws import assembly_draws, fit_modules
    from bayesrob.predict.regions import hdr_levels

    def note(text: str) -> None:
        (say or (lambda t: print(t, file=sys.stderr)))(text)

    rig = load_rig(rig_dir)
    cal = calibrate(rig, groups, sag_steps=sag_steps, polish=polish, max_nfev=max_nfev)
    for n in cal.extra.get("notes", []):  # e.g. the sag not at its equilibrium
        note(f"note: {n}")
    if say:
        say(f"calibrated ({','.join(groups)}): validation "
            f"{cal.errors['validation']['all']['mean_mm']:.2f} mm")
    mods = fit_modules(rig, list(hands), model, groups, seed=seed, calibration=cal)
    out = []
    for k, hand in enumerate(hands):
        u, obs = rig.rows(hand, "validation")
        draws = assembly_draws(mods, [hand], [u], seed=seed + k,
                            side=rig.side_rows(hand, "validation"))
        level = hdr_levels(draws, obs)
        mean = draws.mean(axis=0)
        predicted = float(np.linalg.norm(draws - mean[None], axis=-1).mean())
        observed = float(np.linalg.norm(obs - mean, axis=-1).mean())
        out.append({"hand": hand, "groups": list(groups), "model": model,
                    "sag_steps": sag_steps, "n": len(obs),
                    "coverage50": float(np.mean(level < 0.5)),
                    "coverage90": float(np.mean(level < 0.9)),
                    "predicted_error_mm": predicted, "observed_error_mm": observed,
                    "ratio": predicted / observed})
        if say:
            say(f"{hand} hand: {out[-1]['coverage50']:.3f} / {out[-1]['coverage90']:.3f}, "
                f"error ratio {out[-1]['ratio']:.2f}")
    return out


def run_coverage(seeds: list[int], *, quick: bool, say: Callable[[str], None]
                 ) -> dict[str, Any]:
    if len(seeds) != 1:
        raise ValueError(f"the coverage study is one seeded run on the real data, not {seeds}")
    with TemporaryDirectory(prefix="bayesrob-justin-") as tmp:
        convert(justin_data(), Path(tmp) / "rig")
        # quick: the rigid model (no gravity steps) and one hand, so the whole route runs in
        # a fraction of the time; the other hand's figures are "not run"
        rows = coverage(Path(tmp) / "rig", ("frames", "geometric") if quick else COVERAGE_GROUPS,
                        seed=seeds[0], say=say, hands=HANDS[:1] if quick else HANDS,
                        **(QUICK_FIT if quick else {}))
    figures: dict[str, Any] = {}
    for r in rows:
        figures |= {f"{r['hand']}.{k}": r[k] for k in (
            "coverage50", "coverage90", "ratio", "n", "predicted_error_mm", "observed_error_mm")}
    figures["details"] = {"hands": rows}
    return figures


# ------------------------------------------------------------------------------ compare

COMPARE_MODELS = ("ind", "corr", "cond")


def run_compare(seeds: list[int], *, quick: bool, say: Callable[[str], None]
                ) -> dict[str, Any]:
    """``bayesrob compare`` on the real data with the model the diagnosis names: every joint-
    error model's held-out elpd and coverage at the 200 validation poses of each hand, and
    leave-one-out over the 300 train poses. quick: the rigid geometric model, ind and cond."""
    from bayesrob.compare.comparison import compare_models
    from bayesrob.data.rig import load_rig

    if len(seeds) != 1:
        raise ValueError(f"the compare study is one seeded run on the real data, not {seeds}")
    with TemporaryDirectory(prefix="bayesrob-justin-") as tmp:
        convert(justin_data(), Path(tmp) / "rig")
        models = ("ind", "cond") if quick else COMPARE_MODELS
        groups = ("frames", "geometric") if quick else COVERAGE_GROUPS
        say(f"compare {', '.join(models)} with --params {','.join(groups)}")
        doc = compare_models(load_rig(Path(tmp) / "rig"), list(models), groups=groups
                             ).document()
    figures: dict[str, Any] = {}
    for name in models:
        m = doc["models"][name]
        figures |= {f"{name}.heldout_elpd": m["heldout"]["elpd"],
                    f"{name}.heldout_se": m["heldout"]["se"],
                    f"{name}.loo_elpd": m["loo_train"]["elpd"],
                    f"{name}.heldout_n": m["heldout"]["n"]}
        for hand in HANDS:
            s = m["heldout"]["by_setup"][hand]
            figures |= {f"{name}.{hand}.coverage50": s["coverage50"],
                        f"{name}.{hand}.coverage90": s["coverage90"],
                        f"{name}.{hand}.mean_lpd": s["mean_lpd"]}
    best, second = doc["heldout_compare"][:2]
    figures |= {"winner_elpd_diff": second["elpd_diff"], "winner_dse": second["dse"],
                "details": {"winner": best["model"], "runner_up": second["model"],
                            "groups": list(groups), "heldout_compare": doc["heldout_compare"],
                            "loo_compare": doc["loo_compare"], "seconds": doc["seconds"]}}
    return figures


# ------------------------------------------------------------------------------ tables


def tables(entry: dict[str, Any]) -> dict[str, str]:
    f = entry["figures"]
    if "ind.heldout_elpd" in f:
        rows = ["| model | held-out elpd (se) | LOO elpd, train | right: 50% / 90% | "
                "left: 50% / 90% |", "|---|---|---|---|---|"]
        for m in COMPARE_MODELS:
            if f.get(f"{m}.heldout_elpd") is None:
                continue
            cover = [f"{f[f'{m}.{h}.coverage50']:.3f} / {f[f'{m}.{h}.coverage90']:.3f}"
                     for h in HANDS]
            rows.append(f"| {m} | {f[f'{m}.heldout_elpd']:.1f} ({f[f'{m}.heldout_se']:.1f}) | "
                        f"{f[f'{m}.loo_elpd']:.1f} | {cover[0]} | {cover[1]} |")
        return {"compare": "\n".join(rows)}
    if "right.coverage50" in f:
        rows = ["| hand | 50% / 90% coverage | predicted / observed mean error (mm) |",
                "|---|---|---|"]
        rows += [f"| {h} | {f[f'{h}.coverage50']:.3f} / {f[f'{h}.coverage90']:.3f} | "
                 f"{f[f'{h}.predicted_error_mm']:.2f} / {f[f'{h}.observed_error_mm']:.2f} "
                 f"({f[f'{h}.ratio']:.2f}) |" for h in HANDS]
        return {"coverage": "\n".join(rows)}
    bold = {"compliance", "equilibrium"}  # the README's bold rows: the steps that beat theirs
    rows = ["| `--params` | fitted | ours: mean / sd / max | published: mean / sd / max |",
            "|---|---|---|---|"]
    for step, key in STEP_KEYS.items():
        ours = f"{f[f'{key}.mean_mm']:.2f} / {f[f'{key}.sd_mm']:.2f} / {f[f'{key}.max_mm']:.2f}"
        pub = PUBLISHED.get(step)
        pub_text = "-" if pub is None else " / ".join(f"{p:g}" for p in pub if p is not None)
        if key == "compliance":
            pub_text += " (CAD masses)"
        elif key == "lateral":
            pub_text += " (full, CAD masses)"
        rows.append(f"| {README_LABELS.get(step, step)} | {f[f'{key}.fitted']} | "
                    f"{f'**{ours}**' if key in bold else ours} | {pub_text} |")
    return {"ladder": "\n".join(rows)}
