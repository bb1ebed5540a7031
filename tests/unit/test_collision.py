"""Capsule collision model: segment distances against brute force, capsules
against the URDF cylinders (independent parser and forward kinematics),
arm-arm, arm-bed and arm-part clearances in the default cell, seam zone."""
import io

import numpy as np
import pytest
import yourdfpy

import robot_facts as F
from ambots.collision import (ArmBody, bed_clearance, box_clearance, capsule_distances, clearance_between,
                              part_clearance, seam_zone, seam_zone_mm, segment_distance)
from ambots.config import default_cell_path, load_cell
from ambots.model import arm_urdf
from ambots.workspace import down_in_base, world_to_base


@pytest.fixture(scope="module")
def cell():
    return load_cell(default_cell_path())


@pytest.fixture(scope="module")
def bodies(cell):
    return {a.name: ArmBody.from_arm(a) for a in cell.arms}


def bed_to_world(cell, p):
    T = cell.bed.pose
    return np.asarray(p, dtype=float) @ T[:3, :3].T + T[:3, 3]


def solve(cell, arm, body, bed_pts):
    """Nozzle-down IK from home at bed-frame points (M, 3); every one must solve."""
    Q, ok, _ = body.kin.ik_batch(world_to_base(arm, bed_to_world(cell, bed_pts)),
                                 np.asarray(arm.profile.home), down_in_base(arm))
    assert ok.all(), "test points must be reachable"
    return Q


def seam_normal(cell):
    """Unit vector (bed xy) from the Kinova's base towards the UR10's."""
    inv = np.linalg.inv(cell.bed.pose)
    a, b = (inv[:3, :3] @ np.asarray(arm.base_xyz) + inv[:3, 3] for arm in cell.arms)
    d = (b - a)[:2]
    return d / np.linalg.norm(d)


# ------------------------------------------------------------ segments
def brute_force(p0, p1, q0, q1, n=201):
    """(coarse grid minimum, refined minimum, coarse error bound) of the
    distance between sampled points of two segments."""
    def grid(s_lo, s_hi, t_lo, t_hi):
        s = np.linspace(s_lo, s_hi, n)[:, None, None]
        t = np.linspace(t_lo, t_hi, n)[None, :, None]
        d = np.linalg.norm(p0 + s * (p1 - p0) - q0 - t * (q1 - q0), axis=-1)
        i, j = np.unravel_index(np.argmin(d), d.shape)
        return d[i, j], s[i, 0, 0], t[0, j, 0]
    coarse, s, t = grid(0, 1, 0, 1)
    h = 1.0 / (n - 1)
    fine, _, _ = grid(max(0, s - h), min(1, s + h), max(0, t - h), min(1, t + h))
    bound = (np.linalg.norm(p1 - p0) + np.linalg.norm(q1 - q0)) * h / 2
    return coarse, min(fine, coarse), bound


def random_segment_pairs(rng, n):
    pairs = []
    for k in range(n):
        p0, p1, q0, q1 = rng.normal(size=(4, 3))
        kind = k % 6
        if kind == 1:                       # parallel, offset
            q0 = p0 + rng.normal(size=3) * 0.3
            q1 = q0 + (p1 - p0) * rng.uniform(-2, 2)
        elif kind == 2:                     # crossing: q passes through a point of p
            x = p0 + rng.uniform() * (p1 - p0)
            d = rng.normal(size=3)
            q0, q1 = x - rng.uniform(0.1, 1) * d, x + rng.uniform(0.1, 1) * d
        elif kind == 3:                     # one degenerate
            p1 = p0.copy()
        elif kind == 4:                     # both degenerate
            p1, q1 = p0.copy(), q0.copy()
        elif kind == 5:                     # collinear
            d = p1 - p0
            q0, q1 = p0 + rng.uniform(-2, 2) * d, p0 + rng.uniform(-2, 2) * d
        pairs.append((p0, p1, q0, q1))
    return pairs


def test_segment_distance_matches_brute_force():
    rng = np.random.default_rng(7)
    pairs = random_segment_pairs(rng, 120)
    got = segment_distance(*(np.array(x) for x in zip(*pairs)))
    assert got.shape == (120,)
    for d, (p0, p1, q0, q1) in zip(got, pairs):
        coarse, fine, bound = brute_force(p0, p1, q0, q1)
        assert d <= fine + 1e-12                 # never above a distance actually realised
        assert d >= coarse - bound - 1e-12       # never below the true minimum


@pytest.mark.parametrize("p0, p1, q0, q1, expected", [
    ((-1, 0, 0), (1, 0, 0), (0, -1, 0.2), (0, 1, 0.2), 0.2),          # skew, perpendicular
    ((0, 0, 0), (1, 0, 0), (0.5, 0.3, 0), (2, 0.3, 0), 0.3),          # parallel, overlapping
    ((0, 0, 0), (1, 0, 0), (1.5, 0.4, 0), (3, 0.4, 0), 0.41 ** 0.5),  # parallel, disjoint
    ((0, 0, 0), (1, 0, 0), (1.5, 0, 0), (3, 0, 0), 0.5),              # collinear, disjoint
    ((-1, -1e-7, 0), (1, 1e-7, 0), (-1, 1e-7, 0), (1, -1e-7, 0), 0.0),  # crossing at a tiny angle
    ((0, 0, 0), (0, 0, 0), (1, 1, 0), (1, -1, 0), 1.0),               # point to segment
    ((0, 0, 1), (0, 0, 1), (0, 0, 0), (0, 0, 0), 1.0),                # point to point
    ((0, 0, 0), (1, 1, 1), (0, 0, 0), (-1, 2, 0), 0.0),               # shared endpoint
])
def test_segment_distance_known_cases(p0, p1, q0, q1, expected):
    assert segment_distance(p0, p1, q0, q1) == pytest.approx(expected, abs=1e-12)
    assert segment_distance(q1, q0, p1, p0) == pytest.approx(expected, abs=1e-12)


def test_segment_distance_broadcasts():
    rng = np.random.default_rng(3)
    P0, P1 = rng.normal(size=(2, 5, 1, 3))
    Q0, Q1 = rng.normal(size=(2, 1, 7, 3))
    got = segment_distance(P0, P1, Q0, Q1)
    assert got.shape == (5, 7)
    for i in range(5):
        for j in range(7):
            assert got[i, j] == segment_distance(P0[i, 0], P1[i, 0], Q0[0, j], Q1[0, j])


# ------------------------------------------------------------ capsules
def urdf_capsules(arm, q):
    """Capsule endpoints and radii from the URDF cylinders (and spheres), by
    yourdfpy's own parser and forward kinematics: (names, A, B, r), world
    frame."""
    profile = arm.profile
    robot = yourdfpy.URDF.load(io.BytesIO(arm_urdf(profile).encode()), build_scene_graph=True,
                               load_meshes=False, build_collision_scene_graph=False, load_collision_meshes=False)
    robot.update_cfg(dict(zip(profile.joint_names, q)))
    names, A, B, r = [], [], [], []
    for link in robot.robot.links:
        for col in link.collisions:
            cyl, ball = col.geometry.cylinder, col.geometry.sphere
            radius, length = (ball.radius, 0.0) if ball is not None else (cyl.radius, cyl.length)
            T = arm.base_pose @ robot.get_transform(link.name, profile.base_link) @ col.origin
            ends = [T @ [0, 0, z * length / 2, 1] for z in (-1, 1)]
            inset = min(radius, length / 2)
            axis = T[:3, 2]
            names.append(link.name)
            A.append(ends[0][:3] + inset * axis)
            B.append(ends[1][:3] - inset * axis)
            r.append(radius)
    return np.array(names), np.array(A), np.array(B), np.array(r)


@pytest.mark.parametrize("which", [0, 1])
def test_capsules_agree_with_urdf_cylinders(cell, bodies, which):
    arm = cell.arms[which]
    body = bodies[arm.name]
    rng = np.random.default_rng(11)
    lo = np.where(np.isfinite(body.kin.lower), body.kin.lower, -np.pi)
    hi = np.where(np.isfinite(body.kin.upper), body.kin.upper, np.pi)
    for q in (np.asarray(arm.profile.home), rng.uniform(lo, hi)):
        names, A, B, r = urdf_capsules(arm, q)
        got_A, got_B, got_r = body.capsules(q)
        assert "base_link" in body.names and "nozzle" in body.names
        # every checked capsule is a URDF cylinder's, on the same link ...
        same = ((body.names[:, None] == names[None]) & np.isclose(got_r[:, None], r[None], rtol=0, atol=1e-12)
                & (np.linalg.norm(got_A[0][:, None] - A[None], axis=-1) < 1e-9)
                & (np.linalg.norm(got_B[0][:, None] - B[None], axis=-1) < 1e-9))
        assert same.any(axis=1).all()
        # ... and every URDF cylinder's capsule lies inside a checked one of its link
        # (those inside another are dropped): both segment ends within the radius difference
        for k in np.nonzero(~same.any(axis=0))[0]:
            mine = body.names == names[k]
            inside = [segment_distance(got_A[0][mine], got_B[0][mine], p, p) + r[k] <= got_r[mine] + 1e-9
                      for p in (A[k], B[k])]
            assert np.any(inside[0] & inside[1]), "%s capsule %d is not checked" % (names[k], k)


@pytest.mark.parametrize("which", [0, 1])
def test_nozzle_capsule_stops_5mm_above_the_tip(cell, bodies, which):
    arm = cell.arms[which]
    body = bodies[arm.name]
    rng = np.random.default_rng(5)
    lo = np.where(np.isfinite(body.kin.lower), body.kin.lower, -np.pi)
    hi = np.where(np.isfinite(body.kin.upper), body.kin.upper, np.pi)
    Q = rng.uniform(lo, hi, (50, body.kin.dof))
    T = arm.base_pose @ body.kin.fk_batch(Q)
    tip, axis = T[:, :3, 3], T[:, :3, :3] @ body.kin.tool_axis      # axis points out of the tip
    A, B, r = body.capsules(Q)
    k = np.nonzero(body.names == "nozzle")[0]                         # the print head's bodies
    assert len(k) > 1
    # each head capsule's lowest point along the nozzle axis, measured up from the tip
    above = np.minimum(np.einsum("ij,ikj->ik", axis, tip[:, None] - A[:, k]),
                       np.einsum("ij,ikj->ik", axis, tip[:, None] - B[:, k])) - r[k]
    assert above.min() >= 0.005 - 1e-9
    # and the tip itself is 5 mm from the nearest one's surface (the profiles' heads
    # reach down to 5 mm behind the tip on the nozzle axis)
    near = (segment_distance(A[:, k], B[:, k], tip[:, None], tip[:, None]) - r[k]).min(axis=1)
    np.testing.assert_allclose(near, 0.005, atol=1e-9)


def test_capsules_of_many_configurations(bodies):
    body = bodies["ur10"]
    A, B, r = body.capsules(np.zeros((4, body.kin.dof)))
    assert A.shape == B.shape == (4, len(body), 3) and r.shape == (len(body),)
    with pytest.raises(ValueError, match="no capsule on link"):
        body.mask(["ur10/base_link"])


# ------------------------------------------------------------ arm vs arm
def duct_index(body, arm):
    """Index of the capsule of the head's fan duct (on the nozzle axis)."""
    duct = next(c for c in arm.profile.head if c.name == "fan_duct")
    assert duct.a[:2] == duct.b[:2] == (0.0, 0.0)
    return int(np.nonzero((body.names == "nozzle") & (body.radii == duct.radius))[0][0])


def test_home_poses_do_not_collide(cell, bodies):
    k, u = cell.arms
    c = clearance_between(bodies["kinova"], k.profile.home, bodies["ur10"], u.profile.home)
    assert c.shape == (1,) and c[0] > 0.05


def test_nozzles_side_by_side_collide(cell, bodies):
    k, u = cell.arms
    n = np.append(seam_normal(cell), 0.0)
    centres = np.array([[0.0, 0.0, 0.0], [0.02, -0.1, 0.05], [-0.03, 0.12, 0.1]])
    for gap, expect_touch in ((0.03, True), (0.25, False)):
        Qk = solve(cell, k, bodies["kinova"], centres - n * gap / 2)
        Qu = solve(cell, u, bodies["ur10"], centres + n * gap / 2)
        c = clearance_between(bodies["kinova"], Qk, bodies["ur10"], Qu)
        assert c.shape == (3,)
        assert np.all(c < 0) if expect_touch else np.all(c > 0)
        # the two vertical fan ducts alone (the heads' bodies on the nozzle axis,
        # tool.head in the profiles): their axes are `gap` apart
        A1, B1, r1 = bodies["kinova"].capsules(Qk)
        A2, B2, r2 = bodies["ur10"].capsules(Qu)
        i, j = (duct_index(bodies[a], arm) for a, arm in (("kinova", k), ("ur10", u)))
        nn = capsule_distances(A1[:, [i]], B1[:, [i]], r1[[i]], A2[:, [j]], B2[:, [j]], r2[[j]])[:, 0, 0]
        np.testing.assert_allclose(nn, gap - r1[i] - r2[j], atol=1e-6)
        assert np.all(c <= nn + 1e-12)



def test_firmware_check_says_what_a_pose_is_too_close_to(cell, bodies):
    """The firmware's is_valid (driver trajectory) names the obstacle, the
    clearance in mm and the closest links of a refused pose."""
    from ambots.collision import CollisionCheck
    k, u = cell.arms
    check = CollisionCheck(k, cell, margin=0.005)
    Qk = solve(cell, k, bodies["kinova"], [[-0.01, -0.01, 0.0002], [-0.08, -0.01, 0.0002], [0.0, 0.0, -0.01]])
    qu = solve(cell, u, bodies["ur10"], [[0.025, -0.01, 0.0002]])[0]
    assert check.explain(Qk[0]) == "clear" and check(Qk[:2]).all()         # the other arm not heard of yet
    check.update("ur10", qu)
    # nozzles 35 mm apart across the seam: the two 40 mm fan ducts overlap (105 mm: clear)
    c = clearance_between(bodies["kinova"], Qk[:2], bodies["ur10"], np.stack([qu, qu]))
    assert c[0] < 0 < 0.005 < c[1]
    assert check(Qk[:2]).tolist() == [False, True]
    why = check.explain(Qk[0])
    assert why.startswith("ur10 %.2f mm (needs >= 5 mm): " % (c[0] * 1e3)) and " / " in why
    assert check.explain(Qk[1]) == "clear"
    # the nozzle 10 mm into the bed: the head's lowest body (5 mm short of the tip) 5 mm in
    assert not check(Qk[2:]).any()
    assert check.explain(Qk[2]).startswith("bed -5.00 mm (needs >= 0): nozzle")

# ------------------------------------------------------------ boxes
def sampled_box_clearance(a, b, r, lo, hi, n=4001):
    """Reference: signed distance of n points along the segment, computed
    face by face (outside: distance to the clamped point; inside: minus the
    distance to the nearest face)."""
    t = np.linspace(0, 1, n)[:, None]
    X = a + t * (b - a)
    inside = np.all((X > lo) & (X < hi), axis=1)
    outside = np.linalg.norm(X - np.clip(X, lo, hi), axis=1)
    depth = np.minimum(X - lo, hi - X).min(axis=1)
    return np.where(inside, -depth, outside).min() - r, np.linalg.norm(b - a) / (n - 1) / 2


def test_box_clearance_matches_sampling():
    rng = np.random.default_rng(9)
    N, C = 40, 3
    A = rng.uniform(-1, 1, (N, C, 3))
    B = A + rng.normal(scale=0.6, size=(N, C, 3))
    B[:, 2] = A[:, 2]                                        # some degenerate capsules
    r = np.array([0.05, 0.02, 0.1])
    lo = rng.uniform(-0.5, 0, (N, 3))
    hi = lo + rng.uniform(0.1, 0.8, (N, 3))
    got = box_clearance(A, B, r, lo, hi)
    assert got.shape == (N,)
    for i in range(N):
        ref = [sampled_box_clearance(A[i, c], B[i, c], r[c], lo[i], hi[i]) for c in range(C)]
        best, tol = min(v for v, _ in ref), max(t for _, t in ref)
        assert best - tol - 1e-12 <= got[i] <= best + 1e-9
    assert np.any(got < 0) and np.any(got > 0)


def test_box_clear_answers_as_the_clearance_does():
    """``box_clear`` (a bound first, the search where the bound cannot
    tell) says the same as ``box_clearance >= margin`` on capsules far
    from, near and inside a box, for margins either side of them."""
    from ambots.collision import box_clear
    rng = np.random.default_rng(4)
    N, C = 400, 4
    A = rng.uniform(-2, 2, (N, C, 3))
    B = A + rng.normal(scale=0.5, size=(N, C, 3))
    r = np.array([0.05, 0.02, 0.1, 0.0])
    lo, hi = np.array([-0.5, -0.4, -0.1]), np.array([0.5, 0.4, 0.0])
    ref = box_clearance(A, B, r, lo, hi)
    mask = np.array([True, False, True, True])
    ref_masked = box_clearance(A, B, r, lo, hi, mask)
    for margin in (-0.05, 0.0, 0.005, 0.2, 1.0):
        got = box_clear(A, B, r, lo, hi, margin)
        np.testing.assert_array_equal(got, ref >= margin)
        np.testing.assert_array_equal(box_clear(A, B, r, lo, hi, margin, mask), ref_masked >= margin)
    assert 0 < (ref >= 0.2).sum() < N                  # both answers occur


def test_box_clearance_exact_cases():
    A = np.array([[[-1.0, 0.1, 0.2]], [[-1.0, 2.0, 0.0]]])
    B = np.array([[[1.0, 0.1, 0.2]], [[1.0, 2.0, 0.0]]])
    lo, hi = np.array([-0.5, -0.5, -0.5]), np.array([0.5, 0.5, 0.5])
    got = box_clearance(A, B, [0.05], lo, hi)
    np.testing.assert_allclose(got, [-0.3 - 0.05, 1.5 - 0.05], atol=1e-12)
    with pytest.raises(ValueError):
        box_clearance(A, B, [0.05], hi, lo)


def test_bed_clearance(cell, bodies):
    for arm in cell.arms:
        body = bodies[arm.name]
        Q = solve(cell, arm, body, [[0.0, 0.0, 0.0], [0.05, 0.05, -0.02], [0.0, 0.0, 0.1]])
        c = bed_clearance(body, Q, cell)
        # on the bed the head's lowest body is 5 mm above it (it stops 5 mm short of
        # the tip); 20 mm into it, 15 mm below the top; 100 mm above it, 105 mm
        np.testing.assert_allclose(c, [0.005, -0.015, 0.105], atol=1e-6)
        # the rest of the arm: the last link, at most 50 mm in radius (robot facts:
        # bracelet 50, UR10 wrist 3 47) around the tool axis up to the flange, 100 mm
        # above the tip, stays 50 mm above the tip (30 mm with the tip 20 mm into the bed)
        last = max(F.KINOVA_ENVELOPE["bracelet"][0], F.UR10_ENVELOPE["wrist_3"][0])
        tips = np.array([0.0, -0.02, 0.1])
        assert np.all(bed_clearance(body, Q, cell, skip=("base_link", "nozzle"))
                      >= tips + arm.profile.tool_xyz[2] - last - 1e-9)


def test_part_clearance(cell, bodies):
    arm, body = cell.arms[1], bodies["ur10"]
    # a 40 mm cube on the bed centre; the nozzle on its top face, 10 mm into it, 50 mm beside it
    lo, hi = bed_to_world(cell, [-0.02, -0.02, 0.0]), bed_to_world(cell, [0.02, 0.02, 0.04])
    Q = solve(cell, arm, body, [[0.0, 0.0, 0.04], [0.0, 0.0, 0.03], [0.0, 0.1, 0.02]])
    c = part_clearance(body, Q, lo, hi)
    assert c[0] == pytest.approx(0.005, abs=1e-6)
    assert c[1] == pytest.approx(-0.005, abs=1e-6)
    assert c[2] > 0.04
    assert np.all(part_clearance(body, Q, np.stack([lo] * 3), np.stack([hi] * 3)) == c)


# ------------------------------------------------------------ seam zone
def test_seam_zone_of_the_default_cell(cell, bodies):
    z = seam_zone(cell)
    k, u = cell.arms
    # protrusion towards the neighbour: at least the head's widest body on the
    # nozzle axis (the fan duct, 20 mm), and no more than the worst horizontal
    # direction
    ducts = {arm.name: next(c.radius for c in arm.profile.head if c.name == "fan_duct") * 1000.0
             for arm in cell.arms}
    for (a, b), p in z.protrusion_facing_mm.items():
        assert ducts[a] - 1e-6 <= p <= z.protrusion_any_mm[a] + 1e-9
    assert z.facing_mm == pytest.approx(sum(z.protrusion_facing_mm.values()) + z.margin_mm)
    assert z.any_mm == pytest.approx(sum(z.protrusion_any_mm.values()) + z.margin_mm)
    assert z.facing_mm <= z.any_mm
    assert z.clearance_facing_mm > 0
    zone = seam_zone_mm(cell)                     # rounded up to 0.01 mm (deterministic)
    assert z.facing_mm - 1e-9 <= zone <= z.facing_mm + 0.01 and round(zone * 100) == pytest.approx(zone * 100)
    # the heads sit 100 mm off their flanges, which trail towards the bases: the
    # wrists (the UR10's 76 mm, the Kinova's 50 mm bracelet) stay behind the
    # nozzles, and what faces the other arm is the fan duct (20 mm) and the
    # hot end's heat sink (22 mm, 8 mm towards the flange: 14 mm in front)
    assert z.facing_mm == pytest.approx(ducts["kinova"] + ducts["ur10"] + z.margin_mm, abs=1e-3)
    # independent check: both nozzles at the bed centre line, the zone apart, do not touch ...
    n = np.append(seam_normal(cell), 0.0)
    pts = np.array([[0.0, y, h] for y in (-0.1, 0.0, 0.1) for h in (0.0, 0.15)])
    Z = z.facing_mm / 1000.0
    c = clearance_between(bodies["kinova"], solve(cell, k, bodies["kinova"], pts - n * Z / 2),
                          bodies["ur10"], solve(cell, u, bodies["ur10"], pts + n * Z / 2))
    assert np.all(c > 0)
    np.testing.assert_allclose(c, z.margin_mm / 1000.0, atol=1e-6)     # the two fan ducts, face to face
    # ... and do when the nozzles are closer than the two ducts' radii
    gap = (ducts["kinova"] + ducts["ur10"] - 2.0) / 1000.0
    c = clearance_between(bodies["kinova"], solve(cell, k, bodies["kinova"], pts - n * gap / 2),
                          bodies["ur10"], solve(cell, u, bodies["ur10"], pts + n * gap / 2))
    assert np.all(c < 0)
    with pytest.raises(ValueError):
        seam_zone_mm(cell, direction="sideways")


def test_arms_at_an_angle_to_their_seam_get_the_zone_their_poses_keep_clear():
    """In the four-arm cell each arm faces the bed's centre, 45 degrees off the
    seam it shares with a neighbour, so the protrusions projected on the
    seam's normal count a Kinova's wrist housing reaching sideways although
    it never meets the UR10 there.  The zone is then what the sampled poses
    keep clear (``clearance=``), narrower than the projection.  Checked by a
    second method on poses of our own, random points of the two parts (not
    the zone's grid) solved nozzle down, every capsule against every
    capsule: two nozzles the zone apart across the seam keep the 10 mm
    margin, and the zone is no wider than needed by more than its grid step
    and 5 mm (some pair nearer than that comes within the margin)."""
    import trimesh

    from ambots import data_path
    from ambots.collision import seam_zones_mm
    from ambots.job import split
    from ambots.mesh import place_on_bed
    four = load_cell(data_path("config", "cells", "four_arms.yaml"))
    parts = split(place_on_bed(trimesh.creation.box((220.0, 220.0, 4.0))), four, list(four.arms))
    tight = {}
    zones = seam_zones_mm(four, parts=parts, clearance=tight, pairs=[("kinova1", "ur10_1")])
    zone, projected = tight["kinova1", "ur10_1"], zones["kinova1", "ur10_1"]
    assert 40.0 < zone < projected - 5.0
    rng = np.random.default_rng(7)
    side = {}
    for name in ("kinova1", "ur10_1"):
        part = next(p for p in parts if p.arm.name == name)
        lo, hi = np.asarray(part.manifold.bounding_box()[:3]), np.asarray(part.manifold.bounding_box()[3:])
        pts = rng.uniform(lo, hi, size=(4000, 3))
        pts = pts[np.all([pts @ n - off >= 0.0 for n, off in part.planes], axis=0)][:250]
        n, off = part.planes[part.neighbours.index("ur10_1" if name == "kinova1" else "kinova1")]
        arm = four.arm(name)
        body = ArmBody.from_arm(arm)
        Q = solve(four, arm, body, pts / 1000.0)
        side[name] = (body, Q, pts @ n - off)          # distance to the seam, mm
    (ba, Qa, da), (bb, Qb, db) = side["kinova1"], side["ur10_1"]
    i, j = np.meshgrid(np.arange(len(Qa)), np.arange(len(Qb)), indexing="ij")
    i, j = i.ravel(), j.ravel()
    S = da[i] + db[j]
    c = clearance_between(ba, Qa[i], bb, Qb[j]) * 1000.0
    assert np.all(c[S >= zone] >= 10.0 - 1e-6), c[S >= zone].min()
    assert np.any(c[S < zone - 10.0 - 5.0] < 10.0)


def test_arms_that_face_each_other_keep_the_projected_zone(cell):
    """The default cell's arms face each other along their seam: the
    projection is their zone (the two fan ducts and the margin), also on a
    tower narrower than that, where no two poses are far enough apart
    across the seam to tell what clearance they would keep."""
    import trimesh

    from ambots.collision import seam_zones_mm
    from ambots.job import split
    from ambots.mesh import place_on_bed
    for box in ((240.0, 40.0, 10.0), (20.0, 20.0, 30.0)):
        parts = split(place_on_bed(trimesh.creation.box(box)), cell, list(cell.arms))
        tight = {}
        zones = seam_zones_mm(cell, parts=parts, clearance=tight)
        assert tight == {} and zones["kinova", "ur10"] == pytest.approx(50.0, abs=0.01)
