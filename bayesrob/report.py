"""Terminal tables of the reports (the JSON documents are the contract; these are for people)."""

from __future__ import annotations

from collections.abc import Sequence

from bayesrob.kinematics import PARAM_NAMES


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
    rows = []
    for config, sets in doc["accuracy"].items():
        for s, acc in sets.items():
            lo, hi = acc["ci95_mm"]
            rows.append([config, s, f"{acc['mean_mm']:.2f}", f"[{lo:.2f}, {hi:.2f}]",
                         str(acc["n"])])
    parts.append("\nobserved accuracy (mean Euclidean error, mm)")
    parts.append(format_table(["config", "set", "mean", "95% CI", "n"], rows))
    return "\n".join(parts)


def format_chain_calibration(doc: dict) -> str:
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
    rows = []
    for s, arms in doc["errors"].items():
        for arm, e in arms.items():
            rows.append([s, arm, _fmt(e["mean_mm"]), _fmt(e["sd_mm"]), _fmt(e["max_mm"]),
                         str(e["n"])])
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
