"""The paper's Figures 3-8, drawn from a :class:`bayesrob.reproduction.Reproduction`.

Positions are in mm (the paper plots cm). Each function returns a Figure; the caller saves it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.figure import Figure

if TYPE_CHECKING:
    from bayesrob.reproduction import Reproduction


def _pick(rep: Reproduction, family: str, prefer_paper: bool | None = None) -> list[str]:
    names = [s.name for s in rep.specs if s.family == family]
    if prefer_paper is not None:
        names.sort(key=lambda n: next(s.paper for s in rep.specs if s.name == n) != prefer_paper)
    return names


def _setups(rep: Reproduction) -> list[str]:
    return list(rep.rows)


def _cond_model(rep: Reproduction) -> str | None:
    """The COND variant to show: the paper's figures show COND; prefer the paper-faithful one."""
    names = _pick(rep, "COND", prefer_paper=True)
    return names[0] if names else (rep.specs[0].name if rep.specs else None)


def workspace_errors(rep: Reproduction, scale: float = 10.0,
                     expected_scale: float = 40.0) -> Figure:
    """Figure 3: observed error vectors (top) and COND's expected errors (bottom) per setup."""
    configs = _setups(rep)
    model = _cond_model(rep)
    fig, axes = plt.subplots(2, len(configs), figsize=(4.2 * len(configs), 8.2), squeeze=False,
                             sharex=True, sharey=True)
    for j, c in enumerate(configs):
        r = rep.rows[c]
        start = r["targets"]
        # Expected errors are a fraction of observed ones (noise averages out), so they get
        # their own, larger arrow scale.
        for i, (end, label, colour, k) in enumerate((
            (r["observed"], "observed", "tab:blue", scale),
            (rep.predictions[model][c].expected_point if model else start,
             f"expected ({model})", "tab:red", expected_scale),
        )):
            ax = axes[i, j]
            vec = end - start
            ax.quiver(start[:, 0], start[:, 1], vec[:, 0] * k, vec[:, 1] * k,
                      angles="xy", scale_units="xy", scale=1, color=colour, width=0.006)
            ax.plot(start[:, 0], start[:, 1], "k.", ms=3)
            mean = np.mean(np.linalg.norm(vec, axis=1))
            ax.set_title(f"{c}: {label}\nmean {mean:.2f} mm (arrows x{k:g})", fontsize=9)
            ax.set_aspect("equal")
            ax.grid(alpha=0.3)
            if i == 1:
                ax.set_xlabel("x (mm)")
            if j == 0:
                ax.set_ylabel("y (mm)")
    fig.suptitle("Figure 3. Errors over the workspace: arrow from the model's point to the "
                 "observed (top) or expected (bottom) end point")
    fig.tight_layout()
    return fig


def accuracy(rep: Reproduction) -> Figure:
    """Figure 4: observed mean error with 95% CI, and each model's predicted expected error."""
    doc = rep.accuracy["setups"]
    configs = list(doc)
    models = [s.name for s in rep.specs]
    fig, ax = plt.subplots(figsize=(1.6 + 1.3 * len(configs) * (1 + len(models)) / 3, 4.8))
    width = 0.8 / (1 + len(models))
    colours = plt.cm.tab10(np.arange(len(models)) % 10)
    for k, c in enumerate(configs):
        obs = doc[c]["observed"]
        lo, hi = obs["ci95_mm"]
        x0 = k - 0.4 + width / 2
        ax.bar(x0, obs["mean_mm"], width, color="0.35", label="observed" if k == 0 else None,
               yerr=[[obs["mean_mm"] - lo], [hi - obs["mean_mm"]]], capsize=3)
        for m, name in enumerate(models):
            p = doc[c]["predicted"].get(name)
            if p is None:
                continue
            hatch = "//" if next(s.paper for s in rep.specs if s.name == name) else None
            ax.bar(x0 + (m + 1) * width, p["expected_error_mm"], width, color=colours[m],
                   hatch=hatch, edgecolor="white", label=name if k == 0 else None)
    ax.set_xticks(range(len(configs)), configs)
    ax.set_ylabel("mean Euclidean error (mm)")
    ax.set_title("Figure 4. Accuracy: observed (95% CI) and predicted by each model\n"
                 "(hatched: paper-faithful estimators)", fontsize=10)
    ax.legend(fontsize=8, ncol=2)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    return fig


def ind_densities(rep: Reproduction) -> Figure:
    """Figure 5: IND's 1-D densities of the joint-angle errors, per arm and joint."""
    arms = list(rep.arms)
    models = _pick(rep, "IND", prefer_paper=True)
    fig, axes = plt.subplots(1, len(arms), figsize=(5.5 * len(arms), 4), squeeze=False)
    styles = ["-", "--", ":", "-."]
    for j, a in enumerate(arms):
        ax = axes[0, j]
        err, _ = rep.training_errors(a)
        lo = err.min() - 4 * err.std()
        hi = err.max() + 4 * err.std()
        x = np.linspace(lo, hi, 600)
        for m, name in enumerate(models):
            parts = rep.fitted[name][a].parts
            for k, colour in ((0, "tab:blue"), (1, "tab:orange")):
                dens = np.exp(np.asarray(parts[k].logpdf(jnp.asarray(x[:, None]))))
                ax.plot(x * 1e3, dens / 1e3, styles[m % 4], color=colour,
                        label=f"joint {k + 1}, {name}")
        for k, colour in ((0, "tab:blue"), (1, "tab:orange")):
            ax.plot(err[:, k] * 1e3, np.full(len(err), -0.02 * (k + 1)), "|", color=colour,
                    ms=10)
        ax.set_xlabel("joint-angle error (mrad)")
        ax.set_ylabel("density (per mrad)")
        ax.set_title(f"{a} arm")
        ax.legend(fontsize=8)
        ax.grid(alpha=0.3)
    fig.suptitle("Figure 5. IND: Parzen densities of each joint's angular error "
                 "(ticks: training errors)")
    fig.tight_layout()
    return fig


def corr_densities(rep: Reproduction) -> Figure:
    """Figure 6: CORR's 2-D density of the joint-error pair, per arm and variant."""
    arms = list(rep.arms)
    models = _pick(rep, "CORR", prefer_paper=True)
    fig, axes = plt.subplots(max(1, len(models)), len(arms),
                             figsize=(5 * len(arms), 4.3 * max(1, len(models))), squeeze=False)
    for j, a in enumerate(arms):
        err, _ = rep.training_errors(a)
        pad = 4 * err.std(axis=0)
        x = np.linspace(err[:, 0].min() - pad[0], err[:, 0].max() + pad[0], 120)
        y = np.linspace(err[:, 1].min() - pad[1], err[:, 1].max() + pad[1], 120)
        gx, gy = np.meshgrid(x, y)
        for i, name in enumerate(models):
            ax = axes[i, j]
            kde = rep.fitted[name][a].parts[0]
            dens = np.exp(np.asarray(kde.logpdf(jnp.asarray(np.column_stack(
                [gx.ravel(), gy.ravel()]))))).reshape(gx.shape)
            cs = ax.contourf(gx * 1e3, gy * 1e3, dens / 1e6, levels=12, cmap="viridis")
            fig.colorbar(cs, ax=ax, label="density (per mrad$^2$)")
            ax.plot(err[:, 0] * 1e3, err[:, 1] * 1e3, "w.", ms=5)
            r = np.corrcoef(err.T)[0, 1]
            ax.set_title(f"{a} arm, {name} (sample corr {r:+.2f})", fontsize=10)
            ax.set_xlabel("joint 1 error (mrad)")
            ax.set_ylabel("joint 2 error (mrad)")
    fig.suptitle("Figure 6. CORR: joint density of the two joints' angular errors "
                 "(dots: training errors)")
    fig.tight_layout()
    return fig


def cond_grid(rep: Reproduction, zoom_mm: float = 4.0) -> Figure:
    """Figure 7: COND's p(d | u) around every target, per setup (blue: target, red: expected)."""
    model = _cond_model(rep)
    configs = _setups(rep)
    fig = plt.figure(figsize=(5.2 * len(configs), 5.6))
    subfigs = fig.subfigures(1, len(configs), wspace=0.02)
    subfigs = np.atleast_1d(subfigs)
    for sf, c in zip(subfigs, configs, strict=True):
        pred = rep.predictions[model][c]
        t = len(pred.targets)
        side = int(np.ceil(np.sqrt(t)))
        # Lay panels out as the targets lie in the workspace: rows by y (top first), then x.
        order = np.lexsort((pred.targets[:, 0], -pred.targets[:, 1]))
        axes = sf.subplots(side, side, sharex=True, sharey=True)
        axes = np.atleast_2d(axes)
        ax_grid = pred.grid.axis
        keep = np.abs(ax_grid) <= zoom_mm
        for k, ax in enumerate(axes.ravel()):
            ax.set_xticks([])
            ax.set_yticks([])
            if k >= t:
                ax.axis("off")
                continue
            i = order[k]
            dens = pred.density(i)[np.ix_(keep, keep)]
            ext = [ax_grid[keep][0], ax_grid[keep][-1], ax_grid[keep][0], ax_grid[keep][-1]]
            ax.imshow(dens, origin="lower", extent=ext, cmap="magma", aspect="equal")
            e = pred.expected_point[i] - pred.targets[i]
            ax.plot(0, 0, "s", mfc="none", mec="tab:blue", ms=3)
            ax.plot(e[0], e[1], "s", mfc="none", mec="red", ms=3)
        sf.suptitle(f"{c} ({model}); panels +-{zoom_mm:g} mm", fontsize=10)
    fig.suptitle("Figure 7. COND: p(d | u) at each target (blue: target, red: expected point)",
                 y=1.06)
    return fig


def error_densities(rep: Reproduction, zoom_mm: float = 5.0) -> Figure:
    """Figure 8: observed errors (top row) and each model's error density summed over targets."""
    configs = _setups(rep)
    models = [s.name for s in rep.specs]
    nrow = 1 + len(models)
    fig, axes = plt.subplots(nrow, len(configs), figsize=(3.3 * len(configs), 3.0 * nrow),
                             squeeze=False, sharex=True, sharey=True,
                             gridspec_kw={"hspace": 0.35, "wspace": 0.1})
    for j, c in enumerate(configs):
        r = rep.rows[c]
        err = r["observed"] - r["targets"]
        ax = axes[0, j]
        ax.plot(err[:, 0], err[:, 1], "k.", ms=6)
        ax.set_title(f"{c}: observed\nmean {np.mean(np.linalg.norm(err, axis=1)):.2f} mm",
                     fontsize=9)
        for i, name in enumerate(models, start=1):
            pred = rep.predictions[name][c]
            g = pred.grid.axis
            keep = np.abs(g) <= zoom_mm
            dens = pred.error_density[np.ix_(keep, keep)] / pred.grid.cell_area_mm2
            ax = axes[i, j]
            ext = [g[keep][0], g[keep][-1], g[keep][0], g[keep][-1]]
            ax.imshow(dens, origin="lower", extent=ext, cmap="Blues", interpolation="bilinear")
            ax.plot(err[:, 0], err[:, 1], ".", color="tab:red", ms=2, alpha=0.6)
            ax.set_title(f"{name}: expected {pred.mean_expected_error_mm:.2f} mm", fontsize=9)
    for ax in axes.ravel():
        ax.set_aspect("equal")
        ax.set_xlim(-zoom_mm, zoom_mm)
        ax.set_ylim(-zoom_mm, zoom_mm)
        ax.axhline(0, color="0.7", lw=0.5)
        ax.axvline(0, color="0.7", lw=0.5)
    for ax in axes[-1]:
        ax.set_xlabel("x error (mm)")
    for ax in axes[:, 0]:
        ax.set_ylabel("y error (mm)")
    fig.suptitle("Figure 8. End-point error densities summed over the targets\n"
                 "(top: observed; red dots repeat them)", y=0.93)
    return fig
