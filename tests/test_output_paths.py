"""Output paths: checked before any work, written whole or not at all."""

from __future__ import annotations

from pathlib import Path

import pytest

from bayesrob.report.output_paths import (
    DIRECTORY,
    FILE,
    OutputPathError,
    check_output,
    save_figure,
    staged_directory,
    write_text,
)


def test_paths_that_can_be_written_pass(tmp_path):
    check_output(tmp_path / "new" / "deeper" / "out.json", FILE, "--json")  # parents made later
    check_output(tmp_path / "out.json", FILE, "--json")
    (tmp_path / "old.json").write_text("{}")
    check_output(tmp_path / "old.json", FILE, "--json")  # replacing a file is the contract
    check_output(tmp_path, DIRECTORY, "--out")
    check_output(tmp_path / "fresh", DIRECTORY, "--out")


@pytest.mark.parametrize("make, kind, words", [
    (lambda d: d, FILE, "is a directory"),
    (lambda d: _file(d), DIRECTORY, "is not a directory"),
    (lambda d: _file(d) / "x.json", FILE, "is a file"),
    (lambda d: _file(d) / "sub", DIRECTORY, "is a file"),
    (lambda d: Path("/proc/x.json"), FILE, "cannot write"),
])
def test_paths_that_cannot_be_written_are_one_line_errors(tmp_path, make, kind, words):
    path = make(tmp_path)
    with pytest.raises(OutputPathError) as err:
        check_output(path, kind, "--opt")
    message = str(err.value)
    assert "\n" not in message and message.startswith(f"--opt {path}: ") and words in message


def _file(directory: Path) -> Path:
    path = directory / "a_file"
    path.write_text("x")
    return path


def test_a_write_that_fails_part_way_leaves_the_old_file_and_no_scrap(tmp_path):
    target = tmp_path / "fig.png"
    target.write_bytes(b"old")

    class Broken:
        def savefig(self, path, **kwargs):
            Path(path).write_bytes(b"half")
            raise KeyboardInterrupt  # Ctrl-C in the middle of the write

    with pytest.raises(KeyboardInterrupt):
        save_figure(Broken(), target, dpi=10)
    assert target.read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fig.png"]
    write_text(target, "new")
    assert target.read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fig.png"]


def test_a_staged_directory_is_replaced_whole_or_not_at_all(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "a.json").write_text("old a")
    (out / "b.png").write_text("old b")
    (out / "best").mkdir()
    (out / "best" / "rig.toml").write_text("old rig")
    (out / "mine.txt").write_text("the user's")
    with pytest.raises(KeyboardInterrupt), staged_directory(out) as scratch:
        (scratch / "a.json").write_text("new a")
        raise KeyboardInterrupt  # before b.png and best/ were written
    assert sorted(p.name for p in out.iterdir()) == ["a.json", "b.png", "best", "mine.txt"]
    assert (out / "a.json").read_text() == "old a"
    with staged_directory(out) as scratch:
        (scratch / "a.json").write_text("new a")
        (scratch / "best").mkdir()
        (scratch / "best" / "measurements.csv").write_text("new rows")
    assert sorted(p.name for p in out.iterdir()) == ["a.json", "b.png", "best", "mine.txt"]
    assert (out / "a.json").read_text() == "new a"
    assert [p.name for p in (out / "best").iterdir()] == ["measurements.csv"]
    assert (out / "mine.txt").read_text() == "the user's"


def test_no_output_may_be_a_file_the_command_reads_nor_another_output(tmp_path, capsys):
    """Refused before any work, in one line, exit 2, the file untouched: an output onto the
    rig's own files, onto an input option's file, or two outputs onto one path; a figure
    whose name gives no format matplotlib writes; a scheduler address that is none."""
    import shutil

    from bayesrob.cli import main
    from bayesrob.data.rig import default_rig_dir

    rig = tmp_path / "rig"
    shutil.copytree(default_rig_dir(), rig)
    targets = tmp_path / "targets.csv"
    targets.write_text("x,y\n150,200\n")
    before = {p: p.read_bytes() for p in (*rig.iterdir(), targets)}
    for argv, words in (
            (["calibrate", str(rig), "--json", str(rig / "measurements.csv")],
             "the rig's measurements.csv"),
            (["calibrate", str(rig), "--json", str(rig / "rig.toml")], "the rig's rig.toml"),
            (["predict", str(rig), "--config", "top", "--targets", str(targets),
              "--json", str(targets)], "--targets's input"),
            (["compare", str(rig), "--json", str(tmp_path / "same.png"),
              "--plot", str(tmp_path / "same.png")], "--json writes there too"),
            (["compare", str(rig), "--plot", str(tmp_path / "same.xyz")],
             "ends in its format, one of"),
            (["validate", "plan_sim", "--scheduler", "nonsense", "--out",
              str(tmp_path / "same")], "not a scheduler address")):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and words in err[0], (argv, err)
    assert {p: p.read_bytes() for p in before} == before
    assert not any(tmp_path.glob("same*"))
