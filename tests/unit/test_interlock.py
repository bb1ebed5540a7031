"""The interlocking seam (``--seam interlock``, also ``overlap``) and the
bonded share of a seam's face.

Checked independently of ambots.seams: volumes against formulas; the
alternation by slicing the parts at each layer's mid-height (manifold3d
slices, shapely geometry) and comparing with the straight partition (its
own tests are test_partition's); the layers from the G-code settings'
formula (first layer 0.2 mm, then 0.2 mm); the bonded share recomputed
from the G-code the plan wrote (shapely rectangles of the extruding
moves) and compared with report.json's."""
import math
import os
import re

import manifold3d as m3
import numpy as np
import pytest
import shapely
import trimesh
from shapely.geometry import LineString, Polygon
from shapely.ops import unary_union

from ambots import data_path
from ambots.config import default_cell_path, load_cell
from ambots.partition import partition

W, H, H0 = 0.45, 0.2, 0.2                       # bead width, layer height, first layer (mm): SliceSettings'
#: the interlock depth the docs state: half a bead + one bead spacing (w - h (1 - pi/4))
D = W / 2 + (W - H * (1 - math.pi / 4))
FILAMENT_MM2 = math.pi * (1.75 / 2) ** 2
CELLS = ["kinova_ur10", "three_arms", "four_arms", "eight_arms_beam"]


def box(sx, sy, sz):
    return m3.Manifold.cube([sx, sy, sz]).translate([-sx / 2, -sy / 2, 0])


def mid_heights(z_max):
    """Mid-heights of the slicer's layers under ``z_max``, mm (first layer H0, then H)."""
    out, k = [], 0
    while True:
        z = H0 / 2 if k == 0 else H0 + H * (k - 1) + H / 2
        if z >= z_max:
            return np.array(out)
        out.append(z)
        k += 1


def section(manifold, z):
    """shapely (Multi)Polygon of a manifold's cross-section at z."""
    polys = [Polygon(p) for p in manifold.slice(float(z)).to_polygons() if len(p) >= 3]
    if not polys:
        return Polygon()
    # outer rings and holes: even-odd by symmetric difference
    out = polys[0]
    for p in polys[1:]:
        out = out.symmetric_difference(p)
    return out


@pytest.fixture(scope="module")
def cells():
    return {name: load_cell(data_path("config/cells/%s.yaml" % name)) for name in CELLS}


def bed_model(cell, height=1.0):
    """A box over 90 % of the cell's bed, ``height`` mm high."""
    sx, sy = cell.bed.size[0] * 900.0, cell.bed.size[1] * 900.0
    return box(sx, sy, height)


def test_layer_formula_matches_the_slicer():
    from ambots.slicer import SliceSettings, layer_heights
    tops, heights = layer_heights(3.0, SliceSettings())
    assert np.allclose(tops - heights / 2, mid_heights(3.0))


@pytest.mark.parametrize("name", CELLS)
def test_parts_are_closed_tile_the_model_and_alternate_every_layer(cells, name):
    cell = cells[name]
    model = bed_model(cell)
    sx, sy = cell.bed.size[0] * 900.0, cell.bed.size[1] * 900.0
    straight = partition(model, cell, seam="straight", check_reach=False)
    parts = partition(model, cell, seam="interlock", check_reach=False)
    assert len(parts) == len(cell.arms) >= 2
    for p in parts:                                    # one closed volume each
        mesh = p.to_trimesh()
        assert mesh.is_watertight and mesh.is_volume
        assert len(p.manifold.decompose()) == 1
    # union = the model (formula), nothing printed twice
    assert sum(p.volume for p in parts) == pytest.approx(sx * sy * 1.0, rel=1e-9)
    for i in range(len(parts)):
        for j in range(i + 1, len(parts)):
            assert (parts[i].manifold ^ parts[j].manifold).volume() <= 1e-6
    pairs = 0
    for k, z in enumerate(mid_heights(1.0)):
        inter = [section(p.manifold, z) for p in parts]
        flat = [section(p.manifold, z) for p in straight]
        # each layer tiles the section
        assert sum(s.area for s in inter) == pytest.approx(sx * sy, rel=1e-9)
        assert unary_union(inter).area == pytest.approx(sx * sy, rel=1e-9)
        for s_i, f_i in zip(inter, flat):
            # the interlock moves the boundary by at most d
            assert s_i.difference(f_i.buffer(D + 1e-3, join_style=2)).area <= 1e-6
            assert f_i.buffer(-D - 1e-3, join_style=2).difference(s_i).area <= 1e-6
        for i in range(len(parts)):
            for j in range(i + 1, len(parts)):
                # their shared boundary: where the two straight sections, grown by 0.01 mm, overlap
                shared = flat[i].buffer(0.01).intersection(flat[j].buffer(0.01))
                if shared.area <= 0:
                    continue
                rect = np.asarray(shared.minimum_rotated_rectangle.exterior.coords)[:4]
                sides = [rect[1] - rect[0], rect[2] - rect[1]]
                t = max(sides, key=np.linalg.norm)
                if np.linalg.norm(t) < 20.0:            # not neighbours (or a corner)
                    continue
                t = t / np.linalg.norm(t)
                m = np.asarray(shared.centroid.coords[0])
                n = np.array([-t[1], t[0]])
                if not flat[j].contains(shapely.Point(*(m + n))):
                    n = -n                              # n points from i into j
                assert flat[j].contains(shapely.Point(*(m + n))) and flat[i].contains(shapely.Point(*(m - n)))
                owner = i if k % 2 == 0 else j          # even layers: the lower index reaches past
                for s in (-0.5, 0.5):                   # both sides of the plane, within d
                    assert inter[owner].contains(shapely.Point(*(m + s * D * n))), (name, k, i, j, s)
                # the junction is d past the plane on that side, not on the plane
                far = m + (D + 0.05) * (n if owner == i else -n)
                assert not inter[owner].contains(shapely.Point(*far))
                pairs += 1
    assert pairs >= 2 * (len(parts) - 1)


def test_slabs_follow_the_slicers_layers(cells):
    """Every horizontal step of a part is at a layer boundary, so each
    sliced layer falls wholly on one side."""
    cell = cells["kinova_ur10"]
    model = box(60, 20, 2.05)
    boundaries = np.concatenate([[0.0], H0 + H * np.arange(20)])
    for p in partition(model, cell, seam="interlock", check_reach=False):
        z = np.asarray(p.manifold.to_mesh().vert_properties)[:, 2]
        top = np.isclose(z, 2.05)
        assert np.all(np.min(np.abs(z[~top][:, None] - boundaries[None]), axis=1) <= 1e-5)   # float32 vertices


def test_overlap_is_the_interlock_and_a_bad_seam_is_named(cells):
    cell = cells["kinova_ur10"]
    a = partition(box(40, 40, 4), cell, seam="overlap")
    b = partition(box(40, 40, 4), cell, seam="interlock")
    for p, q in zip(a, b):
        assert (p.manifold ^ q.manifold).volume() == pytest.approx(p.volume, rel=1e-9)
    with pytest.raises(ValueError, match="seam must be one of straight, interlock, overlap, got 'zigzag'"):
        partition(box(40, 40, 4), cell, seam="zigzag")


# ------------------------------------------------------------ bonded share, from the G-code

def gcode_beads(path):
    """Extruding moves of a program: [(z, (x0, y0), (x1, y1), width)] mm,
    width from the filament pushed (E x filament area / length / layer height)."""
    pos, out = {"X": 0.0, "Y": 0.0, "Z": 0.0}, []
    with open(path) as f:
        for line in f:
            if not re.match(r"G[01] ", line):
                continue
            words = dict((w[0], float(w[1:])) for w in line.split(";")[0].split()[1:])
            new = {k: words.get(k, pos[k]) for k in pos}
            e = words.get("E", 0.0)
            L = math.hypot(new["X"] - pos["X"], new["Y"] - pos["Y"])
            if e > 0 and L > 0:
                out.append((new["Z"], (pos["X"], pos["Y"]), (new["X"], new["Y"]), e * FILAMENT_MM2 / L / H))
            pos = new
    return out


def gcode_bonded_share(paths, x_seam, y_half, z_max):
    """Share of the seam face x = x_seam, |y| < y_half, bonded: a point
    every 0.2 mm per layer, bonded when one bead's rectangle covers the
    segment from a quarter bead width before the plane to a quarter after."""
    beads = [b for p in paths for b in gcode_beads(p)]
    bonded = total = 0
    for z in mid_heights(z_max):
        rects = [LineString([a, b]).buffer(w / 2, cap_style=2) for zt, a, b, w in beads
                 if zt - H - 1e-6 <= z <= zt + 1e-6 and min(a[0], b[0]) - w <= x_seam <= max(a[0], b[0]) + w]
        tree = shapely.STRtree(rects)
        for y in np.arange(-y_half + 0.1, y_half, 0.2):
            probe = LineString([(x_seam - W / 4, y), (x_seam + W / 4, y)])
            total += 1
            bonded += any(rects[i].covers(probe) for i in tree.query(probe))
    return bonded / total


@pytest.fixture(scope="module")
def plans(cells, tmp_path_factory):
    from ambots.commands.plan import plan_job
    folder = str(tmp_path_factory.mktemp("interlock"))
    model = os.path.join(folder, "block.stl")
    trimesh.creation.box([60.0, 16.0, 2.0], trimesh.transformations.translation_matrix([0, 0, 1.0])).export(model)
    cell = cells["kinova_ur10"]
    out = {}
    for seam in ("straight", "interlock"):
        path = os.path.join(folder, seam)
        out[seam] = (plan_job(model, cell, list(cell.arms), seam=seam, out=path), path)
    return out


@pytest.mark.parametrize("seam", ["straight", "interlock"])
def test_plan_reports_the_bonded_share_of_the_seam_and_no_collisions(plans, seam):
    rep, path = plans[seam]
    assert rep["finished"] and rep["collisions"] == {"arm_arm": 0, "arm_bed": 0, "arm_part": 0}
    assert rep["seam"] == seam
    (pair, share), = rep["seam_bonded_share"].items()
    assert pair == "kinova/ur10"
    assert share["samples"] == 10 * 80                  # 10 layers x 16 mm / 0.2 mm
    # the seam plane, from the parts as written: where they meet (straight),
    # midway between the kinova part's two alternating edges (interlock)
    stl = trimesh.load(os.path.join(path, "kinova.stl"))
    kinova = m3.Manifold(m3.Mesh(np.asarray(stl.vertices, np.float32), np.asarray(stl.faces, np.uint32)))
    edges = [section(kinova, z).bounds[2] for z in mid_heights(2.0)[:2]]
    x_seam = float(np.mean(edges))
    if seam == "interlock":
        assert edges[0] - edges[1] == pytest.approx(2 * D, abs=1e-3)
    else:
        assert edges[0] == pytest.approx(edges[1], abs=1e-6)
    second = gcode_bonded_share([os.path.join(path, a + ".gcode") for a in ("kinova", "ur10")], x_seam, 8.0, 2.0)
    assert share["bonded_share"] == pytest.approx(second, abs=0.02)
    if seam == "straight":
        # the parts are the whole model's toolpaths clipped at the plane: lines
        # meet end to end there (not bonded), but the solid layers' zig-zag
        # lanes are joined again along the plane, by beads that span it
        assert 0.3 <= share["bonded_share"] < plans["interlock"][0]["seam_bonded_share"]["kinova/ur10"]["bonded_share"]
    else:
        assert share["bonded_share"] >= 0.9
        # each arm's layer near the seam rests on the neighbour's layer below, laid before it
        assert rep["seam_lap_order"] == {"kinova/ur10": {"layers": 18, "early": 0}}


def test_the_interlock_costs_no_makespan(plans):
    """Same work, same zones: within 2 % of the straight seam's makespan."""
    assert plans["interlock"][0]["makespan_s"] == pytest.approx(plans["straight"][0]["makespan_s"], rel=0.02)


def test_lap_order_counts_a_layer_begun_before_the_neighbours_layer_below():
    """Two arms either side of x = 0, two layers (tops 0.2, 0.4 mm): the
    Kinova (x < 0) lays its layer 0 band at t = 1, the UR10 its layer 0 at
    t = 2; the Kinova's layer 1 at t = 3 is in order, the UR10's layer 1 at
    t = 2.5 is in order too (the Kinova's layer 0 was done at 1), but at
    t = 0.5 it is early; far from the seam nothing counts."""
    from ambots.seams import lap_order
    planes = {("kinova", "ur10"): (np.array([-1.0, 0, 0]), 0.0), ("ur10", "kinova"): (np.array([1.0, 0, 0]), 0.0)}
    seg = lambda x0, x1, z: (np.array([[x0, 0.0, z]]), np.array([[x1, 0.0, z]]))

    def arm(items):
        p0 = np.concatenate([seg(*i[:3])[0] for i in items])
        p1 = np.concatenate([seg(*i[:3])[1] for i in items])
        return p0, p1, np.array([i[3] for i in items])

    kinova = arm([(-5, 0.4, 0.2, 1.0), (-5, -0.5, 0.4, 3.0), (-50, -40, 0.4, 0.1)])
    for t_ur10_l1, early in ((2.5, 0), (0.5, 1)):
        ur10 = arm([(5, 0.5, 0.2, 2.0), (5, -0.4, 0.4, t_ur10_l1), (40, 50, 0.2, 9.0)])
        got = lap_order({"kinova": kinova, "ur10": ur10}, planes, 1.0, [0.2, 0.4])
        assert got == {"kinova/ur10": {"layers": 2, "early": early}}
    # a support layer laid 0.1 mm low (z 0.3, the z gap under an overhang) is layer 1, not layer 0:
    # laid at t = 2.5, after the Kinova's layer 0 (done at 1), it is in order (nearest-top gave "early")
    ur10 = arm([(5, 0.5, 0.2, 2.0), (5, -0.4, 0.3, 2.5)])
    assert lap_order({"kinova": kinova, "ur10": ur10}, planes, 1.0, [0.2, 0.4]) == \
        {"kinova/ur10": {"layers": 2, "early": 0}}
