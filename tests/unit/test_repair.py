"""Mesh repair (ambots.repair through ambots.mesh.load_model): holes closed
when small against the model, refused with the figures otherwise.

The models are made here, with holes of our own making; every figure is
checked against something the repair code does not compute: the intact
model's volume (a formula, or the divergence theorem written out below),
and for "volume before" of an open mesh a brute-force generalized winding
number over the whole bounding box (written out below, not the module's
patch-only estimate)."""
import json
import os
import subprocess
import sys

import numpy as np
import pytest
import trimesh

from ambots.errors import MeshError
from ambots.mesh import load_model
from ambots.repair import MAX_FILL_AREA_SHARE, MAX_VOLUME_CHANGE, hole_loops

BOX = (60.0, 30.0, 8.0)                 # mm: the must-show size, across the seam


# ---------------------------------------------------------------- helpers

def save(tmp_path, name, vertices, faces):
    path = str(tmp_path / name)
    trimesh.Trimesh(vertices, faces, process=False).export(path)
    return path


def signed_volume(vertices, faces):
    """Divergence theorem: sum of the tetrahedra (origin, triangle), mm^3."""
    a, b, c = (np.asarray(vertices, float)[np.asarray(faces)[:, i]] for i in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def brute_winding_volume(vertices, faces, n=36):
    """Volume (mm^3) of the points of a regular n^3 grid over the bounding
    box whose generalized winding number w.r.t. the triangles is >= 0.5;
    the solid angle of a triangle from its corners' unit vectors
    (tan(O/2) = a.(b x c) / (1 + a.b + b.c + c.a))."""
    tri = np.asarray(vertices, float)[np.asarray(faces)]
    lo, hi = tri.reshape(-1, 3).min(0) - 0.5, tri.reshape(-1, 3).max(0) + 0.5
    g = (np.stack(np.meshgrid(*[np.arange(n) + 0.5] * 3, indexing="ij"), -1).reshape(-1, 3)) / n
    points = lo + g * (hi - lo)
    w = np.zeros(len(points))
    for s in range(0, len(points), 500):
        d = tri[None] - points[s:s + 500, None, None]
        u = d / np.linalg.norm(d, axis=-1, keepdims=True)
        a, b, c = u[..., 0, :], u[..., 1, :], u[..., 2, :]
        num = np.einsum("...i,...i", a, np.cross(b, c))
        den = 1 + np.einsum("...i,...i", a, b) + np.einsum("...i,...i", b, c) + np.einsum("...i,...i", c, a)
        w[s:s + 500] = 2 * np.arctan2(num, den).sum(-1) / (4 * np.pi)
    return float(np.prod(hi - lo) * np.mean(w >= 0.5))


def box():
    return trimesh.creation.box(BOX)


def open_bottom(mesh):
    return mesh.faces[mesh.face_normals[:, 2] > -0.5]


def report(mesh):
    return mesh.metadata["ambots_repair"]


# ------------------------------------------------------------- repaired

def test_a_box_with_three_faces_removed_is_closed_to_its_volume(tmp_path):
    b = box().subdivide().subdivide()   # 192 triangles: room for three holes that share no corner
    # a triangle in the middle of the top, of a long side and of a short side: three holes of 3 edges
    gone = [int(np.argmin(np.linalg.norm(b.triangles_center - 0.5 * np.multiply(BOX, axis), axis=1)))
            for axis in ((0, 0, 1), (0, 1, 0), (-1, 0, 0))]
    assert len(np.unique(b.faces[gone])) == 9
    path = save(tmp_path, "three holes.stl", b.vertices, np.delete(b.faces, gone, axis=0))
    mesh = load_model(path)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume == pytest.approx(np.prod(BOX), rel=1e-9)
    r = report(mesh)
    assert (r.holes_closed, r.faces_added, r.faces_removed) == (3, 3, 0)
    assert (r.open_edges_before, r.open_edges_after) == (9, 0)
    assert r.volume_before_mm3 == pytest.approx(np.prod(BOX), rel=1e-3)
    assert r.volume_after_mm3 == pytest.approx(np.prod(BOX), rel=1e-9)


@pytest.mark.parametrize("inside_out", [False, True], ids=["outward", "inside out"])
def test_a_box_with_an_open_bottom_is_closed_to_its_volume(tmp_path, inside_out):
    b = box()
    faces = open_bottom(b)[:, ::-1] if inside_out else open_bottom(b)
    path = save(tmp_path, "open bottom.stl", b.vertices, faces)
    mesh = load_model(path)
    assert mesh.is_watertight and mesh.volume == pytest.approx(np.prod(BOX), rel=1e-9)
    np.testing.assert_allclose(mesh.bounds, b.bounds, atol=1e-6)
    r = report(mesh)
    assert (r.holes_closed, r.open_edges_before, r.faces_added) == (1, 4, 2)
    assert r.fill_area_mm2 == pytest.approx(BOX[0] * BOX[1])
    # the whole bottom is 36 % of the surface: under the area limit
    area = 2 * (BOX[0] * BOX[1] + BOX[0] * BOX[2] + BOX[1] * BOX[2])
    assert r.fill_area_share == pytest.approx(BOX[0] * BOX[1] / area) and r.fill_area_share < MAX_FILL_AREA_SHARE
    assert abs(r.volume_change) < 1e-3


def test_a_sphere_with_five_faces_removed_keeps_its_volume(tmp_path):
    s = trimesh.creation.icosphere(subdivisions=3, radius=10.0)
    gone = [0, 77, 200, 513, 1001]                 # far apart: five holes of 3 edges
    path = save(tmp_path, "sphere.obj", s.vertices, np.delete(s.faces, gone, axis=0))
    mesh = load_model(path)
    intact = signed_volume(s.vertices, s.faces)
    assert mesh.is_watertight and mesh.volume == pytest.approx(intact, rel=1e-6)
    assert intact == pytest.approx(4.0 / 3.0 * np.pi * 10.0 ** 3, rel=0.01)   # the polyhedron is a sphere
    r = report(mesh)
    assert (r.holes_closed, r.faces_added, r.open_edges_before) == (5, 5, 15)


def test_the_volume_before_agrees_with_a_brute_force_winding_number(tmp_path):
    s = trimesh.creation.icosphere(subdivisions=3, radius=10.0)
    faces = s.faces[s.triangles_center[:, 2] < 7.0]      # a cap cut off: one 48-edge hole, not flat
    mesh = load_model(save(tmp_path, "capless.stl", s.vertices, faces))
    r = report(mesh)
    expected = brute_winding_volume(s.vertices, faces)
    assert r.volume_before_mm3 == pytest.approx(expected, rel=0.01)
    assert r.volume_after_mm3 == pytest.approx(mesh.volume)
    assert 0 < r.volume_change <= MAX_VOLUME_CHANGE            # the fill is kept


def test_a_t_junction_is_closed_with_a_sliver(tmp_path):
    # a CAD export's defect: the +y face has a vertex in the middle of its top edge, the top
    # face does not: a slit of 3 open edges and no area
    b = trimesh.creation.box((20.0, 20.0, 20.0))
    keep = b.faces[b.face_normals[:, 1] < 0.5]
    corner = {tuple(np.round(p).astype(int)): k for k, p in enumerate(b.vertices)}
    a, bb, c, d = (corner[p] for p in ((-10, 10, -10), (10, 10, -10), (10, 10, 10), (-10, 10, 10)))
    m = len(b.vertices)                                   # (0, 10, 10): on the edge c-d
    face = np.array([[a, d, m], [a, m, bb], [bb, m, c]])
    vertices = np.vstack([b.vertices, [0.0, 10.0, 10.0]])
    normals = np.cross(vertices[face[:, 1]] - vertices[face[:, 0]], vertices[face[:, 2]] - vertices[face[:, 0]])
    face[normals[:, 1] < 0] = face[normals[:, 1] < 0][:, ::-1]           # outward (+y)
    mesh = load_model(save(tmp_path, "t-junction.stl", vertices, np.vstack([keep, face])))
    assert mesh.is_watertight and mesh.volume == pytest.approx(8000.0, rel=1e-9)
    r = report(mesh)
    assert (r.holes_closed, r.open_edges_before, r.faces_added) == (1, 3, 1)
    assert r.fill_area_mm2 == pytest.approx(0.0, abs=1e-9)


def test_two_bodies_one_with_a_hole_are_both_kept(tmp_path):
    b = trimesh.creation.box((20.0, 20.0, 20.0))
    s = trimesh.creation.icosphere(subdivisions=2, radius=5.0)
    s.apply_translation((30.0, 0.0, 0.0))
    faces = np.concatenate([b.faces, np.delete(s.faces, [4, 100], axis=0) + len(b.vertices)])
    path = save(tmp_path, "two bodies.stl", np.concatenate([b.vertices, s.vertices]), faces)
    mesh = load_model(path)
    assert mesh.body_count == 2 and mesh.is_watertight
    volumes = sorted(body.volume for body in mesh.split(only_watertight=False))
    assert volumes == pytest.approx(sorted([8000.0, signed_volume(s.vertices, s.faces)]), rel=1e-6)
    assert report(mesh).holes_closed == 2


@pytest.mark.parametrize("cut", ["five triangles", "a cap"])
def test_a_large_mesh_gives_meshfix_only_the_triangles_near_the_holes(tmp_path, monkeypatch, cut):
    import ambots.repair
    monkeypatch.setattr(ambots.repair, "LOCAL_FILL_TRIANGLES", 100)     # 1280 triangles: the local way
    s = trimesh.creation.icosphere(subdivisions=3, radius=10.0)
    faces = (np.delete(s.faces, [0, 77, 200, 513, 1001], axis=0) if cut == "five triangles"
             else s.faces[s.triangles_center[:, 2] < 7.0])
    mesh = load_model(save(tmp_path, "local.stl", s.vertices, faces))
    assert mesh.is_watertight and mesh.body_count == 1
    r = report(mesh)
    if cut == "five triangles":
        assert (r.holes_closed, r.faces_added) == (5, 5)
        assert mesh.volume == pytest.approx(signed_volume(s.vertices, s.faces), rel=1e-6)
    else:                          # the same as MeshFix on the whole mesh
        monkeypatch.setattr(ambots.repair, "LOCAL_FILL_TRIANGLES", 10 ** 6)
        whole = load_model(save(tmp_path, "whole.stl", s.vertices, faces))
        assert r.holes_closed == 1 and r.faces_added == report(whole).faces_added
        assert mesh.volume == pytest.approx(whole.volume, rel=1e-9)
        assert mesh.area == pytest.approx(whole.area, rel=1e-9)


def test_overlapping_bodies_with_a_hole_are_closed_then_united(tmp_path):
    # parts exported as one mesh, one of them open: closed by MeshFix, then united by manifold3d
    a, b = trimesh.creation.box((20.0, 20.0, 20.0)), trimesh.creation.box((20.0, 20.0, 20.0))
    b.apply_translation((10.0, 0.0, 0.0))                       # overlaps a by half
    faces = np.concatenate([a.faces, b.faces[b.face_normals[:, 2] > -0.5] + len(a.vertices)])
    mesh = load_model(save(tmp_path, "parts.stl", np.concatenate([a.vertices, b.vertices]), faces))
    assert mesh.is_watertight and mesh.body_count == 1
    assert mesh.volume == pytest.approx(30.0 * 20.0 * 20.0, rel=1e-9)
    r = report(mesh)
    assert (r.holes_closed, r.shells_merged) == (1, 2)


# ------------------------------------------------------------- refused

def test_a_fill_that_would_bulge_is_refused_with_the_figures(tmp_path):
    s = trimesh.creation.icosphere(subdivisions=3, radius=10.0)
    c = s.triangles_center
    faces = s.faces[~((c[:, 0] > 0) & (c[:, 2] > 0))]   # an octant's quarter of the surface gone
    path = save(tmp_path, "octant.stl", s.vertices, faces)
    with pytest.raises(MeshError) as info:
        load_model(path)
    msg = str(info.value)
    assert msg.startswith("octant.stl: not a closed volume: 48 open edges in 1 hole, too large to repair: ")
    assert "too large to repair: repair would change the volume from " in msg
    before, after = (float(x) for x in msg.split("volume from ")[1].split(" mm^3")[0].split(" to "))
    change = float(msg.split("mm^3 (")[1].split(" %")[0])
    assert before == pytest.approx(brute_winding_volume(s.vertices, faces), rel=0.01)
    assert change == pytest.approx(100 * (after - before) / before, abs=0.06)
    assert change > 100 * MAX_VOLUME_CHANGE and "more than 3 %" in msg
    assert "of the surface" not in msg                # a quarter of the surface: the area is not the reason


def test_a_band_is_refused_for_its_fill_area(tmp_path):
    n, r, h = 64, 20.0, 10.0
    c = trimesh.creation.cylinder(radius=r, height=h, sections=n)
    faces = c.faces[np.abs(c.face_normals[:, 2]) < 0.5]          # no top, no bottom
    path = save(tmp_path, "band.stl", c.vertices, faces)
    with pytest.raises(MeshError) as info:
        load_model(path)
    msg = str(info.value)
    assert msg.startswith("band.stl: not a closed volume: 128 open edges in 2 holes, too large to repair")
    cap = 0.5 * n * r ** 2 * np.sin(2 * np.pi / n)               # an n-gon
    share = 2 * cap / (2 * cap + n * 2 * r * np.sin(np.pi / n) * h)
    assert share > MAX_FILL_AREA_SHARE
    assert "the fill would be %.1f mm^2, %.1f %% of the surface, more than 50 %%" % (2 * cap, 100 * share) in msg


def test_the_holes_are_judged_one_at_a_time(tmp_path):
    # a flat box with an open bottom and a small hole in the top: with both open, the
    # winding number of a thin slab above the bottom is under 0.5 (the deficits add up:
    # the brute force finds less than the box); each hole alone leaves the box whole
    b = box().subdivide().subdivide()
    faces = b.faces[b.face_normals[:, 2] > -0.5]
    top = trimesh.Trimesh(b.vertices, faces, process=False)
    gone = int(np.argmin(np.linalg.norm(top.triangles_center - (0.0, 0.0, BOX[2] / 2), axis=1)))
    faces = np.delete(faces, gone, axis=0)
    assert brute_winding_volume(b.vertices, faces) < 0.95 * np.prod(BOX)
    for one_hole in (b.faces[b.face_normals[:, 2] > -0.5], np.delete(b.faces, gone, axis=0)):
        assert brute_winding_volume(b.vertices, one_hole) == pytest.approx(np.prod(BOX), rel=0.01)
    mesh = load_model(save(tmp_path, "two holes.stl", b.vertices, faces))
    r = report(mesh)
    assert r.holes_closed == 2 and r.volume_before_mm3 == pytest.approx(np.prod(BOX), rel=1e-3)
    assert mesh.volume == pytest.approx(np.prod(BOX), rel=1e-9)


def test_holes_in_a_non_manifold_mesh_are_not_closed(tmp_path):
    a, b = trimesh.creation.box((20.0, 20.0, 20.0)), trimesh.creation.box((20.0, 20.0, 20.0))
    b.apply_translation((20.0, 0.0, 0.0))           # the cubes touch along a face: non-manifold edges
    top = np.flatnonzero(a.face_normals[:, 2] > 0.5)[:1]
    mesh = trimesh.util.concatenate([trimesh.Trimesh(a.vertices, np.delete(a.faces, top, axis=0)), b])
    mesh.merge_vertices()
    n_open = len(trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1))
    with pytest.raises(MeshError) as info:
        load_model(save(tmp_path, "touching.stl", mesh.vertices, mesh.faces))
    assert str(info.value).startswith("touching.stl: not a closed volume: %d open edges and " % n_open)
    assert "non-manifold edges" in str(info.value)



def test_holes_that_touch_at_a_corner_are_each_filled_alone(tmp_path):
    """Two triangles missing from a box that share one corner: one boundary
    pinched at that corner.  MeshFix alone filled it with triangles whose
    edges three triangles share; each hole's loop is now traced on its own
    (paired at the corner across the gap between the two fans) and filled
    alone, back to the intact box."""
    box = trimesh.creation.box((40.0, 40.0, 40.0)).subdivide().subdivide()
    F = box.faces
    corner = next(k for k in range(1, len(F)) if len(set(F[k]) & set(F[0])) == 1)
    faces = np.delete(F, [0, corner], axis=0)
    open_mesh = trimesh.Trimesh(box.vertices, faces, process=False)
    assert len(trimesh.grouping.group_rows(np.sort(open_mesh.edges, axis=1), require_count=1)) == 6
    loops, pinch = hole_loops(open_mesh)
    assert len(pinch) == 1 and sorted(len(loop) for loop in loops) == [3, 3]
    assert sorted(sorted(loop) for loop in loops) == sorted(sorted(f) for f in F[[0, corner]].tolist())
    mesh = load_model(save(tmp_path, "pinched.stl", box.vertices, faces))
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume == pytest.approx(40.0 ** 3, rel=1e-9)
    r = report(mesh)
    assert (r.holes_closed, r.faces_added, r.open_edges_before, r.open_edges_after) == (2, 2, 6, 0)
    assert r.fill_area_mm2 == pytest.approx(2 * box.area_faces[0], rel=1e-9)


def test_three_holes_around_one_vertex_are_told_apart_by_their_turn(tmp_path):
    """Every other triangle of a 6-triangle fan missing: three holes touch at
    its vertex, between three fans of one triangle each.  Past 'not its own
    fan' two edges are left; the one clockwise next (seen from outside) is
    the same hole's.  (Counter-clockwise gave one 9-edge loop through the
    vertex three times, and 63833 mm^3 for the 64000 mm^3 cube.)"""
    b = trimesh.creation.box((40.0, 40.0, 40.0)).subdivide().subdivide()
    v = int(np.flatnonzero((b.vertex_faces >= 0).sum(axis=1) == 6)[0])
    fan = [int(f) for f in b.vertex_faces[v] if f >= 0]
    ring = [fan.pop(0)]
    while fan:                              # the fan in order around v
        nxt = next(f for f in fan if len(set(b.faces[f]) & set(b.faces[ring[-1]])) == 2)
        ring.append(nxt)
        fan.remove(nxt)
    gone = ring[::2]
    faces = np.delete(b.faces, gone, axis=0)
    loops, pinch = hole_loops(trimesh.Trimesh(b.vertices, faces, process=False))
    assert pinch.tolist() == [v]
    assert sorted(sorted(loop) for loop in loops) == sorted(sorted(f) for f in b.faces[gone].tolist())
    mesh = load_model(save(tmp_path, "three.stl", b.vertices, faces))
    assert mesh.is_watertight and mesh.volume == pytest.approx(40.0 ** 3, rel=1e-9)
    assert report(mesh).holes_closed == 3


@pytest.mark.parametrize("model, seed", [("sphere", 0), ("sphere", 1), ("sphere", 2),
                                         ("box", 0), ("box", 1), ("box", 2)])
def test_a_model_with_25_random_triangles_missing_is_closed_near_its_intact_volume(tmp_path, model, seed):
    """25 triangles removed at random from a coarse model: holes that share
    edges (one larger hole) and holes that touch at corners.  The repaired
    model is closed, oriented, and within the rule of the intact volume (a
    formula for the box, the divergence theorem for the sphere)."""
    base = (trimesh.creation.icosphere(subdivisions=2, radius=20.0) if model == "sphere"
            else box().subdivide().subdivide())          # 320 / 192 triangles
    gone = np.random.default_rng(seed).choice(len(base.faces), 25, replace=False)
    faces = np.delete(base.faces, gone, axis=0)
    assert len(hole_loops(trimesh.Trimesh(base.vertices, faces, process=False))[1]) > 0     # pinched
    mesh = load_model(save(tmp_path, "random.stl", base.vertices, faces))
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.body_count == 1
    intact = signed_volume(base.vertices, base.faces)
    assert abs(mesh.volume - intact) <= MAX_VOLUME_CHANGE * intact
    if model == "sphere":   # convex: a flat fill is the triangle that was there, or cuts a little inside
        assert intact * (1 - 1e-3) <= mesh.volume <= intact * (1 + 1e-12)
    r = report(mesh)
    assert r.open_edges_after == 0 and r.volume_after_mm3 == pytest.approx(mesh.volume)


# ------------------------------------------------------ the must-show

def test_a_holey_model_is_repaired_and_planned_by_both_arms_without_contact(tmp_path):
    # an open bottom and a triangle missing in the middle of the top and of a long side:
    # three holes, 16 + 3 + 3 open edges (the bottom is cut into 4 x 4 edges by the subdivisions)
    b = box().subdivide().subdivide()
    faces = trimesh.Trimesh(b.vertices, open_bottom(b), process=False)
    gone = [int(np.argmin(np.linalg.norm(faces.triangles_center - 0.5 * np.multiply(BOX, axis), axis=1)))
            for axis in ((0, 0, 1), (0, 1, 0))]
    model = save(tmp_path, "holey.stl", b.vertices, np.delete(faces.faces, gone, axis=0))
    out = tmp_path / "plan"
    stdout, rep = plan_both_arms(model, out)
    assert "repaired: 3 holes closed" in stdout and "repaired mesh: model_repaired.stl" in stdout
    assert set(rep["arms"]) == {"kinova", "ur10"}
    for arm in ("kinova", "ur10"):
        assert os.path.getsize(out / (arm + ".gcode")) > 0 and rep["arms"][arm]["extrude_mm"] > 0
    job = json.loads((out / "job.json").read_text())
    r = job["repair"]
    assert (r["holes_closed"], r["open_edges_before"], r["open_edges_after"]) == (3, 22, 0)
    assert r["volume_after_mm3"] == pytest.approx(np.prod(BOX)) and r["path"] == "model_repaired.stl"
    assert rep["repair"] == r
    repaired = trimesh.load(str(out / "model_repaired.stl"))
    assert repaired.is_watertight and repaired.volume == pytest.approx(np.prod(BOX), rel=1e-6)
    np.testing.assert_allclose(repaired.extents, BOX, atol=1e-4)
    # the parts the arms printed add up to the closed model
    assert sum(trimesh.load(str(out / (a + ".stl"))).volume for a in ("kinova", "ur10")) == \
        pytest.approx(np.prod(BOX), rel=1e-3)


# ------------------------------------------------- a surface that crosses itself

SLOT_CUBE = 40.0                        # mm: a cube with a slot from the front to its middle


def slotted(h, gap=1.0):
    """A 40 mm cube with a slot ``gap`` wide (x), 20 mm deep (y >= 0), all
    its height (z 0..40); the vertex nearest the middle of the slot's wall
    at x = -gap/2 pushed ``h`` across (+x, and aside): a pyramid on that wall whose tip
    pokes ``h - gap`` into the other wall.  Returns (mesh, intended volume:
    the slotted cube plus the part of the pyramid in the slot (its tip,
    inside the other wall, is in the solid already), mm^3)."""
    import manifold3d as m3
    from ambots.mesh import from_manifold
    c = SLOT_CUBE
    m = from_manifold(m3.Manifold.cube([c, c, c]).translate([-c / 2, -c / 2, 0])
                      - m3.Manifold.cube([gap, c, c + 2]).translate([-gap / 2, 0, -1]))
    m = m.subdivide().subdivide().subdivide()
    m.merge_vertices()
    v = int(np.argmin(np.linalg.norm(m.vertices - (-gap / 2, c / 4, c / 2), axis=1)))
    assert np.isclose(m.vertices[v, 0], -gap / 2) and 0 < m.vertices[v, 1] < c / 2
    fan = m.faces[np.isin(m.faces, v).any(axis=1)]
    base = trimesh.Trimesh(m.vertices, fan, process=False).area          # flat: the pyramid's base
    slotted_volume = c ** 3 - gap * (c / 2) * c
    m.vertices[v] += (h, 0.6, 1.3)    # oblique (same volume): the pyramid's edges meet no edge of the wall
    return m, slotted_volume + base * h / 3.0 * (1.0 - ((h - gap) / h) ** 3)


@pytest.mark.parametrize("h", [1.5, 2.0])
def test_a_small_pyramid_poking_through_a_wall_is_repaired(tmp_path, h):
    from ambots.selfcross import self_intersections
    mesh, intended = slotted(h)
    assert mesh.is_watertight and mesh.is_winding_consistent and self_intersections(mesh)[0] > 0
    path = save(tmp_path, "poke.stl", mesh.vertices, mesh.faces)
    out = load_model(path)
    r = report(out)
    assert out.is_watertight and out.is_winding_consistent and self_intersections(out)[0] == 0
    assert r.changed and r.crossing_pairs > 0 and r.crossing_area_share <= 0.05
    # the "volume before" is the winding number's solid: the formula's
    assert r.volume_before_mm3 == pytest.approx(intended, rel=1e-3)
    assert out.volume == pytest.approx(intended, rel=MAX_VOLUME_CHANGE)
    assert out.volume == pytest.approx(SLOT_CUBE ** 3 - SLOT_CUBE ** 2 / 2, rel=1e-6)   # the pyramid gone
    assert r.volume_after_mm3 == pytest.approx(out.volume)
    assert any(n.startswith("surface crossed itself at") and "repaired by" in n
               for n in out.metadata["ambots_repairs"])


@pytest.mark.parametrize("jobs", ["1", "2"])
def test_the_job_plans_on_the_repaired_mesh_whether_the_search_runs_aside_or_not(tmp_path, monkeypatch, jobs):
    """With two processes the job searches for a crossing in a worker
    beside the planning (:func:`ambots.job.run_job`), with one in the load:
    either way the parts are cut from the repaired mesh (the pyramid gone:
    the slotted cube's volume by its formula), and the repair is noted."""
    from ambots.config import default_cell_path, load_cell
    from ambots.job import run_job
    from ambots.selfcross import self_intersections
    monkeypatch.setenv("AMBOTS_JOBS", jobs)
    mesh, _ = slotted(1.5)
    path = save(tmp_path, "poke.stl", mesh.vertices, mesh.faces)
    cell = load_cell(default_cell_path())
    job = run_job(path, cell, [cell.arm("ur10")])
    assert self_intersections(job.mesh)[0] == 0 and report(job.mesh).crossing_pairs > 0
    assert any(n.startswith("surface crossed itself at") for n in job.mesh.metadata["ambots_repairs"])
    assert job.mesh.volume == pytest.approx(SLOT_CUBE ** 3 - SLOT_CUBE ** 2 / 2, rel=1e-6)
    assert sum(p.volume for p in job.parts) == pytest.approx(job.mesh.volume, rel=1e-6)


def test_valid_models_cost_one_crossing_check_and_are_not_changed(tmp_path, monkeypatch):
    import ambots.selfcross
    from shapes import MODELS
    calls = []
    real = ambots.selfcross.crossing_pairs
    monkeypatch.setattr(ambots.selfcross, "crossing_pairs", lambda m: calls.append(1) or real(m))
    for name in sorted(MODELS):
        model = MODELS[name]()
        calls.clear()
        out = load_model(save(tmp_path, name + ".stl", model.vertices, model.faces))
        r = report(out)
        assert len(calls) == 1, name               # repair_mesh looked once; validate_mesh did not again
        assert not r.changed and r.crossing_pairs == 0 and len(out.faces) == len(model.faces)
        assert out.volume == pytest.approx(model.volume)


def test_a_crossing_repair_is_written_to_the_job_folder_and_planned_without_contact(tmp_path):
    mesh, intended = slotted(1.5)
    model = save(tmp_path, "poke.stl", mesh.vertices, mesh.faces)
    out = tmp_path / "plan"
    stdout, rep = plan_both_arms(model, out)
    assert "repaired: surface crossed itself" in stdout and "repaired mesh: model_repaired.stl" in stdout
    r = json.loads((out / "job.json").read_text())["repair"]
    assert r["crossing_pairs"] > 0 and r["path"] == "model_repaired.stl"
    assert r["volume_before_mm3"] == pytest.approx(intended, rel=1e-3)
    repaired = trimesh.load(str(out / "model_repaired.stl"))
    assert repaired.is_watertight and repaired.volume == pytest.approx(intended, rel=MAX_VOLUME_CHANGE)
    assert sum(trimesh.load(str(out / (a + ".stl"))).volume for a in ("kinova", "ur10")) == \
        pytest.approx(repaired.volume, rel=1e-3)


def plan_both_arms(model, out):
    """``python -m ambots plan`` of ``model`` on both arms into ``out``: (its
    output, report.json), the print finished without a contact."""
    run = subprocess.run([sys.executable, "-m", "ambots", "plan", model, "--arms", "kinova,ur10",
                          "--out", str(out)], capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stdout + run.stderr
    rep = json.loads((out / "report.json").read_text())
    assert rep["finished"] and rep["collisions"] == {"arm_arm": 0, "arm_bed": 0, "arm_part": 0}
    return run.stdout, rep
