"""The accuracy of an assembly predicted before it is built (``bayesrob predict``).

An assembly is one arm or several arms linked at their end point (``top+bottom+side``). Only
the modules' single-arm ``train`` rows are used: each arm is calibrated on them and its
joint-error model fitted to them, each arm is aimed at every target through its calibrated
inverse model, and the linked end point is predicted by a fusion rule
(:mod:`bayesrob.fusion`). A rig without any linked row works: that is the point.

Per target: the expected end point, the expected distance from the target, and the areas of
the 50% / 90% highest-density regions.
"""

from __future__ import annotations

import csv
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import jax.numpy as jnp
import numpy as np

from bayesrob import kinematics as kin
from bayesrob.calibration import calibrate
from bayesrob.fusion import DEFAULT_FUSION, FUSIONS, fused_posterior
from bayesrob.inference import GridPosterior, check_reach
from bayesrob.noise_models import discover_models, fit_noise_models
from bayesrob.prediction import hdr_area
from bayesrob.rig import Rig, RigError

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = ["AssemblyPrediction", "predict_assembly", "grid_targets", "read_targets",
           "assembly_figure"]


@dataclass
class AssemblyPrediction:
    """Predicted accuracy of one assembly at its targets."""

    rig: str
    config: str
    model: str
    fusion: str
    targets: np.ndarray  # (T, 2) mm
    commands: dict[str, np.ndarray]  # arm -> (T, 2) pulses
    expected_point: np.ndarray  # (T, 2)
    expected_error_mm: np.ndarray  # (T,)
    hdr50_mm2: np.ndarray  # (T,)
    hdr90_mm2: np.ndarray  # (T,)
    posterior: GridPosterior
    seconds: float

    @property
    def document(self) -> dict:
        """The ``bayesrob predict --json`` document."""
        e = self.expected_error_mm
        return {
            "rig": self.rig, "config": self.config, "model": self.model, "fusion": self.fusion,
            "rows_used": "train rows of each arm alone (no linked row is read)",
            "targets": [
                {"target": [float(x) for x in t],
                 "commands": {a: [float(v) for v in u[i]] for a, u in self.commands.items()},
                 "expected_point": [float(x) for x in self.expected_point[i]],
                 "expected_error_mm": float(e[i]),
                 "hdr50_mm2": float(self.hdr50_mm2[i]), "hdr90_mm2": float(self.hdr90_mm2[i])}
                for i, t in enumerate(self.targets)],
            "summary": {"n_targets": int(e.size), "mean_expected_error_mm": float(e.mean()),
                        "max_expected_error_mm": float(e.max()),
                        "mean_hdr50_mm2": float(self.hdr50_mm2.mean()),
                        "mean_hdr90_mm2": float(self.hdr90_mm2.mean())},
            "seconds": self.seconds,
        }

    def format(self) -> str:
        from bayesrob.report import format_table

        rows = [[f"{t[0]:.1f}, {t[1]:.1f}", f"{p[0]:.2f}, {p[1]:.2f}", f"{e:.2f}",
                 f"{a50:.2f}", f"{a90:.2f}"]
                for t, p, e, a50, a90 in zip(self.targets, self.expected_point,
                                             self.expected_error_mm, self.hdr50_mm2,
                                             self.hdr90_mm2, strict=True)]
        head = (f"{self.config} on {self.rig}: model {self.model}, fusion {self.fusion}, "
                f"{len(self.targets)} targets (from single-arm train rows only)")
        s = self.document["summary"]
        tail = (f"mean expected error {s['mean_expected_error_mm']:.2f} mm (max "
                f"{s['max_expected_error_mm']:.2f}); mean 50% / 90% region "
                f"{s['mean_hdr50_mm2']:.2f} / {s['mean_hdr90_mm2']:.2f} mm^2")
        return "\n".join([head, format_table(["target (mm)", "expected point", "E error mm",
                                              "50% mm^2", "90% mm^2"], rows), tail])


def grid_targets(rig: Rig, n: int) -> np.ndarray:
    """An n x n grid of targets over the rig's workspace (cell centres, x fastest)."""
    if rig.workspace is None:
        raise RigError(f"{rig.path}: no 'workspace' in rig.toml to lay a --grid over; give "
                       "--targets FILE instead")
    (x0, x1), (y0, y1) = rig.workspace
    xs = x0 + (x1 - x0) * (np.arange(n) + 0.5) / n
    ys = y0 + (y1 - y0) * (np.arange(n) + 0.5) / n
    gx, gy = np.meshgrid(xs, ys)
    return np.column_stack([gx.ravel(), gy.ravel()])


def read_targets(path: str | Path) -> np.ndarray:
    """Targets (T, 2) from a CSV file with columns ``x,y`` (mm; other columns ignored)."""
    path = Path(path)
    if not path.is_file():
        raise RigError(f"{path}: file not found")
    with path.open(newline="", encoding="utf-8-sig") as fh:
        reader = csv.DictReader(fh)
        if not reader.fieldnames or not {"x", "y"} <= set(reader.fieldnames):
            raise RigError(f"{path}: needs a header with columns x,y, got {reader.fieldnames}")
        out = []
        for i, row in enumerate(reader, start=2):
            try:
                xy = [float(row["x"]), float(row["y"])]
            except (TypeError, ValueError):
                raise RigError(f"{path}: line {i}: x, y must be numbers, got "
                               f"{row.get('x')!r}, {row.get('y')!r}") from None
            if not np.all(np.isfinite(xy)):
                raise RigError(f"{path}: line {i}: x, y must be finite, got {xy}")
            out.append(xy)
    if not out:
        raise RigError(f"{path}: no targets")
    return np.asarray(out, float)


def _aim(arm: kin.Arm, targets: np.ndarray) -> np.ndarray:
    """Pulses aiming the calibrated arm at each target; refuses targets it cannot be aimed at."""
    u = np.asarray(arm.command(jnp.asarray(targets)))
    for t, ut in zip(targets, u, strict=True):
        check_reach(arm, t, ut)
    return u


def predict_assembly(rig: Rig, config: str, targets: np.ndarray, model: str = "cond",
                     fusion: str = DEFAULT_FUSION, models_dir: Any = None, seed: int = 0
                     ) -> AssemblyPrediction:
    """Predict ``config`` (arms joined by '+') at ``targets`` (T, 2) from single-arm rows."""
    t0 = time.perf_counter()
    if fusion not in FUSIONS:
        raise RigError(f"unknown fusion {fusion!r}; choose from {', '.join(FUSIONS)}")
    members = config.split("+")
    unknown = [a for a in members if a not in rig.arms]
    if unknown or len(set(members)) != len(members):
        raise RigError(f"config {config!r}: " + (f"no arm {unknown[0]!r} in the rig (arms: "
                       f"{', '.join(rig.arms)})" if unknown else "an arm appears twice"))
    for a in members:
        if not rig.measurements.mask(a, "train").any():
            raise RigError(f"{rig.path}: arm {a!r} has no train rows of its own to calibrate "
                           "and fit its joint-error model on")
    targets = np.atleast_2d(np.asarray(targets, float))
    spec = discover_models(models_dir, [model])
    cal = calibrate(rig)
    arms = {a: cal[a].arm for a in members}
    commands = {a: _aim(arms[a], targets) for a in members}
    fitted = fit_noise_models(rig, arms, spec)[model]
    stiffness = [rig.arms[a].stiffness for a in members]
    post, _ = fused_posterior([fitted[a] for a in members], [arms[a] for a in members],
                              [commands[a] for a in members], targets, fusion,
                              stiffness if any(s is not None for s in stiffness) else None,
                              seed=seed)
    pts = post.points()
    dist = np.linalg.norm(pts - targets[:, None, :], axis=-1)
    cell = post.cell_mm[:, 0] * post.cell_mm[:, 1]
    return AssemblyPrediction(
        rig.name, config, model, fusion, targets, commands, post.mean,
        np.einsum("tm,tm->t", post.prob, dist),
        hdr_area(post.prob, 0.5, cell), hdr_area(post.prob, 0.9, cell),
        post, time.perf_counter() - t0)


def assembly_figure(pred: AssemblyPrediction, rig: Rig) -> Figure:
    """Expected error over the targets (left) and the 50% / 90% regions of a few (right)."""
    import matplotlib.pyplot as plt

    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4.6))
    t = pred.targets
    sc = ax.scatter(t[:, 0], t[:, 1], c=pred.expected_error_mm, cmap="viridis", s=160,
                    marker="s")
    fig.colorbar(sc, ax=ax, label="expected error (mm)")
    for a in pred.config.split("+"):
        base = rig.arms[a].base
        ax.plot(*base, "k^")
        ax.annotate(a, base, textcoords="offset points", xytext=(4, 4))
    ax.set_aspect("equal")
    ax.set_title(f"{pred.config}: expected error ({pred.model}, {pred.fusion})")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    post = pred.posterior
    worst = int(np.argmax(pred.expected_error_mm))
    n = post.n
    pts = post.points()[worst]
    dens = post.prob[worst]
    order = np.sort(dens)[::-1]
    levels = [order[np.searchsorted(np.cumsum(order), m)] for m in (0.9, 0.5)]
    bx.contour(pts[:, 0].reshape(n, n) - t[worst, 0], pts[:, 1].reshape(n, n) - t[worst, 1],
               dens.reshape(n, n), levels=levels, colors=["C0", "C3"])
    bx.plot(0, 0, "k+")
    bx.set_aspect("equal")
    bx.set_title(f"least accurate target ({t[worst, 0]:.0f}, {t[worst, 1]:.0f}): "
                 "50% (red) / 90% (blue)", fontsize=9)
    bx.set_xlabel("x - target (mm)")
    bx.set_ylabel("y - target (mm)")
    fig.tight_layout()
    return fig
