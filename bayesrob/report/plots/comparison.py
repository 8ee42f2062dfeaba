"""The figure of a model comparison (``bayesrob compare --plot``)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from bayesrob.compare.comparison import elpd_rows

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from bayesrob.compare.comparison import ModelComparison


def comparison_figure(comparison: ModelComparison) -> Figure:
    """elpd difference to the best model, with its standard error, held out and LOO, in the
    style of ``arviz.plot_compare`` on a symmetric-log axis: the histogram COND can trail by
    thousands where the others differ by a few units."""
    import matplotlib.pyplot as plt

    k = len(comparison.specs)
    fig, axes = plt.subplots(1, 2, figsize=(11, 0.45 * k + 2.0))
    for ax, df, title in ((axes[0], comparison.heldout_compare, "held-out points"),
                          (axes[1], comparison.loo_compare, "LOO over training rows")):
        rows = elpd_rows(df)
        y = np.arange(len(rows))[::-1]
        diff = -np.array([r["elpd_diff"] for r in rows])
        dse = np.array([r["dse"] for r in rows])
        paper = [next(s for s in comparison.specs if s.name == r["model"]).paper for r in rows]
        for yi, d, e, p in zip(y, diff, dse, paper, strict=True):
            ax.errorbar(d, yi, xerr=e, fmt="s" if p else "o", color="C1" if p else "C0",
                        capsize=3)
        ax.axvline(0.0, color="0.5", lw=0.8, ls="--")
        ax.set_xscale("symlog", linthresh=10.0)
        ax.set_xlim(min(-5.0, float(np.min(diff - dse))) * 1.5,
                    max(5.0, float(np.max(diff + dse))) * 1.5)
        ax.set_yticks(y, [f"{r['model']}  ({r['elpd']:.0f} \u00b1 {r['se']:.0f})"
                          for r in rows])
        ax.set_xlabel("elpd difference to the best model (nats, \u00b1 dse)")
        ax.set_ylabel("model (elpd \u00b1 se, nats)")
        n = int(comparison.heldout_pointwise(rows[0]["model"]).size) if title.startswith(
            "held") else int(comparison.loo[rows[0]["model"]].size)
        ax.set_title(f"{title}, n = {n}")
    # a 3-D rig's densities are per mm^3; the marker key only where a paper model is drawn
    key = ("circles improved, squares paper-faithful; " if any(s.paper for s in comparison.specs)
           else "")
    fig.suptitle(f"{comparison.rig.name}: elpd, the summed log predictive density of the "
                 f"observed end points (nats; density per mm$^{comparison.rig.robot.dim}$)\n"
                 f"{key}higher is better")
    fig.tight_layout()
    return fig
