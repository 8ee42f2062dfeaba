"""bayesrob: probabilistic accuracy prediction for modular robot arms.

Importing the package switches JAX to 64-bit floats (``jax_enable_x64``): kernel
density sums over thousands of points and the inverse kinematics near the
workspace boundary lose too much precision in float32.

It also turns on JAX's persistent compilation cache, so a new process reuses the
programs earlier ones compiled (a KDE fit then costs its run time, not the 0.4-0.5 s of
XLA compilation). The cache lives in ``$XDG_CACHE_HOME/bayesrob`` (default
``~/.cache/bayesrob``): JAX's entries in ``jax/``, the KDE bandwidth objectives as loadable
executables in ``executables/`` (see :mod:`bayesrob.kde`). ``BAYESROB_CACHE_DIR`` moves it,
``BAYESROB_NO_CACHE=1`` turns it off, and a cache directory set through JAX's own
configuration is left alone. The cache holds executable code: keep it in a directory only
you can write to.
"""

from __future__ import annotations

import os
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

__version__ = "0.1.0"

# Programs compiling faster than this are cheaper to rebuild than to read back from disk.
_CACHE_MIN_COMPILE_SECS = 0.05


def cache_dir() -> Path | None:
    """The root of bayesrob's on-disk caches, or None when caching is turned off."""
    if os.environ.get("BAYESROB_NO_CACHE", "").strip().lower() not in ("", "0", "false", "no"):
        return None
    explicit = os.environ.get("BAYESROB_CACHE_DIR", "").strip()
    if explicit:
        return Path(explicit).expanduser()
    base = os.environ.get("XDG_CACHE_HOME", "").strip()
    return (Path(base) if base else Path.home() / ".cache") / "bayesrob"


def compilation_cache_dir() -> Path | None:
    """Where JAX's persistent compilation cache goes, or None when it is turned off."""
    root = cache_dir()
    return None if root is None else root / "jax"


def _enable_compilation_cache() -> None:
    if jax.config.jax_compilation_cache_dir:
        return  # the user configured JAX's cache directly
    directory = compilation_cache_dir()
    if directory is None:
        return
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError:
        return  # e.g. a read-only home: run uncached rather than fail on import
    jax.config.update("jax_compilation_cache_dir", str(directory))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", _CACHE_MIN_COMPILE_SECS)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)


_enable_compilation_cache()
