"""The figure of an assembly's predicted accuracy (``bayesrob predict --plot``)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from bayesrob.predict.regions import hdr_levels

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from bayesrob.data.rig import Rig
    from bayesrob.predict.assembly import AssemblyPrediction


def assembly_figure(pred: AssemblyPrediction, rig: Rig) -> Figure:
    """The targets coloured by expected error (from above and, in 3-D, the side, on one scale)
    with each arm's base; then the least accurate target's draws by region, on those planes."""
    import matplotlib.pyplot as plt

    t = pred.targets
    planes = [(0, 1), (0, 2)] if t.shape[1] == 3 else [(0, 1)]
    x = rig.robot.layout.nominal
    arms = pred.config.split("+")
    # a planar arm's base is its chain's first joint origin, not an instrument pose
    bases = np.asarray([np.asarray(rig.arms[a].base, float)
                        if getattr(rig.arms[a], "base", None) is not None
                        else np.asarray(rig.robot.instrument_pose(x, a))[:3, 3][:t.shape[1]]
                        for a in arms])
    shown = np.vstack([t, bases])
    lo, hi = shown.min(axis=0), shown.max(axis=0)
    pad = np.maximum(0.1 * (hi - lo).max(), 30.0)  # room for markers and the arms' names
    lo, hi = lo - pad, hi + pad
    # one scale for the views: the same x range, and vertical ranges of one length (the longer
    # of y's and z's) centred on each view's points, so both panels take the same shape
    tall = max(hi[j] - lo[j] for _, j in planes)
    for _, j in planes:
        centre = (hi[j] + lo[j]) / 2
        lo[j], hi[j] = centre - tall / 2, centre + tall / 2
    fig = plt.figure(figsize=(4.3 * 2 * len(planes) + 0.8, 4.6), layout="constrained")
    axs = fig.subplots(1, 2 * len(planes))
    maps, clouds = axs[:len(planes)], axs[len(planes):]
    names = "xyz"
    how = f"{pred.model}, {pred.fusion}" if "+" in pred.config else pred.model
    vmin, vmax = float(pred.expected_error_mm.min()), float(pred.expected_error_mm.max())
    for ax, (i, j) in zip(maps, planes, strict=True):
        sc = ax.scatter(t[:, i], t[:, j], c=pred.expected_error_mm, cmap="viridis", s=60,
                        vmin=vmin, vmax=vmax)
        # bases one behind the other in this view share one marker and one label (drawn
        # apart, "left" over "right" read "lefight" in the x-z view of a symmetric pair)
        marks: list[tuple[np.ndarray, list[str]]] = []
        for a, base in zip(arms, bases, strict=True):
            point = np.array([base[i], base[j]])
            near = [m for m in marks if np.hypot(*(m[0] - point)) < 0.03 * tall]
            if near:
                near[0][1].append(a)
            else:
                marks.append((point, [a]))
        for point, at in marks:
            ax.plot(*point, "k^")
            ax.annotate(", ".join(at), tuple(point), textcoords="offset points",
                        xytext=(4, 4), fontsize=8)
        ax.set_xlim(lo[i], hi[i])
        ax.set_ylim(lo[j], hi[j])
        ax.set_aspect("equal")  # the views share one scale: distances read alike in both
        ax.set_xlabel(f"{names[i]} (mm)")
        ax.set_ylabel(f"{names[j]} (mm)")
        ax.set_title(f"targets, {names[i]}-{names[j]} view", fontsize=9)
    fig.colorbar(sc, ax=list(maps), label="expected error (mm)", shrink=0.8)
    worst = int(np.argmax(pred.expected_error_mm))
    draws = pred.draws[:, worst: worst + 1]
    sub = draws[:1500]
    level = hdr_levels(draws, sub)[:, 0]
    dev = sub[:, 0] - t[worst]
    for ax, (i, j) in zip(clouds, planes, strict=True):
        for low, high, colour, label in ((0.9, 1.01, "0.8", "outside 90%"),
                                         (0.5, 0.9, "C0", "50-90%"), (0.0, 0.5, "C3", "50%")):
            m = (level >= low) & (level < high)
            ax.scatter(dev[m, i], dev[m, j], s=3, color=colour, label=label)
        ax.plot(0, 0, "k+", ms=12)
        ax.set_aspect("equal")
        ax.set_xlabel(f"{names[i]} - target (mm)")
        ax.set_ylabel(f"{names[j]} - target (mm)")
        ax.set_title(f"least accurate target's draws, {names[i]}-{names[j]}", fontsize=9)
    clouds[0].legend(fontsize=7, markerscale=3)
    fig.suptitle(f"{pred.config}: expected error ({how}); least accurate target "
                 f"({', '.join(f'{v:.0f}' for v in t[worst])})", fontsize=10)
    return fig
