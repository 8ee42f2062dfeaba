"""Diagnosis of URDF/DH chains: the simulator's 6-joint arm with joints giving way under
gravity, and without."""

from __future__ import annotations

import json

import pytest

from bayesrob.chain_diagnosis import ChainDiagnosisError, resolve_effects
from bayesrob.chain_simulator import ChainTruth, simulate_chain_rig
from bayesrob.cli import main


@pytest.mark.parametrize("compliance,named", [(True, ["joint_compliance"]), (False, [])])
def test_diagnose_names_joint_compliance_only_where_the_arm_has_it(tmp_path, capsys,
                                                                   compliance, named):
    """Seed 11 (never used to set the rule, whose threshold is the usual 2 standard errors):
    the compliant arm gets joint compliance and not lateral bending, which the simulator does
    not have; the rigid arm gets nothing. The ladder is reported on the validation rows."""
    rig = simulate_chain_rig(tmp_path / "r", ChainTruth(seed=11, compliance=compliance))
    out = tmp_path / "d.json"
    assert main(["diagnose", str(rig), "--json", str(out), "--report", str(tmp_path / "rep"),
                 "--no-progress"]) == 0
    doc = json.loads(out.read_text())
    assert doc["effects"] == named
    assert (tmp_path / "rep" / "ladder.png").stat().st_size > 5_000
    for key in ("steps", "baseline_heldout_error_mm", "final_heldout_error_mm"):
        assert key in doc
    if named:
        step = doc["steps"][0]
        assert step["heldout_error_mm"] < 0.5 * doc["baseline_heldout_error_mm"]
        assert step["heldout_error_sd_mm"] > 0 and step["heldout_error_max_mm"] > 0
    else:
        assert doc["final_heldout_error_mm"] == doc["baseline_heldout_error_mm"]
    assert "ladder on the validation rows" in capsys.readouterr().out


def test_planar_only_effects_are_refused_for_chains_in_one_line():
    assert resolve_effects(["gravity_sag"]) == ["joint_compliance"]  # the planar alias
    with pytest.raises(ChainDiagnosisError, match="'backlash' is not modelled"):
        resolve_effects(["backlash"])
