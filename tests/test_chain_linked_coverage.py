"""Two 6-joint 3-D arms linked at their tool points, predicted before the assembly is built
(``pytest -m slow``, about 12 minutes on two cores): the twelve report rigs of
``benchmarks/bench_predict_3d.py --coverage report --many-rigs --sag-report`` (seeds 311-322,
8 linked points each: 96 points, each rig its own pair of arms with their own stiffnesses,
fixed before their first run), with the stiffness prior whose arm terms are centred on the
arms' fitted sags, its sds chosen on tuning rigs 201-206 and 271-282 (the earlier report rigs
291-302 led to the sag-centred arm term, and 231-242 showed an earlier prior's figures, so
neither reports it; docs/fusion.md keeps their figures). Targets (issue "linked
predictions"): 50% / 90% regions within binomial error of nominal at 96 points (0.40-0.60,
0.84-0.96) and predicted / observed mean error within 0.85-1.15. The sweep is seeded, so the
published figures (docs/fusion.md) are asserted: the error ratio to 0.001, the coverages to two
points of 96, as far as points at a region's edge were seen to flip with the compiled
programs' rounding: the described masses' 50% came out 0.490 under pytest before the
sag-centred prior (whose route it does not take) and 0.510 after it, and 0.510 from the bench
run on its own with either. A change that moves them further must update the docs with it.

Twelve rigs of 8 points rather than four of 24 (the first report rigs, 211-214 and 221-224,
whose figures docs/fusion.md keeps): a rig's points share one pair of arms and their
stiffness ratio, so they fall inside or outside the regions together. On the tuning rigs the
prior route's per-rig 50% coverage varied 5.6 times as much as binomial sampling of 24
independent points would, which leaves a pooled figure over four rigs far noisier than the
binomial range the targets assume.

The same study with the arms' stiffnesses read from compliances fitted under the URDF's link
masses (``--masses description``; each simulated arm's true masses 10% off the URDF's) runs on
its own twelve report rigs, seeds 251-262.

Three arms joined at one point (``--three-arms``: left, right and a front arm facing the
targets from the side), with the same prior and nothing chosen on them, run on twelve report
rigs of their own, seeds 341-352 (fixed before any ran; about 10 minutes).
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

PUBLISHED = {"points": 96, "coverage50": 0.5625, "coverage90": 0.948, "error_ratio": 0.993}
DESCRIBED = {"points": 96, "coverage50": 0.510, "coverage90": 0.885, "error_ratio": 1.016}
THREE = {"points": 96, "coverage50": 0.469, "coverage90": 0.948, "error_ratio": 0.945}


def _coverage(seeds: tuple[int, ...], **kwargs) -> dict:
    """The chosen prior's pooled figures over ``seeds``, rigs of MANY_LINKED linked points
    (``kwargs``: the rest of ``bench_predict_3d.coverage``'s)."""
    import bench_predict_3d as bench

    (figures,) = bench.coverage(seeds, [bench.chosen_prior()], n_linked=bench.MANY_LINKED,
                                **kwargs).values()
    return figures


def _holds_published(figures: dict, published: dict) -> None:
    assert figures["points"] == published["points"]
    for key in ("coverage50", "coverage90"):
        assert figures[key] == pytest.approx(published[key], abs=2.5 / 96), key
    assert figures["error_ratio"] == pytest.approx(published["error_ratio"], abs=1e-3)


def _meets_targets(figures: dict) -> None:
    """The issue's targets at 96 points: regions within binomial error of nominal, and the
    mean error predicted within 15% of the observed."""
    assert 0.40 <= figures["coverage50"] <= 0.60, figures
    assert 0.84 <= figures["coverage90"] <= 0.96, figures
    assert 0.85 <= figures["error_ratio"] <= 1.15, figures


@pytest.fixture(scope="module")
def report() -> dict:
    import bench_predict_3d as bench

    assert bench.chosen_prior()[2] == "sags"  # what predict draws linked arms' stiffnesses from
    return _coverage(bench.MANY_SAG_REPORT_SEEDS)


def test_the_published_report_figures(report):
    _holds_published(report, PUBLISHED)


def test_linked_regions_and_error_ratio_hold(report):
    _meets_targets(report)


@pytest.fixture(scope="module")
def described(tmp_path_factory) -> dict:
    import bench_predict_3d as bench

    return _coverage(bench.MANY_DESCRIPTION_REPORT_SEEDS, masses="description", mass_log_sd=0.1,
                     cache=tmp_path_factory.mktemp("described"))


def test_the_published_figures_with_the_described_masses(described):
    _holds_published(described, DESCRIBED)


def test_described_masses_regions_and_error_ratio_hold(described):
    _meets_targets(described)


@pytest.fixture(scope="module")
def three_arms() -> dict:
    import bench_predict_3d as bench

    return _coverage(bench.THREE_REPORT_SEEDS, three=True)


def test_the_published_figures_of_three_arms(three_arms):
    _holds_published(three_arms, THREE)


def test_three_arms_regions_and_error_ratio_hold(three_arms):
    _meets_targets(three_arms)
