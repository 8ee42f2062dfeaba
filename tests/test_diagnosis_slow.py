"""The proof on hidden effects (``pytest -m slow``): the report rigs, which nothing was chosen on.

Rigs come from ``tests/generators.py``: this project"s simulator (paper geometry, 4x4 and 6x6
grids) and the deliberately different generators (hardening springs and a bending link, or
bending links on stiff joints, for sag; play with approach-direction hysteresis; a tanh servo
map; two geometries, one on a tilted plane). The decision rule was chosen on the tuning rigs
(seeds 21-35); these are the report rigs (seeds 501-534), fixed before any diagnosis ran on
them. Each is diagnosed from its files alone. ``benchmarks/bench_diagnose.py --confusion``
prints the same sweep as markdown tables (docs/diagnose.md).
"""

from __future__ import annotations

from collections import Counter

import pytest
from chain_generators import REPORT_SEEDS, chain_cases, diagnose_chain_case
from generators import diagnose_case, effects_key, exactly_right, report_cases, targets

import bayesrob  # noqa: F401

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def sweep() -> list[dict]:
    return [diagnose_case(case) for case in report_cases()]


# The confusion matrix of docs/diagnose.md: hidden (rows) x named (columns). The sweep is
# seeded and diagnose is deterministic, so the published counts are asserted exactly; a
# change that moves any of them must update the docs with it.
PUBLISHED_CONFUSION: dict[str, dict[str, int]] = {
    "none": {"none": 11},
    "gravity_sag": {"gravity_sag": 4, "none": 4, "backlash": 1, "servo_nonlinearity": 2,
                    "gravity_sag+servo_nonlinearity": 1},
    "backlash": {"backlash": 6, "none": 4},
    "servo_nonlinearity": {"servo_nonlinearity": 10},
    "backlash+gravity_sag": {"backlash+gravity_sag": 5, "backlash": 2,
                             "gravity_sag+servo_nonlinearity": 1, "none": 1},
}
# docs/diagnose.md"s breakdown: (source, geometry, sag in, grid) -> (rigs, correct).
PUBLISHED_BREAKDOWN: dict[tuple, tuple[int, int]] = {
    ("simulator", "paper", "joints", 4): (14, 11),
    ("simulator", "paper", "joints", 6): (5, 5),
    ("generator", "paper_like", "joints", 4): (8, 6),
    ("generator", "paper_like", "joints", 6): (6, 4),
    ("generator", "tilted", "joints", 4): (9, 5),
    ("generator", "tilted", "joints", 6): (6, 3),
    ("generator", "paper_like", "links", 4): (2, 2),
    ("generator", "tilted", "links", 4): (2, 0),
}


def test_the_published_confusion_matrix(sweep):
    assert len(sweep) == len(report_cases())
    counts: dict[str, Counter] = {}
    for r in sweep:
        counts.setdefault(effects_key(r["truth"]), Counter())[r["named"]] += 1
    assert {k: dict(v) for k, v in counts.items()} == PUBLISHED_CONFUSION


def test_the_published_breakdown_by_source_and_geometry(sweep):
    groups: dict[tuple, list[bool]] = {}
    for r in sweep:
        c = r["case"]
        sag = c["sag"] if c["source"] == "generator" else "joints"
        groups.setdefault((c["source"], c["geometry"], sag, c["grid"]), []).append(
            exactly_right(r))
    assert {k: (len(v), sum(v)) for k, v in groups.items()} == PUBLISHED_BREAKDOWN


def test_no_false_alarm_on_any_clean_rig(sweep):
    """11 clean rigs (each its own seed and geometry): nothing named on any."""
    t = targets(sweep)
    assert t["clean"] == 11 and t["false_alarms"] == 0


def test_naming_closes_most_of_the_gap_at_new_poses(sweep):
    """Where effects were named, the error at new poses (holdout rows, which decide nothing)
    above the clean twin"s falls to at most 0.6 of what it was, pooled over those rigs (the
    issue"s target; published: 30%). The plain error ratio keeps noise"s share, which no
    model removes (published: 72%). Both as docs/diagnose.md rounds them, to half a per cent."""
    t = targets(sweep)
    assert t["named"] == 32
    assert t["gap_ratio"] <= 0.6
    assert abs(t["gap_ratio"] - 0.30) <= 0.005
    assert abs(t["holdout_ratio"] - 0.72) <= 0.005


@pytest.mark.xfail(strict=True, reason="target missed on the report rigs: 10 of 13 strong rigs "
                   "named exactly (two sag+backlash rigs name backlash only, the tilted plane's "
                   "play at twice its size names nothing)")
def test_strong_effects_are_named_exactly_in_nine_of_ten_rigs(sweep):
    """The issue"s target: at least 90% exactly right where the hidden effects at least double
    the base model"s error at new poses over noise alone (strength >= 2)."""
    t = targets(sweep)
    assert t["strong"] == 13
    assert t["strong_right"] >= 0.9 * t["strong"]


# ------------------------------------------------------------------ 6-joint 3-D arms
# tests/chain_generators.py: hardening joint springs with rods and motors, bearings tilting
# across their axes, encoder errors once and twice per revolution, play with
# approach-direction hysteresis; and the simulator's own arm6 physics. Tuning seeds 61-62;
# report seeds 74-76, fixed before any run (71-73 reported the candidates before backlash).


@pytest.fixture(scope="module")
def chain_sweep() -> list[dict]:
    return [diagnose_chain_case(case) for case in chain_cases(REPORT_SEEDS)]


CHAIN_PUBLISHED_CONFUSION: dict[str, dict[str, int]] = {
    "none": {"none": 6},
    "joint_compliance": {"joint_compliance": 6},
    "lateral_compliance": {"joint_compliance": 3},
    "encoder_error": {"encoder_error": 6},
    "encoder_error+joint_compliance": {"encoder_error+joint_compliance": 2, "joint_compliance": 1},
    "backlash+joint_compliance": {"backlash+joint_compliance": 2, "joint_compliance": 4},
}


def test_the_published_chain_confusion_matrix(chain_sweep):
    counts: dict[str, Counter] = {}
    for r in chain_sweep:
        counts.setdefault(effects_key(r["truth"]), Counter())[r["named"]] += 1
    assert {k: dict(v) for k, v in counts.items()} == CHAIN_PUBLISHED_CONFUSION


def test_chain_clean_rigs_name_nothing_and_named_effects_close_the_gap(chain_sweep):
    """No false alarm on the 6 clean arms; where effects were named, the error at new poses
    above the clean twin's falls to at most 0.6 of what it was (published: 7.5%)."""
    t = targets(chain_sweep)
    assert t["clean"] == 6 and t["false_alarms"] == 0
    assert t["gap_ratio"] <= 0.6
    assert abs(t["gap_ratio"] - 0.075) <= 0.005


@pytest.mark.xfail(strict=True, reason="target missed on the report arms: 15 of 23 strong rigs "
                   "named exactly (bearings tilting across their axes are named joint "
                   "compliance in 3 of 3; play with compliance is named joint compliance only "
                   "in 4 of 6: its sides in the vertical axis and under weak torques are not in "
                   "the rows)")
def test_strong_chain_effects_are_named_exactly_in_nine_of_ten_rigs(chain_sweep):
    t = targets(chain_sweep)
    assert t["strong"] == 23
    assert t["strong_right"] >= 0.9 * t["strong"]


def test_chain_misses_the_poses_cannot_decide_are_reported_as_rivals(chain_sweep):
    """On every tilting-bearing arm lateral compliance (the links' masses fitted with it) is
    reported as a rival of the joint compliance named: within 2 standard errors of it on the
    selection poses. Counting a named effect as any of its rivals, 18 of the 23 strong arms
    come right (docs/diagnose.md); the other five are play or an encoder error beside
    compliance, which no rival stands for."""
    for r in chain_sweep:
        if r["truth"] == "lateral_compliance":
            assert r["order"] == ["joint_compliance"], r["order"]
            assert "lateral_compliance" in r["rivals"]["joint_compliance"], r["rivals"]
    t = targets(chain_sweep)
    assert t["strong_right_up_to_rivals"] == 18
