"""Terminal tables of the reports (the JSON documents are the contract; these are for people)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from bayesrob.data.vocabulary import EQUILIBRIUM
from bayesrob.robot import PARAM_NAMES

if TYPE_CHECKING:
    from bayesrob.design.search import DesignResult
    from bayesrob.inference.sampling import SampleReport
    from bayesrob.plan.planner import Plan
    from bayesrob.predict.assembly import AssemblyPrediction


def _fmt(x: float | None, nd: int = 2) -> str:
    return "-" if x is None else f"{x:.{nd}f}"


def format_table(header: list[str], rows: list[list[str]]) -> str:
    widths = [max(len(str(r[i])) for r in [header, *rows]) for i in range(len(header))]
    line = "  ".join(h.ljust(w) for h, w in zip(header, widths, strict=True))
    out = [line, "  ".join("-" * w for w in widths)]
    out += ["  ".join(str(c).ljust(w) for c, w in zip(r, widths, strict=True)) for r in rows]
    return "\n".join(out)


def format_calibration(doc: dict) -> str:
    """Parameters with standard errors per arm, then observed accuracy per config and set."""
    parts = [f"calibration: {doc['method']}"]
    for name, arm in doc["arms"].items():
        rows = []
        flat = [v for k in ("base", "links", "gain", "offset") for v in arm["params"][k]]
        se = [v for k in ("base", "links", "gain", "offset") for v in arm["params_se"][k]]
        for pname, v, s in zip(PARAM_NAMES, flat, se, strict=True):
            nd = 6 if pname.startswith("a") else 4
            rows.append([pname, f"{v:.{nd}f}", f"{s:.{nd}f}"])
        parts.append(f"\narm {name} (elbow {arm['elbow']:+d}): train {_fmt(arm['train_error_mm'])} "
                     f"mm, validation {_fmt(arm['validation_error_mm'])} mm")
        spread = "posterior sd" if doc["method"] == "bayes" else "std err"
        parts.append(format_table(["param", "value", spread], rows))
    rows = [[config, s, f"{acc['mean_mm']:.2f}", "[{:.2f}, {:.2f}]".format(*acc["ci95_mm"]),
             str(acc["n"])] for config, sets in doc["accuracy"].items() for s, acc in sets.items()]
    parts.append("\nobserved accuracy (mean Euclidean error, mm)")
    parts.append(format_table(["config", "set", "mean", "95% CI", "n"], rows))
    return "\n".join(parts)


def format_group_calibration(doc: dict) -> str:
    """Groups fitted, what the rank analysis fixed, and the error per set and arm."""
    parts = [f"calibration: {doc['method']} of {doc['rig']}, groups {', '.join(doc['params'])}: "
             f"{doc['n_free']} of {doc['n_parameters']} parameters fitted "
             f"({doc['seconds']:.1f} s, {doc['nfev']} evaluations)"]
    if doc["unidentifiable"]:
        parts.append(f"\nnot identifiable from the train rows, fixed at nominal "
                     f"({len(doc['unidentifiable'])}):")
        for u in doc["unidentifiable"][:12]:
            combo = " + ".join(f"{c:+.3g} {n}" for n, c in u["explained_by"].items())
            parts.append(f"  {u['name']}  ~  {combo}")
        if len(doc["unidentifiable"]) > 12:
            parts.append(f"  ... and {len(doc['unidentifiable']) - 12} more (all in --json)")
    if doc["not_observed"]:
        parts.append(f"no measured point depends on: {', '.join(doc['not_observed'])}")
    if "posterior" in doc:
        p = doc["posterior"]
        parts.append(f"\nposterior (NUTS, {p['chains']} chains, {p['draws']} draws): r_hat max "
                     f"{p['r_hat_max']:.3f}, bulk ESS min {p['ess_bulk_min']:.0f}, "
                     f"{p['divergences']} divergences, noise sd {p['noise_sd_mm']:.3f} mm; "
                     "values below are at the posterior mean")
    rows = [[s, arm, _fmt(e["mean_mm"]), _fmt(e["sd_mm"]), _fmt(e["max_mm"]), str(e["n"])]
            for s, arms in doc["errors"].items() for arm, e in arms.items()]
    parts.append("\nmarker error (mm)")
    parts.append(format_table(["set", "arm", "mean", "sd", "max", "n"], rows))
    parts += [f"note: {n}" for n in doc.get("notes", [])]
    return "\n".join(parts)


WARNINGS_HEADING = "warnings (results may be wrong; see each line for what to change):"
NOTES_HEADING = ("notes (expected for these estimators on this data; nothing to fix, the "
                 "results stand):")


def grouped_notes(warnings: Sequence[str], notes: Sequence[str]) -> list[str]:
    """Warnings and notes under headings that say whether they matter, warnings first."""
    out = []
    for heading, lines, prefix in ((WARNINGS_HEADING, warnings, "warning: "),
                                   (NOTES_HEADING, notes, "note: ")):
        if lines:
            out.append(heading)
            out += [f"  {line.removeprefix(prefix)}" for line in lines]
    return out


def format_diagnosis(doc: dict) -> str:
    """``bayesrob diagnose``'s report on a planar rig: residual structure, each round's
    candidates, the named effects."""
    out = [f"diagnosis of rig {doc['rig']!r}", f"decision rule: {doc['rule']}", "",
           "residual structure of the base model (p values: small means not noise)"]
    rows = []
    for a, t in doc["residual_tests"]["before"].items():
        lof = t.get("lack_of_fit", {})
        jump = t.get("largest_jump", {})
        w = t["worst_region"]
        rows.append([a, _fmt(lof.get("p_value"), 3), _fmt(t["morans_i"]["p_value"], 3),
                     f"{_fmt(jump.get('mm'))} ({_fmt(jump.get('p_value'), 3)})",
                     f"{w['region']} {_fmt(w['mean_mm'])} vs {_fmt(w['elsewhere_mm'])}",
                     " ".join(f"{k}:{_fmt(v['p_value'], 3)}" for k, v in t["score_tests"].items())])
    out.append(format_table(["arm", "lack of fit", "Moran I", "max jump mm (p)",
                             "worst region (mm)", "signature p"], rows))
    for t in doc["residual_tests"]["before"].values():
        w, jump = t["worst_region"], t.get("largest_jump")
        line = (f"  {t['arm']} arm: largest residuals {w['region']} ({w['mean_mm']:.2f} mm "
                f"against {w['elsewhere_mm']:.2f} mm elsewhere)")
        if jump:
            line += f"; largest jump between neighbours {jump['mm']:.2f} mm, {jump['where']}"
        out.append(line)
    for r, scores in enumerate(doc["rounds"], start=1):
        out += ["", f"round {r}: each candidate added to the model named so far"]
        rows = [[s["effect"], ",".join(s["arms"]) or "-",
                 f"{_fmt(s['heldout_error_before_mm'])} -> {_fmt(s['heldout_error_after_mm'])}",
                 f"{_fmt(s['cv_error_before_mm'])} -> {_fmt(s['cv_error_after_mm'])}",
                 f"{s['z']:.2f}", f"{s['elpd_diff']:+.1f} +- {s['elpd_diff_se']:.1f}",
                 "yes" if s["passes"] else "no"] for s in scores]
        out.append(format_table(["candidate", "arms", "held-out mm", "cross-val mm",
                                 "z (cross-val)", "elpd diff", "passes"], rows))
    out += ["", f"named effects: {', '.join(doc['effects']) or 'none'}"]
    gap = [f"base {_fmt(doc['baseline_heldout_error_mm'])} mm"]
    gap += [f"+{s['effect']} ({','.join(s['arms'])}) {_fmt(s['heldout_error_after_mm'])} mm"
            for s in doc["steps"]]
    out.append("held-out error per step: " + " -> ".join(gap))
    if doc.get("baseline_holdout_error_mm") is not None:
        hold = [f"base {_fmt(doc['baseline_holdout_error_mm'])} mm"]
        hold += [f"+{s['effect']} {_fmt(s.get('holdout_error_after_mm'))} mm" for s in doc["steps"]]
        out.append("  (held-out above: validation rows, which repeat the training commands; "
                   "at new poses, the holdout rows: " + " -> ".join(hold) + ")")
    if doc["steps"]:
        # From the final model, where every named effect is fitted jointly (a step's own
        # record keeps the values at the time it was named).
        out.append("fitted magnitudes (final model):")
        for name in doc["effects"]:
            for a, arm in doc["arms"].items():
                if name in arm["magnitudes"]:
                    out.append(f"  {name} in {a}: {arm['magnitudes'][name]['text']}")
    after = doc["residual_tests"]["after"]
    lof = ", ".join(f"{a} {t['lack_of_fit']['p_value']:.3g}" for a, t in after.items()
                    if "lack_of_fit" in t)
    moran = ", ".join(f"{a} {t['morans_i']['p_value']:.3g}" for a, t in after.items())
    out.append(f"final residuals: lack-of-fit p ({lof or '-'}); Moran's I p ({moran})")
    if not doc["steps"]:
        out.append("no candidate effect improves the held-out fit: none is named")
    return "\n".join(out)


def format_group_diagnosis(doc: dict) -> str:
    """``bayesrob diagnose``'s report on a URDF/DH rig: each round's candidates, then the
    ladder on the validation rows."""

    out = [f"diagnosis of rig {doc['rig']!r} (chains)", f"decision rule: {doc['rule']}"]
    for r, scores in enumerate(doc["rounds"], start=1):
        out += ["", f"round {r}: each candidate added to the model named so far"]
        out.append(format_table(
            ["candidate", "added parameters", "selection mm", "z", "passes"],
            [[s["effect"], str(s["parameters"]), f"{s['selection_error_before_mm']:.2f} -> "
              f"{s['selection_error_after_mm']:.2f}", f"{s['z']:.1f}",
              "yes" if s["passes"] else "no"] for s in scores]))
        # the steps this round named: one effect, or a pair ("a+b", the first built on)
        mine = [s for k, s in enumerate(doc["steps"], start=1) if s.get("round", k) == r]
        if not mine:
            continue  # nothing named in this round: no comparison with a named effect
        chosen, rivals = "+".join(s["effect"] for s in mine), mine[0]["rivals"]
        named = next(s for s in scores if s["effect"] == chosen)
        if not named.get("guard_passes", True):
            out.append(f"  {chosen} gains {named['elpd_diff']:+.1f} nats on the selection poses, "
                       f"less than {named['guard_nats']:.0f} for its {named['parameters']} "
                       "parameters (the parameter guard): its step may not carry to new poses")
        for s in (s for s in scores if "z_vs_named" in s):
            if s["effect"] in rivals:
                out.append(f"  {s['effect']} fits the selection poses as well as {chosen} "
                           f"(paired z {s['z_vs_named']:+.1f} of the two fits' errors): these "
                           "poses do not tell them apart")
            elif s["z_vs_named"] < -doc["rule_z"]:
                out.append(f"  {s['effect']} leaves smaller errors than {chosen} (paired z "
                           f"{s['z_vs_named']:+.1f}) with {s['parameters']} parameters "
                           "against its fewer: named later if it still passes on top of it")
    rows = [["geometric calibration", str(doc["baseline"]["n_free"]),
             *_ladder_cells(doc["baseline"])]]
    rows += [[f"+ {s['effect']}" + (f" (torques at equilibrium, {s['sag_steps']} steps)"
                                     if s.get("sag_steps", 1) > 1 else ""),
              str(s["n_free"]), *_ladder_cells(s)] for s in doc["steps"]]
    out += ["", "ladder on the validation rows (never used to decide):",
            format_table(["step", "fitted", "mean mm", "sd mm", "max mm"], rows), "",
            f"named effects: {', '.join(doc['effects']) or 'none'} ({doc['seconds']:.0f} s)",
            *doc["notes"]]
    return "\n".join(out)


def _ladder_cells(row: dict) -> list[str]:
    return [f"{row[k]:.2f}" for k in ("heldout_error_mm", "heldout_error_sd_mm",
                                       "heldout_error_max_mm")]


def format_accuracy(doc: dict) -> str:
    """The accuracy table: observed error per setup and each model's predicted error."""
    rows = []
    for config, s in doc["setups"].items():
        obs = s["observed"]
        lo, hi = obs["ci95_mm"]
        rows.append([config, "observed", f"{obs['mean_mm']:.2f}", f"[{lo:.2f}, {hi:.2f}]", ""])
        for model, p in s["predicted"].items():
            rows.append(["", model, f"{p['expected_error_mm']:.2f}", "",
                         f"{p['ratio']:.2f}"])
    return format_table(["setup", "observed / model", "error mm", "95% CI", "pred/obs"], rows)


def format_comparison(doc: dict) -> str:
    """Terminal tables of a comparison document."""
    parts = []
    unit = "mm^3" if "mm^3" in doc["score"] else "mm^2"
    tables = [("heldout_compare", "heldout", "held-out points"),
              ("loo_compare", "loo_train", "leave-one-out over training rows")]
    if doc.get("holdout_compare"):
        tables.append(("holdout_compare", "holdout", "holdout points (new poses and targets)"))
    for key, summary, title in tables:
        rows = [[r["model"], str(r["rank"]), f"{r['elpd']:.1f}", f"{r['se']:.1f}",
                 f"{r['elpd_diff']:.1f}", f"{r['dse']:.1f}", f"{r['weight']:.2f}"]
                for r in doc[key]]
        n = next(iter(doc["models"].values()))[summary]["n"]
        parts.append(f"{title} (n = {n}; elpd = sum of log density per {unit})")
        parts.append(format_table(["model", "rank", "elpd", "se", "elpd_diff", "dse", "weight"],
                                  rows))
        parts.append("")
    rows = []
    for name, m in doc["models"].items():
        sets = [("heldout", "")]
        if m.get("holdout"):
            sets.append(("holdout", " (holdout)"))
        for key, label in sets:
            for config, s in m[key]["by_setup"].items():
                if m.get("fusion") == EQUILIBRIUM and "+" not in config:
                    continue  # one arm: the same prediction as the product's row
                rows.append([name, config + label, str(s["n"]), f"{s['mean_lpd']:.2f}",
                             f"{s['coverage50']:.2f}", f"{s['coverage90']:.2f}",
                             f"{s['mean_hdr_level']:.2f}"])
    parts.append("held-out points by setup (coverage of the 50% / 90% regions; a calibrated "
                 "model has mean HDR level 0.5)")
    parts.append(format_table(["model", "setup", "n", "mean lpd", "cov50", "cov90",
                               "HDR level"], rows))
    w = doc["winner"]
    if w["over"] is not None:
        parts.append(f"\nwinner on held-out points: {w['model']}, ahead of {w['over']} by "
                     f"{w['elpd_diff']:.1f} elpd (dse {w['dse']:.1f})")
    return "\n".join(parts)


def format_sample(report: SampleReport) -> str:
    """Terminal summary: arviz diagnostics per sampler, moments side by side, the check."""
    doc = report.document
    dim = len(doc["target"])
    parts = [f"{doc['config']} aimed at ({', '.join(f'{v:.2f}' for v in doc['target'])}) mm, "
             f"model {doc['model']}"]
    for name, res in report.results.items():
        parts.append(f"\n{name}: az.summary ({res.seconds:.1f} s sampling, "
                     f"{res.compile_seconds:.1f} s compiling)")
        parts.append(res.summary.round(4).to_string())
    rows = []
    for name, s in doc["samplers"].items():
        sd = np.sqrt(np.diag(np.asarray(s["cov"])))
        # a plane's one correlation; in 3-D the three would crowd the table
        corr = [f"{s['cov'][0][1] / (sd[0] * sd[1]):+.3f}"] if dim == 2 else []
        rows.append([name, *(f"{v:.3f}" for v in s["mean"]), *(f"{v:.3f}" for v in sd), *corr,
                     f"{s['ess_bulk']:.0f}" if "ess_bulk" in s else "-",
                     f"{s['r_hat']:.4f}" if "r_hat" in s else "-", f"{s['seconds']:.2f}"])
    parts.append("")
    axes = "xyz"[:dim]
    parts.append(format_table(["sampler", *(f"mean {a}" for a in axes),
                               *(f"sd {a}" for a in axes), *(["corr"] if dim == 2 else []),
                               "ess_bulk", "r_hat", "seconds"], rows))
    g = doc["samplers"]["grid"]
    half = g.get("box_half_width_mm", 30)
    parts.append(f"grid: zoomed {'x'.join([str(g['n'])] * dim)} cells of "
                 f"{' x '.join(f'{c:.4f}' for c in g['cell_mm'])} mm; mass on the +-{half:g} mm "
                 f"box edge {g['edge_mass']:.1e}")
    check = doc["check"]
    if not check["passed"]:
        parts.append("check FAILED:")
        parts += [f"  {f}" for f in check["failures"]]
    elif not check["compared"]:
        parts.append(f"check: no sampler ran; the grid's box holds the posterior (edge mass "
                     f"<= {check['tolerances']['edge_mass']:g})")
    else:
        t = check["tolerances"]
        verb = "agrees" if len(check["compared"]) == 1 else "agree"
        parts.append(f"check PASSED: {', '.join(check['compared'])} {verb} with the grid "
                     f"(mean within {t['mean_mm']} mm, covariance within {t['cov_rel']:.0%}, "
                     f"r_hat <= {t['r_hat']}, bulk ESS >= {t['ess_bulk']:.0f})")
    parts += grouped_notes([], doc.get("notes", []))
    return "\n".join(parts)


def format_prediction(pred: AssemblyPrediction) -> str:
    """``bayesrob predict``'s table: each target's expected point, error and regions, then the
    summary, the linked arms' stiffnesses and the notes."""
    rows = [[", ".join(f"{v:.1f}" for v in t), ", ".join(f"{v:.2f}" for v in p), f"{e:.2f}",
             f"{a50:.3g}", f"{a90:.3g}"]
            for t, p, e, a50, a90 in zip(pred.targets, pred.expected_point,
                                         pred.expected_error_mm, pred.hdr50,
                                         pred.hdr90, strict=True)]
    head = (f"{pred.config} on {pred.rig}: model {pred.model}, fusion {pred.fusion}, "
            f"{len(pred.targets)} targets (from single-arm train rows only)")
    s = pred.document["summary"]
    u = pred.size_key
    unit = f"mm^{u[-1]}"
    tail = (f"mean expected error {s['mean_expected_error_mm']:.2f} mm (max "
            f"{s['max_expected_error_mm']:.2f}); mean 50% / 90% region "
            f"{s[f'mean_hdr50_{u}']:.3g} / {s[f'mean_hdr90_{u}']:.3g} {unit}")
    note = pred.extrapolation_note()
    springs = [f"joint stiffness of {a}, from {v['from']} ("
               + ("N mm/rad, median): " if "nmm_per_rad" in v else "relative to its first "
                  "joint): ")
               + " ".join(f"{k:.3g}" for k in v.get("nmm_per_rad", v.get("relative")))
               + (f"; the arm {np.exp(v['arm_log_centre']):.3g} times as stiff as the "
                  "linked arms' geometric mean, by its fitted sag"
                  if v.get("arm_log_centre") else "")
               for a, v in pred.stiffness.items()]
    return "\n".join([head, format_table(["target (mm)", "expected point", "E error mm",
                                          f"50% {unit}", f"90% {unit}"], rows), tail,
                      *springs, *([note] if note else []),
                      *([pred.stiffness_note] if pred.stiffness_note else [])])


def _bases_text(bases: Sequence[Sequence[float]]) -> str:
    return "; ".join("(" + ", ".join(f"{v:.0f}" for v in b) + ")" for b in bases)


def format_design(result: DesignResult, top: int = 10) -> str:
    """``bayesrob design``'s table: the ``top`` ranked candidates and the verdict."""
    d = result.design
    q = f"q{round(100 * d.quantile)}"
    rows = [[str(c["rank"]), c["config"],
             _bases_text(c["bases"]),
             f"{c['overall']['error_quantile_mm']:.3f}",
             f"{c['overall']['worst_target_quantile_mm']:.3f}",
             f"{c['overall']['expected_error_mm']:.3f}",
             f"{c['overall']['assured_error_mm']:.3f}", "yes" if c["meets"] else "no"]
            for c in result.candidates[:top]]
    head = (f"{len(result.candidates)} candidate assemblies ({result.n_reachable} of "
            f"{result.n_placements} module placements reach all {len(result.targets)} "
            f"targets), requirement {d.error_mm:g} mm at {d.quantile:g}, fusion "
            f"{d.fusion}, {result.workers} worker(s), {result.seconds:.1f} s")
    table = format_table(["rank", "assembly", "bases (mm)", f"{q} mm", f"worst {q} mm",
                          "E error mm", f"{q} in {d.confidence:.0%} mm", "meets"], rows)
    best = result.best
    if best is None:
        tail = "no candidate"
    elif best["meets"]:
        tail = (f"best: {best['config']} at " + _bases_text(best["bases"])
                + f", predicted {q} {best['overall']['error_quantile_mm']:.3f} mm")
    else:
        tail = (f"no candidate meets {d.error_mm:g} mm at {d.quantile:g} in "
                f"{d.confidence:.0%} of builds; the closest is {best['config']}, within "
                f"{best['overall']['assured_error_mm']:.3f} mm in {d.confidence:.0%}")
    return "\n".join([head, table, *result.notes, tail])


def format_plan(plan: Plan) -> str:
    """``bayesrob plan``'s line: the criterion before and after the planned poses."""
    bias = (f" (with the bias of the omitted {', '.join(plan.omitted)})"
            if plan.omitted else "")
    what = {"accuracy": "predicted end-point error over the task region" + bias,
            "identify": "log det of the parameters' information",
            "discriminate": "summed log det of the effects' own information"}[
        plan.criterion]
    return (f"{plan.criterion}: {what}: {plan.before:.4g} {plan.unit} before "
            f"({plan.n_measured} rows measured), {plan.after:.4g} {plan.unit} after the "
            f"{len(plan.selection.order)} planned poses (from {len(plan.pool)} "
            f"candidates, {plan.seconds:.1f} s)")
