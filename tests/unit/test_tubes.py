"""ambots.tubes: the shaded bead tubes of the RViz deposit markers, checked
independently of the formulas that build them: cross-sections cut out of
the triangles, inside/outside tests against the faces' own planes,
normals from the winding, areas by the shoelace formula."""
import numpy as np
import pytest

from ambots.deposit import bead_area_m2, bead_boxes
from ambots.tubes import LIGHT, bead_tubes, exposed, face_normals, merge_beads, section, shade, tube_triangles


def _cut(tris, point, normal, along=False):
    """The points (N, 3) where a plane through ``point`` with ``normal`` cuts
    the triangles' edges (duplicates at shared edges merged); ``along``: only
    edges parallel to ``normal`` (a tube's long edges: its section's corners)."""
    out = []
    for t in tris:
        s = (t - point) @ normal
        for a, b in ((0, 1), (1, 2), (2, 0)):
            d = t[b] - t[a]
            if along and np.linalg.norm(d - (d @ normal) * normal) > 1e-6 * np.linalg.norm(d):
                continue
            if s[a] * s[b] < 0:
                out.append(t[a] + d * s[a] / (s[a] - s[b]))
    return np.unique(np.round(np.array(out), 12), axis=0)


def _polygon_area(P, normal):
    """Area of the convex polygon P (N, 3) in a plane with unit ``normal``:
    vertices sorted by angle about their centroid, then the shoelace formula."""
    c = P.mean(axis=0)
    e1 = P[0] - c
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    x, y = (P - c) @ e1, (P - c) @ e2
    order = np.argsort(np.arctan2(y, x))
    x, y = x[order], y[order]
    return 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


SEGMENTS = [  # start, end (m): along x, diagonal, sloped, along -y
    ((0.0, 0.0, 0.2e-3), (0.02, 0.0, 0.2e-3)),
    ((0.01, 0.01, 0.4e-3), (0.013, 0.017, 0.4e-3)),
    ((0.0, 0.0, 1e-3), (0.01, 0.005, 3e-3)),
    ((-0.005, 0.02, 0.6e-3), (-0.005, -0.01, 0.6e-3)),
]


@pytest.mark.parametrize("sides", [6, 7, 8])
@pytest.mark.parametrize("seg", SEGMENTS)
def test_cross_section_has_the_bead_area_and_height(seg, sides):
    a, b = np.array(seg[0]), np.array(seg[1])
    area, height = 0.45e-3 * 0.2e-3 * 0.9, 0.2e-3
    tris = tube_triangles(a[None], b[None], area, height, sides)
    u = (b - a) / np.linalg.norm(b - a)
    for f in (0.25, 0.5, 0.9):
        P = _cut(tris, a + f * (b - a), u, along=True)
        assert len(P) == sides
        assert _polygon_area(P, u) == pytest.approx(area, rel=1e-9)
        # the faces' diagonals cross the plane on the polygon's sides: same outline
        assert _polygon_area(_cut(tris, a + f * (b - a), u), u) == pytest.approx(area, rel=1e-9)
    # the nozzle path is the top of the bead; the bead is `height` tall
    # (perpendicular to the segment, in its vertical plane)
    up = np.array([0.0, 0.0, 1.0]) - u[2] * u
    up /= np.linalg.norm(up)
    P = _cut(tris, (a + b) / 2, u)
    rel = (P - (a + b) / 2) @ up
    assert rel.max() == pytest.approx(0.0, abs=1e-12)
    assert rel.min() == pytest.approx(-height, rel=1e-9)


@pytest.mark.parametrize("sides", [6, 8])
def test_triangle_count_and_outward_winding(sides):
    starts = np.array([s for s, _ in SEGMENTS])
    ends = np.array([e for _, e in SEGMENTS])
    tris = tube_triangles(starts, ends, 0.09e-6, 0.2e-3, sides)
    assert tris.shape == (len(SEGMENTS) * 2 * sides, 3, 3)
    n = face_normals(tris)
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0)
    for i, (s, e) in enumerate(zip(starts, ends)):
        mine = slice(2 * sides * i, 2 * sides * (i + 1))
        u = (e - s) / np.linalg.norm(e - s)
        # the tube's axis: the centroid of a cut through the middle
        axis_mid = _cut(tris[mine], (s + e) / 2, u).mean(axis=0)
        c = tris[mine].mean(axis=1)
        radial = (c - axis_mid) - np.outer((c - axis_mid) @ u, u)
        assert np.all(np.sum(n[mine] * radial, axis=1) > 0), "a face points into its tube"
        assert np.allclose(n[mine] @ u, 0.0, atol=1e-9), "a face is not parallel to its segment"


def test_the_tube_encloses_its_axis_and_ends_at_the_segment_ends():
    s, e = np.array(SEGMENTS[1][0]), np.array(SEGMENTS[1][1])
    height = 0.2e-3
    tris = tube_triangles(s[None], e[None], 0.09e-6, height)
    n = face_normals(tris)
    # points of the axis (the segment, height/2 down) are inside every face's plane
    axis = s + np.linspace(0.0, 1.0, 11)[:, None] * (e - s) - [0.0, 0.0, height / 2]
    signed = axis @ n.T - np.sum(tris[:, 0, :] * n, axis=1)[None]      # (points, faces)
    assert np.all(signed < -0.2 * height / 2)
    # ... and the tube spans exactly the segment: no vertex before s or after e
    u = (e - s) / np.linalg.norm(e - s)
    along = (tris.reshape(-1, 3) - s) @ u
    assert along.min() == pytest.approx(0.0, abs=1e-12)
    assert along.max() == pytest.approx(np.linalg.norm(e - s), rel=1e-12)


def test_tube_fits_the_deposit_box_height_and_volume():
    """The tube and the deposit's box of the same bead: same top, bottom and
    cross-section (so the same volume); the 6-sided tube is wider (4/3) with
    a flat top 2/3 of the box's width."""
    s, e = np.array([[0.0, 0.0, 0.4e-3]]), np.array([[0.01, 0.0, 0.4e-3]])
    area, h = np.array([0.085e-6]), np.array([0.2e-3])
    box = bead_boxes(s, e, area, h)[0]
    tris = tube_triangles(s, e, area, h, 6)
    V = tris.reshape(-1, 3)
    assert V[:, 2].max() == pytest.approx(box[:, 2].max(), abs=1e-15)
    assert V[:, 2].min() == pytest.approx(box[:, 2].min(), abs=1e-15)
    box_w = np.ptp(box[:, 1])
    assert np.ptp(V[:, 1]) == pytest.approx(4 / 3 * box_w, rel=1e-9)
    top = V[np.isclose(V[:, 2], box[:, 2].max(), atol=1e-12)]
    assert np.ptp(top[:, 1]) == pytest.approx(2 / 3 * box_w, rel=1e-9)


def test_section_rejects_fewer_than_three_sides():
    with pytest.raises(ValueError):
        section(1e-7, 2e-4, 2)


def _polyline(points, e_per_m=30.0):
    P = np.asarray(points, dtype=float)
    p0, p1 = P[:-1], P[1:]
    e = np.linalg.norm(p1 - p0, axis=1) * e_per_m
    return p0, p1, bead_area_m2(p0, p1, e)


def test_merge_joins_collinear_waypoints_and_keeps_corners_and_volume():
    # a square loop, each side laid as 10 beads (as the firmware lays a G-code line)
    corners = np.array([[0, 0, 0], [0.02, 0, 0], [0.02, 0.02, 0], [0, 0.02, 0], [0, 0, 0]], float)
    pts = np.concatenate([np.linspace(a, b, 11)[:-1] for a, b in zip(corners[:-1], corners[1:])] + [corners[-1:]])
    p0, p1, area = _polyline(pts)
    line = np.repeat(np.arange(4), 10)
    s, e, a, first = merge_beads(p0, p1, area, keys=(line,))
    np.testing.assert_allclose(s, corners[:-1], atol=1e-15)
    np.testing.assert_allclose(e, corners[1:], atol=1e-15)
    assert first.tolist() == [0, 10, 20, 30]
    vol = np.sum(np.linalg.norm(p1 - p0, axis=1) * area)
    assert np.sum(np.linalg.norm(e - s, axis=1) * a) == pytest.approx(vol, rel=1e-12)


def test_merge_never_joins_across_keys_gaps_or_off_the_chord():
    pts = np.linspace([0, 0, 0], [0.01, 0, 0], 6)
    p0, p1, area = _polyline(pts)
    # another layer from bead 2 on; a gap before bead 4
    layer = np.array([0, 0, 1, 1, 1])
    p0[4] += [0, 1e-4, 0]
    s, e, a, first = merge_beads(p0, p1, area, keys=(layer,))
    assert first.tolist() == [0, 2, 4]
    # an arc cut into chords leaves its chord by more than the tolerance: split
    t = np.linspace(0, np.pi / 2, 31)
    arc = np.c_[0.01 * np.cos(t), 0.01 * np.sin(t), np.zeros_like(t)]
    q0, q1, qa = _polyline(arc)
    s, e, a, first = merge_beads(q0, q1, qa, tol_m=5e-5)
    pts_all = np.concatenate([q0, q1[-1:]])
    for i, (a_, b_) in enumerate(zip(s, e)):      # every waypoint within tolerance of its segment
        lo, hi = first[i], (first[i + 1] if i + 1 < len(first) else len(q0))
        inner = pts_all[lo:hi + 1]
        u = (b_ - a_) / np.linalg.norm(b_ - a_)
        x = inner - a_
        dev = np.linalg.norm(x - np.outer(x @ u, u), axis=1)
        assert dev.max() <= 5e-5 + 1e-15
    assert 1 < len(s) < len(q0)
    np.testing.assert_allclose(s[1:], e[:-1])      # the pieces still join


def test_merge_of_nothing():
    s, e, a, first = merge_beads(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))
    assert s.shape == (0, 3) and len(first) == 0
    tris, colours = bead_tubes(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), 2e-4, (1, 0, 0))
    assert tris.shape == (0, 3, 3) and colours.shape == (0, 4)


def test_shading_is_brighter_on_top_and_varies_around_the_tube():
    s, e = np.array([[0.0, 0.0, 0.2e-3]]), np.array([[0.02, 0.0, 0.2e-3]])
    tris = tube_triangles(s, e, 0.09e-6, 0.2e-3, 6)
    n = face_normals(tris)
    colour = (1.0, 0.5, 0.0, 1.0)
    c = shade(n, colour)
    assert c.shape == (len(tris), 4)
    assert np.all(c[:, 3] == 1.0)
    # within the arm's colour, never brighter; the hue kept (g/r = 0.5)
    assert np.all(c[:, :3] <= np.array(colour[:3]) + 1e-12)
    np.testing.assert_allclose(c[:, 1], 0.5 * c[:, 0])
    up, down = n[:, 2] > 0.1, n[:, 2] < -0.1
    assert up.sum() == 6 and down.sum() == 6                 # top and two upper sides; bottom and two lower
    assert c[up, 0].min() > c[down, 0].max() + 0.2           # a wall shows each layer as light over dark
    assert c[down, 0].max() == pytest.approx(0.3)            # turned away: ambient only
    assert len(np.unique(np.round(c[:, 0], 9))) >= 4         # not one flat colour
    # the face turned most to the light is the brightest
    assert np.argmax(c[:, 0]) == np.argmax(n @ LIGHT)
    # the light is a unit vector from above
    assert np.linalg.norm(LIGHT) == pytest.approx(1.0) and LIGHT[2] > 0.7


def test_bead_tubes_counts_and_drops_empty_beads():
    pts = np.linspace([0, 0, 0.2e-3], [0.01, 0, 0.2e-3], 5)
    p0, p1, area = _polyline(pts)
    area[1] = 0.0                       # a travel (no filament) between two extruded pieces
    tris, colours = bead_tubes(p0, p1, area, 0.2e-3, (0.2, 0.4, 1.0), sides=6)
    # beads 0 and 2-3: bead 0 alone, 2 and 3 merged -> 2 segments, 12 triangles each
    assert tris.shape == (2 * 12, 3, 3) and colours.shape == (24, 4)


def _layer(z, x0=0.0, x1=0.02, y0=0.0, y1=0.004, spacing=0.4e-3, infill_gap=None):
    """Segments of one layer at nozzle height z: the outline (4 segments,
    counter-clockwise), then lines along x inside it, ``spacing`` apart
    (solid) or ``infill_gap`` apart (sparse)."""
    c = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1], [x0, y0]])
    s, e = list(c[:-1]), list(c[1:])
    gap = infill_gap or spacing
    for y in np.arange(y0 + spacing, y1 - spacing / 2, gap):
        s.append([x0 + spacing, y])
        e.append([x1 - spacing, y])
    s, e = np.array(s), np.array(e)
    return np.c_[s, np.full(len(s), z)], np.c_[e, np.full(len(e), z)]


def _stack(layers, h=0.2e-3, **kw):
    """(starts, ends, layer index, is-outline) of layers given as dicts of _layer keywords."""
    S, E, lay, outline = [], [], [], []
    for k, opts in enumerate(layers):
        s, e = _layer(h * (k + 1), **dict(kw, **opts))
        S.append(s), E.append(e), lay.append(np.full(len(s), k)), outline.append(np.arange(len(s)) < 4)
    return np.concatenate(S), np.concatenate(E), np.concatenate(lay), np.concatenate(outline)


AREA = 0.4e-3 * 0.2e-3          # a bead as wide as the spacing of the lines: a solid layer


def test_exposed_finds_the_beads_buried_in_a_solid_block():
    s, e, lay, outline = _stack([{}] * 6)
    top = lay == lay.max()
    vis = exposed(s, e, AREA, 0.2e-3, floor_z=0.0)
    assert vis[outline].all() and vis[top].all()            # the walls and the top are seen
    assert not vis[~outline & ~top].any()                     # everything under them is not
    # open below (no bed): the bottom layer is seen from under it too
    vis = exposed(s, e, AREA, 0.2e-3)
    assert vis[lay == 0].all() and not vis[~outline & (lay > 0) & ~top].any()


def test_exposed_sees_into_a_cavity_until_it_is_closed():
    sparse = {"infill_gap": 2e-3}
    closed = [{}] + [sparse] * 5 + [{}]                     # a solid floor, sparse infill, a solid roof
    s, e, lay, outline = _stack(closed, y1=0.008)
    vis = exposed(s, e, AREA, 0.2e-3, floor_z=0.0)
    inside = ~outline & (lay > 0) & (lay < 6)
    assert inside.sum() > 10 and not vis[inside].any()
    assert vis[lay == 6].all() and vis[outline].all()
    # without the roof the infill is seen from above, and the floor's top through its gaps
    s, e, lay, outline = _stack(closed[:-1], y1=0.008)
    vis = exposed(s, e, AREA, 0.2e-3, floor_z=0.0)
    assert vis[~outline & (lay > 0)].all()
    # the floor's lines are seen where no infill line lies right on top of them
    floor = ~outline & (lay == 0)
    y_infill = s[~outline & (lay == 1), 1]
    under = np.isin(np.round(s[floor, 1], 9), np.round(y_infill, 9))
    assert under.sum() == len(y_infill) == 4
    assert vis[floor].tolist() == (~under).tolist()


def test_exposed_single_and_none():
    assert exposed(np.zeros((0, 3)), np.zeros((0, 3)), AREA, 0.2e-3).shape == (0,)
    assert exposed([[0, 0, 2e-4]], [[0.01, 0, 2e-4]], AREA, 0.2e-3, floor_z=0.0).tolist() == [True]
