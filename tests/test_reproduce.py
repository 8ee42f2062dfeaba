"""`bayesrob reproduce` on the embedded default data: the paper's findings and the file contract."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bayesrob.errors.noise_models import discover_models
from bayesrob.paper.reproduction import FIGURES


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


# tests/golden/default_accuracy.json is reproduce's own earlier accuracy.json on the embedded
# default rig: a pin that catches any change of the reproduction's figures (the data are
# embedded and every step deterministic; 1e-6 relative leaves room for summation order only).
GOLDEN = Path(__file__).resolve().parent / "golden" / "default_accuracy.json"
ROOT = Path(__file__).resolve().parents[1]


def test_accuracy_json_matches_the_golden_file(reproduced):
    out, _ = reproduced
    s = json.loads((out / "accuracy.json").read_text())["setups"]
    golden = json.loads(GOLDEN.read_text())["setups"]
    assert set(s) == set(golden)
    for setup, g in golden.items():
        assert s[setup]["observed"]["mean_mm"] == pytest.approx(g["observed"]["mean_mm"],
                                                                rel=1e-6)
        assert s[setup]["observed"]["ci95_mm"] == pytest.approx(g["observed"]["ci95_mm"],
                                                                rel=1e-6)
        assert set(s[setup]["predicted"]) == set(g["predicted"])
        for model, figures in g["predicted"].items():
            for key, value in figures.items():
                assert s[setup]["predicted"][model][key] == pytest.approx(value, rel=1e-6), (
                    setup, model, key)


def _readme_accuracy_rows() -> dict[str, list[str]]:
    """The README's accuracy table ("Results on the default data"): setup -> its cells."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    head = text.index("| setup | observed (95% CI) |")
    rows = {}
    for line in text[head:].splitlines()[2:]:
        if not line.startswith("|"):
            break
        cells = [c.strip() for c in line.strip("|").split("|")]
        rows[cells[0]] = cells[1:]
    return rows


def test_the_readme_accuracy_table_is_the_golden_file():
    """The README prints the golden figures to two decimals: observed mean [CI], then each
    model's predicted error (ratio), in the table's column order."""
    golden = json.loads(GOLDEN.read_text())["setups"]
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    header = text[text.index("| setup | observed (95% CI) |"):].splitlines()[0]
    models = [c.strip() for c in header.strip("|").split("|")][2:]
    rows = _readme_accuracy_rows()
    assert set(rows) == set(golden)
    for setup, g in golden.items():
        obs = g["observed"]
        lo, hi = obs["ci95_mm"]
        assert rows[setup][0] == f"{obs['mean_mm']:.2f} [{lo:.2f}, {hi:.2f}]", setup
        for model, cell in zip(models, rows[setup][1:], strict=True):
            p = g["predicted"][model]
            assert cell == f"{p['expected_error_mm']:.2f} ({p['ratio']:.2f})", (setup, model)


def test_unknown_model_is_a_one_line_error(tmp_path):
    r = subprocess.run([sys.executable, "-m", "bayesrob", "reproduce", "--models", "nope",
                        "--out", str(tmp_path)], capture_output=True, text=True)
    assert r.returncode == 2
    assert r.stderr.strip().count("\n") == 0 and "nope" in r.stderr


