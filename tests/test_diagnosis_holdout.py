"""The diagnosis reports its models' errors at new poses (``holdout`` rows) beside validation.

Validation rows repeat the training commands, so their error measures repeatability; the
holdout rows are poses the training grid does not have. They are scored and reported, and
they decide nothing, as the validation rows do: the decision rule reads cross-validation only.
"""

from __future__ import annotations

import json
from dataclasses import replace

import jax.numpy as jnp
import numpy as np
import pytest

import bayesrob  # noqa: F401  (x64)
from bayesrob import robot as kin
from bayesrob.data.rig import default_rig_dir, load_rig
from bayesrob.diagnose.refits import ArmData, diagnose, evaluate_arm
from bayesrob.report.tables import format_diagnosis


@pytest.fixture(scope="module")
def rig():
    return load_rig(default_rig_dir())


def test_arm_data_carries_the_holdout_rows(rig):
    data = ArmData.from_rig(rig, "top")
    assert data.u_hold.shape == data.d_hold.shape == (9, 2)
    assert data.u.shape == data.u_val.shape == (16, 2)


def test_holdout_errors_are_the_base_models_misses_at_new_poses(rig):
    data = ArmData.from_rig(rig, "bottom")
    ev = evaluate_arm(data, ())
    assert ev.hold_errors.shape == ev.hold_lpd.shape == (9,)
    # The base model has no structural settings to mix: its prediction is f(g(u)).
    pred = np.asarray(kin.forward_u(ev.params, jnp.asarray(data.u_hold)))
    np.testing.assert_allclose(ev.hold_errors, np.linalg.norm(data.d_hold - pred, axis=1),
                               rtol=1e-9)
    assert np.all(np.isfinite(ev.hold_lpd))


def test_holdout_rows_change_no_fit_and_no_score_that_decides(rig):
    data = ArmData.from_rig(rig, "top")
    bare = replace(data, u_hold=np.zeros((0, 2)), d_hold=np.zeros((0, 2)))
    a, b = evaluate_arm(data, ("backlash",)), evaluate_arm(bare, ("backlash",))
    np.testing.assert_array_equal(a.v, b.v)
    for field in ("val_errors", "val_lpd", "cv_errors", "cv_lpd", "train_errors"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    assert b.hold_errors.size == 0 and a.hold_errors.size == 9


def test_json_reports_holdout_beside_validation(rig, clean_rig_dir):
    """Base model only (no candidates): the keys and their values, and None without rows."""
    diag = diagnose(rig, candidates=[])
    doc = diag.to_json()
    json.dumps(doc)
    hold = np.concatenate([diag.baseline[a].hold_errors for a in diag.arms])
    assert hold.size == 18
    assert doc["baseline_holdout_error_mm"] == pytest.approx(hold.mean())
    assert doc["final_holdout_error_mm"] == doc["baseline_holdout_error_mm"]
    assert doc["baseline_heldout_error_mm"] is not None  # the validation figure stays
    for arm in diag.arms:
        before = doc["arms"][arm]["before"]
        assert before["holdout_error_mm"] == pytest.approx(
            diag.baseline[arm].hold_errors.mean())
        assert before["heldout_error_mm"] is not None
    assert "at new poses, the holdout rows: base" in format_diagnosis(doc)
    clean = diagnose(load_rig(clean_rig_dir), candidates=[]).to_json()
    assert clean["baseline_holdout_error_mm"] is None
    assert "at new poses, the holdout rows" not in format_diagnosis(clean)
