"""The design figure (``design.png``): the top candidates of a design run side by side."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from matplotlib.figure import Figure


def design_figure(result: Any, modules: dict[str, Any], top: int = 4) -> Figure:
    """The top candidates of a :class:`~bayesrob.design.search.DesignResult`: each module at
    its mount, outlined aimed at the region's first target (``Module.sketch``), over the
    predicted error quantile at every target (white dots): a map of the region interpolated
    between them in the plane, the targets coloured and seen from above (x-y) in space."""
    import matplotlib.pyplot as plt

    d = result.design
    t = result.targets
    lo, hi = d.region.min(axis=0), d.region.max(axis=0)
    box = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])
    # the task region as seen: the plane's polygon, or a box from above
    outline = d.region if t.shape[1] == 2 else box
    cands = result.candidates[:top]
    if not cands:
        # nothing to rank (every assembly failed to reach the region): say so, with the task
        # region drawn so the reader sees what was asked, rather than leave an empty frame
        fig, ax = plt.subplots(figsize=(6.0, 4.2), layout="constrained")
        ax.fill(*box.T, color="0.9")
        ax.plot(t[:, 0], t[:, 1], "k.", ms=4)
        ax.set_aspect("equal")
        ax.margins(0.3)
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
        ax.set_title("no assembly reaches every target of the task region (grey)\n"
                     "nothing to rank: see the command's output for why", fontsize=10)
        return fig
    n = len(cands)
    fig, axs = plt.subplots(1, n, figsize=(3.6 * n + 1.2, 4.2), squeeze=False, sharex=True,
                            sharey=True, layout="constrained")
    values = [v for c in cands for v in c["error_quantile_mm"]]
    vmin, vmax = min(values), max(values)
    levels = np.linspace(vmin, vmax + 1e-9, 13)  # one scale for every panel and the bar
    q = f"q{round(100 * d.quantile)}"
    sc = None
    for ax, c in zip(axs[0], cands, strict=False):
        ax.fill(*outline[:, :2].T, color="0.93", zorder=0)
        if t.shape[1] == 2:
            sc = ax.tricontourf(t[:, 0], t[:, 1], c["error_quantile_mm"], levels=levels,
                                cmap="viridis", zorder=1)
            ax.plot(t[:, 0], t[:, 1], "o", color="white", ms=2.5, zorder=3)
        else:
            sc = ax.scatter(t[:, 0], t[:, 1], c=c["error_quantile_mm"], cmap="viridis",
                            vmin=vmin, vmax=vmax, s=30, edgecolors="white", zorder=3)
        for a, b in zip(c["arms"], c["bases"], strict=True):
            line = modules[a].sketch(b, t[0])
            ax.plot(line[:, 0], line[:, 1], "-o", color="0.35", ms=3, zorder=2)
            ax.plot(b[0], b[1], "k^", ms=9)
            ax.annotate(a, b[:2], textcoords="offset points", xytext=(5, 5), fontsize=8)
        ax.set_aspect("equal")
        ax.set_title(f"#{c['rank']} {c['config']}\n{q} {c['overall']['error_quantile_mm']:.2f} mm"
                     f", {'meets' if c['meets'] else 'misses'} {d.error_mm:g}", fontsize=9)
        ax.set_xlabel("x (mm)" if t.shape[1] == 2 else "x (mm), seen from above")
    axs[0][0].set_ylabel("y (mm)")
    fig.colorbar(sc, ax=list(axs[0]), label=f"predicted error at {d.quantile:g} (mm)",
                 shrink=0.8, format="%.2f")
    return fig
