"""Figures of the model-criticism workflow (:mod:`bayesrob.diagnose`).

Each function takes a diagnosis (:class:`~bayesrob.diagnose.refits.Diagnosis`, or a
:class:`~bayesrob.diagnose.groups.GroupDiagnosis`'s document) and returns a matplotlib
Figure; saving is the caller's business (:func:`bayesrob.report.outputs.write_diagnosis_report`).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from bayesrob.diagnose.refits import ArmData, ArmEval, Diagnosis


def residual_field(data: ArmData, ev: ArmEval) -> tuple[np.ndarray, np.ndarray]:
    """Observed points (n, 2) and residuals (n, 2), averaged over repeats of a command.

    The mean of a command's train and validation residuals halves the noise, so structure
    shows more clearly than in either set alone.
    """
    field = ev.resid_train.copy()
    ti, vi = data.replicate_pairs()
    if len(ti):
        field[ti] = (ev.resid_train[ti] + ev.resid_val[vi]) / 2
    return data.d, field


def residual_quiver_figure(diag: Diagnosis, arm: str, scale_mm: float | None = None) -> Figure:
    """Residual arrows of one arm over the workspace: the base model, then the final one.

    Arrows are magnified (the key gives the scale) and share it between the panels, so the
    shrinking gap is seen, not read.
    """
    from matplotlib.figure import Figure

    data = diag.data[arm]
    models = [("base model", diag.baseline[arm]),
              ("+ " + (" + ".join(diag.final[arm].effects) or "nothing named"),
               diag.final[arm])]
    fields = [residual_field(data, ev) for _, ev in models]
    longest = max(float(np.max(np.linalg.norm(f, axis=1))) for _, f in fields)
    pts = data.d
    span = float(np.max(np.ptp(pts, axis=0)))
    gap = span / max(math.sqrt(len(pts)) - 1, 1)
    # The longest arrow spans about 0.9 of a grid cell.
    mag = 0.9 * gap / max(longest, 1e-9)
    key = scale_mm or _nice(longest / 2)
    fig = Figure(figsize=(10, 4.8), layout="constrained")
    axes = fig.subplots(1, 2, sharex=True, sharey=True)
    for ax, (title, ev), (p, f) in zip(axes, models, fields, strict=True):
        err = np.linalg.norm(f, axis=1)
        q = ax.quiver(p[:, 0], p[:, 1], f[:, 0] * mag, f[:, 1] * mag, err, angles="xy",
                      scale_units="xy", scale=1, cmap="viridis", clim=(0, longest),
                      width=0.006)
        ax.plot(p[:, 0], p[:, 1], "k.", ms=3)
        held = np.mean(ev.val_errors) if len(ev.val_errors) else float("nan")
        ax.set_title(f"{title}\nheld-out error {held:.2f} mm, fitted noise "
                     f"{ev.sigma_mm:.2f} mm/axis", fontsize=10)
        ax.set_aspect("equal")
        ax.set_xlabel("x (mm)")
        # Room for the longest arrow pointing out of the grid.
        lo, hi = pts.min(axis=0) - gap, pts.max(axis=0) + gap
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
    axes[0].set_ylabel("y (mm)")
    axes[1].quiverkey(q, 0.80, 0.04, key * mag, f"{key:g} mm", labelpos="E",
                      coordinates="axes")
    fig.colorbar(q, ax=axes, label="residual (mm), observed - model", shrink=0.85)
    fig.suptitle(f"arm {arm}: where model and measurement disagree "
                 f"(arrows x{mag:.0f})", fontsize=11)
    return fig


def _nice(x: float) -> float:
    """A round number near x for a scale key."""
    if x <= 0:
        return 1.0
    e = 10 ** math.floor(math.log10(x))
    return min((1, 2, 5, 10), key=lambda m: abs(m * e - x)) * e


def gap_figure(diag: Diagnosis) -> Figure:
    """Held-out and cross-validated error after each named effect, with the noise floor."""
    from matplotlib.figure import Figure

    labels = ["base"] + [f"+ {s['effect']}" for s in diag.steps]
    fig = Figure(figsize=(6.4, 4.2), layout="constrained")
    ax = fig.subplots()
    x = np.arange(len(labels))
    pooled_val = [np.mean(np.concatenate([m[a].val_errors for a in diag.arms]))
                  for m in diag.history]
    pooled_cv = [np.mean(np.concatenate([m[a].cv_errors for a in diag.arms]))
                 for m in diag.history]
    ax.plot(x, pooled_val, "o-", color="C0", lw=2, label="held-out (validation rows)")
    ax.plot(x, pooled_cv, "s--", color="C1", lw=2, label="cross-validated (train rows)")
    for i, a in enumerate(diag.arms):
        ax.plot(x, [np.mean(m[a].val_errors) for m in diag.history], ":", color=f"C{i + 2}",
                marker=".", label=f"held-out, arm {a}")
    floor = _noise_floor(diag)
    if floor is not None:
        ax.axhline(floor, color="0.4", lw=1)
        ax.text(x[-1], floor, " noise floor", va="bottom", ha="right", color="0.3",
                fontsize=8)
    ax.set_xticks(x, labels)
    ax.set_ylabel("mean end-point error (mm)")
    ax.set_ylim(0, None)
    ax.set_title("the gap after each named effect")
    ax.legend(fontsize=8)
    return fig


def _noise_floor(diag: Diagnosis) -> float | None:
    """Mean error a perfect model would still show: sigma sqrt(pi / 2) from repeats."""
    sig = [t["lack_of_fit"]["pure_error_sigma_mm"] for t in diag.tests_before.values()
           if "lack_of_fit" in t]
    if not sig:
        return None
    return float(np.sqrt(np.mean(np.square(sig))) * math.sqrt(math.pi / 2))


PLANES = ((0, 1), (0, 2))  # the x-y and x-z planes of a 3-D rig; a 2-D rig has the first


def marker_residual_figure(residuals: dict[str, dict[str, tuple[np.ndarray, np.ndarray]]],
                          rig: str) -> Figure:
    """Residual arrows of a chain rig's markers, projected on the x-y and x-z planes (a 2-D
    rig's lie in the x-y plane): a row per model (the geometric calibration, then the final
    one), a colour per marker arm.

    ``residuals``: label -> {arm: (observed markers (n, dim), observed - model (n, dim))}. One
    magnification serves every panel, so the shrinking gap is seen, not read.
    """
    from matplotlib.figure import Figure

    names = "xyz"
    pts = np.concatenate([o for by_arm in residuals.values() for o, _ in by_arm.values()])
    longest = max(float(np.max(np.linalg.norm(r, axis=1)))
                  for by_arm in residuals.values() for _, r in by_arm.values())
    span = float(np.max(np.ptp(pts, axis=0)))
    # the longest arrow is a tenth of the markers' spread
    mag = 0.1 * span / max(longest, 1e-9)
    key = _nice(longest / 2)
    planes = PLANES if pts.shape[1] == 3 else PLANES[:1]
    fig = Figure(figsize=(5 * len(planes), 4.4 * len(residuals)), layout="constrained")
    axes = fig.subplots(len(residuals), len(planes), squeeze=False)
    arms = sorted({a for by_arm in residuals.values() for a in by_arm})
    for row, (label, by_arm) in zip(axes, residuals.items(), strict=True):
        mean = float(np.mean(np.concatenate([np.linalg.norm(r, axis=1)
                                             for _, r in by_arm.values()])))
        for ax, (i, j) in zip(row, planes, strict=True):
            for a, (o, r) in sorted(by_arm.items()):
                c = f"C{arms.index(a)}"
                ax.plot(o[:, i], o[:, j], ".", color=c, ms=2)
                q = ax.quiver(o[:, i], o[:, j], r[:, i] * mag, r[:, j] * mag, color=c,
                              angles="xy", scale_units="xy", scale=1, width=0.003, label=a)
            ax.set_aspect("equal")
            ax.set_xlabel(f"{names[i]} (mm)")
            ax.set_ylabel(f"{names[j]} (mm)")
            # two lines: a long model label on one would run past a narrow panel's edge
            ax.set_title(f"{label}\n{names[i]}-{names[j]} plane, mean {mean:.2f} mm",
                         fontsize=10)
        row[-1].quiverkey(q, 0.80, 0.04, key * mag, f"{key:g} mm", labelpos="E",
                          coordinates="axes")
    axes[0][0].legend(fontsize=8, loc="upper left", title="markers on", title_fontsize=8)
    fig.suptitle(f"{rig}: validation residuals, observed - model (arrows x{mag:.0f})",
                 fontsize=11)
    return fig


def ladder_figure(doc: dict, published: dict[str, float] | None = None):
    """Mean validation error (bars: sd) after each step; ``published`` (step label -> mean mm)
    drawn beside it when given."""
    import matplotlib.pyplot as plt

    rows = [("geometric", doc["baseline"])] + [(f"+{s['effect']}", s) for s in doc["steps"]]
    fig, ax = plt.subplots(figsize=(1.6 * len(rows) + 2.5, 3.6), layout="constrained")
    xs = np.arange(len(rows))
    ax.bar(xs, [r["heldout_error_mm"] for _, r in rows],
           yerr=[r["heldout_error_sd_mm"] for _, r in rows], color="tab:blue", capsize=4,
           label="ours (validation mean, sd)", width=0.55)
    ax.plot(xs, [r["heldout_error_max_mm"] for _, r in rows], "v", color="tab:blue",
            ls="none", label="largest validation error")
    if published:
        for x, (label, _) in zip(xs, rows, strict=True):
            if label in published:
                ax.plot(x, published[label], "D", color="tab:red", ms=8)
        ax.plot([], [], "D", color="tab:red", label="published")
    ax.set_xticks(xs, [label for label, _ in rows])
    ax.set_ylabel("marker error (mm)")
    ax.set_title(f"{doc['rig']}: error after each named effect", fontsize=10)
    # below the panel: inside, "best" still sat on a bar's error cap on a one-bar ladder
    fig.legend(fontsize=8, loc="outside lower center", ncols=min(3, len(rows) + 1),
               frameon=False)
    return fig
