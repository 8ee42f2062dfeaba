"""The paper's Figures 3-8 and the comparison plot: every data panel labelled, nothing cut off.

The figures are built from one in-process reproduction of the embedded default rig (four of
the six models: one of each family the figures draw, and both IND variants for Figure 5), so
what is checked is what ``bayesrob reproduce`` draws.
"""

from __future__ import annotations

from types import SimpleNamespace

import matplotlib

matplotlib.use("Agg")

import arviz as az  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from matplotlib.axes import Axes  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from bayesrob.report.plots import paper as figs  # noqa: E402

MODELS = ["ind_paper", "ind", "corr", "cond_paper"]
MAKERS = {
    "fig3": figs.workspace_errors,
    "fig4": figs.accuracy,
    "fig5": figs.ind_densities,
    "fig6": figs.corr_densities,
    "fig7": figs.cond_grid,
    "fig8": figs.error_densities,
}


@pytest.fixture(scope="module")
def rep():
    from bayesrob.data.rig import default_rig_dir, load_rig
    from bayesrob.paper.reproduction import run_reproduction

    return run_reproduction(load_rig(default_rig_dir()), models=MODELS)


@pytest.fixture(scope="module")
def built(rep):
    out = {name: make(rep) for name, make in MAKERS.items()}
    for fig in out.values():
        fig.canvas.draw()  # lays out ticks, as saving does
    yield out
    for fig in out.values():
        plt.close(fig)


def _is_colorbar(ax: Axes) -> bool:
    return ax.get_label() == "<colorbar>"


def _shows_data(ax: Axes) -> bool:
    return ax.get_visible() and ax.axison and bool(
        ax.lines or ax.images or ax.collections or ax.patches)


def _all_axes(fig: Figure) -> list[Axes]:
    """Every axes of a figure, including those in subfigures."""
    out = list(fig.axes)
    for sf in fig.subfigs:
        out += _all_axes(sf)
    return list(dict.fromkeys(out))  # a figure's axes may already hold its subfigures' ones


def _unlabelled(fig: Figure) -> list[str]:
    """Data panels with no x or y label on themselves or on a panel sharing that axis.

    Panels in a shared grid carry the label on the outer row or column only, as in print.
    """
    bad = []
    for ax in _all_axes(fig):
        if _is_colorbar(ax) or not _shows_data(ax):
            continue
        for which, shared, label in (("x", ax.get_shared_x_axes(), Axes.get_xlabel),
                                     ("y", ax.get_shared_y_axes(), Axes.get_ylabel)):
            group = shared.get_siblings(ax)
            if not any(label(a).strip() for a in group):
                bad.append(f"{ax.get_title()!r}: no {which} label")
    return bad


@pytest.mark.parametrize("name", list(MAKERS))
def test_every_data_panel_has_axis_labels(built, name):
    fig = built[name]
    panels = [a for a in _all_axes(fig) if _shows_data(a) and not _is_colorbar(a)]
    assert panels, f"{name} draws nothing"
    assert _unlabelled(fig) == []


def test_fig3_draws_expected_error_with_a_key_and_no_clipped_arrow(built, rep):
    fig = built["fig3"]
    assert fig.legends, "Figure 3 needs a key for its arrows and circles"
    axes = [a for a in fig.axes if _shows_data(a)]
    quivers = [(a, c) for a in axes for c in a.collections
               if isinstance(c, matplotlib.quiver.Quiver)]
    assert quivers
    for ax, q in quivers:
        tips = q.get_offsets() + np.column_stack([q.U, q.V])
        (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
        assert np.all((tips[:, 0] > x0) & (tips[:, 0] < x1)), ax.get_title()
        assert np.all((tips[:, 1] > y0) & (tips[:, 1] < y1)), ax.get_title()
    # The lower row draws the expected error's size: one circle per target, radius x10 of it.
    circles = [p for a in axes for p in a.patches if isinstance(p, matplotlib.patches.Circle)]
    pred = rep.predictions["cond_paper"]
    want = np.concatenate([pred[c].expected_error_mm for c in rep.rows]) * 10.0
    assert len(circles) == want.size
    assert sorted(c.get_radius() for c in circles) == pytest.approx(sorted(want))
    assert want.min() > 5.0  # drawn at least 5 mm wide, not a dot


def test_fig5_has_no_negative_density_ticks(built):
    for ax in built["fig5"].axes:
        ticks = [t for t in ax.get_yticks() if ax.get_ylim()[0] <= t <= ax.get_ylim()[1]]
        assert ticks and min(ticks) >= 0.0, ticks


def test_fig7_has_colour_bars_named_model_and_panels_that_hold_the_density(built, rep):
    fig = built["fig7"]
    axes = _all_axes(fig)
    bars = [a for a in axes if _is_colorbar(a)]
    assert len(bars) == len(rep.rows)  # one shared colour scale per setup
    assert all("mm" in b.get_ylabel() for b in bars)
    assert "cond_paper" in fig.get_suptitle()
    panels = [a for a in axes if a.images and not _is_colorbar(a)]
    assert len(panels) == sum(len(r["targets"]) for r in rep.rows.values())
    cell = rep.predictions["cond_paper"]["top"].grid.cell_area_mm2
    for ax in panels:
        shown = float(np.sum(ax.images[0].get_array()) * cell)
        assert shown >= 0.99, f"{ax.get_title()}: only {shown:.3f} of the mass in the panel"
        # Target and expected point both drawn, in different markers so neither hides the other.
        markers = {ln.get_marker() for ln in ax.lines}
        assert {"+", "o"} <= markers
        for shared, label in ((ax.get_shared_x_axes(), Axes.get_xlabel),
                              (ax.get_shared_y_axes(), Axes.get_ylabel)):
            assert any("(mm)" in label(a) for a in shared.get_siblings(ax))


def _fake_comparison(dim: int = 2, other: str = "cond_paper"):
    """A comparison of two models with fixed pointwise scores on a rig of ``dim`` coordinates:
    enough to draw the figure."""
    from bayesrob.compare.comparison import ModelComparison, elpd_data
    from bayesrob.errors.noise_models import discover_models

    specs = discover_models(names=["ind", other])
    rng = np.random.default_rng(0)
    held = {"ind": rng.normal(-2.5, 0.5, 48), other: rng.normal(-30.0, 20.0, 48)}
    loo = {"ind": rng.normal(-2.6, 0.4, 32), other: rng.normal(-150.0, 50.0, 32)}
    tables = [az.compare({k: elpd_data(v, 1.0) for k, v in d.items()}, method="stacking")
              for d in (held, loo)]
    return ModelComparison(SimpleNamespace(name="rig", robot=SimpleNamespace(dim=dim)), specs,
                           {k: {"top": SimpleNamespace(lpd=v)} for k, v in held.items()},
                           loo, loo, *tables, 0.0)


def test_comparison_figure_has_units_and_labels():
    from bayesrob.report.plots.comparison import comparison_figure

    fig = comparison_figure(_fake_comparison())
    try:
        fig.canvas.draw()
        assert _unlabelled(fig) == []
        title = fig.get_suptitle()
        assert "nats" in title and "mm^2, summed" not in title
        assert "mm$^2$" in title and "squares paper-faithful" in title
        for ax in fig.axes:
            assert "nats" in ax.get_xlabel()
            # Nothing cut off: every error bar's ends lie inside the panel.
            x0, x1 = ax.get_xlim()
            for line in ax.lines:
                xs = np.asarray(line.get_xdata(), float)
                assert np.all((xs >= x0) & (xs <= x1)), (ax.get_title(), xs, (x0, x1))
    finally:
        plt.close(fig)


def test_comparison_figure_of_a_3d_rig_without_paper_models_says_so():
    from bayesrob.report.plots.comparison import comparison_figure

    fig = comparison_figure(_fake_comparison(dim=3, other="cond"))
    try:
        title = fig.get_suptitle()
        # a 3-D marker's density is per mm^3; no paper model is drawn, so no key to one
        assert "mm$^3$" in title and "paper-faithful" not in title
    finally:
        plt.close(fig)


def test_fig8_panels_hold_every_models_density(built, rep):
    # The paper-faithful bottom-arm density spreads widest; a fixed +-5 mm panel held 89% of it.
    cell = rep.predictions["ind_paper"]["top"].grid.cell_area_mm2
    panels = [a for a in built["fig8"].axes if a.images]
    assert len(panels) == len(MODELS) * len(rep.rows)
    for ax in panels:
        shown = float(np.sum(ax.images[0].get_array()) * cell)
        assert shown >= 0.99, f"{ax.get_title()}: only {shown:.3f} of the density in the panel"
        x0, x1 = ax.get_xlim()
        assert ax.images[0].get_extent()[:2] == pytest.approx([x0, x1], abs=0.31)


def _clipped_texts(fig: Figure) -> list[str]:
    """What a saved PNG would cut off: the parts of the drawn artists (titles, labels, the
    tick labels drawn, annotations, legends, colour bars) that reach past the figure's edge,
    as 'side by N px'. Figures saved with bbox_inches='tight' grow to hold them instead."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    if not hasattr(fig.canvas, "get_renderer"):  # a bare Figure(), as the commands save
        FigureCanvasAgg(fig)
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    tight = fig.get_tightbbox(renderer).transformed(fig.dpi_scale_trans)  # to pixels
    box = fig.bbox
    out = {"left": box.x0 - tight.x0, "right": tight.x1 - box.x1,
           "bottom": box.y0 - tight.y0, "top": tight.y1 - box.y1}
    return [f"{side} by {px:.0f} px" for side, px in out.items() if px > 1]


@pytest.mark.parametrize("name", list(MAKERS))
def test_no_text_of_the_papers_figures_is_cut_off(built, name):
    """reproduce saves them with bbox_inches='tight', which would hide the check: drawn as
    they are, nothing of them may lie past the figure's edge."""
    assert _clipped_texts(built[name]) == []


@pytest.mark.parametrize("config", ["top", "top+bottom"])
def test_the_predict_figure_fits_its_content(config):
    """Every text inside the figure, every target and arm base inside the map's axes, and a
    title that names a fusion only for linked arms (planar arms drawn as every robot is)."""
    from bayesrob.data.rig import default_rig_dir, load_rig
    from bayesrob.predict.assembly import grid_targets, predict_assembly
    from bayesrob.report.plots.prediction import assembly_figure

    rig = load_rig(default_rig_dir())
    pred = predict_assembly(rig, config, grid_targets(rig, 3), "ind")
    fig = assembly_figure(pred, rig)
    try:
        assert _clipped_texts(fig) == []
        ax = fig.axes[0]
        # each target's square marker whole inside the axes (in pixels, as drawn)
        half = np.sqrt(ax.collections[0].get_sizes().max()) / 2 * fig.dpi / 72
        shown = np.vstack([pred.targets, [rig.arms[a].base for a in config.split("+")]])
        px = ax.transData.transform(shown)
        box = ax.get_window_extent()
        inside = ((px[:, 0] - half >= box.x0) & (px[:, 0] + half <= box.x1)
                  & (px[:, 1] - half >= box.y0) & (px[:, 1] + half <= box.y1))
        assert inside.all(), shown[~inside]
        title = fig.get_suptitle()
        assert ("equilibrium" in title) == ("+" in config), title
    finally:
        plt.close(fig)


def test_the_marker_residual_figure_fits_its_content():
    """Justin's figure had its last title cut ('mean 3.21 m'): long model labels, two arms."""
    from bayesrob.report.plots.diagnosis import marker_residual_figure

    rng = np.random.default_rng(0)
    pts = {a: (rng.normal(0, 300, (40, 3)), rng.normal(0, 3, (40, 3))) for a in ("left", "right")}
    residuals = {"geometric": pts, "+ joint_compliance + lateral_compliance": pts}
    fig = marker_residual_figure(residuals, "justin")
    assert _clipped_texts(fig) == []
    labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert labels == ["left", "right"]


def test_the_marker_residual_figure_of_a_planar_chain_rig_has_its_one_plane():
    """A 2-D chain rig's markers have no z: its figure is the x-y plane alone (it raised an
    IndexError, so `diagnose --report` wrote nothing on such a rig)."""
    from bayesrob.report.plots.diagnosis import marker_residual_figure

    rng = np.random.default_rng(1)
    pts = {"arm": (rng.normal(0, 100, (30, 2)), rng.normal(0, 1, (30, 2)))}
    fig = marker_residual_figure({"geometric": pts, "+ servo_nonlinearity": pts}, "planar")
    assert len(fig.axes) == 2  # one plane per model
    assert [ax.get_xlabel() + ax.get_ylabel() for ax in fig.axes] == ["x (mm)y (mm)"] * 2
    assert _clipped_texts(fig) == []


@pytest.mark.parametrize("steps", [0, 2])
def test_the_ladder_figures_key_covers_no_bar(steps):
    """On a one-bar ladder the key, drawn inside the panel, sat on the bar's error cap."""
    from bayesrob.report.plots.diagnosis import ladder_figure

    def step(mean):
        return {"heldout_error_mm": mean, "heldout_error_sd_mm": 0.6 * mean,
                "heldout_error_max_mm": 3.0 * mean}

    doc = {"rig": "rig", "baseline": step(0.9),
           "steps": [{"effect": f"effect_{k}", **step(0.5 - 0.1 * k)} for k in range(steps)]}
    fig = ladder_figure(doc, published={"geometric": 1.0})
    try:
        assert _clipped_texts(fig) == []
        (key,) = fig.legends
        assert not key.get_window_extent().overlaps(fig.axes[0].get_window_extent())
        assert len(key.get_texts()) == 3  # mean and sd, largest error, published
    finally:
        plt.close(fig)


def test_fig8_has_a_colour_scale_for_each_model(built):
    """Colour is density: each model's row says on what scale."""
    bars = [ax for ax in built["fig8"].axes if _is_colorbar(ax)]
    assert len(bars) == len(MODELS)
    assert all("density" in ax.get_ylabel() for ax in bars)


def test_a_design_with_no_candidate_draws_a_figure_that_says_so():
    from bayesrob.report.plots.design import design_figure

    region = np.array([[120.0, 220.0], [140.0, 240.0]])
    result = SimpleNamespace(candidates=[], design=SimpleNamespace(region=region),
                             targets=np.array([[125.0, 225.0], [135.0, 235.0]]))
    fig = design_figure(result, {})
    try:
        (ax,) = fig.axes
        assert "no assembly" in ax.get_title() and _shows_data(ax)
        assert _clipped_texts(fig) == []
    finally:
        plt.close(fig)


def _fake_3d_prediction(config: str = "left+right"):
    rng = np.random.default_rng(1)
    targets = np.array([[x, y, z] for x in (300.0, 500.0) for y in (-200.0, 200.0)
                        for z in (100.0, 400.0)])
    draws = targets[None] + rng.normal(0, 2.0, (2000, len(targets), 3))
    pred = SimpleNamespace(targets=targets, draws=draws, config=config, model="ind",
                           fusion="equilibrium",
                           expected_error_mm=np.linspace(2.0, 3.0, len(targets)))
    bases = {"left": [0.0, -600.0, 0.0], "right": [0.0, 600.0, 0.0], "front": [900.0, 0, 0]}

    def instrument_pose(x, arm):
        pose = np.eye(4)
        pose[:3, 3] = bases[arm]
        return pose

    rig = SimpleNamespace(arms={a: SimpleNamespace() for a in bases}, robot=SimpleNamespace(
        layout=SimpleNamespace(nominal=None), instrument_pose=instrument_pose))
    return pred, rig


@pytest.mark.parametrize("config", ["left+right", "left+right+front"])
def test_the_3d_predict_figure_shows_the_targets_in_views_of_equal_scale(config):
    """Seen from above and from the side on one scale, every target and arm base inside
    its view, every panel titled, nothing cut off at the figure's edge."""
    from bayesrob.report.plots.prediction import assembly_figure

    pred, rig = _fake_3d_prediction(config)
    fig = assembly_figure(pred, rig)
    try:
        assert _clipped_texts(fig) == []
        views = [ax for ax in fig.axes if ax.get_title().startswith("targets")]
        assert [ax.get_title() for ax in views] == ["targets, x-y view", "targets, x-z view"]
        scales = [np.diff(ax.transData.transform([[0, 0], [1, 1]]), axis=0)[0] for ax in views]
        assert np.allclose(scales[0], scales[1], rtol=1e-6)  # pixels per mm, both axes, both
        for ax, (i, j) in zip(views, [(0, 1), (0, 2)], strict=True):
            (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
            pts = np.vstack([pred.targets, [rig.robot.instrument_pose(None, a)[:3, 3]
                                            for a in config.split("+")]])
            assert np.all((pts[:, i] > x0) & (pts[:, i] < x1) & (pts[:, j] > y0)
                          & (pts[:, j] < y1))
        assert all(ax.get_title() for ax in fig.axes if not _is_colorbar(ax))
        # the x-z view sees left and right one behind the other: one label names both
        labels = [[tx.get_text() for tx in ax.texts] for ax in views]
        assert sorted(labels[0]) == sorted(config.split("+")), labels
        assert sorted(labels[1]) == sorted(["left, right", *config.split("+")[2:]]), labels
    finally:
        plt.close(fig)
