"""Chain rigs (URDF / DH arms) on the command line: the calibrate report, and one clear line
with exit code 2 for every malformed description, with nothing written."""

from __future__ import annotations

import csv
import json
import re
import shutil
from pathlib import Path

import pytest

from bayesrob.cli import main
from bayesrob.sim.rigs import simulate_arm6_rig
from bayesrob.sim.truth import Arm6Truth


@pytest.fixture(scope="module")
def chain_rig_dir(tmp_path_factory) -> Path:
    return simulate_arm6_rig(tmp_path_factory.mktemp("chain"),
                              Arm6Truth(seed=2, n_train=30, n_validation=10, n_holdout=10))


@pytest.fixture
def chain_copy(chain_rig_dir, tmp_path) -> Path:
    dest = tmp_path / "rig"
    shutil.copytree(chain_rig_dir, dest)
    return dest


def _rewrite_csv(path: Path, edit) -> None:
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    rows = edit(rows)
    with open(path, "w", newline="") as f:
        csv.writer(f).writerows(rows)


def _drop_column(name):
    def edit(rows):
        k = rows[0].index(name)
        return [r[:k] + r[k + 1:] for r in rows]
    return edit


def _set_cell(row, col, value):
    def edit(rows):
        rows[row][rows[0].index(col)] = value
        return rows
    return edit


def _toml(old, new):
    def edit(d: Path):
        p = d / "rig.toml"
        text = p.read_text()
        assert old in text
        p.write_text(text.replace(old, new, 1))
    return edit


def _urdf(edit_text):
    def edit(d: Path):
        p = d / "arm6.urdf"
        p.write_text(edit_text(p.read_text()))
    return edit


BAD = {
    "missing URDF": (lambda d: (d / "arm6.urdf").unlink(),
                     r"arms\.arm: .*arm6\.urdf: URDF file not found"),
    "malformed URDF": (_urdf(lambda t: t.replace("</robot>", "")),
                       r"arm6\.urdf: malformed URDF \(XML\)"),
    # a root below the tip: walking up from the tip never meets it
    "root and tip not connected": (lambda d: (_toml('root = "base_link"',
                                                    'root = "wrist_3_link"')(d),
                                              _toml('tip = "tool0"', 'tip = "shoulder_link"')(d)),
                                   r"links 'wrist_3_link' and 'shoulder_link' are not connected"),
    "unknown tip link": (_toml('tip = "tool0"', 'tip = "tool9"'),
                         r"tip link 'tool9' is not a link of this URDF"),
    "unknown chain key": (_toml('tip = "tool0"', 'tip = "tool0"\nmarkr = [0, 0, 1]'),
                          r"\[arms\.arm\] has unknown key 'markr'; did you mean 'marker'\?"),
    "marker of two numbers": (_toml("marker = [", "marker = [1.0, "),
                              r"arms\.arm\.marker: expected a list of 3 numbers"),
    "joint column missing": (lambda d: _rewrite_csv(d / "measurements.csv",
                                                    _drop_column("arm_u3")),
                             r"measurements\.csv: missing column 'arm_u3'"),
    "2-D data for a 3-D arm": (lambda d: _rewrite_csv(d / "measurements.csv", _drop_column("z")),
                               r"measurements\.csv: 2-D data \(no 'z' column\) for 3-D arm "
                               r"'arm'"),
    "non-finite number": (lambda d: _rewrite_csv(d / "measurements.csv",
                                                 _set_cell(3, "y", "nan")),
                          r"measurements\.csv: line 4: column 'y' is not a finite number"),
    "empty joint cell": (lambda d: _rewrite_csv(d / "measurements.csv",
                                                _set_cell(2, "arm_u6", "")),
                         r"measurements\.csv: line 3: column 'arm_u6' is empty"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_chain_rig_is_one_line_exit_2_and_nothing_written(case, chain_copy, capsys):
    break_it, pattern = BAD[case]
    break_it(chain_copy)
    out = chain_copy / "out.json"
    rc = main(["calibrate", str(chain_copy), "--json", str(out), "--urdf-out",
               str(chain_copy / "cal.urdf")])
    err = capsys.readouterr().err.strip()
    assert rc == 2
    assert len(err.splitlines()) == 1, err
    assert err.startswith("bayesrob calibrate: error: ")
    assert re.search(pattern, err), err
    assert not out.exists() and not (chain_copy / "cal.urdf").exists()


def test_dh_row_of_the_wrong_length_is_named(tmp_path, capsys):
    justin = Path(__file__).resolve().parents[1] / "examples" / "agile_justin" / "rig.toml"
    text = justin.read_text().replace("[105.5, 0.0, 0.0, 0.0]", "[105.5, 0.0, 0.0]")
    (tmp_path / "rig.toml").write_text(text)
    (tmp_path / "measurements.csv").write_text("config,set,x,y,z\n")
    assert main(["calibrate", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "rig.toml: arms.torso.dh[0]: a DH row is [d, theta, a, alpha] (4 numbers)" in err


def test_mounted_arm_on_unknown_arm_is_named(tmp_path, capsys):
    justin = Path(__file__).resolve().parents[1] / "examples" / "agile_justin" / "rig.toml"
    (tmp_path / "rig.toml").write_text(justin.read_text().replace(
        'mount = "torso"', 'mount = "chest"', 1))
    (tmp_path / "measurements.csv").write_text("config,set,x,y,z\n")
    assert main(["calibrate", str(tmp_path)]) == 2
    assert "arms.right.mount: 'chest' is not an arm of this rig" in capsys.readouterr().err


def test_calibrate_report_names_groups_errors_and_fixed_parameters(chain_rig_dir, tmp_path,
                                                                    capsys):
    out = tmp_path / "cal.json"
    rc = main(["calibrate", str(chain_rig_dir), "--params", "frames,geometric", "--json",
               str(out), "--urdf-out", str(tmp_path / "cal.urdf")])
    assert rc == 0
    text = capsys.readouterr().out
    assert "not identifiable from the train rows, fixed at nominal" in text
    doc = json.loads(out.read_text())
    assert doc["params"] == ["frames", "geometric"]
    assert set(doc["errors"]) == {"train", "validation", "holdout"}
    assert doc["errors"]["validation"]["arm"]["mean_mm"] < 1.0
    assert doc["parameters"]["arm.marker.x"]["free"] is True
    assert doc["parameters"]["arm.shoulder_pan.offset"]["free"] is False  # offsets not asked
    assert (tmp_path / "cal.urdf").exists() and (tmp_path / "cal.rig.toml").exists()


def test_unknown_parameter_group_is_a_usage_error(chain_rig_dir, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["calibrate", str(chain_rig_dir), "--params", "frames,geometry"])
    assert exc.value.code == 2
    assert "unknown parameter group 'geometry'" in capsys.readouterr().err


def test_planar_only_commands_refuse_a_chain_rig_in_one_line(chain_rig_dir, capsys):
    assert main(["reproduce", str(chain_rig_dir), "--out", "/nonexistent/x"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Figures 3-8) is of planar arms" in err
