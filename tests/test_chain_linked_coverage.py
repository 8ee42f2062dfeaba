"""The linked 3-D coverage study's own machinery. The study itself (two and three 6-joint arms
predicted before they are built, on report rigs) is run by the validation suite: ``bayesrob
validate linked_chain linked_chain_described linked_chain_three``."""

from __future__ import annotations

import pytest
from bayesrob.validation import linked_chain

import bayesrob.predict.stiffness as st


def test_the_study_reports_the_prior_predict_draws_from():
    """The report rigs 311-322 were fixed for the arm term centred on the fitted sags, with the
    sds chosen for it; the study reads them from ``predict.stiffness`` as ``predict`` does."""
    assert st.CHAIN_STIFFNESS_ARM_CENTRE == "sags"
    assert linked_chain.chosen_prior() == (st.CHAIN_STIFFNESS_CENTRE, st.SAG_SCALED_LOG_SD,
                                           "sags", st.SAG_SCALED_ARM_LOG_SD)


def test_a_prior_variant_is_put_back_after_its_block():
    """A sweep sets the module's prior per variant; leaving the block, even by an error,
    restores every constant, so nothing run next in the process sees the last variant."""
    names = ("CHAIN_STIFFNESS_CENTRE", "CHAIN_STIFFNESS_LOG_SD", "CHAIN_STIFFNESS_ARM_CENTRE",
             "CHAIN_STIFFNESS_ARM_LOG_SD", "SAG_SCALED_LOG_SD", "SAG_SCALED_ARM_LOG_SD")
    before = {n: getattr(st, n) for n in names}
    with linked_chain.prior("equal", 0.75, "equal", 0.0):
        assert linked_chain.chosen_prior() == ("equal", 0.75, "equal", 0.0)
    assert {n: getattr(st, n) for n in names} == before
    with pytest.raises(RuntimeError), linked_chain.prior("effort", 0.25, "sags", 0.15):
        assert linked_chain.chosen_prior() == ("effort", 0.25, "sags", 0.15)
        raise RuntimeError
    assert {n: getattr(st, n) for n in names} == before
