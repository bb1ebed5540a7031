"""Model input: formats, repair, refusals, placement (ambots.mesh)."""
import os
import re

import numpy as np
import pytest
import trimesh

from ambots.errors import MeshError
from ambots.mesh import (check_fits, from_manifold, load_model, place_on_bed,
                         to_manifold)
from ambots.selfcross import self_intersections


from shapes import MODELS, cube, cylinder, overhang  # tests/unit/shapes.py
FORMATS = {"stl-binary": ("stl", "stl"), "stl-ascii": ("stl", "stl_ascii"),
           "obj": ("obj", "obj"), "ply": ("ply", "ply"), "3mf": ("3mf", "3mf")}


def write(path, mesh, file_type=None):
    mesh.export(str(path), file_type=file_type)
    return str(path)


def refusal(path, **kwargs):
    """The MeshError message of loading ``path``; it must name the file."""
    with pytest.raises(MeshError) as info:
        load_model(path, **kwargs)
    message = str(info.value)
    assert os.path.basename(str(path)) in message
    return message


# ------------------------------------------------------------------ formats

@pytest.mark.parametrize("name", sorted(MODELS))
def test_a_binary_stl_is_read_as_trimesh_reads_it(tmp_path, name):
    """The binary STL reader (one numpy call) gives the vertices and
    triangles of trimesh's own loader, to the bit, also for a header that
    begins with "solid" (a binary file by its size) and for a triangle with
    repeated corners; an ASCII STL is left to trimesh."""
    from ambots.mesh import _read, _read_binary_stl
    original = MODELS[name]()
    original.vertices[original.faces[0, 1]] = original.vertices[original.faces[0, 0]]  # a degenerate triangle
    path = write(tmp_path / "model.stl", original)
    with open(path, "r+b") as f:                   # a header that looks like ASCII STL
        f.write(b"solid made by a CAD tool")
    ours = _read(path, "model.stl", "stl")
    theirs = trimesh.load(path, file_type="stl", force="mesh", process=False)
    assert _read_binary_stl(path) is not None and len(ours.faces) == len(original.faces)
    assert ours.vertices.dtype == theirs.vertices.dtype and np.array_equal(ours.vertices, theirs.vertices)
    assert np.array_equal(ours.faces, theirs.faces)
    ascii_path = write(tmp_path / "ascii.stl", original, "stl_ascii")
    assert _read_binary_stl(ascii_path) is None
    assert np.array_equal(_read(ascii_path, "ascii.stl", "stl").faces,
                          trimesh.load(ascii_path, file_type="stl", force="mesh", process=False).faces)


@pytest.mark.parametrize("fmt", sorted(FORMATS))
@pytest.mark.parametrize("name", sorted(MODELS))
def test_round_trip_in_every_format(tmp_path, name, fmt):
    ext, file_type = FORMATS[fmt]
    original = MODELS[name]()
    path = write(tmp_path / ("model." + ext), original, file_type)
    if fmt == "stl-ascii":
        assert open(path, "rb").read(5) == b"solid"
    if fmt == "stl-binary":
        assert os.path.getsize(path) == 84 + 50 * len(original.faces)
    mesh = load_model(path)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume == pytest.approx(original.volume, rel=1e-5)
    np.testing.assert_allclose(mesh.bounds, original.bounds, atol=1e-4)
    assert mesh.metadata["ambots_source"] == "model." + ext


def test_scale_converts_to_millimetres(tmp_path):
    path = write(tmp_path / "inches.obj", trimesh.creation.box((1.0, 2.0, 0.5)))
    mesh = load_model(path, scale=25.4)
    np.testing.assert_allclose(mesh.extents, [25.4, 50.8, 12.7])
    assert "scale" in refusal(path, scale=-1.0)


# ------------------------------------------------------------------- repair

def test_flipped_faces_are_fixed(tmp_path):
    box = cube()
    faces = box.faces.copy()
    faces[[0, 4, 7]] = faces[[0, 4, 7], ::-1]
    path = write(tmp_path / "flipped.stl", trimesh.Trimesh(box.vertices, faces, process=False))
    mesh = load_model(path)
    assert mesh.is_winding_consistent
    assert mesh.volume == pytest.approx(8000.0)
    assert any("flipped 3 triangles" in note for note in mesh.metadata["ambots_repairs"])
    assert "not consistently oriented" in refusal(path, repair=False)


def test_inside_out_mesh_is_turned_outward(tmp_path):
    box = cube()
    path = write(tmp_path / "inverted.ply",
                 trimesh.Trimesh(box.vertices, box.faces[:, ::-1], process=False))
    assert load_model(path).volume == pytest.approx(8000.0)
    assert "normals point inward" in refusal(path, repair=False)


def test_missing_face_is_filled(tmp_path):
    box = cube()
    path = write(tmp_path / "missing.stl",
                 trimesh.Trimesh(box.vertices, box.faces[1:], process=False))
    mesh = load_model(path)
    assert mesh.is_watertight and len(mesh.faces) == 12
    assert mesh.volume == pytest.approx(8000.0)
    assert "not a closed volume: 3 open edges" in refusal(path, repair=False)


def test_an_open_top_is_closed_and_a_band_is_refused(tmp_path):
    tube = cylinder()          # 48 sections: the top cap is bounded by 48 edges
    top = tube.face_normals[:, 2] > 0.99
    path = write(tmp_path / "open top.stl",
                 trimesh.Trimesh(tube.vertices, tube.faces[~top], process=False))
    mesh = load_model(path)    # a flat 48-edge hole: closed, the volume of the intact cylinder
    assert mesh.is_watertight and mesh.volume == pytest.approx(tube.volume, rel=1e-6)
    assert "not a closed volume: 48 open edges" in refusal(path, repair=False)
    ring = trimesh.creation.cylinder(radius=8.0, height=4.0, sections=48)
    side = np.abs(ring.face_normals[:, 2]) < 0.5     # no top, no bottom: a band, 2/3 of it missing
    path = write(tmp_path / "band.stl", trimesh.Trimesh(ring.vertices, ring.faces[side], process=False))
    assert "not a closed volume: 96 open edges in 2 holes, too large to repair" in refusal(path)


def test_overlapping_shells_are_merged(tmp_path):
    a, b = cube(), cube()
    b.apply_translation((10.0, 0.0, 0.0))   # overlaps a by half: a self-intersecting mesh
    path = write(tmp_path / "two parts.stl", trimesh.util.concatenate([a, b]))
    mesh = load_model(path)
    assert mesh.volume == pytest.approx(12000.0)
    assert mesh.body_count == 1
    assert any("self-intersection" in note for note in mesh.metadata["ambots_repairs"])


def test_a_cavity_stays_a_cavity(tmp_path):
    outer = trimesh.creation.box((20.0, 20.0, 20.0))
    inner = trimesh.creation.box((10.0, 10.0, 10.0))
    inner.invert()
    path = write(tmp_path / "hollow.stl", trimesh.util.concatenate([outer, inner]))
    assert load_model(path).volume == pytest.approx(8000.0 - 1000.0)


def spike():
    """One shell that crosses itself: the centre of the top of a 20 mm cube
    (192 triangles) pushed down to z = -15, through the bottom (z = -10)."""
    b = trimesh.creation.box((20.0, 20.0, 20.0)).subdivide().subdivide()
    v = int(np.argmin(np.linalg.norm(b.vertices - (0.0, 0.0, 10.0), axis=1)))
    vertices = b.vertices.copy()
    vertices[v] = (0.0, 0.0, -15.0)
    return trimesh.Trimesh(vertices, b.faces, process=False)


def tubed():
    """Two 20 mm cubes overlapping (the second moved by (10, 5, 5)), made one
    shell: a triangle off each, joined by a tube of 6 triangles."""
    a, b = cube(), cube()
    b.apply_translation((10.0, 5.0, 5.0))
    ta = int(np.flatnonzero(a.face_normals[:, 1] > 0.5)[0])
    tb = int(np.flatnonzero(b.face_normals[:, 1] < -0.5)[0])
    la, lb = a.faces[ta][::-1], b.faces[tb][::-1] + 8           # the two holes' loops
    faces = np.vstack([np.delete(a.faces, ta, 0), np.delete(b.faces, tb, 0) + 8])
    vertices = np.vstack([a.vertices, b.vertices])
    for shift in range(3):                          # the tube that is closed and oriented
        lbb = np.roll(lb[::-1], shift)
        tube = [t for i in range(3) for t in ([la[(i + 1) % 3], la[i], lbb[i]],
                                              [la[(i + 1) % 3], lbb[i], lbb[(i + 1) % 3]])]
        mesh = trimesh.Trimesh(vertices, np.vstack([faces, tube]), process=False)
        if mesh.is_watertight and mesh.is_winding_consistent:
            return mesh
    raise AssertionError("no tube")


@pytest.mark.parametrize("make, where", [(spike, (-0.5, 0.5, -10.0)), (tubed, (0.0, 0.0, 10.0))],
                         ids=["spike through the bottom", "two cubes in one shell"])
def test_a_shell_that_crosses_itself_is_refused_naming_where(tmp_path, make, where):
    """Before: loaded without a word and sliced (the spike's protruding tip
    dropped, its volume 7375 mm^3 counted with the tip negative; the cubes'
    12000 mm^3, their union being 13750 mm^3)."""
    mesh = make()
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.body_count == 1
    n, points = self_intersections(mesh)
    assert n > 0 and np.allclose(points[0], where)
    message = refusal(write(tmp_path / "crossed.stl", mesh))
    assert message.startswith("crossed.stl: the surface crosses itself: %d pairs of triangles intersect, "
                              "at (%.2f, %.2f, %.2f)" % ((n,) + where)), message
    assert "mm (the model's frame)" in message and "not repaired" in message
    # the figure that broke the rule (ambots.selfcross.repair_crossings): too much of the surface changed
    shares = [float(x) for x in re.findall(r"([\d.]+) % of the surface, more than 5 %", message)]
    assert shares and min(shares) > 5.0, message


def test_valid_models_are_not_taken_for_self_intersecting():
    """Neighbours share corners and edges, cavities and unions of shells
    touch nothing: no false alarm; and a spike that only reaches the bottom
    face's plane from inside is not a crossing."""
    for mesh in [MODELS[k]() for k in sorted(MODELS)] + [
            trimesh.creation.icosphere(subdivisions=5, radius=50.0),       # 20,480 triangles
            trimesh.creation.torus(30.0, 5.0, major_sections=128, minor_sections=32),
            trimesh.creation.cylinder(radius=10.0, height=20.0, sections=256)]:    # long thin fans
        assert self_intersections(mesh)[0] == 0
    inner = trimesh.creation.box((10.0, 10.0, 10.0))
    inner.invert()
    assert self_intersections(trimesh.util.concatenate([cube(), inner]))[0] == 0
    s = spike()
    s.vertices[np.argmin(s.vertices[:, 2])] = (0.0, 0.0, -9.0)    # the dent stops 1 mm short
    assert self_intersections(s)[0] == 0


# ----------------------------------------------------------------- refusals

def test_empty_file(tmp_path):
    path = tmp_path / "empty.stl"
    path.write_bytes(b"")
    assert "file is empty" in refusal(path)


@pytest.mark.parametrize("ext", ["stl", "obj", "ply", "3mf"])
def test_random_bytes(tmp_path, ext):
    path = tmp_path / ("noise." + ext)
    path.write_bytes(np.random.default_rng(1).bytes(3001))
    message = refusal(path)
    assert "not a readable" in message or "contains no triangles" in message


@pytest.mark.parametrize("ext", ["stl", "obj", "ply", "3mf"])
def test_text_file(tmp_path, ext):
    path = tmp_path / ("notes." + ext)
    path.write_text("Shopping list:\n- filament\n- nozzles\n")
    message = refusal(path)
    assert "not a readable" in message or "contains no triangles" in message


def test_unknown_extension_and_missing_file(tmp_path):
    path = write(tmp_path / "model.step", cube(), "stl")
    assert "unknown model format '.step'" in refusal(path)
    assert "no such file" in refusal(tmp_path / "absent.stl")


def test_zero_volume(tmp_path):
    # a closed tetrahedron whose four corners lie in one plane
    corners = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [10, 10, 0]], dtype=float)
    faces = [[0, 1, 2], [1, 3, 2], [0, 2, 3], [0, 3, 1]]
    path = write(tmp_path / "flat.stl", trimesh.Trimesh(corners, faces, process=False))
    assert "zero volume" in refusal(path)


@pytest.mark.parametrize("bad", ["nan", "inf"])
def test_non_finite_vertices(tmp_path, bad):
    path = tmp_path / "broken.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 %s\n" % bad
                    + "f 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n")
    assert "1 vertices have NaN or infinite coordinates" in refusal(path)


def test_triangle_limit(tmp_path):
    stl = write(tmp_path / "big.stl", cube())          # checked from the binary header
    obj = write(tmp_path / "big.obj", cube())          # checked after reading
    for path in (stl, obj):
        assert "12 triangles, more than the limit of 10" in refusal(path, max_triangles=10)
    assert len(load_model(stl, max_triangles=12).faces) == 12


def test_every_refusal_is_a_mesh_error_not_a_traceback(tmp_path):
    for i, content in enumerate([b"\x00" * 84, b"solid x\nfacet normal 0 0 1\n", b"\xff" * 200]):
        path = tmp_path / ("odd%d.stl" % i)
        path.write_bytes(content)
        refusal(path)


# ---------------------------------------------------------- placement, fit

def test_place_on_bed_centres_the_bounding_box():
    mesh = overhang()
    mesh.apply_translation((7.0, -3.0, 5.0))
    placed = place_on_bed(mesh, bed_center_xy_mm=(100.0, 50.0), bed_z_mm=2.0)
    lo, hi = placed.bounds
    np.testing.assert_allclose((lo[:2] + hi[:2]) / 2.0, [100.0, 50.0])
    assert lo[2] == pytest.approx(2.0)
    np.testing.assert_allclose(placed.extents, mesh.extents)
    assert mesh.bounds[0][2] == pytest.approx(5.0)        # the input is not moved
    np.testing.assert_allclose(place_on_bed(mesh).bounds[0], [-12.0, -3.0, 0.0])


def test_check_fits_says_by_how_much():
    wide = trimesh.creation.box((230.0, 20.0, 10.0))
    with pytest.raises(MeshError, match=r"model is 230\.0 mm wide in x, bed is 200\.0 mm: "
                                        r"30\.0 mm too large"):
        check_fits(wide, (200.0, 200.0), 100.0)
    tall = trimesh.creation.box((20.0, 250.0, 120.0))
    with pytest.raises(MeshError) as info:
        check_fits(tall, (200.0, 200.0), 100.0)
    assert "250.0 mm deep in y, bed is 200.0 mm: 50.0 mm too large" in str(info.value)
    assert "120.0 mm high, maximum height is 100.0 mm: 20.0 mm too large" in str(info.value)
    check_fits(cube(), (20.0, 20.0), 20.0)   # exactly fits


# --------------------------------------------------------------- manifold3d

@pytest.mark.parametrize("name", sorted(MODELS))
def test_manifold_round_trip(name):
    mesh = MODELS[name]()
    solid = to_manifold(mesh)
    assert solid.volume() == pytest.approx(mesh.volume, rel=1e-9)
    back = from_manifold(solid)
    assert back.is_watertight and back.volume == pytest.approx(mesh.volume, rel=1e-9)


def test_to_manifold_refuses_an_open_mesh():
    box = cube()
    with pytest.raises(MeshError, match="NotManifold"):
        to_manifold(trimesh.Trimesh(box.vertices, box.faces[1:], process=False))


def _fresh_manifold(mesh):
    import manifold3d
    return manifold3d.Manifold(manifold3d.Mesh64(vert_properties=np.array(mesh.vertices, dtype=np.float64),
                                                 tri_verts=np.array(mesh.faces, dtype=np.uint64)))


@pytest.mark.parametrize("offset", [(0.0, 0.0, 0.0), (3.3, -7.1, 11.7), (900.0, 700.0, 300.0)])
def test_a_placed_mesh_gets_the_manifold_a_fresh_conversion_would_make(offset):
    """place_on_bed carries the load's Manifold to the placed copy only when
    it is the one converting the copy makes (vertices, triangles, tolerance:
    a model moved from far away towards the origin is converted again)."""
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=30.0)
    mesh.apply_translation(offset)
    to_manifold(mesh)
    placed = place_on_bed(mesh)
    got, fresh = to_manifold(placed), _fresh_manifold(placed)
    assert got.get_tolerance() == fresh.get_tolerance()
    for a, b in ((got, fresh), (got.trim_by_plane([1.0, 0.3, 0.0], 0.7), fresh.trim_by_plane([1.0, 0.3, 0.0], 0.7))):
        a, b = a.to_mesh64(), b.to_mesh64()
        assert np.array_equal(a.vert_properties, b.vert_properties) and np.array_equal(a.tri_verts, b.tri_verts)
    placed.vertices[0] += 0.5                              # changed since: converted again
    assert np.array_equal(to_manifold(placed).to_mesh64().vert_properties,
                          _fresh_manifold(placed).to_mesh64().vert_properties)


def test_edge_counts_are_counted_again_after_a_change():
    from ambots.mesh import nonmanifold_edge_count, open_edge_count
    mesh = cube()
    assert (open_edge_count(mesh), nonmanifold_edge_count(mesh)) == (0, 0)
    mesh.update_faces(np.arange(1, len(mesh.faces)))      # a triangle removed: a hole of 3 edges
    assert (open_edge_count(mesh), nonmanifold_edge_count(mesh)) == (3, 0)
    mesh.faces = np.concatenate([mesh.faces, mesh.faces[:1], mesh.faces[:1]])   # edges used 3 or 4 times
    uses = np.unique(mesh.edges_sorted, axis=0, return_counts=True)[1]
    assert (open_edge_count(mesh), nonmanifold_edge_count(mesh)) == ((uses == 1).sum(), (uses > 2).sum())
    assert nonmanifold_edge_count(mesh) > 0


@pytest.mark.parametrize("name", sorted(MODELS) + ["sphere", "soup"])
def test_weld_is_trimesh_merge_vertices(tmp_path, name):
    """ambots.mesh.weld gives what trimesh's merge_vertices(merge_tex=True,
    merge_norm=True) gives: the same vertices in the same order, the same triangles."""
    from ambots.mesh import weld
    rng = np.random.default_rng(3)
    if name == "soup":                   # repeated points at several scales, unreferenced ones
        pts = np.repeat(rng.random((60, 3)) * 10.0 ** rng.integers(-4, 3, (60, 1)), 3, axis=0)[rng.permutation(180)]
        read = lambda: trimesh.Trimesh(pts, rng.integers(0, 170, (120, 3)), process=False)
    else:
        shape = trimesh.creation.icosphere(subdivisions=4, radius=30.0) if name == "sphere" else MODELS[name]()
        path = write(tmp_path / "m.stl", shape)
        read = lambda: trimesh.load(path, process=False)
    ours, theirs = read(), read()
    if name == "soup":
        theirs = trimesh.Trimesh(ours.vertices.copy(), ours.faces.copy(), process=False)
    weld(ours)
    theirs.merge_vertices(merge_tex=True, merge_norm=True)
    assert np.array_equal(ours.vertices, theirs.vertices) and np.array_equal(ours.faces, theirs.faces)


@pytest.mark.parametrize("name", sorted(MODELS) + ["inside-out", "soup"])
def test_signed_volume_is_trimesh_volume_to_the_bit(name):
    from ambots.mesh import signed_volume
    if name == "soup":
        rng = np.random.default_rng(5)
        mesh = trimesh.Trimesh(rng.random((30, 3)) * 100 - 50, rng.integers(0, 30, (40, 3)), process=False)
    else:
        mesh = MODELS["overhang" if name == "inside-out" else name]()
        if name == "inside-out":
            mesh.invert()
    assert signed_volume(mesh) == float(mesh.volume)
