"""Two 6-joint 3-D arms linked at their tool points, predicted before the assembly is built
(``pytest -m slow``, about 10 minutes on two cores): the report rigs 211-214 of
``benchmarks/bench_predict_3d.py --coverage report`` (96 linked points, each rig its own pair
of arms with their own stiffnesses, fixed before any run), with the stiffness prior chosen on
tuning rigs 201-206. Targets (issue "linked predictions"): 50% / 90% regions within binomial
error of nominal at 96 points (0.40-0.60, 0.84-0.96) and predicted / observed mean error
within 0.85-1.15. The sweep is seeded, so the published figures (docs/fusion.md) are asserted
to 0.001: a change that moves them must update the docs with it.

The same study with the arms' stiffnesses read from compliances fitted under the URDF's link
masses (``--masses description``; each simulated arm's true masses 10% off the URDF's) runs on
its own report rigs 221-224, fixed before its first report run.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

PUBLISHED = {"points": 96, "coverage50": 0.646, "coverage90": 0.958, "error_ratio": 1.035}
DESCRIBED = {"points": 96, "coverage50": 0.552, "coverage90": 0.8125, "error_ratio": 0.998}


def _coverage(seeds: tuple[int, ...], *args) -> dict:
    import bench_predict_3d as bench

    import bayesrob.chain_prediction as cp

    chosen = (cp.CHAIN_STIFFNESS_CENTRE, cp.CHAIN_STIFFNESS_LOG_SD,
              cp.CHAIN_STIFFNESS_ARM_LOG_SD)
    (figures,) = bench.coverage(seeds, [chosen], *args).values()
    return figures


def _holds_published(figures: dict, published: dict) -> None:
    assert figures["points"] == published["points"]
    for key in ("coverage50", "coverage90", "error_ratio"):
        assert figures[key] == pytest.approx(published[key], abs=1e-3), key


@pytest.fixture(scope="module")
def report() -> dict:
    import bench_predict_3d as bench

    return _coverage(bench.REPORT_SEEDS)


def test_the_published_report_figures(report):
    _holds_published(report, PUBLISHED)


def test_linked_90_percent_regions_and_error_ratio_hold(report):
    assert 0.84 <= report["coverage90"] <= 0.96
    assert 0.85 <= report["error_ratio"] <= 1.15


@pytest.mark.xfail(strict=True, reason="target missed on the report rigs: the 50% regions "
                   "hold 0.646 of 96 linked points (0.40-0.60 asked); per rig 0.33-0.92, as "
                   "each rig's pair of arms has one stiffness ratio the prior only brackets")
def test_linked_50_percent_regions_hold(report):
    assert 0.40 <= report["coverage50"] <= 0.60


@pytest.fixture(scope="module")
def described(tmp_path_factory) -> dict:
    import bench_predict_3d as bench

    return _coverage(bench.DESCRIPTION_REPORT_SEEDS, tmp_path_factory.mktemp("described"),
                     "description", 0.1)


def test_the_published_figures_with_the_described_masses(described):
    _holds_published(described, DESCRIBED)


def test_described_masses_50_percent_regions_and_error_ratio_hold(described):
    assert 0.40 <= described["coverage50"] <= 0.60
    assert 0.85 <= described["error_ratio"] <= 1.15


@pytest.mark.xfail(strict=True, reason="target missed on report rigs 221-224: the 90% regions "
                   "hold 0.8125 of 96 linked points (0.84-0.96 asked): rig 222 holds 0.58, "
                   "the others 0.79-1.00; the wrists gravity hardly turns are read least well")
def test_described_masses_90_percent_regions_hold(described):
    assert 0.84 <= described["coverage90"] <= 0.96
