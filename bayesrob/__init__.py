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

Every compiled program maps its machine code into the process (about two dozen memory maps
each), and Linux caps a process's maps (``vm.max_map_count``, 65530 by default): past it XLA
dies with a segmentation fault in whatever maps next (a compilation, or the cache's
(de)serialiser). A process that compiles programs for robot after robot (a diagnosis sweep, a
designer's worker, a test session) calls :func:`release_compiled_programs` between them.
"""

from __future__ import annotations

import gc
import os
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

__version__ = "0.1.0"

# In a checkout, the top-level models/ and validation/ are this package's bayesrob.models and
# bayesrob.validation, as an install lays them out (pyproject's package-dir): the tests and the
# validation suite then run the checkout's files, not an installed copy's.
_checkout = Path(__file__).resolve().parent.parent
if (_checkout / "pyproject.toml").exists() and (_checkout / "validation" / "suite.py").exists():
    __path__.append(str(_checkout))

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

# Where JAX's compiled programs are dropped: the share of the kernel's cap on a process's
# memory maps. A test worker on the chain tests went from 3,700 to 28,000 maps in two minutes:
# a release at half the cap leaves the next fits that much room and more.
RELEASE_MAPS_SHARE = 0.5


def memory_maps() -> tuple[int, int] | None:
    """This process's memory maps and the kernel's cap on them, or None where the system does
    not say (not Linux)."""
    try:
        limit = int(Path("/proc/sys/vm/max_map_count").read_text())
        with open("/proc/self/maps", "rb") as maps:
            return sum(1 for _ in maps), limit
    except (OSError, ValueError):
        return None


def release_compiled_programs(share: float = RELEASE_MAPS_SHARE) -> bool:
    """Drop JAX's compiled programs (``jax.clear_caches``) when this process holds more than
    ``share`` of the memory maps the kernel allows; True when it did. A program used again is
    compiled again, or read back from the persistent cache."""
    counts = memory_maps()
    if counts is None or counts[0] <= share * counts[1]:
        return False
    jax.clear_caches()
    gc.collect()  # the programs' code is unmapped when the last reference goes
    return True
