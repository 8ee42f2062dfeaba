"""Robots and chains are values: equal when built apart from the same description, unequal when
any field differs, and hashed alike in every process. The compiled programs take the robot's
structure as their static argument and its nominal values as arrays: robots of one structure
share a program whatever their numbers, and the structure's equality decides which program a
robot runs."""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

from bayesrob import robot as kin
from bayesrob.data.rig import default_rig_dir, load_rig


def _robot() -> kin.Robot:
    return load_rig(default_rig_dir()).robot


def _with_chain(robot: kin.Robot, name: str, **changes) -> kin.Robot:
    return replace(robot, chains={**robot.chains, name: replace(robot.chains[name], **changes)})


def test_robots_built_apart_from_one_description_are_equal():
    a, b = _robot(), _robot()
    assert a is not b and a == b and hash(a) == hash(b)
    assert {a: 1}[b] == 1
    for name in a.chains:
        assert a.chains[name] == b.chains[name]
    copy = pickle.loads(pickle.dumps(a))
    assert copy == a and hash(copy) == hash(a)


def _one_value_changed(robot: kin.Robot) -> dict[str, kin.Robot]:
    name = next(iter(robot.chains))
    c = robot.chains[name]

    def bumped(a: np.ndarray, index: tuple) -> np.ndarray:
        a = a.copy()
        a[index] = np.nextafter(a[index], np.inf)  # the smallest change a float can make
        return a

    return {
        "origin": _with_chain(robot, name, origins=bumped(c.origins, (1, 0))),
        "axis": _with_chain(robot, name, axes=bumped(c.axes, (0, 0))),
        "gain": _with_chain(robot, name, gain=bumped(c.gain, (0,))),
        "offset": _with_chain(robot, name, offset=bumped(c.offset, (0,))),
        "coupling": _with_chain(robot, name, coupling=bumped(c.coupling, (0, 0))),
        "marker": _with_chain(robot, name, marker=bumped(c.marker, (0,))),
        "instrument": _with_chain(robot, name, instrument=bumped(c.instrument, (2,))),
        "float32 origins": _with_chain(robot, name, origins=c.origins.astype(np.float32)),
        "source": _with_chain(robot, name, source={**c.source, "kind": "dh"}),
        "gravity": replace(robot, gravity=np.array([0.0, -1.0, 0.0])),
        # against the rig's robot without gravity a change of structure; against one with
        # gravity along -y (test_only_a_change_of_structure...), of a value
        "gravity direction": replace(robot, gravity=np.array([1.0, 0.0, 0.0])),
        "sag steps": replace(robot, sag_steps=2),
        "dim": replace(robot, dim=3),
        "chain order": replace(robot, chains=dict(reversed(robot.chains.items()))),
    }


@pytest.mark.parametrize("what", list(_one_value_changed(_robot())))
def test_robots_differing_in_one_value_are_unequal(what):
    base = _robot()
    other = _one_value_changed(base)[what]
    assert other != base and base != other
    assert hash(other) != hash(base)  # 64 bits of a digest: a collision is not expected
    assert len({base, other}) == 2


# what the compiled programs are specialised on; every other field is a nominal value, an
# argument of the program (or, as ``source``, read by none)
STRUCTURAL = {"axis", "coupling", "gravity", "sag steps", "dim", "chain order"}


@pytest.mark.parametrize("what", list(_one_value_changed(_robot())))
def test_only_a_change_of_structure_changes_the_structure(what):
    base = _robot()
    other = _one_value_changed(base)[what]
    if what == "gravity direction":
        base = replace(base, gravity=np.array([0.0, -1.0, 0.0]))
    if what in STRUCTURAL:
        assert other.structure != base.structure
        assert hash(other.structure) != hash(base.structure)
    else:
        assert other.structure == base.structure
        assert hash(other.structure) == hash(base.structure)


def _count_traces(monkeypatch) -> list:
    """A list that grows by one at each call of ``Robot.marker_points``: each trace of a
    compiled program, and each eager call."""
    traced = []
    marker_points = kin.Robot.marker_points
    monkeypatch.setattr(kin.Robot, "marker_points", lambda self, *a, **k: (
        traced.append(1), marker_points(self, *a, **k))[1])
    return traced


def test_robots_of_one_structure_share_one_program_and_compute_their_own_points(monkeypatch):
    """Robots of one structure, whatever their nominal values (a URDF at another path, a
    calibrated robot), run one compiled program; a robot of another structure traces its
    own."""
    import jax
    import jax.numpy as jnp

    traced = _count_traces(monkeypatch)
    base = _robot()
    name = next(iter(base.chains))
    x = jnp.asarray(base.layout.nominal)
    u = jnp.full((3, base.chains[name].n_columns), 100.0)
    calibrated = base.with_values(np.asarray(x) + 1e-3 * base.layout.scales)
    jax.clear_caches()  # programs an earlier test traced for this structure would serve here
    points = {}
    for what, robot in {"base": base, "calibrated": calibrated,
                        **_one_value_changed(base)}.items():
        if robot.structure == base.structure and all(
                c.origins.dtype == np.float64 for c in robot.chains.values()):
            points[what] = np.asarray(robot.compiled_points(name)(x, u))
            # the same as the robot computes outside any compiled program
            np.testing.assert_allclose(points[what],
                                       np.asarray(robot.marker_points(x, name, u)),
                                       rtol=0, atol=1e-9)
    assert len(traced) == 1 + len(points)  # one trace, and the eager calls
    assert not np.allclose(points["calibrated"], points["base"])
    other = _one_value_changed(base)["sag steps"]
    other.compiled_points(name)(x, u)
    assert len(traced) == 2 + len(points)


def test_row_counts_of_one_bucket_share_one_program(monkeypatch):
    """The compiled points and joint Jacobian pad their rows to a bucket (64 rows, else the
    next quarter octave): 1, 5 and 64 rows run one traced program, 65 rows a second, and every
    row comes back as it is computed alone (the padding is cut off, no row sees another)."""
    import jax
    import jax.numpy as jnp

    from bayesrob.errors.latent_errors import joint_jacobian

    traced = _count_traces(monkeypatch)
    robot = _robot()
    name = next(iter(robot.chains))
    x = jnp.asarray(robot.layout.nominal)
    u = 1500.0 + 300.0 * np.random.default_rng(0).uniform(
        -1, 1, (65, robot.chains[name].n_columns))
    jax.clear_caches()  # programs an earlier test traced for this structure would serve here
    points = robot.compiled_points(name)
    full = np.asarray(points(x, u[:64]))
    for n in (1, 5):
        np.testing.assert_array_equal(np.asarray(points(x, u[:n])), full[:n])
    np.testing.assert_array_equal(np.asarray(points(x, u[63:64]))[0], full[63])
    assert len(traced) == 1
    assert np.asarray(points(x, u)).shape == (65, robot.dim) and len(traced) == 2
    traced.clear()
    jac = np.asarray(joint_jacobian(robot, x, name, u[:50]))
    assert jac.shape == (50, robot.dim, robot.n_path_joints(name))
    np.testing.assert_array_equal(np.asarray(joint_jacobian(robot, x, name, u[49:50]))[0],
                                  jac[49])
    assert len(traced) == 1

def test_a_changed_nominal_value_changes_what_the_compiled_program_computes():
    """A robot one origin apart runs the program of the first (one structure) with its own
    nominal values, not the first's."""
    import jax.numpy as jnp

    base = _robot()
    name = next(iter(base.chains))
    origins = base.chains[name].origins.copy()
    origins[0, 0] += 1.0  # the base joint 1 mm along the instrument's x
    moved = _with_chain(base, name, origins=origins)
    x = jnp.asarray(base.layout.nominal)
    u = jnp.zeros((1, base.chains[name].n_columns))
    shift = (np.asarray(moved.compiled_points(name)(x, u))
             - np.asarray(base.compiled_points(name)(x, u)))
    np.testing.assert_allclose(shift, [[1.0, 0.0]], atol=1e-9)


def test_a_robots_hash_is_the_same_in_every_process():
    """A robot pickled to a Dask worker carries its cached hash: it must be what the worker
    would compute itself, whatever its string hashing seed."""
    code = ("from bayesrob.data.rig import default_rig_dir, load_rig; "
            "r = load_rig(default_rig_dir()).robot; print(hash(r), hash(r.structure))")
    hashes = set()
    for seed in ("1", "2"):
        env = {**os.environ, "PYTHONHASHSEED": seed}
        out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                             text=True, check=True)
        hashes.add(tuple(int(v) for v in out.stdout.split()))
    assert hashes == {(hash(_robot()), hash(_robot().structure))}
