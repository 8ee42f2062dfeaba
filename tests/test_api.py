"""The package's Python API: the names it exports, and rigs built in memory from arrays."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

import bayesrob
from bayesrob.data.rig import Measurements, Rig, RigError, default_rig_dir, load_rig
from bayesrob.sim.rigs import simulate_arm6_rig
from bayesrob.sim.truth import Arm6Truth


def test_every_exported_name_resolves_and_the_import_stays_light():
    missing = [n for n in bayesrob.__all__ if getattr(bayesrob, n, None) is None]
    assert missing == []
    with pytest.raises(AttributeError, match="no attribute 'nothing_here'"):
        bayesrob.nothing_here  # noqa: B018
    # importing the package loads no numerical library: argument errors stay instant
    out = subprocess.run([sys.executable, "-c", "import sys, bayesrob; "
                          "print('jax' in sys.modules, 'numpy' in sys.modules)"],
                         capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "False"]


def _arrays(meas: Measurements) -> dict:
    return {"config": meas.config, "set": meas.set, "observed": meas.observed,
            "commands": meas.commands}


@pytest.fixture(scope="module")
def arm6_dir(tmp_path_factory):
    return simulate_arm6_rig(tmp_path_factory.mktemp("arm6"), Arm6Truth(seed=3))


def test_a_chain_rig_from_a_urdf_string_and_arrays_calibrates_as_its_directory(arm6_dir):
    from bayesrob.calibrate import calibrate

    disk = load_rig(arm6_dir)
    chain = disk.robot.chains["arm"]
    text = (arm6_dir / "arm6.urdf").read_text()
    arm = bayesrob.urdf_chain("arm6.urdf", "base_link", "tool0", "arm", text=text,
                              marker=chain.marker, instrument=chain.instrument)
    np.testing.assert_array_equal(arm.origins, chain.origins)
    rig = Rig.from_arrays({"arm": arm}, Measurements.from_arrays(**_arrays(disk.measurements)),
                          name="mem")
    groups = ("frames", "geometric")
    a, b = calibrate(rig, groups), calibrate(disk, groups)
    np.testing.assert_allclose(a.x, b.x, rtol=0, atol=1e-9)
    assert a.errors["validation"]["all"]["n"] == 40


def test_a_planar_rig_from_arrays_is_the_default_rig():
    from bayesrob.calibrate import calibrate_arms

    disk = load_rig(default_rig_dir())
    m = disk.measurements
    rig = Rig.from_arrays(dict(disk.arms), Measurements.from_arrays(
        m.config, m.set, m.observed, m.commands, m.target))
    assert rig.gravity == disk.gravity and not rig.is_chain
    for name, fit in calibrate_arms(rig).items():
        np.testing.assert_allclose(fit.arm.params.to_vector(),
                                   calibrate_arms(disk)[name].arm.params.to_vector(), atol=1e-9)


@pytest.mark.parametrize("change, message", [
    (lambda d: d | {"observed": d["observed"][:, :1]}, r"observed: expected \(\d+, 2\)"),
    (lambda d: d | {"set": ["train"] * 3}, r"set: expected \d+ values"),
    (lambda d: d | {"set": np.where(np.arange(len(d["set"])) == 5, "later", d["set"])},
     "set: row 5: 'later' is not one of"),
    (lambda d: d | {"observed": np.where(np.arange(len(d["set"]))[:, None] == 2, np.nan,
                                         d["observed"])}, "observed: row 2 is not finite"),
    (lambda d: d | {"commands": {"arm": d["commands"]["arm"][:4]}},
     r"commands\['arm'\]: expected"),
])
def test_bad_arrays_are_refused_in_one_line(arm6_dir, change, message):
    d = _arrays(load_rig(arm6_dir).measurements)
    with pytest.raises(RigError, match=message):
        Measurements.from_arrays(**change(d))


def test_a_rig_from_arrays_checks_its_arms_against_its_rows(arm6_dir):
    disk = load_rig(arm6_dir)
    arm = disk.robot.chains["arm"]
    d = _arrays(disk.measurements)
    with pytest.raises(RigError, match=r"commands\['arm'\]: arm 'arm' needs 6 command columns"):
        Rig.from_arrays({"arm": arm}, Measurements.from_arrays(
            **d | {"commands": {"arm": d["commands"]["arm"][:, :5]}}))
    with pytest.raises(RigError, match="config 'elbow' names 'elbow', not a measured arm"):
        Rig.from_arrays({"arm": arm}, Measurements.from_arrays(
            **d | {"config": np.where(np.arange(len(d["set"])) == 0, "elbow", d["config"])}))
    with pytest.raises(RigError, match="arm 'arm' has no train rows"):
        Rig.from_arrays({"arm": arm}, Measurements.from_arrays(
            **d | {"set": np.where(d["set"] == "train", "validation", d["set"])}))
    with pytest.raises(RigError, match="gravity: expected a non-zero 3-vector"):
        Rig.from_arrays({"arm": arm}, Measurements.from_arrays(**d), gravity=(0.0, -1.0))
