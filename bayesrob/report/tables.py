"""Terminal tables of the reports (the JSON documents are the contract; these are for people)."""

from __future__ import annotations

from collections.abc import Sequence

from bayesrob.robot import PARAM_NAMES


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
