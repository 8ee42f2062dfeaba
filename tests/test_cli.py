"""The ``bayesrob`` command, run as a user runs it (a subprocess).

Bad rigs and bad arguments give exit code 2 and no traceback; a bad rig gives exactly one
line on stderr and leaves the rig's files untouched; ``calibrate --json`` writes the
documented schema, also for a rig this project's simulator did not write.
Each subprocess pays the JAX import, so the cases here are a representative subset of
``test_rig.py``'s, and the failing runs are started together, a few at a time.
"""

from __future__ import annotations

import csv
import json
import math
import os
import re
import shutil
import subprocess
import sys
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from bayesrob.cli import COMMANDS, main
from bayesrob.data.rig import MEASUREMENTS_FILE, RIG_FILE, load_rig


def bayesrob(*args: str, cwd: Path, columns: int = 80) -> subprocess.CompletedProcess:
    env = dict(os.environ, COLUMNS=str(columns), PYTHONUNBUFFERED="1")
    return subprocess.run([sys.executable, "-m", "bayesrob", *map(str, args)], cwd=cwd,
                          env=env, capture_output=True, text=True, timeout=300)


def snapshot(directory: Path) -> dict[str, bytes | None]:
    """Every file's bytes (None for folders) under a directory."""
    return {str(p.relative_to(directory)): (p.read_bytes() if p.is_file() else None)
            for p in sorted(directory.rglob("*"))}


def edit_csv(rig: Path, edit: Callable[[list[str], list[list[str]]], int]) -> int:
    path = rig / MEASUREMENTS_FILE
    with path.open(newline="", encoding="utf-8") as fh:
        header, *rows = list(csv.reader(fh))
    line = edit(header, rows)
    with path.open("w", newline="", encoding="utf-8") as fh:
        csv.writer(fh, lineterminator="\n").writerows([header, *rows])
    return line


def set_cells(config: str, set_name: str, /, **cells: str):
    """An ``edit_csv`` edit: change cells of the last row of a config and set."""
    def edit(header: list[str], rows: list[list[str]]) -> int:
        i = max(i for i, r in enumerate(rows)
                if r[header.index("config")] == config and r[header.index("set")] == set_name)
        for column, value in cells.items():
            rows[i][header.index(column)] = value
        return i + 2
    return edit


def _missing_measurements(rig: Path) -> tuple[str, list[str]]:
    (rig / MEASUREMENTS_FILE).unlink()
    return MEASUREMENTS_FILE, ["not found"]


def _unknown_arm(rig: Path) -> tuple[str, list[str]]:
    line = edit_csv(rig, set_cells("top+bottom", "test", config="top+elbow"))
    return MEASUREMENTS_FILE, [f"line {line}:", "unknown arm 'elbow'"]


def _pulse_outside_limits(rig: Path) -> tuple[str, list[str]]:
    line = edit_csv(rig, set_cells("bottom", "train", bottom_u1="3000"))
    return MEASUREMENTS_FILE, [f"line {line}:", "'bottom_u1'", "pulse_limits"]


def _linked_row_missing_commands(rig: Path) -> tuple[str, list[str]]:
    line = edit_csv(rig, set_cells("top+bottom", "test", top_u1="", top_u2=""))
    return MEASUREMENTS_FILE, [f"line {line}:", "missing arm 'top'"]


def _nan_observed(rig: Path) -> tuple[str, list[str]]:
    line = edit_csv(rig, set_cells("top", "validation", y="NaN"))
    return MEASUREMENTS_FILE, [f"line {line}:", "'y'", "finite"]


def _non_utf8(rig: Path) -> tuple[str, list[str]]:
    path = rig / MEASUREMENTS_FILE
    lines = path.read_bytes().split(b"\n")
    lines[20] = lines[20].replace(b"validation", b"valid\xe9ation")  # Latin-1
    path.write_bytes(b"\n".join(lines))
    return MEASUREMENTS_FILE, ["line 21:", "UTF-8"]


def _fewer_rows_than_parameters(rig: Path) -> tuple[str, list[str]]:
    def edit(header: list[str], rows: list[list[str]]) -> int:
        bottom_train = [r for r in rows if r[0] == "bottom" and r[1] == "train"]
        rows[:] = [r for r in rows if r not in bottom_train] + bottom_train[:5]
        return 0
    edit_csv(rig, edit)
    return MEASUREMENTS_FILE, ["arm 'bottom'", "5 train rows"]


def _invalid_toml(rig: Path) -> tuple[str, list[str]]:
    path = rig / RIG_FILE
    path.write_text(path.read_text(encoding="utf-8").replace("elbow = -1", "elbow = -", 1),
                    encoding="utf-8")
    return RIG_FILE, ["invalid TOML", "line "]


def _elbow_not_pm1(rig: Path) -> tuple[str, list[str]]:
    path = rig / RIG_FILE
    path.write_text(path.read_text(encoding="utf-8").replace("elbow = -1", "elbow = -2", 1),
                    encoding="utf-8")
    return RIG_FILE, ["arms.bottom.elbow", "+1 or -1"]


BAD_RIGS = {f.__name__.lstrip("_"): f for f in (
    _missing_measurements, _unknown_arm, _pulse_outside_limits, _linked_row_missing_commands,
    _nan_observed, _non_utf8, _fewer_rows_than_parameters, _invalid_toml, _elbow_not_pm1)}


BAD_ARGUMENTS = {
    "unknown-effect": (["simulate", "{out}", "--effects", "gravity_sag,wobble"],
                       "unknown effect 'wobble'"),
    "grid-1": (["simulate", "{out}", "--grid", "1"], "at least 2"),
    "planned-linked": (["simulate", "{out}", "--planned", "--robot", "arm6", "--linked"],
                       "--linked and --third-arm make a new rig"),
    # a chain effect with no planar instance, asked of a planar rig
    "lateral-planar": (["diagnose", "{rig}", "--effects", "gravity_sag,lateral_compliance"],
                       "'lateral_compliance' is for URDF/DH chains"),
    "unknown-method": (["calibrate", "{rig}", "--method", "newton"], "invalid choice: 'newton'"),
    "sag-steps-0": (["calibrate", "{rig}", "--sag-steps", "0"], "must be at least 1, got 0"),
    "sag-steps-planar": (["calibrate", "{rig}", "--sag-steps", "3"],
                         "--sag-steps is for URDF/DH rigs"),
    "masses-planar": (["calibrate", "{rig}", "--masses", "description"],
                      "--masses is for URDF/DH rigs"),
    # the planar arm as a chain: no compliance group asked for, and no link masses described
    "masses-without-sag": (["calibrate", "{rig}", "--params", "frames,offsets",
                            "--masses", "description"], "add compliance, lateral or backlash"),
    "masses-undescribed": (["calibrate", "{rig}", "--params", "frames,compliance",
                            "--masses", "description"],
                           "does not give every moving link a mass"),
}


@pytest.fixture(scope="module")
def failing_runs(clean_rig_dir, tmp_path_factory) -> dict[str, dict]:
    """Every run expected to fail, prepared first and then run a few at a time."""
    jobs: dict[str, dict] = {}
    for case, prepare in BAD_RIGS.items():
        work = tmp_path_factory.mktemp(case)
        rig = work / "rig"
        shutil.copytree(clean_rig_dir, rig)
        file, parts = prepare(rig)
        jobs[case] = dict(work=work, rig=rig, parts=[str(rig / file), *parts],
                          before=snapshot(rig), report=work / "report.json",
                          args=["calibrate", rig, "--json", work / "report.json"])
    work = tmp_path_factory.mktemp("missing-rig")
    jobs["missing_rig_directory"] = dict(
        work=work, rig=work / "no-such-rig", parts=[str(work / "no-such-rig"), "not found"],
        before={}, report=work / "report.json",
        args=["calibrate", work / "no-such-rig", "--json", work / "report.json"])
    for case, (args, expected) in BAD_ARGUMENTS.items():
        work = tmp_path_factory.mktemp(case)
        jobs[case] = dict(work=work, out=work / "out", expected=expected,
                          args=[a.format(out=work / "out", rig=clean_rig_dir) for a in args])
    workers = min(4, max(2, os.cpu_count() or 1))
    with ThreadPoolExecutor(workers) as pool:
        procs = {case: pool.submit(bayesrob, *job["args"], cwd=job["work"])
                 for case, job in jobs.items()}
        for case, proc in procs.items():
            jobs[case]["proc"] = proc.result()
    return jobs


@pytest.mark.parametrize("case", [*BAD_RIGS, "missing_rig_directory"])
def test_calibrate_bad_rig_one_line_exit_2_files_untouched(failing_runs, case):
    job = failing_runs[case]
    proc = job["proc"]
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    lines = proc.stderr.splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("bayesrob calibrate: error: "), lines[0]
    for part in job["parts"]:
        assert part in lines[0], f"{part!r} not in {lines[0]!r}"
    assert proc.stdout == ""
    rig = job["rig"]
    assert (snapshot(rig) if rig.exists() else {}) == job["before"], \
        "calibrate modified the rig's files"
    assert not job["report"].exists()


# ----------------------------------------------------------------------------- bad arguments


@pytest.mark.parametrize("case", list(BAD_ARGUMENTS))
def test_bad_arguments_exit_2(failing_runs, case):
    job = failing_runs[case]
    proc = job["proc"]
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    last = proc.stderr.splitlines()[-1]
    command = job["args"][0]
    assert last.startswith(f"bayesrob {command}: error: ") and job["expected"] in last, \
        proc.stderr
    assert proc.stdout == ""
    assert not job["out"].exists()


@pytest.mark.parametrize("argv", [[], ["frobnicate"], ["simulate"], ["simulate", "x", "--grid",
                                                                     "four"]])
def test_more_bad_arguments_in_process(argv, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as info:
        main(argv)
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "error:" in err.splitlines()[-1]
    assert not (tmp_path / "x").exists()


# ----------------------------------------------------------------------------- help


@pytest.fixture(scope="module")
def help_text(tmp_path_factory) -> str:
    proc = bayesrob("--help", cwd=tmp_path_factory.mktemp("help"), columns=80)
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == ""
    return proc.stdout


def test_help_lists_every_registered_command(help_text):
    assert COMMANDS, "no commands registered"
    listed = {m[1] for m in re.finditer(r"^ {4}(\S+)", help_text, re.MULTILINE)}
    assert set(COMMANDS) <= listed, help_text


def test_help_gives_each_command_one_line(help_text):
    lines = help_text.splitlines()
    for name, (summary, *_) in COMMANDS.items():
        pattern = re.compile(rf"\s+{re.escape(name)}\s+{re.escape(summary)}")
        assert any(pattern.fullmatch(line) for line in lines), f"{name!r}:\n{help_text}"


# ----------------------------------------------------------------------------- calibrate --json


def _check_number(x, *, nonnegative: bool = False) -> None:
    assert isinstance(x, float | int) and not isinstance(x, bool), x
    assert math.isfinite(x), x
    if nonnegative:
        assert x >= 0


def _check_pair(x) -> None:
    assert isinstance(x, list) and len(x) == 2, x
    for v in x:
        _check_number(v)


def _no_nan(name: str):
    raise AssertionError(f"report is not strict JSON: {name}")


def check_calibration_json(doc: dict, rig_dir: Path, method: str) -> None:
    """The documented ``calibrate --json`` schema, with counts checked against the rig."""
    rig = load_rig(rig_dir)
    assert doc["method"] == method
    assert list(doc["arms"]) == list(rig.arms)
    for arm in doc["arms"].values():
        assert set(arm["params"]) == {"base", "links", "gain", "offset"}
        for pair in arm["params"].values():
            _check_pair(pair)
        assert all(v > 0 for v in arm["params"]["links"])
        _check_number(arm["train_error_mm"], nonnegative=True)
        _check_number(arm["validation_error_mm"], nonnegative=True)
    expected = {c: {s for s in ("train", "validation", "test")
                    if rig.measurements.mask(c, s).any()} for c in rig.configs}
    assert {c: set(v) for c, v in doc["accuracy"].items()} == expected
    for config, sets in doc["accuracy"].items():
        for s, acc in sets.items():
            assert set(acc) >= {"mean_mm", "ci95_mm", "n"}
            _check_number(acc["mean_mm"], nonnegative=True)
            _check_pair(acc["ci95_mm"])
            lo, hi = acc["ci95_mm"]
            assert lo <= acc["mean_mm"] <= hi
            assert isinstance(acc["n"], int) and not isinstance(acc["n"], bool)
            assert acc["n"] == int(rig.measurements.mask(config, s).sum())


def test_calibrate_json_report(clean_rig_dir, tmp_path):
    before = snapshot(clean_rig_dir)
    out = tmp_path / "reports" / "cal.json"  # the folder does not exist yet
    proc = bayesrob("calibrate", clean_rig_dir, "--json", out, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    assert "least-squares" in proc.stdout  # the table for people still goes to stdout
    doc = json.loads(out.read_text(encoding="utf-8"), parse_constant=_no_nan)
    check_calibration_json(doc, clean_rig_dir, "least-squares")
    assert set(doc["arms"]) == {"top", "bottom"}
    assert set(doc["accuracy"]) == {"top", "bottom", "top+bottom"}
    assert set(doc["accuracy"]["top"]) == {"train", "validation"}
    assert set(doc["accuracy"]["top+bottom"]) == {"test"}
    assert doc["accuracy"]["top"]["validation"]["n"] == 16
    assert doc["accuracy"]["top+bottom"]["test"]["n"] == 16
    for arm in doc["arms"].values():
        assert arm["train_error_mm"] < 5 and arm["validation_error_mm"] < 5
    assert snapshot(clean_rig_dir) == before


def test_calibrate_handmade_rig_json_to_stdout(handmade_rig_dir, tmp_path):
    """A rig from another tool: three arms with other names, a three-arm linked config."""
    before = snapshot(handmade_rig_dir)
    proc = bayesrob("calibrate", handmade_rig_dir, "--method", "hill-climb", "--json", "-",
                    cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    doc = json.loads(proc.stdout, parse_constant=_no_nan)  # stdout holds the JSON alone
    check_calibration_json(doc, handmade_rig_dir, "hill-climb")
    assert set(doc["arms"]) == {"left", "right", "middle"}
    assert doc["accuracy"]["left+middle+right"]["test"]["n"] == 2
    assert snapshot(handmade_rig_dir) == before


@pytest.mark.parametrize("argv", [["--help"], ["predict", "--help"], ["predict", "--bogus"],
                                  ["simulate", "x", "--effects", "nope"],
                                  ["calibrate", "--params", "nope"]])
def test_help_and_argument_errors_import_no_numerical_library(argv):
    """``bayesrob --help`` and argument errors answer at once: they import neither JAX nor
    SciPy, NumPy or arviz (the start-up is timed by benchmarks/bench_startup.py)."""
    code = ("import sys\nfrom bayesrob.cli import main\ntry:\n    main(sys.argv[1:])\n"
            "except SystemExit:\n    pass\n"
            "heavy = sorted(m for m in ('jax', 'numpy', 'scipy', 'arviz', 'matplotlib') "
            "if m in sys.modules)\nprint('heavy:', heavy, file=sys.stderr)\n")
    r = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True,
                       cwd=Path(__file__).resolve().parents[1], timeout=60)
    assert "heavy: []" in r.stderr, r.stderr


def test_the_names_the_command_line_checks_are_the_registered_ones():
    """The command line checks effect names against bayesrob.data.vocabulary without importing the
    diagnosis: the planar effects registered there must be exactly those names."""
    from bayesrob.data.vocabulary import EFFECTS
    from bayesrob.robot.effects import REGISTRY

    assert set(REGISTRY) == set(EFFECTS)


_RUN_MAIN = ("import sys\nfrom bayesrob.cli import main\ncode = main(sys.argv[1:])\n"
             "heavy = sorted(m for m in ('jax', 'scipy', 'arviz') if m in sys.modules)\n"
             "print('heavy:', heavy, 'exit:', code, file=sys.stderr)\n")


def _bad_output_cases(tmp: Path) -> list[tuple[list[str], str]]:
    """(argv, the option the one-line error must name) for output paths no command can use."""
    a_dir = tmp / "a_dir"
    a_dir.mkdir()
    a_file = tmp / "a_file"
    a_file.write_text("keep me\n")
    return [
        (["calibrate", "--json", str(a_dir)], "--json"),
        (["calibrate", "--urdf-out", str(a_dir)], "--urdf-out"),
        (["calibrate", "--json", str(a_file / "cal.json")], "--json"),
        (["reproduce", "--out", str(a_file)], "--out"),
        (["diagnose", "--report", str(a_file)], "--report"),
        (["diagnose", "--json", "/proc/diagnosis.json"], "--json"),
        (["sample", "--target", "140", "220", "--json", str(a_dir)], "--json"),
        (["predict", "RIG", "--config", "top", "--grid", "2", "--plot", str(a_dir)], "--plot"),
        (["predict", "RIG", "--config", "top", "--grid", "2", "--json", "/proc/p.json"],
         "--json"),
        (["compare", "--json", str(a_dir)], "--json"),
        (["design", "design.toml", "--out", str(a_file)], "--out"),
        (["simulate", str(a_file)], "OUT_DIR"),
        (["validate", "--out", str(a_file)], "--out"),
    ]


def test_a_bad_output_path_is_refused_before_any_work(tmp_path):
    """Each command checks its output paths as soon as it has read its arguments: one line
    naming the option and path, exit 2, no numerical library imported (so no work done),
    and the file already there untouched."""
    for argv, option in _bad_output_cases(tmp_path):
        r = subprocess.run([sys.executable, "-c", _RUN_MAIN, *argv], capture_output=True,
                           text=True, cwd=Path(__file__).resolve().parents[1], timeout=60)
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 2 and lines[-1] == "heavy: [] exit: 2", (argv, r.stderr)
        assert lines[0].startswith(f"bayesrob {argv[0]}: error: {option} "), (argv, lines[0])
    assert (tmp_path / "a_file").read_text() == "keep me\n"


def _design_with_limits(tmp: Path, limits: str) -> Path:
    """The example design file with its [limits] replaced, its modules read where they are."""
    example = Path(__file__).resolve().parents[1] / "examples" / "design"
    text = (example / "design.toml").read_text()
    text = text.replace('rig = "modules"', f'rig = "{example / "modules"}"')
    head, _, _ = text.partition("[limits]")
    path = tmp / "design.toml"
    path.write_text(head + "[limits]\n" + limits)
    return path


@pytest.mark.parametrize("argv, words", [
    (["reproduce", "--grid-half-width", "-5"], "--grid-half-width: must be more than 0"),
    (["reproduce", "--grid-half-width", "nan"], "--grid-half-width: must be finite"),
    (["simulate", "OUT", "--measurement-noise-mm", "-1"], "--measurement-noise-mm: must be 0"),
    (["simulate", "OUT", "--joint-noise-rad", "inf"], "--joint-noise-rad: must be 0 or more "
                                                      "and finite"),
    (["simulate", "OUT", "--seed", "-3"], "--seed: must be at least 0"),
    (["simulate", "OUT", "--robot", "arm6", "--compliance", "--no-compliance"],
     "--compliance and --no-compliance contradict each other"),
    (["diagnose", "--seed", "x"], "--seed: expected a whole number"),
    (["design", "DESIGN", "--out", "OUTDIR", "--no-progress"],
     "min_arms = 2 is more than max_arms = 1"),
])
def test_numbers_out_of_range_and_contradictions_are_refused_in_one_line(argv, words, tmp_path,
                                                                          capsys):
    """Refused as the arguments are read (the design file as it is loaded), before any work:
    one line, exit 2, nothing written."""
    design = _design_with_limits(tmp_path, "min_arms = 2\nmax_arms = 1\n")
    argv = [{"OUT": str(tmp_path / "sim"), "DESIGN": str(design),
             "OUTDIR": str(tmp_path / "out")}.get(a, a) for a in argv]
    try:
        code = main(argv)
    except SystemExit as exc:
        code = exc.code
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and words in err[0], (argv, err)
    assert not (tmp_path / "sim").exists() and not (tmp_path / "out").exists()


def test_a_planar_targets_file_with_z_is_refused(tmp_path, capsys):
    """A z column would be dropped for planar arms: refused, naming the file and column."""
    targets = tmp_path / "t.csv"
    targets.write_text("x,y,z\n140,220,5\n")
    from bayesrob.data.rig import default_rig_dir

    assert main(["predict", str(default_rig_dir()), "--config", "top+bottom", "--targets",
                 str(targets)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{targets}: column z" in err[0], err


def test_calibrate_help_names_every_parameter_group(capsys):
    from bayesrob.data.vocabulary import ALL_GROUPS

    with pytest.raises(SystemExit):
        main(["calibrate", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    missing = [g for g in ALL_GROUPS if f"{g} (" not in text and f"{g}," not in text]
    assert missing == [], missing


@pytest.fixture(scope="module")
def arm6_rig_dir(tmp_path_factory) -> Path:
    """A simulated 6-joint URDF rig (read only: copy it to change it)."""
    out = tmp_path_factory.mktemp("arm6") / "rig"
    assert main(["simulate", str(out), "--robot", "arm6", "--no-progress"]) == 0
    return out


@pytest.mark.parametrize("old, new, words", [
    ('<parent link="shoulder_link"/>', '<parent link="shoulder_lnk"/>',
     "names parent link 'shoulder_lnk', which is not a link of this URDF"),
    ('<child link="forearm_link"/>', '<child link="forearm_link"/><mimic joint="elbo"/>',
     "mimics 'elbo', which is not a joint of this URDF"),
])
def test_a_rig_whose_urdf_names_what_it_lacks_is_refused(arm6_rig_dir, tmp_path, capsys, old,
                                                         new, words):
    """A misspelt link would silently cut the chain: calibrate refuses the rig in one line
    naming the URDF, exit 2, and writes nothing."""
    rig = tmp_path / "rig"
    shutil.copytree(arm6_rig_dir, rig)
    urdf = rig / "arm6.urdf"
    text = urdf.read_text()
    assert old in text
    urdf.write_text(text.replace(old, new, 1))
    before = snapshot(rig)
    capsys.readouterr()
    code = main(["calibrate", str(rig), "--json", str(tmp_path / "c.json")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert err[0].startswith("bayesrob calibrate: error: ") and str(urdf) in err[0] \
        and words in err[0], err
    assert snapshot(rig) == before and not (tmp_path / "c.json").exists()


def test_a_design_file_mistake_is_found_before_the_numerical_stack(tmp_path):
    """The whole design file is checked first: its one-line error comes with no numerical
    library imported, so before any module is calibrated."""
    design = _design_with_limits(tmp_path, "min_arms = 2\nmax_arms = 1\n")
    r = subprocess.run([sys.executable, "-c", _RUN_MAIN, "design", str(design), "--out",
                        str(tmp_path / "out")], capture_output=True, text=True,
                       cwd=Path(__file__).resolve().parents[1], timeout=60)
    lines = r.stderr.strip().splitlines()
    assert lines == [f"bayesrob design: error: {design}: [limits] min_arms = 2 is more than "
                     "max_arms = 1", "heavy: [] exit: 2"], r.stderr
    assert not (tmp_path / "out").exists()
