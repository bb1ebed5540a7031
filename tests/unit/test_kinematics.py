"""Kinematics core: KDL and numpy agree, Jacobians are right, IK round-trips,
respects limits and reports unreachable targets."""
import numpy as np
import pytest

from ambots.config import load_arm_profile
from ambots.errors import KinematicsError, UnreachableError
from ambots.kinematics import DOWN, ArmKinematics, chain_from_urdf, kdl_chain
from ambots.model import arm_kinematics, arm_urdf

ARMS = ["ur10", "kinova_gen3", "panda"]


@pytest.fixture(scope="module", params=ARMS)
def arm(request):
    prof = load_arm_profile("config/arms/%s.yaml" % request.param)
    return prof, arm_kinematics(prof)


def sample(kin, n, rng):
    lo = np.where(np.isfinite(kin.lower), kin.lower, -np.pi)
    hi = np.where(np.isfinite(kin.upper), kin.upper, np.pi)
    return rng.uniform(lo, hi, (n, kin.dof))


def test_kdl_and_numpy_forward_kinematics_agree(arm):
    _, kin = arm
    Q = sample(kin, 50, np.random.default_rng(1))
    np.testing.assert_allclose(kin.fk_batch(Q), np.stack([kin.fk(q) for q in Q]), atol=1e-12)
    assert kdl_chain(kin.chain).getNrOfJoints() == kin.dof


def test_link_frames_end_at_the_tool(arm):
    _, kin = arm
    Q = sample(kin, 10, np.random.default_rng(2))
    frames = kin.link_frames(Q)
    assert frames.shape == (10, len(kin.chain.segments) + 1, 4, 4)
    np.testing.assert_allclose(frames[:, -1], kin.fk_batch(Q), atol=1e-12)
    np.testing.assert_allclose(frames[:, 0], np.broadcast_to(np.eye(4), (10, 4, 4)))


def test_jacobian_matches_finite_differences(arm):
    _, kin = arm
    Q = sample(kin, 5, np.random.default_rng(3))
    J = kin.jacobian_batch(Q)
    h = 1e-7
    for k in range(kin.dof):
        dQ = Q.copy()
        dQ[:, k] += h
        dp = (kin.fk_batch(dQ)[:, :3, 3] - kin.fk_batch(Q)[:, :3, 3]) / h
        np.testing.assert_allclose(J[:, :3, k], dp, atol=1e-5)


def test_ik_round_trip_on_1000_random_reachable_poses(arm):
    """Random configurations -> nozzle position and axis -> IK from a nearby
    seed, the turn about the nozzle axis left free: >= 99 % solved with
    position error <= 1e-5 m, inside the limits."""
    _, kin = arm
    kin = ArmKinematics(kin.chain, kin.tool_axis)           # the profile's chain, no trail
    rng = np.random.default_rng(4)
    Qt = sample(kin, 1000, rng)
    T = kin.fk_batch(Qt)
    P, A = T[:, :3, 3], T[:, :3, 2]
    seeds = np.clip(Qt + rng.uniform(-0.1, 0.1, Qt.shape), kin.lower, kin.upper)
    Q, ok, _ = kin.ik_batch(P, seeds, A)
    assert ok.mean() >= 0.99, ok.mean()
    T2 = kin.fk_batch(Q[ok])
    assert np.linalg.norm(T2[:, :3, 3] - P[ok], axis=1).max() <= 1e-5
    cosang = np.einsum("ij,ij->i", T2[:, :3, 2], A[ok])
    assert np.arccos(np.clip(cosang, -1, 1)).max() <= 1e-5
    assert kin.within_limits(Q[ok]).all()


REACH_DOWN = {"ur10": (0.30, 1.30), "kinova_gen3": (0.33, 0.78), "panda": (0.40, 0.86)}


def test_ik_keeps_the_flange_between_the_nozzle_and_the_base(arm):
    """The profiles' ``tool.turn: toward_base``: 1000 random nozzle-down
    targets 0-0.15 m above the base's floor, around the arm's front, at radii
    the arm reaches (:data:`REACH_DOWN`), solved from home: all solved, and
    the flange's origin, from a second chain that ends at the flange (no
    trail, no tool), is 0.1 m from the nozzle's vertical on the line from
    the nozzle to the base's axis, 0.2 m above the tip."""
    prof, kin = arm
    rng = np.random.default_rng(5)
    r = rng.uniform(*REACH_DOWN[prof.name], 1000)
    a = rng.uniform(-0.6, 0.6, 1000)
    P = np.column_stack([r * np.cos(a), r * np.sin(a), rng.uniform(0.0, 0.15, 1000)])
    Q, ok, _ = kin.ik_batch(P, np.asarray(prof.home), DOWN)
    assert ok.all(), P[~ok]
    T = kin.fk_batch(Q)
    np.testing.assert_allclose(T[:, :3, 3], P, atol=1e-6)
    np.testing.assert_allclose(T[:, :3, 2], np.broadcast_to(DOWN, P.shape), atol=1e-5)
    flange = ArmKinematics.from_urdf(arm_urdf(prof), tip=prof.flange_link).fk_batch(Q)[:, :3, 3]
    inward = -P[:, :2] / np.linalg.norm(P[:, :2], axis=1, keepdims=True)
    np.testing.assert_allclose(flange[:, :2] - P[:, :2], 0.1 * inward, atol=1e-5)
    np.testing.assert_allclose(flange[:, 2] - P[:, 2], 0.2, atol=1e-5)


def test_single_ik_points_the_nozzle_down(arm):
    prof, kin = arm
    home = np.asarray(prof.home)
    target = kin.fk(home)[:3, 3] + [0.05, -0.03, -0.02]
    q = kin.ik(target, home)
    T = kin.fk(q)
    np.testing.assert_allclose(T[:3, 3], target, atol=1e-6)
    np.testing.assert_allclose(T[:3, 2], DOWN, atol=1e-6)


def test_unreachable_poses_fail_clearly(arm):
    prof, kin = arm
    with pytest.raises(UnreachableError, match=r"nozzle at \(3\.0000, 0\.0000, 0\.2000\) m"):
        kin.ik([3.0, 0.0, 0.2], prof.home)
    Q, ok, err = kin.ik_batch([[0.0, 0.0, -2.0], [0.0, 5.0, 0.0]], np.asarray(prof.home))
    assert not ok.any() and (err > 0.1).all()


def test_ik_respects_joint_limits():
    """A narrowed joint makes a reachable pose unreachable; the solver fails
    rather than return a configuration outside the limits."""
    prof = load_arm_profile("config/arms/ur10.yaml")
    kin = arm_kinematics(prof)
    home = np.asarray(prof.home)
    target = kin.fk(home)[:3, 3] + [0.0, 0.25, 0.0]     # needs the shoulder pan to turn
    q = kin.ik(target, home)
    narrow = kin.chain._replace(lower=kin.lower.copy(), upper=kin.upper.copy())
    narrow.lower[0], narrow.upper[0] = home[0] - 0.01, home[0] + 0.01
    tight = ArmKinematics(narrow)
    assert abs(q[0] - home[0]) > 0.01
    with pytest.raises(UnreachableError):
        tight.ik(target, home)


def test_ik_path_along_a_line_is_continuous_and_exact(arm):
    prof, kin = arm
    home = np.asarray(prof.home)
    start = kin.fk(home)[:3, 3]
    P = start + np.linspace(0, 1, 2001)[:, None] * np.array([0.0, 0.2, -0.1])   # 0.1 mm steps
    Q, ok = kin.ik_path(P, home)
    assert ok.all()
    np.testing.assert_allclose(kin.fk_batch(Q)[:, :3, 3], P, atol=1e-6)
    assert np.abs(np.diff(Q, axis=0)).max() < 0.01


def test_ik_path_stops_at_the_first_unreachable_point(arm):
    prof, kin = arm
    home = np.asarray(prof.home)
    start = kin.fk(home)[:3, 3]
    P = start + np.linspace(0, 1, 400)[:, None] * np.array([3.0, 0.0, 0.0])   # runs out of reach
    Q, ok = kin.ik_path(P, home)
    assert ok[0] and not ok[-1]
    first_bad = np.argmin(ok)
    assert not ok[first_bad:].any()
    np.testing.assert_allclose(kin.fk_batch(Q[:first_bad])[:, :3, 3], P[:first_bad], atol=1e-6)


def test_bad_urdf_raises_typed_errors():
    with pytest.raises(KinematicsError, match="malformed URDF"):
        chain_from_urdf("<robot name='x'><link name='a'>", "a", "b")
    urdf = arm_urdf(load_arm_profile("config/arms/ur10.yaml"))
    with pytest.raises(KinematicsError, match="no tip link 'tool0'"):
        chain_from_urdf(urdf, "base_link", "tool0")
    with pytest.raises(KinematicsError, match="does not descend"):
        chain_from_urdf(urdf, "nozzle", "base_link")


def _odd_chain():
    """A chain with every kind of joint the fast paths handle differently:
    revolute about z, about a tilted axis, prismatic, and fixed links."""
    from ambots.kinematics import Chain, Segment

    from ambots.kinematics import _rodrigues

    def origin(xyz, rpy=(0.0, 0.0, 0.0)):
        T = np.eye(4)
        T[:3, :3] = np.linalg.multi_dot([_rodrigues(np.eye(3)[k], np.array([rpy[k]]))[0] for k in (2, 1, 0)])
        T[:3, 3] = xyz
        return T

    tilted = np.array([1.0, 2.0, 0.5]) / np.linalg.norm([1.0, 2.0, 0.5])
    segs = [Segment("j1", "l1", "revolute", origin((0, 0, 0.2)), np.array([0.0, 0.0, 1.0])),
            Segment("j2", "l2", "revolute", origin((0.1, 0, 0.3), (0.3, -0.2, 0.1)), tilted),
            Segment("j3", "l3", "prismatic", origin((0, 0.05, 0.2)), np.array([0.0, 1.0, 0.0])),
            Segment("f1", "l4", "fixed", origin((0.02, 0, 0.1), (0.0, 0.4, 0.0)), np.array([1.0, 0.0, 0.0])),
            Segment("j4", "l5", "continuous", origin((0, 0, 0.15)), np.array([0.0, 0.0, 1.0])),
            Segment("j5", "tool", "revolute", origin((0, 0.03, 0.1), (0.2, 0, 0)), np.array([1.0, 0.0, 0.0]))]
    inf = np.inf
    return Chain("base", "tool", segs, ["j1", "j2", "j3", "j4", "j5"], np.array([-3, -2, -0.1, -inf, -2.5]),
                 np.array([3, 2, 0.3, inf, 2.5]), np.ones(5))


@pytest.mark.parametrize("which", ARMS + ["odd"])
def test_fast_paths_agree_with_the_matrix_products(which):
    """Many poses (rotations as rows of vectors), one pose in plain floats
    and IK in pieces give what the (N, 4, 4) matrix products give, to
    rounding."""
    kin = ArmKinematics(_odd_chain()) if which == "odd" else arm_kinematics(
        load_arm_profile("config/arms/%s.yaml" % which))
    rng = np.random.default_rng(7)
    Q = sample(kin, 300, rng)
    T_mat, _, J_mat = ArmKinematics._forward(kin, Q[:kin.ROWS_FROM - 1], jacobian=True)
    T_rows, _, J_rows = kin._forward_rows(Q[:kin.ROWS_FROM - 1], jacobian=True)
    np.testing.assert_allclose(T_rows, T_mat, atol=1e-13)
    np.testing.assert_allclose(J_rows, J_mat, atol=1e-13)
    for q, T, J in zip(Q[:20], T_mat, J_mat):
        p, R, cols = kin._fk_one(list(q))
        np.testing.assert_allclose(p, T[:3, 3], atol=1e-13)
        np.testing.assert_allclose(np.reshape(R, (3, 3)), T[:3, :3], atol=1e-13)
        np.testing.assert_allclose(np.array(cols).T, J, atol=1e-13)
    # IK: one target at a time (floats) == the same targets in one batch (arrays)
    Qt = sample(kin, 40, rng)
    T = kin.fk_batch(Qt)
    targets, axes = T[:, :3, 3], T[:, :3, :3] @ kin.tool_axis
    targets[::8] += 5.0                                  # out of reach
    seeds = np.clip(Qt + rng.normal(0.0, 0.2, Qt.shape), kin.lower, kin.upper)
    Qb, okb, errb = kin.ik_batch(targets, seeds, axes)
    one = [kin.ik_batch(t[None], q, a) for t, q, a in zip(targets, seeds, axes)]
    np.testing.assert_array_equal(np.concatenate([o[1] for o in one]), okb)
    assert 20 <= okb.sum() <= 35      # (where a target is not reached, the last iterates drift apart)
    np.testing.assert_allclose(np.concatenate([o[0] for o in one])[okb], Qb[okb], atol=1e-9)
    np.testing.assert_allclose(np.concatenate([o[2] for o in one])[okb], errb[okb], atol=1e-9)
    # in pieces == at once
    big = [np.repeat(x, 3, axis=0) for x in (targets, seeds, axes)]
    chunk = kin.CHUNK
    try:
        kin.CHUNK = 7
        Qc, okc, errc = kin.ik_batch(*big)
    finally:
        kin.CHUNK = chunk
    Qa, oka, erra = kin.ik_batch(*big)
    np.testing.assert_array_equal(okc, oka)
    np.testing.assert_allclose(Qc[oka], Qa[oka], atol=1e-12)
