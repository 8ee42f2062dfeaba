"""Model comparison: exact held-out and leave-one-out scores through arviz's compare. The
default rig's comparison tables (README, docs/comparison.md) are the validation study
comparison_default's."""

from __future__ import annotations

import json

import arviz as az
import jax.numpy as jnp
import numpy as np
import pytest

from bayesrob.calibrate.arms import calibrate_arm, calibrate_arms
from bayesrob.cli import main
from bayesrob.compare.comparison import (
    compare_models,
    elpd_data,
    loo_calibrations,
    loo_training_scores,
    refit_at_bandwidths,
    refit_without,
    score_points,
)
from bayesrob.data.rig import default_rig_dir, load_rig
from bayesrob.errors.noise_models import discover_models, fit_noise_models, joint_errors, models_dir
from bayesrob.report.tables import format_comparison


@pytest.mark.filterwarnings("ignore:The inplace keyword")  # arviz's own pandas call
def test_az_compare_on_exact_pointwise_values_gives_the_textbook_figures():
    """elpd_diff = sum of pointwise differences, dse = sqrt(n) * sd(differences)."""
    rng = np.random.default_rng(0)
    a = rng.normal(-2.0, 0.5, 40)
    b = a - 0.3 + rng.normal(0, 0.2, 40)
    df = az.compare({"a": elpd_data(a, 1.0), "b": elpd_data(b, 2.0)})
    assert list(df.index) == ["a", "b"]
    diff = a - b
    assert df.loc["b", "elpd_diff"] == pytest.approx(diff.sum())
    assert df.loc["b", "dse"] == pytest.approx(np.sqrt(40 * np.var(diff)))
    assert df.loc["a", "elpd_loo"] == pytest.approx(a.sum())
    assert df.loc["a", "se"] == pytest.approx(np.sqrt(40 * np.var(a)))
    assert df.loc["a", "weight"] > df.loc["b", "weight"]


def test_leave_one_out_drops_exactly_one_training_row():
    rig = load_rig(default_rig_dir())
    arm = calibrate_arms(rig)["top"].arm
    arms = {"top": arm}
    spec = discover_models(names=["corr"])[0]
    model = fit_noise_models(rig, arms, [spec])["corr"]["top"]
    keep = np.arange(16) != 3
    m3 = refit_without(model, keep)
    np.testing.assert_array_equal(m3.theta_err, model.theta_err[keep])
    np.testing.assert_array_equal(m3.bandwidth, model.bandwidth)  # bandwidths are kept
    loo = loo_training_scores(rig, arm, model, recalibrate=False)
    u, d = rig.rows("top", "train")
    target = np.asarray(arm.forward_u(jnp.asarray(u)))
    full, _ = score_points([model], [arm], [u], target, d)
    assert loo.shape == (16,) and np.all(np.isfinite(loo))
    # Scoring a point with its own kernel removed can only lower its density.
    assert np.all(loo < full.lpd)
    # Row 3's LOO score is the full-data machinery applied to the refitted model.
    s3, _ = score_points([m3], [arm], [u[3:4]], target[3:4], d[3:4])
    assert loo[3] == pytest.approx(float(s3.lpd[0]))


def test_leave_one_out_refits_the_calibration_without_the_row():
    """Row i is scored by an arm calibrated on the other 15 rows, whose joint errors (under
    that arm) the density is refitted to; compare's LOO is this by default."""
    rig = load_rig(default_rig_dir())
    arm = calibrate_arms(rig)["bottom"].arm
    spec = discover_models(names=["corr"])[0]
    model = fit_noise_models(rig, {"bottom": arm}, [spec])["corr"]["bottom"]
    u, d = rig.rows("bottom", "train")
    uv, dv = rig.rows("bottom", "validation")
    loo = loo_training_scores(rig, arm, model)
    kept_cal = loo_training_scores(rig, arm, model, recalibrate=False)
    i = 5
    keep = np.arange(16) != i
    arm_i = calibrate_arm(rig.arms["bottom"], u[keep], d[keep], "least-squares", uv, dv).arm
    assert not np.allclose(arm_i.params.to_vector(), arm.params.to_vector())
    m_i = refit_at_bandwidths(model, joint_errors(arm_i, u[keep], d[keep]), u[keep])
    np.testing.assert_array_equal(m_i.bandwidth, model.bandwidth)
    target = np.asarray(arm_i.forward_u(jnp.asarray(u[i:i + 1])))
    s_i, _ = score_points([m_i], [arm_i], [u[i:i + 1]], target, d[i:i + 1])
    # Same arithmetic, same inputs: equal to rounding.
    assert loo[i] == pytest.approx(float(s_i.lpd[0]), abs=1e-9)
    # A calibration that has seen the row pulls the arm towards it (leverage about 0.25), so
    # keeping it flatters the row: summed over the 16 rows, honest LOO scores lower.
    assert loo.sum() < kept_cal.sum()


def test_histogram_cond_leave_one_out_keeps_its_bin_margin():
    """The paper COND's grid (data extent plus a quarter of the range, ``bin_margin``) is
    re-derived from the kept rows. A left-out row then scores the histogram's floor (log
    1e-300 = -690.8) exactly when it lies outside that grid, which is the model's support;
    without the margin every row at the edge of the data fell there."""
    rig = load_rig(default_rig_dir())
    arms = {n: c.arm for n, c in calibrate_arms(rig).items()}
    spec = discover_models(names=["cond_paper"])[0]
    assert spec.bin_widths is None and spec.bin_margin > 0
    fitted = fit_noise_models(rig, arms, [spec])["cond_paper"]
    inside_all = []
    for name, arm in arms.items():
        model = fitted[name]
        u, d = rig.rows(name, "train")
        cals = loo_calibrations(rig, name)
        loo = loo_training_scores(rig, arm, model, calibrations=cals)
        for i, arm_i in enumerate(cals):
            keep = np.arange(16) != i
            m = refit_at_bandwidths(model, joint_errors(arm_i, u[keep], d[keep]), u[keep])
            c = m.conditional
            np.testing.assert_allclose(c.bin_widths, spec._bin_widths(m.theta_err, m.u))
            p = np.r_[joint_errors(arm_i, u[i:i + 1], d[i:i + 1])[0], u[i]]
            rel = (p - c.grid_lo) / c.bin_widths
            inside = bool(np.all((rel >= 0) & (rel <= c.bins)))
            inside_all.append(inside)
            # Inside the grid every score here is above -15; the floor puts one near -700.
            assert (loo[i] > -100.0) == inside, (name, i, loo[i])
    # The margin keeps all but the most extreme rows on the grid (31 of 32 on this rig).
    assert sum(inside_all) >= 30


def test_compare_command_writes_table_json_and_plot(tmp_path, capsys):
    """Two IND variants from a models directory of our own: the shipped LOO-ML one and one
    with a fixed, much too wide bandwidth, which must lose."""
    models = tmp_path / "models"
    models.mkdir()
    (models / "ind.toml").write_text((models_dir() / "ind.toml").read_text())
    (models / "ind_wide.toml").write_text('name = "ind_wide"\nfamily = "IND"\n'
                                          "bandwidth = 0.02\njacobian = true\n")
    out = tmp_path / "cmp" / "compare.json"
    rc = main(["compare", "--models-dir", str(models), "--json", str(out)])
    printed = capsys.readouterr().out
    assert rc == 0
    doc = json.loads(out.read_text())
    assert (tmp_path / "cmp" / "compare.png").stat().st_size > 10_000
    assert doc["plot"].endswith("compare.png")
    assert set(doc["models"]) == {"ind_wide", "ind", "ind_wide:equilibrium",
                                  "ind:equilibrium"}
    assert {m["fusion"] for m in doc["models"].values()} == {"product", "equilibrium"}
    assert doc["winner"]["model"] == "ind" and doc["winner"]["over"] == "ind_wide"
    assert doc["heldout_rows"] == {"top": 16, "bottom": 16, "top+bottom": 16}
    for table in ("heldout_compare", "loo_compare"):
        rows = doc[table]
        assert [r["rank"] for r in rows] == [0, 1]
        assert rows[0]["elpd_diff"] == 0.0 and rows[1]["elpd_diff"] > 0
        assert abs(sum(r["weight"] for r in rows) - 1.0) < 1e-6
    m = doc["models"]["ind"]
    assert m["heldout"]["n"] == 48 and m["loo_train"]["n"] == 32
    assert m["heldout"]["elpd"] == pytest.approx(
        sum(s["elpd"] for s in m["heldout"]["by_setup"].values()))
    ppc = m["heldout"]["by_setup"]["top+bottom"]["ppc"]
    assert 0.0 <= ppc["ppp"] <= 1.0 and ppc["mean_error_obs_mm"] > 0
    w = doc["winner"]
    assert w["model"] == doc["heldout_compare"][0]["model"]
    assert "winner on held-out points" in printed


def _relabel(src, dest, pick) -> None:
    """Copy a rig, turning the rows ``pick(index, row)`` selects into ``holdout`` rows."""
    import csv
    import shutil

    shutil.copytree(src, dest)
    path = dest / "measurements.csv"
    with path.open(newline="") as fh:
        rows = list(csv.DictReader(fh))
        fields = list(rows[0])
    for i, row in enumerate(rows):
        if pick(i, row):
            row["set"] = "holdout"
    with path.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fields, lineterminator="\n")
        w.writeheader()
        w.writerows(rows)


@pytest.mark.filterwarnings("ignore:The inplace keyword")
def test_compare_reports_holdout_rows_beside_the_held_out_ones(clean_rig_dir, tmp_path):
    """Every other validation/test row relabelled ``holdout``: those rows are scored apart,
    each exactly as it was scored as a held-out row (models see only the train rows)."""
    before = compare_models(load_rig(clean_rig_dir), ["ind"], recalibrate=False)
    _relabel(clean_rig_dir, tmp_path / "rig",
             lambda i, row: row["set"] in ("validation", "test") and i % 2 == 0)
    rig = load_rig(tmp_path / "rig")
    after = compare_models(rig, ["ind"], recalibrate=False)
    doc = after.document()
    m = doc["models"]["ind"]
    n_hold = int(rig.measurements.mask(set="holdout").sum())
    assert n_hold > 0
    assert m["holdout"]["n"] == n_hold == sum(doc["holdout_rows"].values())
    assert m["heldout"]["n"] + n_hold == before.document()["models"]["ind"]["heldout"]["n"]
    assert set(doc["holdout_rows"]) == set(doc["heldout_rows"])
    assert [r["model"] for r in doc["holdout_compare"]] == ["ind"]
    assert doc["holdout_compare"][0]["elpd"] == pytest.approx(m["holdout"]["elpd"])
    for config in doc["holdout_rows"]:
        mask = rig.measurements.mask(config)
        sets = rig.measurements.set[mask & (rig.measurements.set != "train")]
        old = before.heldout["ind"][config].lpd
        np.testing.assert_allclose(after.holdout["ind"][config].lpd, old[sets == "holdout"],
                                   rtol=1e-9)
        np.testing.assert_allclose(after.heldout["ind"][config].lpd, old[sets != "holdout"],
                                   rtol=1e-9)
    # LOO is over the train rows, which did not change.
    np.testing.assert_allclose(after.loo["ind"], before.loo["ind"], rtol=1e-9)
    text = format_comparison(doc)
    assert "holdout points" in text and "top+bottom (holdout)" in text
    # Without holdout rows the keys are there, empty.
    plain = before.document()
    assert plain["holdout_rows"] == {} and plain["holdout_compare"] == []
    assert plain["models"]["ind"]["holdout"] is None
    assert "holdout points" not in format_comparison(plain)


def test_corr_on_a_one_joint_chain_is_ind():
    """A single joint has no correlation to fit (numpyro's LKJ needs two; `bayesrob compare`
    raised on a one-joint arm): CORR's covariance draws are then IND's, joint sd squared."""
    from bayesrob import Measurements, Rig, dh_chain
    from bayesrob.calibrate.least_squares import calibrate
    from bayesrob.errors.latent_errors import fit_latent_errors

    rng = np.random.default_rng(4)
    q = rng.uniform(-1.5, 1.5, 24)
    r = 120.0 + 0.5
    pts = np.column_stack([r * np.cos(q + 0.02), r * np.sin(q + 0.02)])
    pts += rng.normal(0, 0.2, pts.shape)
    rows = Measurements.from_arrays(config=["arm"] * 24, set=["train"] * 24, observed=pts,
                                    commands={"arm": q[:, None]})
    rig = Rig.from_arrays({"arm": dh_chain("arm", [[0.0, 0.0, 120.0, 0.0]], "standard")},
                          rows)
    cal = calibrate(rig, ("frames", "geometric"))
    fit = fit_latent_errors(rig, cal.robot, cal.x, "arm", "corr",
                            n_free=int(cal.ident.free.sum()), warmup=100, samples=100,
                            chains=1)
    assert fit.corr_chol is not None and np.all(fit.corr_chol == 1.0)
    assert np.allclose(fit.covariance[:, 0, 0], fit.joint_sd[:, 0] ** 2)
    assert np.all(np.isfinite(fit.noise_sd))
