"""``bayesrob compare`` on one rig: every shipped model's elpd on the held-out end points and by
exact leave-one-out over the training rows (each row left out of the calibration too),
through arviz's compare (elpd, se, elpd_diff, dse, stacking weight).

The seed names the rig: 2009 is the embedded default rig (the simulator regenerates it
byte for byte from that seed), the one the README's and docs/comparison.md's tables describe;
another seed simulates a rig of the same setup (the paper's, with gravity sag and backlash).
The study takes one seed: elpds of different rigs do not pool. Its figures are recorded, not
judged: the models were built looking at the default rig, and no issue set a range for them.
A quick run compares two models, the improved IND and the paper's, with the same code.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from tempfile import TemporaryDirectory
from typing import Any

from bayesrob.compare.comparison import compare_models
from bayesrob.data.rig import default_rig_dir, load_rig
from bayesrob.sim.rigs import simulate_rig
from bayesrob.sim.truth import paper_truth

DEFAULT_SEED = 2009
EFFECTS = ("gravity_sag", "backlash")
COLUMNS = ("elpd", "se", "elpd_diff", "dse", "weight", "rank")
KINDS = {"heldout": "heldout_compare", "loo": "loo_compare"}
QUICK_MODELS = ("ind", "ind_paper")


def run(seeds: list[int], *, quick: bool, say: Callable[[str], None]) -> dict[str, Any]:
    if len(seeds) != 1:
        raise ValueError(f"the comparison describes one rig: give one seed, not {seeds}")
    (seed,) = seeds
    with TemporaryDirectory(prefix="bayesrob-compare-") as tmp:
        rig_dir = (default_rig_dir() if seed == DEFAULT_SEED
                   else simulate_rig(Path(tmp) / "rig", paper_truth(EFFECTS, seed=seed)))
        rig = load_rig(rig_dir)
        say(f"comparing {'ind and ind_paper' if quick else 'every model'} on the rig of seed "
            f"{seed} ({'about half a minute' if quick else 'about two minutes'})")
        doc = compare_models(rig, QUICK_MODELS if quick else None).document()
    figures: dict[str, Any] = {}
    order: dict[str, list[str]] = {}
    for kind, key in KINDS.items():
        order[kind] = [r["model"] for r in doc[key]]
        for r in doc[key]:
            for col in COLUMNS:
                figures[f"{kind}.{r['model']}.{col}"] = r[col]
    some = order["heldout"][0]
    figures["heldout.points"] = doc["models"][some]["heldout"]["n"]
    figures["loo.points"] = doc["models"][some]["loo_train"]["n"]
    figures["details"] = {"order": order, "seed": seed}
    return figures


def _compare_table(f: dict[str, Any], kind: str, order: list[str], caption: str) -> str:
    rows = [f"| {caption} (n = {f[f'{kind}.points']}) | elpd | se | elpd_diff | dse | weight |",
            "|---|---|---|---|---|---|"]
    for m in order:
        g = {c: f[f"{kind}.{m}.{c}"] for c in COLUMNS}
        diff = ("0 | 0" if g["rank"] == 0 else f"{g['elpd_diff']:.1f} | {g['dse']:.1f}")
        rows.append(f"| {m} | {g['elpd']:.1f} | {g['se']:.1f} | {diff} | {g['weight']:.2f} |")
    return "\n".join(rows)


def tables(entry: dict[str, Any]) -> dict[str, str]:
    f, order = entry["figures"], entry["details"]["order"]
    readme = ["| model | held-out elpd (se) | LOO elpd (se) |", "| --- | --- | --- |"]
    for m in order["heldout"]:
        readme.append(f"| {m} | {f[f'heldout.{m}.elpd']:.1f} ({f[f'heldout.{m}.se']:.1f}) | "
                      f"{f[f'loo.{m}.elpd']:.1f} ({f[f'loo.{m}.se']:.1f}) |")
    return {"readme": "\n".join(readme),
            "heldout": _compare_table(f, "heldout", order["heldout"], "held out"),
            "loo": _compare_table(f, "loo", order["loo"], "LOO over train rows")}
