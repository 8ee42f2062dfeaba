"""`bayesrob reproduce` on the embedded default data: the paper's findings and the file contract."""

import json
import subprocess
import sys

import numpy as np
import pytest

from bayesrob.noise_models import discover_models
from bayesrob.reproduction import FIGURES


@pytest.fixture(scope="module")
def reproduced(tmp_path_factory):
    out = tmp_path_factory.mktemp("repro")
    r = subprocess.run([sys.executable, "-m", "bayesrob", "reproduce", "--out", str(out)],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    return out, r.stdout


def test_writes_every_figure_and_accuracy_json(reproduced):
    out, stdout = reproduced
    for name in FIGURES:
        assert (out / name).stat().st_size > 10_000, name  # a real picture, not an empty canvas
    doc = json.loads((out / "accuracy.json").read_text())
    assert set(doc["setups"]) == {"top", "bottom", "top+bottom"}
    models = {s.name for s in discover_models()}
    for s in doc["setups"].values():
        obs = s["observed"]
        assert obs["n"] == 16 and obs["ci95_mm"][0] < obs["mean_mm"] < obs["ci95_mm"][1]
        assert set(s["predicted"]) == models
        for p in s["predicted"].values():
            assert p["ratio"] == pytest.approx(p["expected_error_mm"] / obs["mean_mm"])
    assert "pred/obs" in stdout and "top+bottom" in stdout


def test_reproduces_the_papers_findings(reproduced):
    out, _ = reproduced
    s = json.loads((out / "accuracy.json").read_text())["setups"]
    linked = s["top+bottom"]
    # the linked arms are observed to be more accurate than either arm alone
    assert linked["observed"]["mean_mm"] < s["top"]["observed"]["mean_mm"]
    assert linked["observed"]["mean_mm"] < s["bottom"]["observed"]["mean_mm"]
    # and every model variant predicts so
    for model, p in linked["predicted"].items():
        for arm in ("top", "bottom"):
            assert p["expected_error_mm"] < s[arm]["predicted"][model]["expected_error_mm"], model
    # the paper's IND and CORR estimators are conservative: they over-predict the error
    for model in ("ind_paper", "corr_paper"):
        for setup in s.values():
            assert setup["predicted"][model]["ratio"] > 1.2
    # the improved estimators close most of that gap
    for fam in ("ind", "corr"):
        for setup in s.values():
            assert abs(np.log(setup["predicted"][fam]["ratio"])) < abs(
                np.log(setup["predicted"][f"{fam}_paper"]["ratio"]))


# The README's table ("Results on the default data"): per setup, the observed mean error and
# its 95% CI, then each model's predicted expected error and ratio to the observation.
README_TABLE = {
    "top": ((1.36, 1.04, 1.68), {
        "ind_paper": (2.33, 1.71), "ind": (1.26, 0.93), "corr_paper": (2.32, 1.70),
        "corr": (1.28, 0.94), "cond_paper": (1.58, 1.16), "cond": (1.28, 0.94)}),
    "bottom": ((1.32, 0.99, 1.65), {
        "ind_paper": (2.99, 2.27), "ind": (1.62, 1.22), "corr_paper": (2.98, 2.26),
        "corr": (1.59, 1.21), "cond_paper": (2.03, 1.54), "cond": (1.59, 1.21)}),
    "top+bottom": ((0.85, 0.63, 1.07), {
        "ind_paper": (1.34, 1.58), "ind": (0.80, 0.94), "corr_paper": (1.35, 1.59),
        "corr": (0.86, 1.02), "cond_paper": (1.11, 1.31), "cond": (0.86, 1.02)}),
}


def test_the_readme_reproduction_table(reproduced):
    """Every figure of the README's table, as printed (two decimals).

    The data are embedded and every step is deterministic, so the only tolerance is the
    table's rounding: half a unit of the last printed digit (plus 1e-9 for float noise).
    """
    out, _ = reproduced
    s = json.loads((out / "accuracy.json").read_text())["setups"]
    tol = 0.005 + 1e-9
    for setup, ((mean, lo, hi), predicted) in README_TABLE.items():
        obs = s[setup]["observed"]
        assert obs["mean_mm"] == pytest.approx(mean, abs=tol), setup
        assert obs["ci95_mm"] == pytest.approx([lo, hi], abs=tol), setup
        for model, (err, ratio) in predicted.items():
            p = s[setup]["predicted"][model]
            assert p["expected_error_mm"] == pytest.approx(err, abs=tol), (setup, model)
            assert p["ratio"] == pytest.approx(ratio, abs=tol), (setup, model)


def test_unknown_model_is_a_one_line_error(tmp_path):
    r = subprocess.run([sys.executable, "-m", "bayesrob", "reproduce", "--models", "nope",
                        "--out", str(tmp_path)], capture_output=True, text=True)
    assert r.returncode == 2
    assert r.stderr.strip().count("\n") == 0 and "nope" in r.stderr


