"""The persistent compilation cache: where it goes, how to move or stop it, and that a new
process reuses what an earlier one compiled."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

import bayesrob

FIT = """
import numpy as np
import jax
import bayesrob
from bayesrob.kde import KDE
print(jax.config.jax_compilation_cache_dir)
x = np.random.default_rng(0).normal(size=(300, 3))
print(KDE.fit(x, "loo-ml-diag").bandwidth.tolist())
"""


def _run(env: dict[str, str]) -> list[str]:
    base = {k: v for k, v in os.environ.items()
            if k not in ("BAYESROB_CACHE_DIR", "BAYESROB_NO_CACHE", "XDG_CACHE_HOME")}
    r = subprocess.run([sys.executable, "-c", FIT], env={**base, **env}, capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    return r.stdout.strip().splitlines()


def _entries(directory: Path) -> set[str]:
    return {p.name for p in directory.rglob("*") if p.is_file()}


def test_cache_directory_follows_the_environment(monkeypatch, tmp_path):
    for var in ("BAYESROB_CACHE_DIR", "BAYESROB_NO_CACHE", "XDG_CACHE_HOME"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert bayesrob.compilation_cache_dir() == tmp_path / "home" / ".cache" / "bayesrob" / "jax"
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert bayesrob.compilation_cache_dir() == tmp_path / "xdg" / "bayesrob" / "jax"
    monkeypatch.setenv("BAYESROB_CACHE_DIR", str(tmp_path / "mine"))
    assert bayesrob.compilation_cache_dir() == tmp_path / "mine"
    for off in ("1", "yes", "true"):
        monkeypatch.setenv("BAYESROB_NO_CACHE", off)
        assert bayesrob.compilation_cache_dir() is None
    monkeypatch.setenv("BAYESROB_NO_CACHE", "0")
    assert bayesrob.compilation_cache_dir() == tmp_path / "mine"


def test_a_second_process_reuses_the_first_ones_compilations(tmp_path):
    cache = tmp_path / "cache"
    first = _run({"BAYESROB_CACHE_DIR": str(cache)})
    assert first[0] == str(cache)
    written = _entries(cache)
    assert written, "the first process compiled the KDE objective and stored it"
    second = _run({"BAYESROB_CACHE_DIR": str(cache)})
    # Every program the second process needed was found, so it stored nothing new; and the
    # executables read back compute the same bandwidths.
    assert _entries(cache) == written
    assert second[1] == first[1]


@pytest.mark.parametrize("how", ["off", "xdg"])
def test_cache_can_be_turned_off_or_moved_with_xdg(tmp_path, how):
    xdg = tmp_path / "xdg"
    env = {"XDG_CACHE_HOME": str(xdg), "HOME": str(tmp_path / "home")}
    if how == "off":
        env["BAYESROB_NO_CACHE"] = "1"
    out = _run(env)
    if how == "off":
        assert out[0] == "None" and not xdg.exists() and not (tmp_path / "home").exists()
    else:
        assert out[0] == str(xdg / "bayesrob" / "jax") and _entries(xdg / "bayesrob" / "jax")
