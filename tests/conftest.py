"""Shared fixtures: one small simulated rig per test session, and fresh copies to break."""

from __future__ import annotations

import atexit
import os
import shutil
import tempfile
from pathlib import Path

import pytest

# Compiled programs go to a scratch cache, not the user's ~/.cache (set before any test module
# imports bayesrob, which reads it once), removed when the session ends.
if "BAYESROB_CACHE_DIR" not in os.environ:
    os.environ["BAYESROB_CACHE_DIR"] = tempfile.mkdtemp(prefix="bayesrob-test-cache-")
    atexit.register(shutil.rmtree, os.environ["BAYESROB_CACHE_DIR"], ignore_errors=True)
# Each xdist worker (and the processes it starts: Dask workers, the command run as a
# subprocess) has a directory of its own in it, so no entry is written by two processes at once.
_worker = os.environ.get("PYTEST_XDIST_WORKER", "")
if _worker and not os.environ.get("BAYESROB_CACHE_DIR", "").endswith(_worker):
    os.environ["BAYESROB_CACHE_DIR"] = os.path.join(os.environ["BAYESROB_CACHE_DIR"], _worker)


def _seed_from_the_users_cache(scratch: Path) -> None:
    """Hard-link the programs this machine's own cache holds (the one a command run here
    used, e.g. CI's validation suite) into the scratch cache.

    Most of the tests' time is compilation (three of the slowest took 192 s in an empty cache,
    67 s in a warm one). Links leave the user's cache as it was: JAX writes an entry only
    under a name its directory does not hold, so it never writes through a link; and linking
    takes no space or time. On another file system than the scratch's, nothing is linked."""
    import bayesrob  # reads BAYESROB_CACHE_DIR (the scratch) once, as it is imported

    saved = os.environ.pop("BAYESROB_CACHE_DIR")
    try:
        users = bayesrob.compilation_cache_dir()  # where it would be without the scratch
    finally:
        os.environ["BAYESROB_CACHE_DIR"] = saved
    if users is None or not users.is_dir() or users.resolve() == scratch.resolve():
        return
    scratch.mkdir(parents=True, exist_ok=True)
    for entry in users.iterdir():
        try:
            os.link(entry, scratch / entry.name)
        except FileExistsError:
            continue
        except OSError:
            break  # another file system, or links not allowed: run with an empty cache


def _one_xla_thread() -> None:
    """Two test workers share two cores, as a LocalCluster's two workers do: each gets what
    theirs get, one XLA thread (two busy processes with a pool each ran at half speed). The
    same flags also give the same programs: XLA's flags are part of a program's key in the
    persistent cache, so what the validation suite's workers compiled serves the tests."""
    from bayesrob.cluster import WORKER_ENV

    for name, value in WORKER_ENV.items():
        os.environ.setdefault(name, value)


_one_xla_thread()
_seed_from_the_users_cache(Path(os.environ["BAYESROB_CACHE_DIR"]) / "jax")


@pytest.fixture(autouse=True)
def _release_compiled_programs():
    """A worker runs hundreds of tests, each compiling programs for robots of its own: past
    the kernel's cap on a process's memory maps XLA dies in whatever maps next. The slow suite
    died that way three times (in compilation and in the cache's (de)serialiser), and again,
    reproduced, with the cap lowered to the maps a worker had reached."""
    yield
    from bayesrob import release_compiled_programs

    release_compiled_programs()


@pytest.fixture(scope="session")
def clean_rig_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A valid two-arm rig (grid 4, no physical effects, seed 0), simulated once per session.

    Shared by every test: read it, never write to it (use ``rig_copy`` to mutate). It has the
    paper's 80 rows only (no ``holdout`` rows): the rig-format tests pin that layout, and the
    holdout rows are tested on the rigs that carry them (the default rig, test_simulator).
    """
    from bayesrob.sim.rigs import simulate_rig
    from bayesrob.sim.truth import paper_truth

    return simulate_rig(tmp_path_factory.mktemp("clean_rig"), paper_truth((), seed=0, grid=4),
                        holdout=False)


@pytest.fixture
def rig_copy(clean_rig_dir: Path, tmp_path: Path) -> Path:
    """A private copy of ``clean_rig_dir`` that a test may edit or break."""
    dest = tmp_path / "rig"
    shutil.copytree(clean_rig_dir, dest)
    return dest


# A rig written by hand, as another tool or a person would: three arms with other names,
# integers where floats are expected, no gravity/workspace, optional keys left out, a
# column order of its own, extra columns, empty targets and a three-arm linked config.
HANDMADE_TOML = """\
# bench rig, measured with calipers
name = "bench"

[arms.left]
base = [0, 0]
links = [200, 150]
gain = [0.0015, 0.0015]
offset = [-1.65, -1.25]
pulse_limits = [[1000, 2000], [900, 2100]]

[arms.right]
base = [300.0, 0.0]
links = [200.0, 150.0]
gain = [-0.0015, -0.0015]
offset = [4.8, 3.5]
elbow = -1

[arms.middle]
base = [150, 320]
links = [190.5, 160.25]
gain = [0.0016, 0.0014]
offset = [-6.9, -1.1]
elbow = 1
"""
HANDMADE_ARMS = {
    "left": ((0.0, 0.0), (200.0, 150.0), (0.0015, 0.0015), (-1.65, -1.25)),
    "right": ((300.0, 0.0), (200.0, 150.0), (-0.0015, -0.0015), (4.8, 3.5)),
    "middle": ((150.0, 320.0), (190.5, 160.25), (0.0016, 0.0014), (-6.9, -1.1)),
}
HANDMADE_COLUMNS = ["timestamp", "x", "y", "set", "config", "right_u2", "right_u1", "middle_u1",
                    "middle_u2", "left_u1", "left_u2", "target_y", "target_x", "operator"]
HANDMADE_LINKED = {"left+right": [(150.0, 120.0), (140.0, 150.0), (170.0, 100.0)],
                   "left+middle+right": [(150.0, 120.0), (160.0, 140.0)]}


def handmade_rows() -> list[dict[str, str]]:
    """Rows of the hand-made rig as column -> text; observed points follow the nominal arms."""
    import numpy as np

    rng = np.random.default_rng(7)
    rows = []
    for name, (base, links, gain, offset) in HANDMADE_ARMS.items():
        pulses = [(u1, u2) for u1 in (1300, 1450, 1600) for u2 in (1350, 1500, 1650)]
        pulses += [(1375, 1425), (1525, 1575), (1450.5, 1600.25)]
        for i, (u1, u2) in enumerate(pulses):
            t1 = gain[0] * u1 + offset[0]
            t12 = t1 + gain[1] * u2 + offset[1]
            x = base[0] + links[0] * np.cos(t1) + links[1] * np.cos(t12) + rng.normal(0, 0.3)
            y = base[1] + links[0] * np.sin(t1) + links[1] * np.sin(t12) + rng.normal(0, 0.3)
            rows.append({"config": name, "set": "train" if i < 9 else "validation",
                         f"{name}_u1": str(u1), f"{name}_u2": str(u2),
                         "x": f"{x:.3f}", "y": f"{y:.3f}"})
    for config, targets in HANDMADE_LINKED.items():
        for tx, ty in targets:
            row = {"config": config, "set": "test", "target_x": f"{tx:g}", "target_y": f"{ty:g}",
                   "x": f"{tx + 0.4:.2f}", "y": f"{ty - 0.3:.2f}"}
            for arm in config.split("+"):
                row[f"{arm}_u1"], row[f"{arm}_u2"] = "1500", "1499.75"
            rows.append(row)
    for i, row in enumerate(rows):
        row["timestamp"] = f"2024-05-0{1 + i % 9}T10:{i % 60:02d}:00"
        row["operator"] = "kim"
    return rows


def write_handmade_rig(directory: Path) -> Path:
    import csv

    directory.mkdir(parents=True, exist_ok=True)
    (directory / "rig.toml").write_text(HANDMADE_TOML, encoding="utf-8")
    with (directory / "measurements.csv").open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(HANDMADE_COLUMNS)
        w.writerows([[row.get(c, "") for c in HANDMADE_COLUMNS] for row in handmade_rows()])
    return directory


@pytest.fixture
def handmade_rig_dir(tmp_path: Path) -> Path:
    """A valid three-arm rig (left, right, middle) written without this project's simulator."""
    return write_handmade_rig(tmp_path / "bench")


@pytest.fixture
def forearm_unweighed(tmp_path: Path) -> Path:
    """arm6's URDF with the forearm's <inertial> taken out, written as half.urdf: a
    description that does not weigh every moving link."""
    from bayesrob.sim.truth import arm6_urdf_path

    text = arm6_urdf_path().read_text()
    start = text.index('<link name="forearm_link">')
    end = text.index("</link>", start) + len("</link>")
    path = tmp_path / "half.urdf"
    path.write_text(text[:start] + '<link name="forearm_link"/>' + text[end:])
    return path
