"""Kinematics: round trips, branch choice, unreachable points, Jacobians (property tests)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bayesrob import robot as kin

PARAMS = kin.ArmParams(jnp.array([20.0, -20.0]), jnp.array([220.0, 200.0]),
                       jnp.array([0.0015, 0.00155]), jnp.array([-0.5, -4.1]))
L1, L2 = 220.0, 200.0

reachable_points = st.tuples(
    st.floats(L1 - L2 + 1.0, L1 + L2 - 1.0), st.floats(-np.pi, np.pi)
).map(lambda ra: np.array([20.0 + ra[0] * np.cos(ra[1]), -20.0 + ra[0] * np.sin(ra[1])]))


@settings(max_examples=200, deadline=None)
@given(reachable_points, st.sampled_from([1, -1]))
def test_forward_of_inverse_is_identity(d, elbow):
    theta, ok = kin.inverse(PARAMS, jnp.asarray(d), elbow)
    assert bool(ok)
    np.testing.assert_allclose(np.asarray(kin.forward(PARAMS, theta)), d, atol=1e-7)
    # the branch is the one asked for
    assert np.sign(float(theta[1])) in (elbow, 0.0)


@settings(max_examples=100, deadline=None)
@given(st.floats(-3.0, 3.0), st.floats(0.05, 3.0), st.sampled_from([1, -1]))
def test_inverse_of_forward_recovers_angles_on_their_branch(t1, t2_abs, elbow):
    theta = jnp.array([t1, elbow * t2_abs])
    back, ok = kin.inverse(PARAMS, kin.forward(PARAMS, theta), elbow)
    assert bool(ok)
    np.testing.assert_allclose(np.asarray(kin.wrap_angle(back - theta)), 0.0, atol=1e-6)


@settings(max_examples=100, deadline=None)
@given(st.floats(1.0, 2000.0), st.floats(1.0, 2000.0))
def test_servo_round_trip(u1, u2):
    u = jnp.array([u1, u2])
    np.testing.assert_allclose(np.asarray(kin.servo_inverse(PARAMS, kin.servo(PARAMS, u))),
                               np.asarray(u), rtol=1e-10)


def test_unreachable_points_are_flagged_and_finite():
    far = jnp.array([[20.0 + L1 + L2 + 5.0, -20.0], [20.0 + 10.0, -20.0]])  # too far, too near
    theta, ok = kin.inverse(PARAMS, far, 1)
    assert not np.any(np.asarray(ok))
    assert np.all(np.isfinite(np.asarray(theta)))
    g = jax.grad(lambda d: jnp.sum(kin.inverse(PARAMS, d, 1)[0]))(far[0])
    assert np.all(np.isfinite(np.asarray(g)))


def test_vectorised_over_leading_dimensions():
    d = jnp.stack(jnp.meshgrid(jnp.linspace(150, 250, 7), jnp.linspace(100, 200, 5)), -1)
    theta, ok = kin.inverse(PARAMS, d, -1)
    assert theta.shape == (5, 7, 2) and ok.shape == (5, 7)
    np.testing.assert_allclose(np.asarray(kin.forward(PARAMS, theta)), np.asarray(d), atol=1e-8)


@settings(max_examples=50, deadline=None)
@given(st.floats(-3.0, 3.0), st.floats(0.2, 2.9))
def test_jacobian_matches_autodiff_and_log_det(t1, t2):
    theta = jnp.array([t1, t2])
    J = kin.jacobian(PARAMS, theta)
    np.testing.assert_allclose(np.asarray(J), np.asarray(jax.jacfwd(
        lambda t: kin.forward(PARAMS, t))(theta)), atol=1e-9)
    # log|det df^-1/dd| at f(theta) is -log|det J|
    np.testing.assert_allclose(float(kin.log_abs_det_inverse_jacobian(PARAMS, theta)),
                               -np.log(abs(np.linalg.det(np.asarray(J)))), rtol=1e-9)


def test_choose_elbow_picks_the_branch_of_the_training_data():
    rng = np.random.default_rng(0)
    for true_elbow in (1, -1):
        d = np.column_stack([rng.uniform(150, 300, 16), rng.uniform(100, 250, 16)])
        theta, _ = kin.inverse(PARAMS, jnp.asarray(d), true_elbow)
        u = np.asarray(kin.servo_inverse(PARAMS, theta))
        assert kin.choose_elbow(PARAMS, u, d, default=-true_elbow) == true_elbow
    assert kin.choose_elbow(PARAMS, np.zeros((0, 2)), np.zeros((0, 2)), default=-1) == -1


def test_arm_command_lands_in_servo_range():
    arm = kin.Arm("bottom", PARAMS, -1, ((600.0, 2400.0), (600.0, 2400.0)))
    targets = jnp.array([[100.0, 120.0], [250.0, 270.0]])
    u = np.asarray(arm.command(targets))
    np.testing.assert_allclose(np.asarray(arm.forward_u(u)), np.asarray(targets), atol=1e-7)
    # the 2 pi turn nearest mid range is chosen
    assert np.all(np.abs(u - 1500.0) < np.pi / 0.0015)


_URDF = """<robot name="r">
  <link name="base"/><link name="l1"/><link name="tip"/>
  <joint name="j1" type="revolute"><parent link="{p1}"/><child link="l1"/>
    <axis xyz="0 0 1"/></joint>
  <joint name="j2" type="revolute"><parent link="l1"/><child link="tip"/>
    <axis xyz="0 0 1"/>{mimic}</joint>
</robot>"""


@pytest.mark.parametrize("p1, mimic, words", [
    ("bse", "", "joint 'j1' names parent link 'bse', which is not a link"),
    ("base", '<mimic joint="j9"/>', "joint 'j2' mimics 'j9', which is not a joint"),
])
def test_a_urdf_naming_what_it_does_not_have_is_refused(tmp_path, p1, mimic, words):
    """Checked whatever chain is asked for: a misspelt link would silently cut a tree."""
    from bayesrob.robot import KinematicsError, urdf_chain

    path = tmp_path / "r.urdf"
    path.write_text(_URDF.format(p1=p1, mimic=mimic))
    with pytest.raises(KinematicsError) as err:
        urdf_chain(path, "l1", "tip", "arm")
    assert str(err.value) == f"{path}: {words} of this URDF"
    path.write_text(_URDF.format(p1="base", mimic=""))
    assert urdf_chain(path, "base", "tip", "arm") is not None
