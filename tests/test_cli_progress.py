"""What the commands tell the person running them: progress off a terminal, "wrote" lines,
grouped notes, and ``simulate`` refusing to replace measurements."""

from __future__ import annotations

import json
import re

import pytest

from bayesrob.cli import main
from bayesrob.data.rig import load_rig
from bayesrob.report.tables import NOTES_HEADING, WARNINGS_HEADING, grouped_notes

# A status line of bayesrob.progress: "desc: n/total unit (pct%), seconds s[, ...]".
STATUS = r"{desc}: \d+/\d+ {unit} \(\d+%\), \d+\.\d s(, .+)?"


# ------------------------------------------------------------------------------ simulate


@pytest.mark.parametrize("name", ["measurements.csv", "rig.toml", "truth.toml"])
def test_simulate_refuses_a_directory_with_rig_files(tmp_path, capsys, name):
    out = tmp_path / "rig"
    out.mkdir()
    kept = out / name
    kept.write_text("real data, measured by hand\n")
    assert main(["simulate", str(out), "--grid", "2"]) == 2
    captured = capsys.readouterr()
    lines = captured.err.splitlines()
    assert len(lines) == 1, captured.err
    assert lines[0].startswith("bayesrob simulate: error: ") and str(kept) in lines[0]
    assert "--force" in lines[0]
    assert captured.out == ""
    assert kept.read_text() == "real data, measured by hand\n"
    assert sorted(p.name for p in out.iterdir()) == [name]  # nothing else written


def test_simulate_names_measurements_first(tmp_path, capsys):
    """The file that may hold data no one can measure again is the one named."""
    out = tmp_path / "rig"
    out.mkdir()
    for name in ("rig.toml", "measurements.csv"):
        (out / name).write_text("x\n")
    assert main(["simulate", str(out)]) == 2
    assert str(out / "measurements.csv") in capsys.readouterr().err


def test_simulate_refuses_a_file_as_directory(tmp_path, capsys):
    path = tmp_path / "notes.txt"
    path.write_text("keep\n")
    assert main(["simulate", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(path) in err and "not a directory" in err
    assert path.read_text() == "keep\n"


def test_simulate_force_overwrites_and_says_so_with_progress_lines(tmp_path, capsys):
    out = tmp_path / "rig"
    out.mkdir()
    (out / "measurements.csv").write_text("old\n")
    assert main(["simulate", str(out), "--grid", "2", "--force"]) == 0
    captured = capsys.readouterr()
    assert f"replaced (--force): {out / 'measurements.csv'}" in captured.out
    assert "wrote" in captured.out and "measurements.csv, rig.toml, truth.toml" in captured.out
    rows = load_rig(out, min_train_rows=0).measurements.observed.shape[0]
    assert rows == 23  # 2 arms x (train + validation) x 4 points + 4 linked + 3 holdout
    # capsys's stderr is not a terminal: plain status lines, the first one before any work.
    err = captured.err.splitlines()
    assert err, "no progress off a terminal"
    assert re.fullmatch(r"simulate: 0/23 pt \(0%\), \d+\.\d s", err[0]), err[0]
    assert all(re.fullmatch(STATUS.format(desc="simulate", unit="pt"), x) for x in err), err
    assert err[-1].startswith("simulate: 23/23 pt (100%)") and err[-1].endswith(", done")


def test_no_progress_prints_nothing_on_stderr(tmp_path, capsys):
    assert main(["simulate", str(tmp_path / "rig"), "--grid", "2", "--no-progress"]) == 0
    captured = capsys.readouterr()
    assert captured.err == ""
    assert "wrote" in captured.out
    assert "replaced" not in captured.out


# ------------------------------------------------------------------------------ wrote lines


def test_calibrate_json_says_what_it_wrote(clean_rig_dir, tmp_path, capsys):
    report = tmp_path / "cal.json"
    assert main(["calibrate", str(clean_rig_dir), "--json", str(report)]) == 0
    out = capsys.readouterr().out
    assert out.splitlines()[-1] == f"wrote {report}"
    assert json.loads(report.read_text())["method"] == "least-squares"


def test_calibrate_json_to_stdout_stays_pure_json(clean_rig_dir, capsys):
    assert main(["calibrate", str(clean_rig_dir), "--json", "-"]) == 0
    captured = capsys.readouterr()
    assert json.loads(captured.out)["rig"]  # no "wrote" line mixed into the JSON
    assert "wrote" not in captured.err


# ------------------------------------------------------------------------------ notes


def test_grouped_notes_headings_say_whether_they_matter():
    warnings = ["warning: top+bottom / ind: up to 3% of the predicted mass lies on the edge"]
    notes = ["note: ind_paper / top: bandwidth on the bound", "note: cond / top: bound"]
    out = grouped_notes(warnings, notes)
    assert out == [WARNINGS_HEADING,
                   "  top+bottom / ind: up to 3% of the predicted mass lies on the edge",
                   NOTES_HEADING,
                   "  ind_paper / top: bandwidth on the bound",
                   "  cond / top: bound"]
    assert "may be wrong" in WARNINGS_HEADING and "nothing to fix" in NOTES_HEADING
    assert grouped_notes([], notes)[0] == NOTES_HEADING
    assert grouped_notes([], []) == []


def test_reproduce_groups_its_notes_and_reports_progress(clean_rig_dir, tmp_path, capsys):
    """The paper's J_LOO bandwidth always ends on its bound: a note under the notes heading."""
    out = tmp_path / "repro"
    assert main(["reproduce", str(clean_rig_dir), "--models", "ind_paper", "--grid-n", "20",
                 "--out", str(out)]) == 0
    captured = capsys.readouterr()
    err = captured.err.splitlines()
    assert re.fullmatch(STATUS.format(desc="reproduce", unit="steps"), err[0]), err[0]
    assert err[0].startswith("reproduce: 0/") and "calibrating" in err[0]
    status = [i for i, x in enumerate(err) if x.startswith("reproduce: ")]
    assert err[status[-1]].endswith(", done")
    notes = err[status[-1] + 1:]
    assert notes[0] == NOTES_HEADING, captured.err
    assert WARNINGS_HEADING not in err  # the commands aim at the targets: no edge mass
    assert {line.split(":")[0] for line in notes[1:]} == {"  ind_paper / top",
                                                          "  ind_paper / bottom"}
    assert f"wrote 7 files to {out}/" in captured.out


def test_sample_notes_are_under_the_notes_heading():
    from bayesrob.inference.sampling import SampleReport
    from bayesrob.report.tables import format_sample

    grid = {"mean": [140.0, 220.0], "cov": [[0.2, 0.0], [0.0, 0.3]], "seconds": 0.5,
            "n": 150, "cell_mm": [0.05, 0.05], "edge_mass": 0.0}
    doc = {"config": "top+bottom", "target": [140.0, 220.0], "model": "cond_paper",
           "samplers": {"grid": grid},
           "check": {"passed": True, "failures": [], "compared": [],
                     "tolerances": {"mean_mm": 0.1, "cov_rel": 0.1, "r_hat": 1.01,
                                    "ess_bulk": 400, "edge_mass": 1e-3}},
           "notes": ["NUTS divergences are trajectories that left the table's support"]}
    lines = format_sample(SampleReport(doc, None, {})).splitlines()
    i = lines.index(NOTES_HEADING)
    assert lines[i + 1] == "  NUTS divergences are trajectories that left the table's support"
    assert lines[i - 1].startswith("check: no sampler ran; the grid's box holds the posterior")


def test_predict_reports_progress_from_its_start_to_done(tmp_path, capsys):
    """predict had been silent for minutes off a terminal: its first line comes at once, its
    last says done."""
    from bayesrob.data.rig import default_rig_dir

    assert main(["predict", str(default_rig_dir()), "--config", "top", "--grid", "2",
                 "--json", str(tmp_path / "p.json")]) == 0
    lines = [x for x in capsys.readouterr().err.splitlines() if x.startswith("predict:")]
    # a warm run may end before its first clock line: then the done line alone
    assert all(re.fullmatch(r"predict: \d+\.\d s, top, 4 targets(, done)?", x)
               for x in lines), lines
    assert lines[-1].endswith(", done"), lines
