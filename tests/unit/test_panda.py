"""The Franka Emika Panda (7 DOF, redundant), added as data only
(``urdf/panda.xacro`` + ``config/arms/panda.yaml``): its model agrees with
the manufacturer's modified-DH table and limits, the generic IK handles its
seven joints within their limits, and it loads like any other arm."""
import xml.etree.ElementTree as ET

import numpy as np
import pytest

import robot_facts as F
from ambots.collision import ArmBody
from ambots.config import load_arm_profile
from ambots.errors import UnreachableError
from ambots.kinematics import DOWN, ArmKinematics
from ambots.model import arm_kinematics, arm_urdf

PROFILE = "config/arms/panda.yaml"


def mdh(a, alpha, d, q):
    """Modified (Craig) DH: RotX(alpha) TransX(a) RotZ(q) TransZ(d)."""
    ca, sa, cq, sq = np.cos(alpha), np.sin(alpha), np.cos(q), np.sin(q)
    return np.array([[cq, -sq, 0, a],
                     [sq * ca, cq * ca, -sa, -d * sa],
                     [sq * sa, cq * sa, ca, d * ca],
                     [0, 0, 0, 1]])


def panda_frames(q):
    """Independent forward kinematics from the published table: DH frames
    1..7, then the flange."""
    T, out = np.eye(4), []
    for qi, (a, alpha, d) in zip(q, F.PANDA_MDH):
        T = T @ mdh(a, alpha, d, qi)
        out.append(T)
    out.append(T @ mdh(*F.PANDA_FLANGE, 0.0))
    return out


@pytest.fixture(scope="module")
def prof():
    return load_arm_profile(PROFILE)


@pytest.fixture(scope="module")
def urdf(prof):
    return arm_urdf(prof)


@pytest.fixture(scope="module")
def flange(urdf):
    return ArmKinematics.from_urdf(urdf, tip="flange")


@pytest.fixture(scope="module")
def kin(prof):
    return arm_kinematics(prof)


def random_q(kin, n, rng):
    return rng.uniform(kin.lower, kin.upper, (n, kin.dof))


# ------------------------------------------------------------ kinematics
def test_flange_at_zero_is_the_table_check_value(flange):
    """q = 0 (outside the limits of joints 4 and 6, but defined): the flange
    sits at x = a3 + a4 + a6, z = d1 + d3 + d5 - d_flange, pointing down."""
    T = flange.fk(np.zeros(7))
    np.testing.assert_allclose(T[:3, 3], (0.088, 0.0, 0.926), atol=1e-9)
    np.testing.assert_allclose(T[:3, 2], (0.0, 0.0, -1.0), atol=1e-9)


def test_flange_pose_agrees_with_modified_dh_at_200_random_configurations(flange):
    Q = random_q(flange, 200, np.random.default_rng(7))
    expected = np.stack([panda_frames(q)[-1] for q in Q])
    for got in (flange.fk_batch(Q), np.stack([flange.fk(q) for q in Q])):   # numpy, KDL
        pos_err = np.linalg.norm(got[:, :3, 3] - expected[:, :3, 3], axis=1)
        # rotation angle between the two orientations: |R - R'|_F = 2 sqrt(2) sin(angle / 2)
        rot_err = 2 * np.arcsin(np.clip(np.linalg.norm(got[:, :3, :3] - expected[:, :3, :3], axis=(1, 2))
                                        / (2 * np.sqrt(2)), 0.0, 1.0))
        assert pos_err.max() <= 1e-6 and rot_err.max() <= 1e-6, (pos_err.max(), rot_err.max())
        np.testing.assert_allclose(got, expected, atol=1e-6)


def test_every_link_frame_is_its_dh_frame(urdf, flange):
    """panda_link<i> is DH frame i (as in Franka's description), not just the tip."""
    Q = random_q(flange, 20, np.random.default_rng(8))
    F_urdf = flange.link_frames(Q)
    links = [s.link for s in flange.chain.segments]
    assert links == ["panda_link%d" % i for i in range(1, 8)] + ["flange"]
    for n, q in enumerate(Q):
        np.testing.assert_allclose(F_urdf[n, 1:], np.stack(panda_frames(q)), atol=1e-9)


# ----------------------------------------------------------------- limits
def test_joint_names_limits_and_speeds_in_the_urdf_are_the_facts(prof, urdf, flange):
    robot = ET.fromstring(urdf)
    movable = [j for j in robot.iter("joint") if j.get("type") != "fixed"]
    assert [j.get("name") for j in movable] == F.PANDA_JOINTS
    for j, (lo, hi), v in zip(movable, F.PANDA_LIMITS, F.PANDA_MAX_SPEED):
        assert j.get("type") == "revolute"
        lim = j.find("limit")
        assert float(lim.get("lower")) == pytest.approx(lo, abs=1e-12)
        assert float(lim.get("upper")) == pytest.approx(hi, abs=1e-12)
        assert float(lim.get("velocity")) == pytest.approx(v, abs=1e-12)
    np.testing.assert_allclose(flange.lower, [l for l, _ in F.PANDA_LIMITS], atol=1e-12)
    np.testing.assert_allclose(flange.upper, [h for _, h in F.PANDA_LIMITS], atol=1e-12)
    np.testing.assert_allclose(flange.chain.velocity, F.PANDA_MAX_SPEED, atol=1e-12)
    assert flange.joint_names == F.PANDA_JOINTS
    assert list(prof.driver_joint_names) == F.PANDA_JOINTS
    assert prof.reach == pytest.approx(F.PANDA_REACH)


# --------------------------------------------------------------------- IK
def test_ik_round_trip_on_1000_random_reachable_poses(kin):
    """Random configurations -> nozzle position and axis -> IK from a nearby
    seed, the turn about the nozzle axis left free: >= 99 % solved to 1e-5 m
    / 1e-5 rad, inside the limits."""
    kin = ArmKinematics(kin.chain, kin.tool_axis)           # the profile's chain, no trail
    rng = np.random.default_rng(9)
    Qt = random_q(kin, 1000, rng)
    T = kin.fk_batch(Qt)
    P, A = T[:, :3, 3], T[:, :3, 2]
    seeds = np.clip(Qt + rng.uniform(-0.1, 0.1, Qt.shape), kin.lower, kin.upper)
    Q, ok, _ = kin.ik_batch(P, seeds, A)
    assert ok.mean() >= 0.99, ok.mean()
    T2 = kin.fk_batch(Q[ok])
    assert np.linalg.norm(T2[:, :3, 3] - P[ok], axis=1).max() <= 1e-5
    assert np.arccos(np.clip(np.einsum("ij,ij->i", T2[:, :3, 2], A[ok]), -1, 1)).max() <= 1e-5
    assert kin.within_limits(Q).all()          # every iterate, solved or not


def test_ik_from_home_reaches_every_nozzle_down_point_of_a_print_volume(prof, kin):
    """The job's case: nozzle straight down, anywhere in a 0.35 x 0.5 x 0.3 m
    box in front of the arm, solved from the home pose (0.40 m out: with
    the flange 0.1 m behind the nozzle, nearer is out of reach at bed level)."""
    rng = np.random.default_rng(10)
    P = np.stack([rng.uniform(0.40, 0.75, 500), rng.uniform(-0.25, 0.25, 500), rng.uniform(0.0, 0.3, 500)], 1)
    Q, ok, err = kin.ik_batch(P, np.asarray(prof.home))
    assert ok.all(), err[~ok]
    T = kin.fk_batch(Q)
    np.testing.assert_allclose(T[:, :3, 3], P, atol=1e-6)
    np.testing.assert_allclose(T[:, :3, 2], np.broadcast_to(DOWN, P.shape), atol=1e-6)
    assert kin.within_limits(Q).all()


def test_ik_never_leaves_limits_that_exclude_zero(kin):
    """Joints 4 and 6 cannot be at zero.  Seeds anywhere, inside or outside
    the limits (all zeros included), are brought inside them, and every
    answer, solved or not, stays there; what is solved is exact."""
    rng = np.random.default_rng(11)
    Qt = random_q(kin, 300, rng)
    T = kin.fk_batch(Qt)
    seeds = rng.uniform(kin.lower - 1.0, kin.upper + 1.0, Qt.shape)
    seeds[:100] = 0.0
    Q, ok, _ = kin.ik_batch(T[:, :3, 3], seeds, T[:, :3, 2])
    assert kin.within_limits(Q, tol=0.0).all()
    assert (Q[:, 3] <= F.PANDA_LIMITS[3][1]).all() and (Q[:, 5] >= F.PANDA_LIMITS[5][0]).all()
    assert ok.sum() >= 50, ok.sum()     # a local solver from random seeds: some, not all
    T2 = kin.fk_batch(Q[ok])
    assert np.linalg.norm(T2[:, :3, 3] - T[ok, :3, 3], axis=1).max() <= 1e-5


def test_ik_fails_rather_than_leave_narrowed_limits(prof, kin):
    """With every joint narrowed to +-0.01 rad around home, a point 0.1 m away
    is out of reach; the solver says so instead of leaving the limits."""
    home = np.asarray(prof.home)
    target = kin.fk(home)[:3, 3] + [0.0, 0.1, 0.0]
    q = kin.ik(target, home)                       # reachable with the real limits
    assert kin.within_limits(q).all()
    narrow = kin.chain._replace(lower=home - 0.01, upper=home + 0.01)
    tight = ArmKinematics(narrow)
    with pytest.raises(UnreachableError):
        tight.ik(target, home)
    Q, ok, _ = tight.ik_batch(target[None], home)
    assert not ok[0] and tight.within_limits(Q).all()


def test_ik_path_along_a_line_uses_all_seven_joints_continuously(prof, kin):
    home = np.asarray(prof.home)
    start = kin.fk(home)[:3, 3]
    P = start + np.linspace(0, 1, 2001)[:, None] * np.array([0.0, 0.2, -0.1])   # 0.1 mm steps
    Q, ok = kin.ik_path(P, home)
    assert ok.all() and Q.shape == (2001, 7)
    np.testing.assert_allclose(kin.fk_batch(Q)[:, :3, 3], P, atol=1e-6)
    assert np.abs(np.diff(Q, axis=0)).max() < 0.01


def _passes(kin, home, n):
    """``n`` passes of a 200 x 200 mm zigzag (5 lines, 1 mm steps), 0.12 m
    under and 0.1 m beyond the home nozzle, each from its corner and back to
    it, as the firmware follows a print (each path from the joints before):
    the joints at the corner before each pass, and the largest joint step
    between neighbouring points of any path."""
    p0 = kin.fk(home)[:3, 3]
    c = p0 + np.array([0.1, 0.0, -0.12])
    corner = c + np.array([-0.1, -0.1, 0.0])
    line = lambda a, b: np.linspace(a, b, int(np.ceil(np.linalg.norm(b - a) / 0.001)) + 1)   # 1 mm steps
    paths = [line(p0, corner)]
    for rep in range(n):
        for y in np.linspace(-0.1, 0.1, 5):
            xs = np.linspace(-0.1, 0.1, 201) * (1 if rep % 2 == 0 else -1)
            paths.append(np.column_stack([c[0] + xs, np.full(201, c[1] + y), np.full(201, c[2])]))
        paths.append(None)                       # back to the corner
    q, at, step = np.asarray(home, dtype=float), [], 0.0
    for P in paths:
        here = kin.fk(q)[:3, 3]
        P = line(here, corner) if P is None else np.vstack([line(here, P[0]), P])
        Q, ok = kin.ik_path(P, q)
        assert ok.all()
        step = max(step, float(np.abs(np.diff(Q, axis=0)).max()))
        q = Q[-1]
        if np.allclose(P[-1], corner):
            at.append(q)
    return np.array(at), corner, step


def test_ik_path_keeps_the_spare_joint_near_home_instead_of_drifting(prof, kin):
    """Each key point of a path is seeded by the one before, so a redundant
    arm drifted along its self-motion: after hours on a hex plate the Panda
    stood 2.6 rad off on joints 1 and 3.  With the home posture as ``rest``
    (:data:`ambots.kinematics.POSTURE_RAD_PER_M`) the same zigzag flown
    again and again starts every pass in the same joints, and those are the
    joints nearest home that put the nozzle there (found apart: the
    self-motion sampled by 2,400 IK solves from seeds along joints 1 and 3,
    the nearest kept); without it they wander."""
    home = np.asarray(prof.home)
    at, corner, step = _passes(kin, home, 6)
    assert np.abs(at[2:] - at[1]).max() < 0.002
    assert step < 0.01                           # 1 mm steps: no jump where the keys turn towards home
    free = ArmKinematics(kin.chain, kin.tool_axis, kin.trail)        # no rest posture: as before
    drifted, _, _ = _passes(free, home, 6)
    assert np.abs(drifted[2:] - drifted[1]).max() > 0.05       # 0.09 rad after 6 passes, growing
    S = np.tile(home, (2402, 1))
    S[:1201, 2] = S[1201:, 0] = np.linspace(-1.5, 1.5, 1201)
    Q, ok, _ = free.ik_batch(np.tile(corner, (len(S), 1)), S, DOWN)
    nearest = Q[ok][np.argmin(np.sum((Q[ok] - home) ** 2, axis=1))]
    assert ok.sum() > 1000
    np.testing.assert_allclose(at[-1], nearest, atol=0.005)


def test_ik_path_from_a_drifted_posture_returns_to_home_s_within_a_metre(prof, kin):
    """A path started in joints turned along the self-motion (the same nozzle
    pose, joint 1 0.8 rad off) turns back towards the home posture by at most
    POSTURE_RAD_PER_M a metre of path, and is there after 1.2 m."""
    from ambots.kinematics import POSTURE_RAD_PER_M
    home = np.asarray(prof.home)
    start = kin.fk(home)[:3, 3]
    seed = home.copy()
    seed[0] += 1.6
    q0 = ArmKinematics(kin.chain, kin.tool_axis, kin.trail).ik_batch(start[None], seed, DOWN)[0][0]
    assert np.abs(q0 - home).max() > 0.7                     # the same pose, other joints
    t = np.linspace(0.0, 1.0, 1201)[:, None]                 # 1.2 m back and forth along a 0.2 m line, 1 mm steps
    P = start + (1.0 - np.abs(((t * 6.0) % 2.0) - 1.0)) * np.array([0.0, 0.2, 0.0])
    Q, ok = kin.ik_path(P, q0)
    assert ok.all()
    np.testing.assert_allclose(kin.fk_batch(Q)[:, :3, 3], P, atol=1e-6)
    back, _ = kin.ik_path(np.linspace(start, start + [0, 0.05, 0], 51), home)     # from home, the same path
    end, _ = kin.ik_path(np.linspace(start, start + [0, 0.05, 0], 51), Q[-1])
    np.testing.assert_allclose(end[-1], back[-1], atol=0.005)
    # the turn is spread over the path: no joint moves faster than the task plus the posture's share
    first = np.abs(np.diff(Q[:100], axis=0)).max()
    assert first < 0.001 * (1.0 + POSTURE_RAD_PER_M) + 0.005


# ------------------------------------------------------ profile and model
def test_profile_loads_with_a_home_pointing_down_in_front(prof, kin):
    assert prof.name == "panda" and len(prof.joints) == 7 and kin.dof == 7
    assert prof.driver_command_topic == "position_joint_trajectory_controller/command"
    T = kin.fk(np.asarray(prof.home))
    assert T[0, 3] > 0.3 and abs(T[1, 3]) < 0.01 and 0.1 < T[2, 3] < 0.4   # in front, above the bed
    np.testing.assert_allclose(T[:3, 2], DOWN, atol=1e-6)
    assert prof.tool_xyz == pytest.approx((0.10, 0.0, 0.20))


def test_filament_colour_differs_from_the_other_arms(prof):
    others = [load_arm_profile("config/arms/%s.yaml" % n).colour for n in ("ur10", "kinova_gen3")]
    for c in others:
        assert np.abs(np.subtract(prof.colour[:3], c[:3])).max() > 0.3


def test_prefixed_urdf_has_every_name_prefixed(prof):
    robot = ET.fromstring(arm_urdf(prof, "panda/"))
    names = [e.get("name") for e in robot if e.tag in ("link", "joint")]
    assert len(names) == 10 + 9 and all(n.startswith("panda/") for n in names)
    kin = ArmKinematics.from_urdf(arm_urdf(prof, "panda/"), prefix="panda/")
    assert kin.joint_names == ["panda/" + n for n in F.PANDA_JOINTS]


def test_collision_capsules_cover_every_link(prof, kin):
    body = ArmBody.from_arm(prof)
    assert set(body.names) == {"base_link", "nozzle"} | {"panda_link%d" % i for i in range(1, 8)}
    # the links' bodies (Franka's capsules; the print head is the profile's tool.head,
    # checked with the other arms' in test_envelopes)
    links = body.names != "nozzle"
    assert ((body.radii[links] >= 0.025) & (body.radii[links] <= 0.09)).all()
    A, B, r = body.capsules(np.asarray(prof.home))
    assert A.shape == (1, len(body), 3)
    assert (np.minimum(A[0, :, 2], B[0, :, 2]) - r >= -1e-9).all(), "nothing below the floor at home"
    # home points the nozzle down: the head is above the tip, its lowest body 5 mm above it
    tip = kin.fk(np.asarray(prof.home))[:3, 3]
    head = ~links
    low = np.minimum(A[0, head, 2], B[0, head, 2]) - r[head]
    assert low.min() == pytest.approx(tip[2] + 0.005)
    on_axis = np.linalg.norm(A[0, head, :2] - tip[:2], axis=1) < 1e-9
    assert on_axis.any() and low[on_axis].min() == pytest.approx(tip[2] + 0.005)   # right above the tip
