"""Model comparison: exact held-out and leave-one-out scores through arviz's compare."""

from __future__ import annotations

import json

import arviz as az
import jax.numpy as jnp
import numpy as np
import pytest

from bayesrob.calibration import calibrate
from bayesrob.cli import main
from bayesrob.comparison import _elpd_data, loo_training_scores, refit_without, score_points
from bayesrob.noise_models import discover_models, fit_noise_models, models_dir
from bayesrob.rig import default_rig_dir, load_rig


@pytest.mark.filterwarnings("ignore:The inplace keyword")  # arviz's own pandas call
def test_az_compare_on_exact_pointwise_values_gives_the_textbook_figures():
    """elpd_diff = sum of pointwise differences, dse = sqrt(n) * sd(differences)."""
    rng = np.random.default_rng(0)
    a = rng.normal(-2.0, 0.5, 40)
    b = a - 0.3 + rng.normal(0, 0.2, 40)
    df = az.compare({"a": _elpd_data(a, 1.0), "b": _elpd_data(b, 2.0)})
    assert list(df.index) == ["a", "b"]
    diff = a - b
    assert df.loc["b", "elpd_diff"] == pytest.approx(diff.sum())
    assert df.loc["b", "dse"] == pytest.approx(np.sqrt(40 * np.var(diff)))
    assert df.loc["a", "elpd_loo"] == pytest.approx(a.sum())
    assert df.loc["a", "se"] == pytest.approx(np.sqrt(40 * np.var(a)))
    assert df.loc["a", "weight"] > df.loc["b", "weight"]


def test_leave_one_out_drops_exactly_one_training_row():
    rig = load_rig(default_rig_dir())
    arm = calibrate(rig)["top"].arm
    arms = {"top": arm}
    spec = discover_models(names=["corr"])[0]
    model = fit_noise_models(rig, arms, [spec])["corr"]["top"]
    keep = np.arange(16) != 3
    m3 = refit_without(model, keep)
    np.testing.assert_array_equal(m3.theta_err, model.theta_err[keep])
    np.testing.assert_array_equal(m3.bandwidth, model.bandwidth)  # bandwidths are kept
    loo = loo_training_scores(rig, arm, model)
    u, d = rig.arm_rows("top", "train")
    target = np.asarray(arm.forward_u(jnp.asarray(u)))
    full, _ = score_points([model], [arm], [u], target, d)
    assert loo.shape == (16,) and np.all(np.isfinite(loo))
    # Scoring a point with its own kernel removed can only lower its density.
    assert np.all(loo < full.lpd)
    # Row 3's LOO score is the full-data machinery applied to the refitted model.
    s3, _ = score_points([m3], [arm], [u[3:4]], target[3:4], d[3:4])
    assert loo[3] == pytest.approx(float(s3.lpd[0]))


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
    assert set(doc["models"]) == {"ind_wide", "ind"}
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
