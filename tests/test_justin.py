"""DLR's Agile Justin (real data, read from ../shared/data/, never shipped): the geometric
ladder reproduces the published figures. Runs where the data is (CI has it)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "agile-justin" / "measurements.csv"

pytestmark = [pytest.mark.slow,
              pytest.mark.skipif(not DATA.is_file(), reason=f"{DATA} not present")]


def test_justin_ladder_matches_the_published_one(tmp_path):
    sys.path.insert(0, str(ROOT / "examples" / "agile_justin"))
    from convert import convert
    from ladder import ladder

    convert(DATA, tmp_path / "rig")
    rows = {r["params"]: r for r in ladder(tmp_path / "rig")}
    val = {k: r["validation"] for k, r in rows.items()}
    assert all(v["n"] == 400 for v in val.values())  # 200 validation poses x 2 markers
    # The targets (published 21.33 / 18.18 / 10.5) and the figures the README states
    # (20.14 / 17.87 / 10.97 / 10.20): least squares from fixed starts is deterministic to far
    # below 0.05 mm, so a change that moves them is seen.
    assert 19.5 <= val["frames"]["mean_mm"] <= 21.5
    assert val["frames"]["mean_mm"] == pytest.approx(20.14, abs=0.05)
    assert 17.0 <= val["frames,offsets"]["mean_mm"] <= 19.0
    assert val["frames,offsets"]["mean_mm"] == pytest.approx(17.87, abs=0.05)
    assert val["frames,geometric"]["mean_mm"] == pytest.approx(10.97, abs=0.05)
    assert val["frames,offsets,geometric,servo"]["mean_mm"] == pytest.approx(10.20, abs=0.05)
    assert val["frames,offsets,geometric,servo"]["mean_mm"] <= 10.5
    # joint compliance without masses, both arms weighing on the torso (README: 4.34; the
    # issue's target and the published step with CAD masses: 5.64). Its fit has ~130
    # parameters and a rank analysis between two rounds, so it is held to 0.1 mm.
    comp = val["frames,geometric,compliance"]
    assert comp["mean_mm"] <= 5.64 and comp["mean_mm"] == pytest.approx(4.34, abs=0.1)
    # with bending across the axes and its prior (README: 3.21; their full calibration 3.12,
    # not reached with one step of the torques)
    lateral = val["frames,geometric,compliance,lateral"]["mean_mm"]
    assert lateral < comp["mean_mm"] and lateral == pytest.approx(3.21, abs=0.1)
    # the same model at its torque equilibrium (README: 3.08, below their 3.12): six steps are
    # a fixed point, a seventh moves no train marker by more than 0.01 mm
    eq = rows["frames,geometric,compliance,lateral --sag-steps 6"]
    assert eq["sag_steps"] == 6 and eq["sag_next_step_mm"] <= 0.01
    assert eq["validation"]["mean_mm"] <= 3.12
    assert eq["validation"]["mean_mm"] == pytest.approx(3.08, abs=0.05)
    # a torso shared by both hands: one calibration fits both markers
    assert rows["frames"]["n_free"] == 12  # base pose (6) + two markers (3 + 3)


def test_justin_hands_predicted_regions_hold_their_coverage(tmp_path):
    """Issue target (linked predictions, real data): with the model the diagnosis names, each
    hand's 50% / 90% regions hold their share of its 200 validation points within binomial
    error (95% ranges at n = 200: 0.43-0.57 and 0.855-0.94), and the predicted mean error is
    within 0.85-1.15 of the observed. The NUTS fits are seeded, so the figures
    docs/fusion.md states are held to five points in 200 as well: the seeded run follows
    rounding-level changes of the fitted parameters, which have moved its figures by up to
    three points (docs/fusion.md)."""
    sys.path.insert(0, str(ROOT / "examples" / "agile_justin"))
    from convert import convert
    from coverage import coverage

    convert(DATA, tmp_path / "rig")
    rows = {r["hand"]: r for r in coverage(tmp_path / "rig", (
        "frames", "geometric", "compliance", "lateral"))}
    published = {"right": (0.495, 0.875, 0.92), "left": (0.480, 0.865, 0.93)}
    for hand, (c50, c90, ratio) in published.items():
        r = rows[hand]
        assert r["n"] == 200
        assert 0.43 <= r["coverage50"] <= 0.57 and 0.855 <= r["coverage90"] <= 0.94, r
        assert 0.85 <= r["ratio"] <= 1.15, r
        assert (r["coverage50"], r["coverage90"]) == pytest.approx((c50, c90), abs=0.026), r
        assert r["ratio"] == pytest.approx(ratio, abs=0.01), r
