"""The command line's contract, pinned: every command, option, default, choice, help text and
the full ``--help`` output of every command, against a snapshot taken from the parser before
cli.py was refactored (``tests/golden/cli_contract.json``, a regression pin: it guards the
interface users and scripts call, not a computed figure).

Each option's ``type`` is pinned by what it does, not by its name: the values it accepts and
what it makes of them, for a fixed set of probe strings.

A deliberate change to the interface regenerates the snapshot:
``python tests/test_cli_contract.py --write``.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import sys
from pathlib import Path

GOLDEN = Path(__file__).parent / "golden" / "cli_contract.json"
PROBES = ("-1", "0", "0.5", "1", "2", "127", "128", "nan", "inf", "x", "", "a,b",
          "frames,geometric", "backlash", "gravity_sag")


def _jsonable(value):
    if isinstance(value, tuple | list):
        return [_jsonable(v) for v in value]
    if value is None or isinstance(value, bool | int | float | str):
        return value
    return repr(value)


def _probe(kind) -> dict[str, object]:
    out = {}
    for text in PROBES:
        try:
            out[text] = _jsonable(kind(text))
        except (argparse.ArgumentTypeError, ValueError, TypeError):
            out[text] = "<rejected>"
    return out


def _action(a: argparse.Action, groups: dict[int, int]) -> dict:
    return {
        "option_strings": a.option_strings, "dest": a.dest, "default": _jsonable(a.default),
        "choices": _jsonable(list(a.choices) if a.choices is not None else None),
        "nargs": _jsonable(a.nargs), "required": a.required, "help": a.help,
        "metavar": _jsonable(a.metavar), "const": _jsonable(a.const),
        "action": type(a).__name__.lstrip("_"),
        "type": None if a.type is None else _probe(a.type),
        "exclusive_group": groups.get(id(a)),
    }


def _parser(p: argparse.ArgumentParser) -> dict:
    groups = {id(a): i for i, g in enumerate(p._mutually_exclusive_groups)
              for a in g._group_actions}
    return {"prog": p.prog, "description": p.description, "epilog": p.epilog,
            "exclusive_groups_required": [g.required for g in p._mutually_exclusive_groups],
            "actions": [_action(a, groups) for a in p._actions
                        if not isinstance(a, argparse._SubParsersAction)]}


def _help(argv: list[str]) -> str:
    from bayesrob.cli import main

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf), contextlib.suppress(SystemExit):
        main(argv)
    return buf.getvalue()


def contract() -> dict:
    from bayesrob.cli import build_parser

    os.environ["COLUMNS"] = "80"  # argparse wraps help to the terminal's width
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return {
        "parser": _parser(parser),
        "commands": {name: {"summary": next(c.help for c in sub._choices_actions
                                            if c.dest == name),
                            **_parser(p)} for name, p in sub.choices.items()},
        "help": {"": _help(["--help"]),
                 **{name: _help([name, "--help"]) for name in sub.choices}},
    }


def test_parser_and_help_match_the_snapshot(monkeypatch):
    monkeypatch.setenv("COLUMNS", "80")
    want = json.loads(GOLDEN.read_text())
    got = json.loads(json.dumps(contract()))
    assert list(got["commands"]) == list(want["commands"])  # the order --help lists them in
    for name in want["commands"]:
        assert got["commands"][name] == want["commands"][name], name
    assert got["parser"] == want["parser"]
    for name in want["help"]:
        assert got["help"][name] == want["help"][name], f"bayesrob {name} --help"


def test_every_user_error_type_the_cli_catches_exists():
    """The CLI names the library's user-error types by module path (so a command that never
    imports a module never loads it); a moved module must not turn its errors into tracebacks."""
    import importlib

    from bayesrob.cli import USER_ERRORS

    for dotted in USER_ERRORS:
        module, name = dotted.rsplit(".", 1)
        assert issubclass(getattr(importlib.import_module(module), name), Exception), dotted


if __name__ == "__main__" and sys.argv[1:] == ["--write"]:
    GOLDEN.write_text(json.dumps(contract(), indent=1, sort_keys=False) + "\n")
    print(f"wrote {GOLDEN}")
