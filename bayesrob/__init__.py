"""bayesrob: probabilistic accuracy prediction for modular robot arms.

Importing the package switches JAX to 64-bit floats (``jax_enable_x64``): kernel
density sums over thousands of points and the inverse kinematics near the
workspace boundary lose too much precision in float32.

It also turns on JAX's persistent compilation cache, so a new process reuses the
programs earlier ones compiled (a KDE fit then costs its run time, not the 0.4-0.5 s of
XLA compilation). The cache lives in ``$XDG_CACHE_HOME/bayesrob`` (default
``~/.cache/bayesrob``): JAX's entries in ``jax/``, the KDE bandwidth objectives as loadable
executables in ``executables/`` (see :mod:`bayesrob.errors.kde`). ``BAYESROB_CACHE_DIR`` moves it,
``BAYESROB_NO_CACHE=1`` turns it off, and a cache directory set through JAX's own
configuration is left alone. The cache holds executable code: keep it in a directory only
you can write to.

Every compiled program maps its machine code into the process (about two dozen memory maps
each), and Linux caps a process's maps (``vm.max_map_count``, 65530 by default): past it XLA
dies with a segmentation fault in whatever maps next (a compilation, or the cache's
(de)serialiser). Programs are keyed by a robot's structure, so fitting robot after robot of
one design adds none; a process that compiles many different programs (the validation suite
between studies, a designer's worker, a test session) calls :func:`release_compiled_programs`
between them.
"""

from __future__ import annotations

import gc
import os
import sys
from pathlib import Path

__version__ = "0.1.0"

# The objects a user needs, as ``bayesrob.<name>``: the rig (from a directory or from arrays),
# the robot model, calibration, prediction, comparison, sampling and diagnosis. Each is
# imported on first use, so ``import bayesrob`` (and every command's argument errors) stays
# free of JAX and the rest of the numerical stack. docs/api.md walks through them.
_API = {
    "Rig": "data.rig", "Measurements": "data.rig", "ArmSpec": "data.rig",
    "RigError": "data.rig", "load_rig": "data.rig", "default_rig_dir": "data.rig",
    "Robot": "robot", "Chain": "robot", "urdf_chain": "robot", "dh_chain": "robot",
    "GROUPS": "robot",
    "Calibration": "calibrate", "calibrate_arms": "calibrate",
    "predict_assembly": "predict.assembly", "compare_models": "compare.comparison",
    "sample_linked": "inference.sampling", "diagnose_rig": "diagnose.refits",
    "diagnose_groups": "diagnose.groups", "discover_models": "errors.noise_models",
}
__all__ = ["__version__", "cache_dir", "release_compiled_programs", "calibrate", *_API]


def __getattr__(name: str):
    if name == "calibrate":  # the subpackage: its ``calibrate`` fits any robot
        import importlib

        return importlib.import_module("bayesrob.calibrate")
    if name in _API:
        import importlib

        value = getattr(importlib.import_module(f"bayesrob.{_API[name]}"), name)
        globals()[name] = value  # later lookups skip this function
        return value
    raise AttributeError(f"module 'bayesrob' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_API))

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


# JAX reads its options from JAX_* variables when it is first imported. Setting them here,
# rather than importing JAX to configure it, keeps ``import bayesrob`` (and so ``bayesrob
# --help`` and every argument error) free of the numerical stack. _OURS marks the cache
# directory as this package's choice, so a child process (a Dask worker, a command run by a
# test) that sees it recomputes it from its own BAYESROB_* variables.
_OURS = "_BAYESROB_JAX_CACHE_DIR"


def _cache_directory() -> Path | None:
    """The compilation cache's directory, made; None when caching is off or it cannot be."""
    directory = compilation_cache_dir()
    if directory is None:
        return None
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None  # e.g. a read-only home: run uncached rather than fail on import
    return directory


def _configure_jax() -> None:
    """64-bit floats, and the persistent cache unless caching is off or the user configured
    JAX's own cache directory."""
    jax = sys.modules.get("jax")
    inherited = os.environ.get(_OURS)
    current = (jax.config.jax_compilation_cache_dir if jax is not None
               else os.environ.get("JAX_COMPILATION_CACHE_DIR")) or None
    user_set = current is not None and current != inherited
    directory = None if user_set else _cache_directory()
    options = {"jax_enable_x64": True}
    if directory is not None:
        # "none" of XLA's GPU caches: JAX puts their directory under the cache's and hashes
        # that path into every program's key, even on the CPU, so that a cache copied, linked
        # or moved elsewhere (the test workers' scratch caches, seeded from this machine's)
        # would never be read.
        options |= {"jax_compilation_cache_dir": str(directory),
                    "jax_persistent_cache_min_compile_time_secs": _CACHE_MIN_COMPILE_SECS,
                    "jax_persistent_cache_min_entry_size_bytes": 0,
                    "jax_persistent_cache_enable_xla_caches": "none"}
    if jax is not None:  # imported before this package: set its options directly
        for name, value in options.items():
            jax.config.update(name, value)
        if directory is None and current is not None and not user_set:
            jax.config.update("jax_compilation_cache_dir", None)  # a parent's, off here
        return
    for name, value in options.items():
        os.environ[name.upper()] = str(int(value) if isinstance(value, bool) else value)
    if directory is not None:
        os.environ[_OURS] = str(directory)
    elif not user_set:
        os.environ.pop("JAX_COMPILATION_CACHE_DIR", None)  # a parent's, off here
        os.environ.pop(_OURS, None)


_configure_jax()

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
    if counts is None or counts[0] <= share * counts[1] or "jax" not in sys.modules:
        return False
    sys.modules["jax"].clear_caches()
    gc.collect()  # the programs' code is unmapped when the last reference goes
    return True
