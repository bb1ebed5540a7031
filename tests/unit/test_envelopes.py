"""The collision bodies cover the real arms: every figure of the robot facts'
"Body envelopes" table (copied into ``robot_facts``) is checked by sampling
points on the published envelope, posed by forward kinematics computed here
from the published kinematic tables, and asserting that each lies inside
the union of the capsules :class:`~ambots.collision.ArmBody` checks, at
several random joint vectors.  And the print head: the profile's
``tool.head`` bodies are what the URDF draws and what is checked, and a
nozzle printing on the part's top face is no contact.

The envelope of one table row (one link), in the link's own frame:

* the link tube: the solid cylinder of the row's radius around the line
  between the two joint centres the link connects (its boundary sampled);
* each housing: the solid cylinder coaxial with the joint axis, of the
  housing's radius, reaching the row's "beyond" distance past the joint
  centre both ways along the axis;
* the disc of the housing's radius about the link axis at the joint centre
  (the radius "at the housing");
* and the housing reaching the "beyond" distance past the joint centre in
  every direction across the joint axis (so also along the link, whichever
  way the table measures it): the disc of that radius about the joint axis.

Housings are taken around each link's own joint (the joint whose axis is
the link's z) and, for the UR10's upper arm, also around the elbow, as its
row says; the flange is no joint.  Where the table gives a range of radii,
its largest value is taken along the whole link.
"""
import io
import math

import numpy as np
import pytest
import yaml
import yourdfpy

import robot_facts as F
from ambots.collision import ArmBody, part_clearance
from ambots.config import load_arm_profile, load_cell
from ambots.model import arm_urdf
from ambots.workspace import down_in_base, world_to_base

Z = (0.0, 0.0, 1.0)
UR10 = "config/arms/ur10.yaml"
KINOVA = "config/arms/kinova_gen3.yaml"
PROFILES = [UR10, KINOVA, "config/arms/panda.yaml"]


# ------------------------------------------------------------ kinematics
def rot_x(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1.0]])


def rot_z(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])


def trans(x, y, z):
    T = np.eye(4)
    T[:3, 3] = x, y, z
    return T


def rpy(r, p, y):
    c, s = math.cos(p), math.sin(p)
    ry = np.array([[c, 0, s, 0], [0, 1, 0, 0], [-s, 0, c, 0], [0, 0, 0, 1.0]])
    return rot_z(y) @ ry @ rot_x(r)


def ur10_links(q):
    """Frames of the UR10's links base .. wrist 3 from the standard DH table:
    link i sits on joint i's axis, d_i along it from DH origin i-1, turned by
    q_i (link 6 is the flange)."""
    T, out, prev = np.eye(4), [np.eye(4)], (0.0, 0.0)
    for qi, (d, a, alpha) in zip(q, F.UR10_DH):
        T = T @ trans(prev[0], 0, 0) @ rot_x(prev[1]) @ trans(0, 0, d) @ rot_z(qi)
        out.append(T)
        prev = (a, alpha)
    return out


def kinova_links(q):
    """Frames of the Kinova's links base .. bracelet from its joint origins."""
    T, out = np.eye(4), [np.eye(4)]
    for qi, (xyz, r) in zip(q, F.KINOVA_ORIGINS):
        T = T @ trans(*xyz) @ rpy(*r) @ rot_z(qi)
        out.append(T)
    return out


# ------------------------------------------------------------ envelopes
def ur10_envelope():
    """[(link index, name, link axis (p0, p1), tube radius, [(centre, joint
    axis, housing radius, beyond)])] in the UR10's link frames."""
    E = F.UR10_ENVELOPE
    (d1, _, _), (_, a2, _), (_, a3, _), (d4, _, _), (d5, _, _), (d6, _, _) = F.UR10_DH
    uz, fz = F.UR10_UPPER_ARM_TUBE_Z, F.UR10_FOREARM_TUBE_Z
    r, x = E["upper_arm"][1], E["upper_arm_housings"]
    return [
        (0, "base", ((0, 0, 0), (0, 0, d1)), E["base"][0], [((0, 0, d1), Z) + E["base"]]),
        (1, "shoulder", ((0, 0, 0), (0, -uz, 0)), E["shoulder"][0], [((0, 0, 0), Z) + E["shoulder"]]),
        (2, "upper arm", ((0, 0, uz), (a2, 0, uz)), E["upper_arm"][0],
         [((0, 0, uz), Z, x, r), ((a2, 0, uz), Z, x, r)]),
        (3, "forearm", ((0, 0, fz), (a3, 0, fz)), E["forearm"][0],
         [((0, 0, fz), Z, E["forearm_elbow_housing"], E["forearm"][1])]),
        # J4 where the forearm tube meets its axis, J5 and J6 where the wrist axes cross
        (4, "wrist 1", ((0, 0, fz - d4), (0, 0, 0)), E["wrist_1"][0], [((0, 0, fz - d4), Z) + E["wrist_1"]]),
        (5, "wrist 2", ((0, 0, -d5), (0, 0, 0)), E["wrist_2"][0], [((0, 0, -d5), Z) + E["wrist_2"]]),
        (6, "wrist 3", ((0, 0, -d6), (0, 0, 0)), E["wrist_3"][0], [((0, 0, -d6), Z) + E["wrist_3"]]),
    ]


def kinova_envelope():
    """The same for the Kinova: each link from its joint's origin to the
    next joint's (the bracelet: to the end effector)."""
    E = F.KINOVA_ENVELOPE
    ends = [xyz for xyz, _ in F.KINOVA_ORIGINS] + [F.KINOVA_EE[0]]
    # J1's axis in the base frame: the shoulder's z
    j1_axis = tuple(rpy(*F.KINOVA_ORIGINS[0][1])[:3, 2])
    rows = [(0, "base", ((0, 0, 0), ends[0]), E["base"][0], [(ends[0], j1_axis) + E["base"]])]
    for i, key in enumerate(["shoulder", "bicep", "forearm", "spherical_wrist_1", "spherical_wrist_2",
                             "bracelet"], start=1):
        rows.append((i, key, ((0, 0, 0), ends[i]), E[key][0], [((0, 0, 0), Z) + E[key]]))
    return rows


def basis(w):
    """Unit w and two unit vectors perpendicular to it and each other."""
    w = np.asarray(w, dtype=float) / np.linalg.norm(w)
    helper = np.eye(3)[np.argmin(np.abs(w))]
    u = np.cross(w, helper)
    u /= np.linalg.norm(u)
    return w, u, np.cross(w, u)


def disc(centre, normal, radius, n_rings=4, n_around=24):
    """Points of a disc: its centre and n_rings circles out to its rim."""
    _, u, v = basis(normal)
    t = np.linspace(0, 2 * np.pi, n_around, endpoint=False)
    rho = np.linspace(0, radius, n_rings + 1)[1:]
    ring = (np.cos(t)[:, None] * u + np.sin(t)[:, None] * v)                     # (n_around, 3)
    pts = (rho[:, None, None] * ring[None]).reshape(-1, 3)
    return np.vstack([np.zeros((1, 3)), pts]) + np.asarray(centre, dtype=float)


def solid_cylinder(p0, p1, radius, n_len=9, n_around=24):
    """Points on the boundary of the solid cylinder of ``radius`` around
    p0-p1: its side at n_len stations, both end discs, and its axis."""
    p0, p1 = np.asarray(p0, dtype=float), np.asarray(p1, dtype=float)
    w, u, v = basis(p1 - p0)
    s = np.linspace(0, 1, n_len)[:, None]
    t = np.linspace(0, 2 * np.pi, n_around, endpoint=False)
    ring = radius * (np.cos(t)[:, None] * u + np.sin(t)[:, None] * v)
    side = (p0 + s * (p1 - p0))[:, None, :] + ring[None]
    return np.vstack([side.reshape(-1, 3), disc(p0, w, radius), disc(p1, w, radius), p0 + s * (p1 - p0)])


def envelope_points(rows):
    """{(link index, what): (M, 3) points in that link's frame} of every row."""
    out = {}
    for i, name, (p0, p1), radius, housings in rows:
        out[i, "%s: tube of radius %g mm" % (name, radius * 1e3)] = solid_cylinder(p0, p1, radius)
        link_axis = np.subtract(p1, p0)
        for c, k, rh, beyond in housings:
            w = basis(k)[0]
            what = "%s: housing at %s, radius %g mm, %g mm beyond" % (name, c, rh * 1e3, beyond * 1e3)
            out[i, what] = solid_cylinder(np.add(c, -beyond * w), np.add(c, beyond * w), rh)
            out[i, what + ", about the link axis"] = disc(c, link_axis, rh)
            out[i, what + ", across the joint axis"] = disc(c, w, beyond)
    return out


def pose(frames, points):
    """{what: (M, 3) world points} from link-frame points."""
    return {key: pts @ frames[key[0]][:3, :3].T + frames[key[0]][:3, 3] for key, pts in points.items()}


def depth_outside(P, A, B, r):
    """(M,) how far (m) each point lies outside the union of capsules A-B, r
    (<= 0 inside): the smallest distance to a segment minus its radius."""
    d = B - A                                                             # (C, 3)
    w = P[:, None, :] - A[None]                                           # (M, C, 3)
    dd = np.einsum("ci,ci->c", d, d)
    t = np.clip(np.einsum("mci,ci->mc", w, d) / np.where(dd > 0, dd, 1.0), 0.0, 1.0)
    return (np.linalg.norm(w - t[..., None] * d, axis=-1) - r).min(axis=1)


def uncovered(body, links, rows, q):
    """{what: mm} of the envelope parts that stick out of the body's capsules
    at joint vector q."""
    A, B, r = body.capsules(q)
    out = {}
    for what, P in pose(links(q), envelope_points(rows)).items():
        worst = float(depth_outside(P, A[0], B[0], r).max())
        if worst > 1e-9:
            out[what[1]] = round(worst * 1e3, 3)
    return out


ARMS = {"ur10": (UR10, ur10_links, ur10_envelope), "kinova": (KINOVA, kinova_links, kinova_envelope)}


def random_qs(body, n, seed):
    rng = np.random.default_rng(seed)
    lo = np.where(np.isfinite(body.kin.lower), body.kin.lower, -np.pi)
    hi = np.where(np.isfinite(body.kin.upper), body.kin.upper, np.pi)
    return rng.uniform(lo, hi, (n, body.kin.dof))


@pytest.mark.parametrize("arm", sorted(ARMS))
def test_our_link_frames_are_the_published_ones(arm):
    # the envelopes are posed by this file's kinematics: they must agree with the model's
    path, links, _ = ARMS[arm]
    body = ArmBody.from_arm(load_arm_profile(path))
    frames = body.kin.link_frames(random_qs(body, 5, 1))
    for k, q in enumerate(random_qs(body, 5, 1)):
        mine = links(q)
        np.testing.assert_allclose(frames[k, 1:len(mine)], np.stack(mine[1:]), atol=1e-9)


@pytest.mark.parametrize("arm", sorted(ARMS))
def test_every_envelope_figure_is_covered(arm):
    path, links, rows = ARMS[arm]
    body = ArmBody.from_arm(load_arm_profile(path))
    for q in random_qs(body, 6, 2):
        bad = uncovered(body, links, rows(), q)
        assert not bad, "%s at q = %s: envelope outside the collision bodies (mm): %s" % (arm, q.round(3), bad)


@pytest.mark.parametrize("arm", sorted(ARMS))
def test_the_models_own_cylinders_alone_leave_the_envelope_out(arm, tmp_path):
    # the check above can fail: without the profile's bodies most rows stick out
    path, links, rows = ARMS[arm]
    data = yaml.safe_load(open(path))
    del data["bodies"]
    bare = tmp_path / "bare.yaml"
    bare.write_text(yaml.safe_dump(data))
    body = ArmBody.from_arm(load_arm_profile(str(bare)))
    bad = uncovered(body, links, rows(), random_qs(body, 1, 3)[0])
    assert len(bad) >= len(rows())


# ------------------------------------------------------------ drawn as checked
def profile_capsules(path):
    """{link: [(a, b, r)]} of a profile's bodies and head (nozzle link), read
    here from the YAML by the kinds' definitions."""
    data = yaml.safe_load(open(path))
    out = {}
    for link, items in list((data.get("bodies") or {}).items()) + [("nozzle", data["tool"]["head"])]:
        for it in items:
            if "tube" in it:
                a, b = it["tube"]
            elif "ball" in it:
                a = b = it["ball"]
            else:
                k = np.asarray(it["axis"], dtype=float)
                k *= it["reach"] / np.linalg.norm(k)
                a, b = np.subtract(it["housing"], k), np.add(it["housing"], k)
            out.setdefault(link, []).append((np.asarray(a, dtype=float), np.asarray(b, dtype=float),
                                             float(it["radius"])))
    return out


def urdf_capsules(urdf):
    """{link: [(a, b, r)]} of the URDF's collisions in their link frames by
    yourdfpy's parser: a cylinder's axis inset by min(radius, length / 2)."""
    robot = yourdfpy.URDF.load(io.BytesIO(urdf.encode()), build_scene_graph=False, load_meshes=False,
                               build_collision_scene_graph=False, load_collision_meshes=False)
    out = {}
    for link in robot.robot.links:
        for col in link.collisions:
            g, T = col.geometry, col.origin
            if g.sphere is not None:
                r, half = g.sphere.radius, 0.0
            else:
                r, half = g.cylinder.radius, g.cylinder.length / 2 - min(g.cylinder.radius, g.cylinder.length / 2)
            out.setdefault(link.name, []).append((T[:3, 3] - half * T[:3, 2], T[:3, 3] + half * T[:3, 2], r))
    return out


def same(c1, c2):
    (a1, b1, r1), (a2, b2, r2) = c1, c2
    return abs(r1 - r2) < 1e-12 and (np.allclose([a1, b1], [a2, b2], atol=1e-12)
                                     or np.allclose([a1, b1], [b2, a2], atol=1e-12))


@pytest.mark.parametrize("path", PROFILES)
def test_profile_bodies_and_head_are_what_the_urdf_draws(path):
    drawn = urdf_capsules(arm_urdf(load_arm_profile(path)))
    wanted = profile_capsules(path)
    assert wanted["nozzle"] and (path != UR10 or len(wanted) > 5)
    for link, caps in wanted.items():
        for c in caps:
            assert any(same(c, d) for d in drawn.get(link, [])), "%s: %s body %s not drawn" % (path, link, c)
    # the nozzle link carries the head and nothing else (no leftover extruder cylinder)
    assert len(drawn["nozzle"]) == len(wanted["nozzle"])


@pytest.mark.parametrize("path", PROFILES)
def test_the_head_is_what_collisions_check(path):
    prof = load_arm_profile(path)
    body = ArmBody.from_arm(prof)
    head = profile_capsules(path)["nozzle"]
    robot = yourdfpy.URDF.load(io.BytesIO(arm_urdf(prof).encode()), load_meshes=False,
                               build_collision_scene_graph=False, load_collision_meshes=False)
    q = random_qs(body, 1, 4)[0]
    robot.update_cfg(dict(zip(prof.joint_names, q)))
    T = robot.get_transform("nozzle", prof.base_link)
    head = [(T[:3, :3] @ a + T[:3, 3], T[:3, :3] @ b + T[:3, 3], r) for a, b, r in head]
    A, B, R = body.capsules(q)
    on_nozzle = np.nonzero(body.names == "nozzle")[0]
    checked = [(A[0, k], B[0, k], R[k]) for k in on_nozzle]
    # every checked nozzle body is a head body, and every head body is checked or lies
    # inside one that is (a body inside another of its link is dropped)
    assert checked and all(any(same(c, h) for h in head) for c in checked)
    for a, b, r in head:
        assert depth_outside(np.array([a, b]), A[0, on_nozzle], B[0, on_nozzle], R[on_nozzle] - r).max() <= 1e-9


@pytest.mark.parametrize("path", PROFILES)
def test_the_head_stays_5mm_behind_the_tip(path):
    # nozzle frame: the tip at the origin, z out of the tip; the head lies at z < 0
    for a, b, r in profile_capsules(path)["nozzle"]:
        assert max(a[2], b[2]) + r <= -F.HEAD_TIP_GAP + 1e-12
    data = yaml.safe_load(open(path))["tool"]["head"]
    # a real hot end with its fan duct is about 40 mm across: the head is at least that wide
    widest = max(2 * it["radius"] + abs(np.subtract(*it["tube"])[0]) for it in data if "tube" in it)
    assert widest >= 0.040


def test_a_nozzle_on_the_part_is_no_contact():
    cell = load_cell("config/cells/three_arms.yaml")
    bed = cell.bed.pose
    # a 40 mm cube on the bed centre; each nozzle down on its top face, on an edge, and 1 mm into it
    lo, hi = np.array([-0.02, -0.02, 0.0]), np.array([0.02, 0.02, 0.04])
    tips = np.array([[0.0, 0.0, 0.04], [0.02, 0.0, 0.04], [0.0, 0.0, 0.039]])
    world = lambda p: p @ bed[:3, :3].T + bed[:3, 3]  # noqa: E731
    for arm in cell.arms:
        body = ArmBody.from_arm(arm)
        Q, ok, _ = body.kin.ik_batch(world_to_base(arm, world(tips)), np.asarray(arm.profile.home),
                                     down_in_base(arm))
        assert ok.all()
        c = part_clearance(body, Q, world(lo), world(hi))
        # the head's nearest bodies stop 5 mm short of the tip (profile), the rest is farther
        np.testing.assert_allclose(c, [F.HEAD_TIP_GAP, F.HEAD_TIP_GAP, F.HEAD_TIP_GAP - 0.001], atol=1e-6)
