"""What the commands write: the calibration document and calibrated URDF, the reproduction's
accuracy.json and figures, the diagnosis figures, the design's outputs.

This module sits above the ones that compute results and the ones that draw them, so neither
needs the other: plots take results as arguments, results never import plots, and the
Bayesian calibration builds on the point-estimate one without being called back by it.
"""

from __future__ import annotations

import json
from pathlib import Path

from bayesrob import robot as kin
from bayesrob.calibrate.arms import METHODS, ArmCalibration, calibrate_arms, observed_accuracy
from bayesrob.calibrate.bayes import calibrate_arms_bayes, report_extras
from bayesrob.calibrate.least_squares import Calibration, calibrated_rig_document
from bayesrob.data.rig import Rig, dump_toml
from bayesrob.diagnose.groups import GroupDiagnosis
from bayesrob.diagnose.refits import Diagnosis
from bayesrob.paper.reproduction import Reproduction
from bayesrob.report.output_paths import write_text

CALIBRATION_METHODS: tuple[str, ...] = (*METHODS, "bayes")


def calibrate_rig(rig: Rig, method: str = "least-squares") -> dict[str, ArmCalibration]:
    """Calibrate every planar arm of a rig on its ``train`` rows by any of the three methods."""
    if method not in CALIBRATION_METHODS:
        raise ValueError(f"unknown calibration method {method!r}; use one of "
                         f"{CALIBRATION_METHODS}")
    return calibrate_arms_bayes(rig) if method == "bayes" else calibrate_arms(rig, method)


def calibration_report(rig: Rig, method: str = "least-squares") -> dict:
    """The ``bayesrob calibrate --json`` document of a planar rig."""
    cal = calibrate_rig(rig, method)
    arms = {n: c.arm for n, c in cal.items()}
    doc = {
        "method": method,
        "rig": rig.name,
        "arms": {n: c.to_json() for n, c in cal.items()},
        "accuracy": observed_accuracy(rig, arms),
        "param_names": list(kin.PARAM_NAMES),
    }
    if method == "bayes":  # adds predicted accuracy with parameter uncertainty
        doc.update(report_extras(rig, cal))
    return doc


def write_calibrated_robot(doc: dict, rig: Rig, cal: Calibration, path: str | Path) -> None:
    """``calibrate --urdf-out``: the calibrated robot as URDF at ``path`` and a rig.toml that
    loads it back (``path`` with suffix .rig.toml); ``doc`` (the calibration's JSON) is told
    where, and which fitted groups neither file can hold."""
    out = Path(path)
    kin.write_urdf(rig.robot, cal.x, out, name=rig.name)
    toml_path = out.with_suffix(".rig.toml")
    write_text(toml_path, dump_toml(calibrated_rig_document(rig, cal, out.name)))
    doc["urdf_out"] = str(out)
    doc["rig_toml_out"] = str(toml_path)
    beyond = [g for g in cal.groups if g in kin.OPTIONAL_GROUPS]
    if beyond:
        doc.setdefault("notes", []).append(
            f"the URDF and rig.toml hold the calibrated geometry; the fitted "
            f"{', '.join(beyond)} values are in this document's parameters, not in them")


def write_reproduction(rep: Reproduction, out: str | Path) -> list[Path]:
    """Write accuracy.json and Figures 3-8 into ``out``; returns the paths written."""
    import matplotlib.pyplot as plt

    from bayesrob.report.plots import paper as figs

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written = [out / "accuracy.json"]
    written[0].write_text(json.dumps(rep.accuracy, indent=2) + "\n")
    makers = {
        "fig3_workspace_errors.png": figs.workspace_errors,
        "fig4_accuracy.png": figs.accuracy,
        "fig5_ind_densities.png": figs.ind_densities,
        "fig6_corr_densities.png": figs.corr_densities,
        "fig7_cond_grid.png": figs.cond_grid,
        "fig8_error_densities.png": figs.error_densities,
    }
    for name, make in makers.items():
        fig = make(rep)
        fig.savefig(out / name, dpi=110, bbox_inches="tight")
        plt.close(fig)
        written.append(out / name)
    return written


def write_diagnosis_report(diag: Diagnosis | GroupDiagnosis, directory: str | Path,
                           published: dict[str, float] | None = None) -> list[Path]:
    """Save the diagnosis figures (PNG) into ``directory``; returns the files written. A
    planar rig's: residual arrows per arm and the gap per step; any other robot's: the ladder
    (``published``, step label -> mean mm, drawn beside it) and the residual arrows."""
    import matplotlib.pyplot as plt

    from bayesrob.report.plots import diagnosis as plots

    if isinstance(diag, GroupDiagnosis):
        doc = diag.to_json()
        figures = [("ladder.png", plots.ladder_figure(doc, published)),
                   ("residuals.png", plots.marker_residual_figure(diag.residuals, doc["rig"]))]
        dpi = 120
    else:
        figures = [(f"residuals_{a}.png", plots.residual_quiver_figure(diag, a))
                   for a in diag.arms] + [("gap_per_step.png", plots.gap_figure(diag))]
        dpi = 110
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    for name, fig in figures:
        fig.savefig(out / name, dpi=dpi)
    plt.close("all")
    return [out / name for name, _ in figures]


def write_design(result, modules: dict, top: int, out: str | Path) -> list[Path]:
    """``bayesrob design``'s outputs in ``out``: design.json, design.png (the best ``top``
    candidates, up to 4) and the best candidate's rig directory (best/), if there is one;
    returns the paths written."""
    from bayesrob.design.search import write_candidate_rig
    from bayesrob.report.plots.design import design_figure

    out = Path(out)
    written = [out / "design.json", out / "design.png"]
    written[0].write_text(json.dumps(result.document, indent=1))
    design_figure(result, modules, min(top, 4)).savefig(written[1], dpi=120)
    if result.best is not None:
        written.append(write_candidate_rig(result.best, result, modules, out / "best"))
    return written
