"""The install ships every subpackage: pyproject.toml lists its packages by name (models/ and
validation/ are mapped in from the top level), so a subpackage missing from the list would
import from a source checkout and fail on an installed copy, as CI installs it."""

from __future__ import annotations

import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_pyproject_lists_every_subpackage_of_bayesrob():
    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
                 ["packages"])
    on_disk = {".".join(p.parent.relative_to(ROOT).parts)
               for p in (ROOT / "bayesrob").rglob("__init__.py")}
    assert len(on_disk) > 5  # the walk found the package
    assert on_disk - listed == set(), "add these to [tool.setuptools] packages"
    assert listed - on_disk == {"bayesrob.models", "bayesrob.validation"}
