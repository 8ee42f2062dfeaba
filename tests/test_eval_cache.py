"""The persistent compilation cache: where it goes, how to move or stop it, and that a new
process reuses what an earlier one compiled."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import bayesrob

FIT = """
import numpy as np
import jax
import bayesrob
from bayesrob.errors.kde import KDE
print(jax.config.jax_compilation_cache_dir)
x = np.random.default_rng(0).normal(size=(300, 3))
kde = KDE.fit(x, "loo-ml-diag")
print(kde.bandwidth.tolist())
print(np.asarray(kde.logpdf(x[:5])).tolist())
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
    assert bayesrob.cache_dir() == tmp_path / "mine"
    assert bayesrob.compilation_cache_dir() == tmp_path / "mine" / "jax"
    for off in ("1", "yes", "true"):
        monkeypatch.setenv("BAYESROB_NO_CACHE", off)
        assert bayesrob.compilation_cache_dir() is None and bayesrob.cache_dir() is None
    monkeypatch.setenv("BAYESROB_NO_CACHE", "0")
    assert bayesrob.compilation_cache_dir() == tmp_path / "mine" / "jax"


def test_a_second_process_reuses_the_first_ones_compilations(tmp_path):
    cache = tmp_path / "cache"
    first = _run({"BAYESROB_CACHE_DIR": str(cache)})
    assert first[0] == str(cache / "jax")
    written = _entries(cache)
    assert {e for e in _entries(cache / "jax") if "kde_logpdf" in e}, "JAX stored logpdf"
    assert _entries(cache / "executables"), "and bayesrob the LOO objective, loadable"
    second = _run({"BAYESROB_CACHE_DIR": str(cache)})
    # Both were read back, not compiled again: nothing of them was stored anew (small
    # programs near the cache's compile-time threshold may be, so only theirs count); and
    # what was read back computes the same bandwidths and densities.
    def ours(entries):
        return {e for e in entries if "loo" in e or "kde_logpdf" in e}

    assert ours(_entries(cache)) == ours(written)
    assert second[1:] == first[1:]


def test_a_cache_copied_to_another_directory_is_read_there(tmp_path):
    """A program's key does not hold the cache's path (JAX hashes its GPU caches' directory,
    under the cache's, into every key unless they are off): the test workers' scratch caches,
    seeded by links from this machine's, depend on it."""
    first = _run({"BAYESROB_CACHE_DIR": str(tmp_path / "a")})
    (tmp_path / "b").mkdir()
    shutil.copytree(tmp_path / "a" / "jax", tmp_path / "b" / "jax")
    copied = {e for e in _entries(tmp_path / "b" / "jax") if "kde_logpdf" in e}
    assert copied
    second = _run({"BAYESROB_CACHE_DIR": str(tmp_path / "b")})
    assert {e for e in _entries(tmp_path / "b" / "jax") if "kde_logpdf" in e} == copied
    assert second[1:] == first[1:]


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


def test_a_lost_or_damaged_executable_is_rebuilt(tmp_path):
    """Deleted while JAX's own cache still holds the program (whose copy XLA:CPU cannot
    re-serialise), or overwritten with junk: the next process compiles afresh, gets the same
    bandwidths and stores a working file again, which the process after it loads."""
    cache = tmp_path / "cache"
    first = _run({"BAYESROB_CACHE_DIR": str(cache)})
    (stored,) = (cache / "executables").iterdir()
    good = stored.read_bytes()
    stored.unlink()
    assert _run({"BAYESROB_CACHE_DIR": str(cache)})[1] == first[1]
    assert stored.is_file()
    stored.write_bytes(b"junk" + good[:100])
    assert _run({"BAYESROB_CACHE_DIR": str(cache)})[1] == first[1]
    rebuilt = stored.read_bytes()
    assert rebuilt[:4] != b"junk"
    assert _run({"BAYESROB_CACHE_DIR": str(cache)})[1] == first[1]
    assert stored.read_bytes() == rebuilt  # loaded, not rebuilt again


@pytest.mark.skipif(bayesrob.memory_maps() is None, reason="needs Linux's /proc")
def test_compiled_programs_are_released_when_the_maps_crowd():
    """Each compiled program maps its code (about two dozen maps on this jaxlib): 40 programs
    held by live functions add hundreds of maps, and a release (share 0: always crowded) drops
    JAX's compiled programs and gives most of them back; a share of 1 never releases. The
    functions still work after, compiled again."""
    import jax
    import jax.numpy as jnp

    def program(k):
        return jax.jit(lambda x: jnp.sin(x * k).cumsum() @ jnp.cos(x[:, None] + k * x[None]).sum(1))

    assert bayesrob.release_compiled_programs(share=1.0) is False
    before = bayesrob.memory_maps()[0]
    held = [program(k) for k in range(40)]
    first = [float(f(jnp.ones(30 + k))) for k, f in enumerate(held)]
    grown = bayesrob.memory_maps()[0]
    assert grown - before > 200
    assert bayesrob.release_compiled_programs(share=0.0) is True
    assert bayesrob.memory_maps()[0] < grown - 200
    assert [float(f(jnp.ones(30 + k))) for k, f in enumerate(held)] == first
