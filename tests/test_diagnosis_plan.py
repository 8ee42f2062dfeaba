"""The diagnosis-on-planned-poses study's measuring step: rows appended by another plant
(a validation generator's) keep measure_arm6_poses' format and approach sides."""

from __future__ import annotations

import csv

import numpy as np


def test_measure_arm6_poses_with_a_plant_of_its_own(tmp_path):
    from bayesrob.sim.rigs import measure_arm6_poses

    header = ["config", "set", *[f"arm_u{k + 1}" for k in range(6)], "x", "y", "z"]
    (tmp_path / "measurements.csv").write_text(
        ",".join(header) + "\narm,validation,0,0,0,0,0,0,1,2,3\n")
    seen = {}

    def plant(q, approach):
        seen["approach"] = approach
        return q[:, :3] * 10.0

    q = np.array([[0.1, -0.1, 0.0, 0.2, 0.0, -0.3], [0.0, 0.1, 0.0, 0.1, 0.1, -0.3]])
    assert measure_arm6_poses(tmp_path, ["train"] * 2, q, plant=plant) == 2
    # the first row's sides are its move from the file's last command, the second's from it
    np.testing.assert_array_equal(seen["approach"], [[1, -1, 0, 1, 0, -1], [-1, 1, 0, -1, 1, 0]])
    with (tmp_path / "measurements.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert [r["set"] for r in rows] == ["validation", "train", "train"]
    assert rows[0]["arm_d1"] == "" and rows[1]["arm_d2"] == "-1" and rows[2]["arm_d5"] == "1"
    assert float(rows[2]["y"]) == 1.0 and float(rows[1]["x"]) == 1.0
