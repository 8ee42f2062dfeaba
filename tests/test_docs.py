"""The README and docs/*.md: every Python block runs, every link resolves, the README stays short.

Python blocks (```python) are executed one by one, each in a fresh namespace and in a scratch
directory, so a block that uses a name it does not define fails here. Shell blocks (```bash)
are commands for a terminal and are not run; every fenced block must say which it is.
"""

from __future__ import annotations

import re
from pathlib import Path

import matplotlib
import pytest

matplotlib.use("Agg")

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
FENCE = re.compile(r"^```([^\n`]*)\n(.*?)^```\s*$", re.S | re.M)
LANGUAGES = {"python", "bash", "toml", "text"}

# The README's two set-up commands are run by CI exactly as written.
SETUP_COMMANDS = (
    "python3 -m venv .venv && .venv/bin/pip install . && .venv/bin/bayesrob reproduce",
    "python3 -m venv .venv && .venv/bin/pip install '.[test]' && .venv/bin/python -m pytest -q "
    "-n 2",
)


def _blocks(path: Path) -> list[tuple[str, int, str]]:
    """(language, first line number, code) of every fenced block of a markdown file."""
    text = path.read_text(encoding="utf-8")
    return [(m.group(1).strip(), text.count("\n", 0, m.start()) + 1, m.group(2))
            for m in FENCE.finditer(text)]


PYTHON_BLOCKS = [pytest.param(code, id=f"{p.relative_to(ROOT)}:{line}")
                 for p in DOCS for lang, line, code in _blocks(p) if lang == "python"]


def test_docs_exist_and_have_python_blocks():
    assert (ROOT / "docs").is_dir() and len(DOCS) > 5
    assert len(PYTHON_BLOCKS) >= 4  # the library, KDE, sampling and calibration examples


@pytest.mark.parametrize("code", PYTHON_BLOCKS)
def test_python_block_runs(code, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # whatever a block writes lands in a scratch directory
    namespace: dict = {"__name__": "__doc_block__"}
    exec(compile(code, "<doc block>", "exec"), namespace)  # noqa: S102 - our own docs


@pytest.mark.parametrize("path", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_fenced_block_names_its_language(path):
    bad = [(line, lang) for lang, line, _ in _blocks(path) if lang not in LANGUAGES]
    assert bad == [], f"{path.name}: blocks with no or an unknown language (line, tag): {bad}"


@pytest.mark.parametrize("path", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(path):
    text = path.read_text(encoding="utf-8")
    missing = []
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if re.match(r"[a-z]+://", target) or target.startswith("#"):
            continue
        if not (path.parent / target.split("#")[0]).exists():
            missing.append(target)
    assert missing == [], f"{path.name} links to missing files: {missing}"


def test_no_document_cites_a_missing_notes_file():
    for path in DOCS:
        assert "NOTES.md" not in path.read_text(encoding="utf-8"), path.name


def test_readme_is_short_and_keeps_the_setup_commands():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(text) <= 15_000, f"README.md is {len(text)} characters"
    for command in SETUP_COMMANDS:
        assert command in text
    # Every docs page is reachable from the README.
    for page in (ROOT / "docs").glob("*.md"):
        assert f"docs/{page.name}" in text, f"README does not link docs/{page.name}"


def test_gitignore_holds_the_output_directories_the_docs_create():
    ignored = (ROOT / ".gitignore").read_text().split()
    text = "\n".join(p.read_text(encoding="utf-8") for p in DOCS)
    wanted = {"reproduction"}  # bayesrob reproduce's default --out
    name = r"([a-z][\w.-]*)"  # a real directory name, not a placeholder such as DIR
    wanted |= set(re.findall(rf"--(?:report|out) {name}", text))
    wanted |= set(re.findall(rf"--json {name}/", text))
    wanted |= set(re.findall(rf"^(?:\.venv/bin/)?bayesrob simulate {name}", text, re.M))
    wanted |= set(re.findall(rf"^mkdir {name}", text, re.M))
    assert {"reproduction", "diagnosis-default", "compare-default"} <= wanted
    for d in sorted(wanted):
        assert f"/{d}/" in ignored, f"{d}/ is created by a documented command but not ignored"


def _documented_command_lines() -> list[tuple[str, str]]:
    """(file, command line) of every concrete ``bayesrob ...`` line in a bash block.

    Synopsis lines with placeholders (``RIG``, ``[--json OUT]``, ``a|b``) are left out: they
    describe a command rather than run one.
    """
    out = []
    for path in DOCS:
        for lang, _, code in _blocks(path):
            if lang != "bash":
                continue
            for line in code.replace("\\\n", " ").splitlines():
                line = line.split("#")[0].strip().removeprefix(".venv/bin/").rstrip("&").strip()
                if not line.startswith("bayesrob ") or re.search(r"[\[|]|\.\.\.|\b[A-Z_]{2,}\b",
                                                                  line):
                    continue
                out.append((path.name, line))
    return out


def test_documented_command_lines_parse():
    import shlex

    from bayesrob.cli import build_parser

    lines = _documented_command_lines()
    assert len(lines) >= 6  # the README's first session, diagnose, collect, sim-device ...
    parser = build_parser()
    for name, line in lines:
        try:
            parser.parse_args(shlex.split(line)[1:])
        except SystemExit as exc:  # argparse's way of rejecting a command line
            pytest.fail(f"{name}: `{line}` does not parse (exit {exc.code})")


def test_result_tables_agree_with_the_committed_validation():
    """Every result table in the README and docs/ is what the committed full validation run
    renders: a figure cannot move without a new run, nor be edited by hand (regenerate with
    ``python -m bayesrob.validation.tables --write``)."""
    from bayesrob.validation.suite import load_committed
    from bayesrob.validation.tables import BLOCK, documents, sync

    report = load_committed()
    assert report["quick"] is False, "the committed report is a --quick run"
    blocks = [m["key"] for p in documents(ROOT) for m in BLOCK.finditer(p.read_text())]
    assert len(blocks) >= 5, blocks
    assert sync(ROOT, report) == []


def test_the_committed_validation_covers_every_study():
    """The committed run holds every study the suite has, each passed (a known miss is
    reported as such inside a passing study), so no study is published without its run."""
    from bayesrob.validation.study import discover_studies
    from bayesrob.validation.suite import load_committed

    report = load_committed()
    assert set(report["studies"]) == {s.name for s in discover_studies()}
    failed = {name: s["status"] for name, s in report["studies"].items() if s["status"] != "pass"}
    assert failed == {}, failed
