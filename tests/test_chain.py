"""The general kinematic model: URDF and DH chains, trees, couplings, the planar arm as a chain,
the analytic marker Jacobian, and the calibrated URDF written back. How well NUTS's posterior
covers a simulated arm's truth, and the compliance group's held-out error on arms that sag,
are the validation studies calibration_chain_bayes and calibration_chain_compliance."""

from __future__ import annotations

import shutil
from dataclasses import replace
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bayesrob import robot as kin
from bayesrob.data.rig import Rig, default_rig_dir, dump_toml, load_rig, load_rig_toml
from bayesrob.sim.rigs import simulate_arm6_rig
from bayesrob.sim.truth import Arm6Truth, arm6_urdf_path

JUSTIN_TOML = Path(__file__).resolve().parents[1] / "examples" / "agile_justin" / "rig.toml"
# a Justin row's joint columns: the torso's three, then each arm's seven
JUSTIN_COLUMNS = ([f"torso_u{k}" for k in range(1, 4)] + [f"right_u{k}" for k in range(1, 8)]
                  + [f"left_u{k}" for k in range(1, 8)])


def _rot(axis: str, a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    m = {"x": [[1, 0, 0], [0, c, -s], [0, s, c]], "y": [[c, 0, s], [0, 1, 0], [-s, 0, c]],
         "z": [[c, -s, 0], [s, c, 0], [0, 0, 1]]}[axis]
    t = np.eye(4)
    t[:3, :3] = m
    return t


def _trans(x: float = 0.0, y: float = 0.0, z: float = 0.0) -> np.ndarray:
    t = np.eye(4)
    t[:3, 3] = x, y, z
    return t


def test_planar_arm_is_a_two_joint_chain_of_the_general_model():
    rng = np.random.default_rng(1)
    for _ in range(5):
        p = kin.ArmParams(jnp.asarray(rng.normal(0, 100, 2)), jnp.asarray(rng.uniform(50, 300, 2)),
                          jnp.asarray(rng.uniform(5e-4, 2e-3, 2)), jnp.asarray(rng.normal(0, 1, 2)))
        robot = kin.Robot({"a": kin.planar_chain("a", p)}, dim=2)
        u = rng.uniform(500, 2500, (50, 2))
        chain = np.asarray(robot.marker_points(robot.layout.nominal, "a", u))
        planar = np.asarray(kin.forward_u(p, jnp.asarray(u)))
        np.testing.assert_allclose(chain, planar, atol=1e-9)


def test_modified_and_standard_dh_follow_their_textbook_products():
    rng = np.random.default_rng(2)
    rows = rng.normal(0, 1, (5, 4)) * [100, 1, 100, 1]
    q = rng.normal(0, 1, (7, 5))
    for convention in ("modified", "standard"):
        chain = kin.dh_chain("a", rows, convention)
        robot = kin.Robot({"a": chain})
        got = np.asarray(robot.tip_transforms(robot.layout.nominal, "a", q))
        for n in range(len(q)):
            t = np.eye(4)
            for (d, theta, a, alpha), qi in zip(rows, q[n], strict=True):
                if convention == "modified":
                    t = t @ _rot("x", alpha) @ _trans(x=a) @ _rot("z", theta + qi) @ _trans(z=d)
                else:
                    t = t @ _rot("z", theta + qi) @ _trans(z=d) @ _trans(x=a) @ _rot("x", alpha)
            np.testing.assert_allclose(got[n], t, atol=1e-9)


def test_urdf_chain_follows_the_joint_origins_axes_and_folds_fixed_joints(tmp_path):
    chain = kin.urdf_chain(arm6_urdf_path(), "base_link", "tool0", "arm")
    assert chain.joint_names == ("shoulder_pan", "shoulder_lift", "elbow", "wrist_1", "wrist_2",
                                 "wrist_3")
    robot = kin.Robot({"arm": chain})
    q = np.random.default_rng(3).normal(0, 1.5, (4, 6))
    got = np.asarray(robot.tip_transforms(robot.layout.nominal, "arm", q))
    # The same product written out from the file's numbers (metres -> mm).
    origins = [((0, 0, 89), (0, 0, 0)), ((0, 136, 0), (0, np.pi / 2, 0)),
               ((0, -120, 425), (0, 0, 0)), ((0, 0, 392), (0, np.pi / 2, 0)),
               ((0, 93, 0), (0, 0, 0)), ((0, 0, 95), (0, 0, 0))]
    axes = ["z", "y", "y", "y", "z", "y"]
    for n in range(len(q)):
        t = np.eye(4)
        for ((x, y, z), (r, p, w)), ax, qi in zip(origins, axes, q[n], strict=True):
            t = t @ _trans(x, y, z) @ _rot("z", w) @ _rot("y", p) @ _rot("x", r) @ _rot(ax, qi)
        t = t @ _trans(0, 82, 0) @ _rot("x", -np.pi / 2)
        np.testing.assert_allclose(got[n], t, atol=1e-9)


def test_urdf_torque_limits_are_kept_where_every_joint_gives_one(tmp_path):
    """The stiffness prior may centre on the drives' torque limits: each movable joint's
    <limit effort>, in path order; None when any joint lacks one."""
    chain = kin.urdf_chain(arm6_urdf_path(), "base_link", "tool0", "arm")
    assert chain.source["efforts"] == [150.0, 150.0, 150.0, 28.0, 28.0, 28.0]
    text = arm6_urdf_path().read_text()
    start = text.index('<joint name="wrist_3"')
    limit = text.index("<limit", start)
    path = tmp_path / "no-effort.urdf"
    path.write_text(text[:limit] + text[text.index("/>", limit) + 2:])
    assert kin.urdf_chain(path, "base_link", "tool0", "arm").source["efforts"] is None


def test_urdf_link_masses_fold_fixed_links_and_need_every_moving_link(tmp_path,
                                                                     forearm_unweighed):
    """Each movable joint's link weighs what its <inertial> says, at its centre (mm, in the
    link's frame); a link bolted on by a fixed joint (here a 0.5 kg tool past the tool flange's
    turn) adds its weight through that joint's transform; a moving link without <inertial>
    leaves the chain unweighed (None, and which link says so), as does a mass that is not a
    number >= 0: the chain still loads, and only a fit that holds the masses refuses it."""
    chain = kin.urdf_chain(arm6_urdf_path(), "base_link", "tool0", "arm")
    m = np.array(chain.source["link_masses_kg"])
    h = np.array(chain.source["link_moments_kg_mm"])
    np.testing.assert_allclose(m, Arm6Truth().masses_kg)
    # arm6 states the simulator's point masses: each link's middle, half way to the next origin
    np.testing.assert_allclose(h, m[:, None] * 0.5 * chain.origins[1:, :3], atol=1e-9)
    text = arm6_urdf_path().read_text()
    tool = text.replace('<link name="tool0"/>', '<link name="tool0"><inertial><origin '
                        'xyz="0 0 0.02"/><mass value="0.5"/></inertial></link>')
    (tmp_path / "tool.urdf").write_text(tool)
    c = kin.urdf_chain(tmp_path / "tool.urdf", "base_link", "tool0", "arm")
    assert c.source["link_masses_kg"][-1] == pytest.approx(0.7)
    # the flange: 82 mm along y, then turned -90 deg about x, so the tool's z is the link's y
    np.testing.assert_allclose(c.source["link_moments_kg_mm"][-1],
                               h[-1] + 0.5 * np.array([0.0, 82.0 + 20.0, 0.0]), atol=1e-9)
    half = kin.urdf_chain(forearm_unweighed, "base_link", "tool0", "arm")
    assert half.source["link_masses_kg"] is None and half.source["link_moments_kg_mm"] is None
    assert half.source["unweighed"] == f"{tmp_path / 'half.urdf'}: link 'forearm_link' has no " \
                                       "<inertial>"
    # a malformed mass is only an error to a fit that holds the masses: the chain loads
    (tmp_path / "bad.urdf").write_text(text.replace('<mass value="2.3"/>',
                                                    '<mass value="-2.3"/>'))
    bad = kin.urdf_chain(tmp_path / "bad.urdf", "base_link", "tool0", "arm")
    assert bad.source["link_masses_kg"] is None
    assert "link 'forearm_link': <inertial> needs <mass value> a number >= 0" in \
        bad.source["unweighed"]


def test_compliances_fitted_under_the_described_masses_are_the_joints_own(tmp_path,
                                                                        forearm_unweighed):
    """With the links' masses held at the URDF's (the simulator's, here), the compliance
    group's fit gives each joint's own stiffness: the shoulder and elbow, whose gravity
    torques are large, within 10% of the simulator's (measured 1%); the first
    joint, whose axis is vertical, is not identified; the masses stay as described. A robot
    whose URDF does not weigh every moving link is refused by name."""
    from bayesrob.calibrate.least_squares import calibrate, described_links

    truth = Arm6Truth(seed=3, compliance=True)
    rig = load_rig(simulate_arm6_rig(tmp_path / "r", truth))
    cal = calibrate(rig, ("frames", "offsets", "geometric", "compliance"),
                          masses="description")
    lay = cal.robot.layout
    comp = lay.slices["arm", "compliance"]
    free = cal.ident.free[comp]
    assert not free[0] and free[1] and free[2]
    true_k = np.asarray(truth.stiffness_nmm_per_rad)
    print("fitted / true stiffness, joints 2-3:", 1.0 / cal.x[comp][1:3] / true_k[1:3])
    np.testing.assert_allclose(1.0 / cal.x[comp][1:3], true_k[1:3], rtol=0.10)
    links = lay.slices["arm", "links"]
    assert not cal.ident.free[links].any()
    np.testing.assert_allclose(cal.x[links].reshape(-1, 4)[:, 0], truth.masses_kg)
    assert cal.masses == "description" and cal.to_json()["masses"] == "description"
    robot = kin.Robot({"arm": kin.urdf_chain(forearm_unweighed, "base_link", "tool0",
                                             "arm")})
    with pytest.raises(ValueError, match=r"chain 'arm': its description does not give every "
                                         r"moving link a mass \(.*half.urdf: link "
                                         r"'forearm_link' has no <inertial>\)"):
        described_links(robot, robot.layout.nominal.copy())


def test_mimic_joint_is_a_coupling(tmp_path):
    text = arm6_urdf_path().read_text().replace(
        '<joint name="wrist_3" type="revolute">',
        '<joint name="wrist_3" type="revolute"><mimic joint="wrist_2" multiplier="-2" '
        'offset="0.1"/>')
    path = tmp_path / "m.urdf"
    path.write_text(text)
    chain = kin.urdf_chain(path, "base_link", "tool0", "arm")
    assert chain.n_columns == 5 and chain.coupling[5].tolist() == [0, 0, 0, 0, -2]
    free = kin.urdf_chain(arm6_urdf_path(), "base_link", "tool0", "arm")
    q5 = np.random.default_rng(4).normal(0, 1, (3, 5))
    q6 = np.column_stack([q5, -2 * q5[:, 4] + 0.1])
    a = kin.Robot({"arm": chain})
    b = kin.Robot({"arm": free})
    np.testing.assert_allclose(a.marker_points(a.layout.nominal, "arm", q5),
                               b.marker_points(b.layout.nominal, "arm", q6), atol=1e-9)


@pytest.mark.parametrize("which", ["justin-tree", "arm6"])
def test_analytic_marker_jacobian_equals_autodiff(which):
    if which == "arm6":
        robot = kin.Robot({"arm": kin.urdf_chain(arm6_urdf_path(), "base_link", "tool0", "arm")})
        arms, cols = ["arm"], 6
    else:
        robot = kin.Robot(load_rig_toml(JUSTIN_TOML)["chains"])
        arms, cols = ["right", "left"], 10
    rng = np.random.default_rng(5)
    x = robot.layout.nominal + rng.normal(0, 3, len(robot.layout.params)) * robot.layout.scales
    u = rng.normal(0, 1, (9, cols))
    for arm in arms:
        auto = jax.jacfwd(lambda v, a=arm: robot.marker_points(v, a, u))(jnp.asarray(x))
        mine = robot.marker_jacobian(jnp.asarray(x), arm, u)
        np.testing.assert_allclose(mine, auto, atol=1e-8 * float(jnp.abs(auto).max()))


@pytest.mark.parametrize("lateral", [False, True])
def test_compliant_marker_jacobian_is_autodiff_up_to_the_sags_second_order(lateral):
    """With joints giving way under gravity, the analytic Jacobian takes the sag's derivative
    in the commanded frames only (and a bend's at zero bend). Without lateral bending the
    compliance and mass columns are then exact; every column leaves out how the geometry
    moves a sag of a few mrad: within 1% of each column's largest entry at up to 3 mrad
    (measured 0.5%; 2% at 10 mrad)."""
    robot = kin.Robot(load_rig_toml(JUSTIN_TOML)["chains"], gravity=np.array([0, 0, -1.0]))
    lay = robot.layout
    sags = lay.group_mask(("compliance", "lateral"))
    rng = np.random.default_rng(5)
    # the encoder and curve terms and the play stay zero (their columns are exact: the test
    # above; the play's: the test below) and take no draw, so the parameters drawn are those
    # this tolerance was measured on
    x = lay.nominal.copy()
    drawn = ~lay.group_mask(("encoder", "backlash", "servo_curve"))
    x[drawn] += rng.normal(0, 3, drawn.sum()) * lay.scales[drawn] * ~sags[drawn]
    joint = np.array([p.name.endswith(".compliance") for p in lay.params])
    x[joint] = rng.uniform(0, 5e-8, joint.sum())  # rad per N mm
    if lateral:
        bending = lay.group_mask(("lateral",))
        x[bending] = rng.uniform(0, 2e-8, bending.sum())
    u = rng.normal(0, 1, (9, 10))
    for arm in ("right", "left"):
        defl, bend = robot.sag(jnp.asarray(x), arm, u)
        assert 5e-4 < float(jnp.abs(defl).max()) < 3e-3
        assert (float(jnp.abs(bend).max()) > 5e-4) == lateral, float(jnp.abs(bend).max())
        assert float(jnp.abs(bend).max()) < 3e-3
        auto = np.asarray(jax.jacfwd(lambda v, a=arm: robot.marker_points(v, a, u))(
            jnp.asarray(x)))
        mine = np.asarray(robot.marker_jacobian(jnp.asarray(x), arm, u))
        # a column zero by the geometry (a first moment along gravity) is rounding in one
        # and zero in the other: judged against 1e-9 mm per typical step of its parameter
        scale = np.maximum(np.abs(auto).max(axis=(0, 1)), 1e-9 / lay.scales)
        rel = np.abs(mine - auto).max(axis=(0, 1)) / scale
        if not lateral:
            assert rel[sags].max() < 1e-6
        assert rel.max() < 0.01, lay.names[int(rel.argmax())]


@pytest.mark.parametrize("sag_steps,approach", [(1, False), (3, True)])
def test_sags_derivative_written_out_is_forward_mode_autodiff(tmp_path, sag_steps, approach):
    """The analytic Jacobian's sag part (how the masses, first moments, compliances, lateral
    compliances and play move the marker through the deflections and bending), written out
    from the torques' linearity, is ``jax.jacfwd`` of the sag in the same frames contracted
    with the marker's derivatives by the joint values and bends (random weights here): on
    the two-handed rig (the other arm hanging off the torso) and the planar default rig,
    every parameter non-zero (some deflections within the play's smooth step, so its slope
    counts). With recorded approach sides (random +1, -1, 0 per joint and row) the play's side
    and each chain's stick deflection enter too. Both are exact; the sums along the chain are
    taken in another order: 1e-10 of each column's largest entry (measured 6e-13), or of 1e-9
    of the largest entry anywhere where that is larger."""
    from bayesrob.calibrate import least_squares

    rng = np.random.default_rng(21)
    for rig in (_two_handed_rig(tmp_path, rng), load_rig(default_rig_dir())):
        robot = least_squares.with_gravity(rig, sag_steps)
        lay = robot.layout
        # the curve terms (last in the vector) stay zero: their columns are exact (the test
        # above), and the draws are those this tolerance was measured on
        x = lay.nominal.copy()
        drawn = ~lay.group_mask(("servo_curve",))
        x[drawn] += rng.normal(0, 1, drawn.sum()) * lay.scales[drawn]
        joint = np.array([p.name.endswith(".compliance") for p in lay.params])
        # compliances over four decades: some deflections within the play's step
        x[joint] = 10 ** rng.uniform(-11, -7, joint.sum())
        lateral, play = lay.group_mask(("lateral",)), lay.group_mask(("backlash",))
        x[lateral] = rng.uniform(0, 3e-8, lateral.sum())
        x[play] = rng.uniform(0, 1e-3, play.sum())
        x = jnp.asarray(x)
        idx = np.flatnonzero(lay.group_mask(kin.SAG_GROUPS))
        for arm in robot.measured_arms():
            u = jnp.asarray(rig.rows(arm, "train")[0])
            frames = robot._sag_frames(x, arm, u, least_squares.side_rows(rig, robot, arm,
                                                                        "train"))
            defl = np.asarray(robot._sag_at(x.at[np.flatnonzero(play)].set(0.0), arm,
                                            *frames)[0])
            assert ((np.abs(defl) > 0) & (np.abs(defl) < 2 * kin.PLAY_SIDE_RAD)).any()
            n_e, n = frames[0].shape[:2]
            sides = (jnp.asarray(rng.choice([-1.0, 0.0, 1.0], size=(n_e, n))) if approach
                     else None)
            d_defl, d_bend = jax.jacfwd(lambda v, r=robot, x=x, i=idx, a=arm, f=frames,
                                        s=sides: r._sag_at(x.at[i].set(v), a, *f, s))(x[idx])
            w_q = jnp.asarray(rng.normal(size=(n_e, n, 3)))
            w_phi = jnp.asarray(rng.normal(size=(n_e, n, 3, 3)))
            auto = np.asarray(jnp.einsum("eni,nec->nic", w_q, d_defl)
                              + jnp.einsum("enki,nekc->nic", w_phi, d_bend))
            mine = np.asarray(robot._sag_marker_jacobian(x, arm, *frames, idx, w_q, w_phi,
                                                         robot._torques(x, arm, *frames),
                                                         sides))
            stick = np.array([lay.params[i].name.endswith(".stick") for i in idx])
            assert stick.any()
            assert (np.abs(auto[..., stick]).max() > 0) == approach
            assert mine.shape == auto.shape == (n, 3, len(idx))
            auto, mine = auto.reshape(-1, len(idx)), mine.reshape(-1, len(idx))
            assert np.abs(auto).max() > 0
            # the play's slope 1 - tanh^2 rounds at 1e-16 where a joint sits deep on one side:
            # a stick column (measured 1e-6 against 5e4) is judged against 1e-9 of the largest
            scale = np.maximum(np.abs(auto).max(axis=0), 1e-9 * np.abs(auto).max())
            assert (np.abs(mine - auto).max(axis=0) / scale).max() < 1e-10


def test_sag_steps_iterate_the_torques_to_equilibrium():
    """``sag_steps`` takes the gravity torques again at the pose the last step sagged into.
    With about 20 mrad of sag (Justin's robot, compliances drawn large) each step shrinks the
    change at least tenfold, six steps are a fixed point (the torques at the sagged pose give
    the same sag to 1e-9 rad) and differ from one step by more than 1e-5 rad; the unrolled
    loop differentiates in reverse mode (NUTS through a sagging chain) as in forward mode
    and as finite differences, to 1e-6 relative (central differences at 1e-10 rad per N mm
    are good to about 1e-8 here)."""
    from dataclasses import replace

    base = kin.Robot(load_rig_toml(JUSTIN_TOML)["chains"], gravity=np.array([0, 0, -1.0]))
    lay = base.layout
    rng = np.random.default_rng(5)
    x = lay.nominal.copy()
    joint = np.array([p.name.endswith(".compliance") for p in lay.params])
    x[joint] = rng.uniform(0, 3e-7, joint.sum())
    x = jnp.asarray(x)
    u = rng.normal(0, 1, (5, 10))
    robots = {k: replace(base, sag_steps=k) for k in range(1, 7)}
    sagged = {k: r.sag(x, "right", u) for k, r in robots.items()}
    sags = {k: np.asarray(s[0]) for k, s in sagged.items()}
    assert 0.01 < np.abs(sags[1]).max() < 0.05
    change = [np.abs(sags[k + 1] - sags[k]).max() for k in range(1, 6)]
    assert change[0] > 1e-5
    assert all(b < 0.1 * a for a, b in zip(change[:3], change[1:4], strict=True)), change
    six = robots[6]
    defl, bend = sagged[6]  # six.sag(x, "right", u), taken once
    again, _ = six._sag_at(x, "right", *six.element_frames(x, "right", u, defl, bend))
    assert float(jnp.abs(again - defl).max()) < 1e-9

    three = replace(base, sag_steps=3)

    def total(v):
        return three.marker_points(v, "right", u).sum()

    rev = np.asarray(jax.grad(total)(x))
    fwd = np.asarray(jax.jacfwd(total)(x))
    cols = np.flatnonzero(joint)[1:6]
    fd = np.array([(total(x.at[k].add(1e-10)) - total(x.at[k].add(-1e-10))) / 2e-10
                   for k in cols])
    np.testing.assert_allclose(rev, fwd, rtol=1e-10, atol=1e-6)
    np.testing.assert_allclose(rev[cols], fd, rtol=1e-6)


def test_play_is_taken_on_the_side_each_joint_gives_way_to():
    """With ``backlash`` each joint moves by its half play towards its gravity deflection:
    nothing while no compliance is fitted (the side is unknown), p tanh(defl / 0.1 mrad)
    with one; its Jacobian columns are exact where the compliance's are (no lateral bending:
    the test above), to 1e-6 of each column's largest entry."""
    robot = kin.Robot(load_rig_toml(JUSTIN_TOML)["chains"], gravity=np.array([0, 0, -1.0]))
    lay = robot.layout
    rng = np.random.default_rng(8)
    u = rng.normal(0, 1, (9, 10))
    play = lay.group_mask(("backlash",))
    x = lay.nominal.copy()
    x[play] = rng.uniform(5e-4, 2e-3, play.sum())
    stiff, _ = robot.sag(jnp.asarray(x), "right", u)
    assert float(jnp.abs(stiff).max()) == 0.0  # no compliance: no side, no play
    joint = np.array([p.name.endswith(".compliance") for p in lay.params])
    x[joint] = rng.uniform(0, 5e-8, joint.sum())
    with_play, _ = robot.sag(jnp.asarray(x), "right", u)
    x0 = x.copy()
    x0[play] = 0.0
    without, _ = robot.sag(jnp.asarray(x0), "right", u)
    # each element's half play (the tools' index points past x: no play)
    half = np.append(x, 0.0)[robot._elements("right")["play_idx"]]
    without = np.asarray(without)
    extra = np.asarray(with_play) - without
    np.testing.assert_allclose(extra, half * np.tanh(without / kin.PLAY_SIDE_RAD), atol=1e-12)
    clear = np.abs(without) > 3e-4
    assert clear.sum() > 20 and np.all(np.sign(extra[clear]) == np.sign(without[clear]))
    auto = np.asarray(jax.jacfwd(lambda v: robot.marker_points(v, "right", u))(jnp.asarray(x)))
    mine = np.asarray(robot.marker_jacobian(jnp.asarray(x), "right", u))
    cols = lay.group_mask(("backlash", "compliance"))
    # a column zero by the geometry: judged against 1e-9 mm per typical step (test above)
    scale = np.maximum(np.abs(auto).max(axis=(0, 1)), 1e-9 / lay.scales)
    assert (np.abs(mine - auto).max(axis=(0, 1)) / scale)[cols].max() < 1e-6


def test_recorded_approach_holds_a_joint_on_its_side_below_the_stick_deflection():
    """Where the rows record each joint's approach side, friction holds the joint there
    unless its gravity deflection is larger than its chain's stick deflection: the play's side
    is tanh((deflection + stick * approach) / 0.1 mrad), so joints deflected less than the
    stick (by 0.5 mrad, five smooth-step widths) rest on the approach side and joints
    deflected more on the gravity side; rows with side 0 (unknown) are as without the record."""
    robot = kin.Robot(load_rig_toml(JUSTIN_TOML)["chains"], gravity=np.array([0, 0, -1.0]))
    lay = robot.layout
    rng = np.random.default_rng(9)
    u = rng.normal(0, 1, (40, 10))
    play = np.array([p.name.endswith(".play") for p in lay.params])
    stick = np.array([p.name.endswith(".stick") for p in lay.params])
    x = lay.nominal.copy()
    x[play] = 1e-3
    x[stick] = 2e-3
    joint = np.array([p.name.endswith(".compliance") for p in lay.params])
    x[joint] = rng.uniform(0, 5e-7, joint.sum())  # deflections of 0-10 mrad
    x0 = x.copy()
    x0[play] = 0.0
    without = np.asarray(robot.sag(jnp.asarray(x0), "right", u)[0])
    unknown = np.asarray(robot.sag(jnp.asarray(x), "right", u)[0])
    a = rng.choice([-1.0, 0.0, 1.0], size=(40, 10))
    side = {kin.APPROACH: jnp.asarray(a)}
    extra = np.asarray(robot.sag(jnp.asarray(x), "right", u, side)[0]) - without
    el = robot._elements("right")
    on = a[:, np.minimum(el["q_idx"], 9)] * (el["q_idx"] < 10)  # per element, tools 0
    known = on != 0
    held = known & (np.abs(without) < 1.5e-3)
    pulled = known & (np.abs(without) > 2.5e-3)
    assert held.sum() > 20 and pulled.sum() > 20
    assert np.all(np.sign(extra[held]) == on[held])
    assert np.all(np.sign(extra[pulled]) == np.sign(without[pulled]))
    np.testing.assert_array_equal(extra[~known] + without[~known], unknown[~known])


def test_a_shared_torso_bends_under_both_arms_whichever_hand_is_measured():
    """Given the other arm's pose, the torso joints' deflections are the same from either
    hand's path (both arms weigh on them); without it, each hand sees only its own arm."""
    robot = kin.Robot(load_rig_toml(JUSTIN_TOML)["chains"], gravity=np.array([0, 0, -1.0]))
    lay = robot.layout
    x = lay.nominal.copy()
    x[[p.name.endswith(".compliance") for p in lay.params]] = 1e-7
    rng = np.random.default_rng(2)
    torso, right, left = (rng.uniform(-1, 1, (5, n)) for n in (3, 7, 7))
    u = {"right": np.hstack([torso, right]), "left": np.hstack([torso, left])}
    n_torso = robot.chains["torso"].n_joints
    seen = {}
    for arm, other in (("right", "left"), ("left", "right")):
        alone = np.asarray(robot.deflections(x, arm, u[arm]))[:, :n_torso]
        both = np.asarray(robot.deflections(x, arm, u[arm], {other: jnp.asarray(u[other])}))
        seen[arm] = (alone, both[:, :n_torso])
        # the arm's own joints carry only what hangs beyond them
        np.testing.assert_allclose(both[:, n_torso + 1:],
                                   np.asarray(robot.deflections(x, arm, u[arm]))[:, n_torso + 1:])
    np.testing.assert_allclose(seen["right"][1], seen["left"][1], rtol=1e-9, atol=1e-15)
    assert np.abs(seen["right"][0] - seen["left"][0]).max() > 1e-4


def test_justin_tree_shares_the_torso_and_couples_its_fourth_joint():
    robot = kin.Robot(load_rig_toml(JUSTIN_TOML)["chains"])
    assert [c.name for c in robot.path("left")] == ["torso", "left"]
    assert robot.columns("right")[:3] == ["torso_u1", "torso_u2", "torso_u3"]
    q = jnp.asarray([[0.3, -0.4, 0.9]])
    torso = robot.chains["torso"]
    values = np.asarray(robot.joint_values(robot.layout.nominal, torso, q))
    np.testing.assert_allclose(values, [[0.3, -0.4, 0.9, -0.5]])
    # a torso parameter moves both hands, an arm's parameter only its own
    names = robot.layout.names
    for arm, other in (("right", "left"), ("left", "right")):
        jac = np.asarray(robot.marker_jacobian(robot.layout.nominal, arm,
                                               np.zeros((1, 10))))[0]
        assert np.abs(jac[:, names.index("torso.j2.offset")]).max() > 1
        assert np.abs(jac[:, names.index(f"{other}.j2.offset")]).max() == 0


@pytest.fixture(scope="module")
def arm6_rig(tmp_path_factory):
    return simulate_arm6_rig(tmp_path_factory.mktemp("arm6"), Arm6Truth(seed=11))


def test_geometric_calibration_reaches_the_noise_floor_on_new_poses(arm6_rig):
    from bayesrob.calibrate.least_squares import calibrate
    from bayesrob.sim.truth import load_true_params

    rig = load_rig(arm6_rig)
    truth = load_true_params(arm6_rig)
    x_true = np.array([truth[n] for n in rig.robot.layout.names])
    cal = calibrate(rig, ("frames", "geometric"))
    for s in ("validation", "holdout"):
        u, obs = rig.rows("arm", s)
        floor = np.linalg.norm(np.asarray(rig.robot.marker_points(x_true, "arm", u)) - obs,
                               axis=1).mean()
        # the floor is what noise alone leaves with the true geometry; 60 fitted numbers from
        # 240 coordinates inflate held-out errors by about sqrt(1 + 60/240) at most
        assert cal.errors[s]["all"]["mean_mm"] <= 1.3 * floor, (s, floor)
    frames_only = calibrate(rig, ("frames",))
    assert frames_only.errors["validation"]["all"]["mean_mm"] > 5 * floor


def test_rank_analysis_names_what_the_rows_cannot_tell_apart(arm6_rig):
    from bayesrob.calibrate.least_squares import calibrate

    cal = calibrate(load_rig(arm6_rig), ("frames", "offsets", "geometric"))
    fixed = {u["name"]: u["explained_by"] for u in cal.ident.unidentifiable}
    # a turn of the base about z is the instrument's own turn about its z
    assert fixed["arm.shoulder_pan.origin.rz"] == pytest.approx(
        {"arm.instrument.rz": 1.0}, abs=1e-6)
    # the pan joint's zero offset is not: a frames-first analysis keeps the instrument's
    assert "arm.shoulder_pan.offset" in fixed
    # the tool flange's shift is the marker's
    assert fixed["arm.tool.origin.x"]["arm.marker.x"] == pytest.approx(1.0, abs=1e-6)
    assert not np.isnan(cal.se[cal.ident.free]).any()


def test_calibrated_urdf_loads_back_as_the_same_robot(arm6_rig, tmp_path):
    from bayesrob.calibrate.least_squares import calibrate, calibrated_rig_document

    rig = load_rig(arm6_rig)
    cal = calibrate(rig, ("frames", "offsets", "geometric", "servo"))
    out = tmp_path / "back"
    out.mkdir()
    kin.write_urdf(rig.robot, cal.x, out / "cal.urdf")
    (out / "rig.toml").write_text(dump_toml(calibrated_rig_document(rig, cal, "cal.urdf")))
    shutil.copy(arm6_rig / "measurements.csv", out)
    back = load_rig(out)
    u, _ = rig.rows("arm", "validation")
    np.testing.assert_allclose(back.robot.marker_points(back.robot.layout.nominal, "arm", u),
                               rig.robot.marker_points(cal.x, "arm", u), atol=1e-6)
    # the URDF kept what calibration does not touch
    assert "<limit" in (out / "cal.urdf").read_text()


def test_dh_tree_writes_a_urdf_that_loads_back(tmp_path):
    chains = load_rig_toml(JUSTIN_TOML)["chains"]
    robot = kin.Robot(chains)
    rng = np.random.default_rng(6)
    # a URDF holds geometry: an encoder's eccentricity, a curved command map or a joint's play
    # has no place in it (calibrate says so)
    x = robot.layout.nominal + rng.normal(0, 2, len(robot.layout.params)) * robot.layout.scales \
        * ~robot.layout.group_mask(("encoder", "backlash", "servo_curve"))
    calibrated = kin.write_urdf(robot, x, tmp_path / "j.urdf")
    keys = kin.urdf.generated_arm_keys(calibrated)
    rebuilt = {}
    for name, c in calibrated.chains.items():
        chain = kin.urdf_chain(tmp_path / "j.urdf", keys[name]["root"], keys[name]["tip"], name,
                               marker=c.marker, mount=c.mount, instrument=c.instrument)
        rebuilt[name] = replace(chain, coupling=c.coupling, gain=c.gain, offset=c.offset)
    back = kin.Robot(rebuilt)
    u = rng.normal(0, 1, (6, 10))
    for arm in ("right", "left"):
        np.testing.assert_allclose(back.marker_points(back.layout.nominal, arm, u),
                                   robot.marker_points(x, arm, u), atol=1e-6)


def test_chain_path_calibrates_the_planar_default_rig_like_the_planar_fit():
    """The planar arm as an instance of the general model: fitting every group of its chain
    (the rank analysis leaves exactly the planar arm's eight freedoms) predicts what the
    eight-parameter fit predicts."""
    from bayesrob.calibrate.arms import calibrate_arms
    from bayesrob.calibrate.least_squares import calibrate

    rig = load_rig(default_rig_dir())
    planar = calibrate_arms(rig)
    cal = calibrate(rig)
    assert cal.ident.free.sum() == 8 * len(rig.arms)
    for arm in rig.arms:
        u, _ = rig.rows(arm, "validation")
        np.testing.assert_allclose(rig.robot.marker_points(cal.x, arm, u),
                                   planar[arm].arm.forward_u(u), atol=1e-6)


def test_bayesian_chain_priors_are_proper_and_sag_groups_are_refused(arm6_rig):
    """Every group NUTS samples has a proper prior (the encoder's sinusoids had sd 0 from a
    nominal of 0, and the fit failed on numpyro's scale check); the groups gravity's torques
    drive are refused with one line before any fitting, as NUTS did not mix over them."""
    from bayesrob.calibrate.bayes import Priors, calibrate_bayes

    rig = load_rig(arm6_rig)
    layout = rig.robot.layout
    sd = Priors().sd(layout)
    sampled = ~layout.group_mask(kin.SAG_GROUPS)
    assert np.all(np.isfinite(sd[sampled]) & (sd[sampled] > 0))
    encoder = layout.group_mask(("encoder",))
    assert np.allclose(sd[encoder], 10 * layout.scales[encoder])
    for group in kin.SAG_GROUPS:
        with pytest.raises(ValueError, match=f"does not sample {group} .*least-squares"):
            calibrate_bayes(rig, ("frames", "geometric", group))


def test_calibrations_with_gravity_share_one_robot_and_its_compiled_fits(arm6_rig,
                                                                         monkeypatch):
    """A diagnosis calibrates one rig many times with joints giving way under gravity: every
    such fit of the rig (and of a copy of it with other sets, as the diagnosis's selection
    split is) uses an equal robot, so the residuals and Jacobians traced for the first fit
    serve the next of the same rows, not traced once per fit (the split's fewer train rows
    are new shapes, traced once)."""
    from bayesrob.calibrate import least_squares

    rig = load_rig(arm6_rig)
    traced = []
    for name in ("marker_points", "marker_jacobian"):
        real = getattr(kin.Robot, name)
        monkeypatch.setattr(kin.Robot, name, lambda self, *a, _real=real, **k: (
            traced.append(1), _real(self, *a, **k))[1])
    jax.clear_caches()  # programs an earlier test traced for an equal robot would serve here
    a = least_squares.calibrate(rig, ("frames", "compliance"), polish=False)
    n_first = len(traced)
    b = least_squares.calibrate(rig, ("frames", "geometric", "compliance"), polish=False)
    assert n_first > 0 and len(traced) == n_first
    sets = rig.measurements.set.copy()
    sets[np.flatnonzero(sets == "train")[:5]] = "selection"
    split = replace(rig, measurements=replace(rig.measurements, set=sets))
    c = least_squares.calibrate(split, ("frames", "lateral"), polish=False)
    assert a.robot == b.robot == c.robot and a.robot.gravity is not None


def test_lateral_compliances_carry_a_zero_centred_prior(arm6_rig, monkeypatch):
    """Bending across the axes is penalised towards zero (least_squares.LATERAL_PRIOR_MM): the
    penalty rows exist exactly for the lateral parameters and only when ``lateral`` is fitted,
    and on a rig with no bending (the simulator's arm6) the prior's fit holds the lateral
    compliances at a fraction of what the same fit without it leaves (noise fitted)."""
    from bayesrob.calibrate import least_squares

    rig = load_rig(arm6_rig)
    layout = rig.robot.layout
    lateral = layout.group_mask(("lateral",))
    pen = least_squares.prior_penalty(layout, ("frames", "geometric", "lateral"))
    assert np.all(pen[~lateral] == 0) and np.allclose(
        pen[lateral], least_squares.LATERAL_PRIOR_MM / layout.scales[lateral])
    assert not least_squares.prior_penalty(layout, ("frames", "compliance")).any()
    groups = ("frames", "compliance", "lateral")
    with_prior = least_squares.calibrate(rig, groups, polish=False)
    assert with_prior.to_json()["lateral_prior_mm"] == least_squares.LATERAL_PRIOR_MM
    monkeypatch.setattr(least_squares, "LATERAL_PRIOR_MM", 0.0)
    without = least_squares.calibrate(rig, groups, polish=False)
    size = [float(np.linalg.norm(c.x[lateral] / layout.scales[lateral]))
            for c in (with_prior, without)]
    # measured: 0.02 scales with the prior, 62 without (free masses let noise and the joint
    # compliances' share wander into them); a tenth leaves room for solver paths
    assert size[0] < 0.1 * size[1], size
    # the prior's information narrows the lateral standard errors
    assert np.nanmax(with_prior.se[lateral]) < np.nanmax(without.se[lateral])


def _two_handed_rig(tmp_path: Path, rng: np.random.Generator) -> Rig:
    """Justin's robot with seven train rows per hand, each row carrying the other arm's
    columns (the side rows that bend the shared torso), asserted present: the checks that
    use it are void without them."""
    shutil.copy(JUSTIN_TOML, tmp_path / "rig.toml")
    lines = ["config,set," + ",".join(JUSTIN_COLUMNS) + ",x,y,z"]
    for hand in ("right", "left"):
        for pose in rng.uniform(-1, 1, (7, 17)):
            lines.append(f"{hand},train," + ",".join(f"{v:.6f}" for v in pose) + ",1,2,3")
    (tmp_path / "measurements.csv").write_text("\n".join(lines) + "\n")
    rig = load_rig(tmp_path, min_train_rows=0)
    assert rig.side_rows("right", "train") is not None
    assert rig.side_rows("left", "train") is not None
    return rig


def _exact_against_forward_mode(rig, rng, compliance: float, picked=()):
    """The fit's exact Jacobian at a random point (three steps of the torques, every kind of
    parameter moved), on 40 columns in random order with ``picked`` among them, beside
    forward-mode autodiff of the whole residual vector: largest error per column over the
    column's largest entry (or 1e-12 of the whole Jacobian's, where that is larger)."""
    from bayesrob.calibrate import least_squares

    robot = least_squares.with_gravity(rig, 3)
    lay = robot.layout
    x = lay.nominal + rng.normal(0, 1, lay.nominal.size) * lay.scales
    joint = np.array([p.name.endswith(".compliance") for p in lay.params])
    x[joint] = rng.uniform(0, compliance, joint.sum())
    bending = lay.group_mask(("lateral",))
    x[bending] = rng.uniform(0, 0.3 * compliance, bending.sum())
    res, _, n_res, exact = least_squares.residual_function(
        robot, least_squares.set_rows(rig, robot, "train"))
    picked = list(picked)
    rest = rng.permutation(np.setdiff1d(np.arange(lay.nominal.size), picked))
    idx = rng.permutation(np.concatenate([picked, rest[: 40 - len(picked)]]).astype(int))
    # forward mode on the 40 columns alone (a pushforward per column), not the whole Jacobian
    tangents = jnp.eye(lay.nominal.size)[idx]
    auto = np.asarray(jax.vmap(lambda v: jax.jvp(res, (jnp.asarray(x),), (v,))[1],
                               out_axes=1)(tangents))
    mine = np.asarray(exact(jnp.asarray(x), idx))
    assert mine.shape == (n_res, 40) and np.abs(auto).max() > 0
    # a column the markers do not depend on (a planar marker's z) is zero in one and rounding
    # in the other: measured against the whole Jacobian's largest entry there
    scale = np.maximum(np.abs(auto).max(axis=0), 1e-12 * np.abs(auto).max())
    return float((np.abs(mine - auto).max(axis=0) / scale).max())


def test_exact_jacobian_of_the_fits_is_forward_mode_autodiff(tmp_path):
    """The polish's exact Jacobian (reverse mode, row by row) is forward-mode autodiff of the
    whole residual vector: on a two-handed rig whose rows carry the other arm (the side rows
    that bend the torso; play columns among those checked) and on the planar default rig (no
    side rows, two coordinates per marker). Both are exact, so they agree to rounding (1e-9
    of each column's largest entry; 1e-15 measured on Justin's model at its data)."""
    rng = np.random.default_rng(8)
    rig = _two_handed_rig(tmp_path, rng)
    play = np.flatnonzero(rig.robot.layout.group_mask(("backlash",)))[:4]
    assert len(play) == 4
    assert _exact_against_forward_mode(rig, rng, 1e-7, play) < 1e-9
    planar = load_rig(default_rig_dir())
    assert planar.robot.dim == 2 and planar.side_rows("top", "train") is None
    assert _exact_against_forward_mode(planar, rng, 1e-6) < 1e-9


def test_rows_may_carry_the_rest_of_the_pose(tmp_path):
    """A hand's row may also carry the other arm's columns (read as the rest of the pose);
    side rows are given only when every row of the arm and set carries them."""
    shutil.copy(JUSTIN_TOML, tmp_path / "rig.toml")
    pose = ",".join(["0.1"] * 17)
    lines = ["config,set," + ",".join(JUSTIN_COLUMNS) + ",x,y,z"]
    lines += [f"right,train,{pose},1,2,3"] * 2 + [f"left,train,{pose},1,2,3"]
    lines += ["left,train," + ",".join(["0.1"] * 3 + [""] * 7 + ["0.1"] * 7) + ",1,2,3"]
    lines += ["right,train,0.1,0.1,0.1," + ",".join(["0.1"] * 7 + [""] * 7) + ",1,2,3"]
    (tmp_path / "measurements.csv").write_text("\n".join(lines) + "\n")
    rig = load_rig(tmp_path, min_train_rows=0)
    assert rig.side_rows("right", "train") is None  # one right row lacks the left arm
    assert rig.side_rows("left", "train") is None  # and one left row the right arm
    del lines[-2:]
    (tmp_path / "measurements.csv").write_text("\n".join(lines) + "\n")
    rig = load_rig(tmp_path, min_train_rows=0)
    side = rig.side_rows("right", "train")
    assert set(side) == {"left"} and side["left"].shape == (2, 10)
    assert rig.side_rows("left", "train")["right"].shape == (1, 10)
    assert rig.rows("right", "train")[0].shape == (2, 10)


def test_lateral_compliance_alone_fits_the_links_masses(arm6_rig):
    """The lateral compliances bend the joints under the same unknown gravity torques as the
    joint compliances, so fitted without them they still free the links' masses and first
    moments (the compliance group's columns), as far as the rank analysis sees them: not the
    layout's guessed masses. With ``masses="description"`` they stay held."""
    from bayesrob.calibrate import least_squares

    rig = load_rig(arm6_rig)
    cal = least_squares.calibrate(rig, ("frames", "geometric", "lateral"), polish=False)
    links = least_squares.link_mask(cal.robot.layout)
    assert links.sum() == 4 * 6
    assert cal.ident.free[links].any()
    assert np.any(cal.x[links] != cal.robot.layout.nominal[links])
    assert not cal.ident.free[cal.robot.layout.group_mask(("compliance",)) & ~links].any()
    held = least_squares.calibrate(rig, ("frames", "geometric", "lateral"), polish=False,
                                       masses="description")
    assert not held.ident.free[links].any()
