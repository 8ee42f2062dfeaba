"""The README's and docs' result tables, generated from the committed ``validation.json``.

A table in a Markdown file sits between two markers naming the study and the table::

    <!-- validation-table: linked_planar.coverage -->
    | model | 50% | 90% |
    ...
    <!-- end validation-table -->

and its rows are what the study module's ``tables(entry)`` renders from that study's entry of
the report (``entry["figures"]``, ``entry["details"]``). ``python -m bayesrob.validation.tables
--write`` rewrites every block from the committed report; without ``--write`` it lists the
blocks that differ and exits 1 (a fast test runs the same check), so a published figure can
neither move silently nor be edited by hand.
"""

from __future__ import annotations

import argparse
import importlib
import re
import sys
from pathlib import Path
from typing import Any

from bayesrob.validation.study import discover_studies
from bayesrob.validation.suite import COMMITTED, load_committed

BLOCK = re.compile(r"(<!-- validation-table: (?P<key>[\w.]+) -->\n)(?P<body>.*?)"
                   r"(<!-- end validation-table -->)", re.S)


def documents(root: Path) -> list[Path]:
    """The Markdown files whose tables may come from the report: the README and docs/."""
    return [p for p in [root / "README.md", *sorted((root / "docs").rglob("*.md"))]
            if p.exists()]


def render(key: str, report: dict[str, Any], studies: dict[str, Any] | None = None) -> str:
    """The table ``study.table`` from ``report``; a one-line error if either is unknown.
    ``studies``: name -> study, when the caller has read the targets files already."""
    study_name, _, table = key.partition(".")
    if studies is None:
        studies = {s.name: s for s in discover_studies()}
    if study_name not in studies:
        raise KeyError(f"no study {study_name!r}")
    if study_name not in report["studies"]:
        raise KeyError(f"study {study_name!r} is not in the report")
    module = importlib.import_module(f"bayesrob.validation.{studies[study_name].module}")
    tables = module.tables(report["studies"][study_name])
    if table not in tables:
        raise KeyError(f"study {study_name!r} has no table {table!r} (has {sorted(tables)})")
    return tables[table].rstrip("\n") + "\n"


def sync(root: Path, report: dict[str, Any], write: bool = False) -> list[str]:
    """Blocks that differ from the report, as 'file: key'; ``write`` rewrites them."""
    stale = []
    studies = {s.name: s for s in discover_studies()}  # read once for every block
    for path in documents(root):
        text = path.read_text(encoding="utf-8")

        def replace(m: re.Match, path: Path = path) -> str:
            try:
                body = render(m["key"], report, studies)
            except KeyError as exc:
                stale.append(f"{path.relative_to(root)}: {m['key']}: {exc.args[0]}")
                return m[0]
            if body != m["body"]:
                stale.append(f"{path.relative_to(root)}: {m['key']}")
            return m[1] + body + m[4]

        new = BLOCK.sub(replace, text)
        if write and new != text:
            path.write_text(new, encoding="utf-8")
    return stale


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bayesrob.validation.tables",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--root", type=Path, default=Path.cwd(),
                        help="the repository (default: the current directory)")
    parser.add_argument("--report", type=Path, default=COMMITTED,
                        help="the validation.json to read (default: the committed one)")
    parser.add_argument("--write", action="store_true", help="rewrite the blocks that differ")
    args = parser.parse_args(argv)
    stale = sync(args.root, load_committed(args.report), write=args.write)
    for line in stale:
        print(("rewrote " if args.write else "differs: ") + line)
    return 1 if stale and not args.write else 0


if __name__ == "__main__":
    sys.exit(main())
