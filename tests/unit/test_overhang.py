"""Unsupported extrusion measured on the G-code (ambots.overhang): hand-made
toolpaths whose unsupported length follows from plain geometry, and the
figure a job reports for a T whose overhang is known from its shape."""
import json
import math
import subprocess
import sys

import pytest
import trimesh

from ambots.gcode import parse_gcode_text
from ambots.overhang import layer_ranges, unsupported_extrusion

W = 0.45


def gcode(*layers):
    """G-code text: ``layers`` = [(z, [path, ...]), ...], a path = [(x, y), ...]
    extruded end to end, with a travel before each path."""
    out = ["G21", "G90", "M83"]
    for z, paths in layers:
        out.append(";LAYER_CHANGE")
        out.append("G1 Z%.3f F600" % z)
        for path in paths:
            out.append("G0 X%.3f Y%.3f" % path[0])
            for x, y in path[1:]:
                out.append("G1 X%.3f Y%.3f E0.05 F1200" % (x, y))
    return "\n".join(out) + "\n"


def measure(*programs, **kw):
    return unsupported_extrusion([list(parse_gcode_text(p, "t%d.gcode" % i)) for i, p in enumerate(programs)], **kw)


def test_a_line_longer_than_the_one_below_is_unsupported_past_a_bead_width():
    r = measure(gcode((0.2, [[(0, 0), (20, 0)]]), (0.4, [[(0, 0), (40, 0)]])))
    # supported up to x = 20 + W; the rest (19.55 mm) hangs in the air, and ends in it: no bridge
    assert r["extruded_mm"] == pytest.approx(60.0, abs=1e-6)
    assert r["unsupported_mm"] == pytest.approx(40 - 20 - W, abs=0.2)
    assert r["unsupported_share"] == pytest.approx((40 - 20 - W) / 60, abs=0.2 / 60)
    assert r["layers"] == 2
    assert [l["layer"] for l in r["unsupported_layers"]] == [2]
    assert r["unsupported_layers"][0]["z_mm"] == pytest.approx(0.4)


def test_the_lowest_layer_lies_on_the_bed():
    r = measure(gcode((0.2, [[(0, 0), (30, 0), (30, 30)]])))
    assert r["unsupported_mm"] == 0.0 and r["extruded_mm"] == pytest.approx(60.0)


@pytest.mark.parametrize("gap, bridged", [(9.0, True), (10.0 + 2 * W - 0.3, True), (14.0, False), (30.0, False)])
def test_a_span_between_supports_is_a_bridge_up_to_10_mm(gap, bridged):
    # two pillars' tops, ``gap`` apart, and a line across them on the layer above
    a = 5.0
    below = [[(0, 0), (a, 0)], [(a + gap, 0), (2 * a + gap, 0)]]
    r = measure(gcode((0.2, below), (0.4, [[(0, 0), (2 * a + gap, 0)]])))
    air = gap - 2 * W                     # the stretch farther than one bead width from both pillars
    if bridged:
        assert r["unsupported_mm"] == 0.0
        assert r["bridged_mm"] == pytest.approx(air, abs=0.2)
    else:
        assert r["unsupported_mm"] == pytest.approx(air, abs=0.2)


def test_a_bead_beside_the_one_below_is_supported_within_one_bead_width():
    base = [(0, 0), (20, 0)]
    near = measure(gcode((0.2, [base]), (0.4, [[(0, W - 0.05), (20, W - 0.05)]])))
    far = measure(gcode((0.2, [base]), (0.4, [[(0, W + 0.05), (20, W + 0.05)]])))
    assert near["unsupported_mm"] == 0.0
    assert far["unsupported_mm"] == pytest.approx(20.0, abs=1e-6)


@pytest.mark.parametrize("off", [-0.005, 0.005])
def test_the_distance_to_the_layer_below_is_exact_along_a_line_and_past_its_end(off):
    """Support within one bead width by the exact distance to the bead below,
    5 micrometres either side of it: beside a line at 30 degrees
    (between the points the measure samples on it) and past its end, where
    the reach is a half circle (a polygon of it falls short)."""
    c, s = math.cos(math.radians(30)), math.sin(math.radians(30))
    base = [(0, 0), (20 * c, 20 * s)]
    d = W + off
    beside = [(-d * s + 2 * c, d * c + 2 * s), (-d * s + 18 * c, d * c + 18 * s)]     # 16 mm, parallel
    # past the end, 11.25 degrees off the line's axis (half-way between two corners of a
    # 16-gon): 0.2 mm across that direction, centred on it
    u, v = math.cos(math.radians(41.25)), math.sin(math.radians(41.25))
    past = [(20 * c + d * u - 0.1 * v, 20 * s + d * v + 0.1 * u), (20 * c + d * u + 0.1 * v, 20 * s + d * v - 0.1 * u)]
    for path, length in ((beside, 16.0), (past, 0.2)):
        r = measure(gcode((0.2, [base]), (0.4, [path])))
        assert r["unsupported_mm"] == (0.0 if off < 0 else pytest.approx(length, abs=0.005))


def test_a_long_program_measured_by_several_processes_gives_the_one_process_figures(monkeypatch):
    """Above :data:`PARALLEL_MIN_MOVES` moves the levels are shared among
    worker processes, each a run of levels that reads the levels below its
    first one: a staircase whose every line overhangs the one below by
    3 mm (3 - W in mid-air a layer), with a lowered support layer on the way,
    measures the same with 1, 2 and 3 processes, and what geometry says."""
    import ambots.overhang as overhang
    from ambots.parallel import JOBS_ENV
    layers = []
    for k in range(1, 31):
        z = round(0.2 * k, 3)
        layers.append((z, [[(0, 0), (10 + 3 * k, 0)], [(0, 5), (30, 5)]]))
        if k == 14:                         # a layer of its own 0.1 mm lower, as a support's top
            layers.append((round(z + 0.1, 3), [[(0, 5), (30, 5)]]))
    text = gcode(*sorted(layers, key=lambda l: l[0]))
    monkeypatch.setattr(overhang, "PARALLEL_MIN_MOVES", 0)
    got = []
    for jobs in ("1", "2", "3"):
        monkeypatch.setenv(JOBS_ENV, jobs)
        got.append(measure(text, layer_height_mm=0.2))
    assert got[0]["unsupported_mm"] == pytest.approx(29 * (3 - W), abs=29 * 0.1)     # samples 0.2 mm apart
    assert [l["layer"] for l in got[0]["unsupported_layers"]] == list(range(2, 31))
    for r in got[1:]:
        assert r["unsupported_layers"] == got[0]["unsupported_layers"]
        for key in ("extruded_mm", "unsupported_mm", "bridged_mm", "unsupported_share"):
            assert r[key] == pytest.approx(got[0][key], rel=1e-12, abs=1e-9)


def test_a_bead_may_rest_on_another_programs_bead():
    """A job's programs are measured together: one arm prints on the other's layer."""
    first = gcode((0.2, [[(0, 0), (20, 0)]]))
    second = gcode((0.4, [[(0, 0), (20, 0)]]))
    assert measure(first, second)["unsupported_mm"] == 0.0
    assert measure(second)["unsupported_mm"] == 0.0          # alone, its only layer is the lowest: the bed
    assert measure(first, gcode((0.4, [[(0, 5), (20, 5)]])))["unsupported_mm"] == pytest.approx(20.0, abs=1e-6)


def test_a_retraction_and_prime_inside_a_path_keep_it_one_path_for_the_bridge_rule():
    text = gcode((0.2, [[(0, 0), (5, 0)], [(13, 0), (18, 0)]]))
    text += ";LAYER_CHANGE\nG1 Z0.4\nG0 X0 Y0\nG1 X5 Y0 E0.1\nG1 E-0.8\nG1 E0.8\nG1 X18 Y0 E0.3\n"
    r = measure(text)
    assert r["unsupported_mm"] == 0.0 and r["bridged_mm"] > 0


def test_a_support_layer_lowered_under_an_overhang_stays_in_its_layer():
    """A z gap: the support's top layer is laid 0.1 mm lower than the part's
    layer beside it.  Both are one layer (the 0.2 mm slab), so the part's
    next layer rests on the part and the overhang on the support."""
    stem, support, top = [(0, 0), (5, 0)], [(5, 0.7), (20, 0.7)], [(0, 0.35), (20, 0.35)]
    below = [(0.2 * k, [stem, support]) for k in range(1, 6)]                # five layers of both, to z = 1.0
    text = gcode(*below, (1.2, [stem]), (1.1, [support]), (1.4, [top]))
    r = measure(text)
    assert r["layer_height_mm"] == pytest.approx(0.2)                    # the most common step
    assert r["layers"] == 7 and r["unsupported_mm"] == 0.0
    assert measure(text, layer_height_mm=0.2)["unsupported_mm"] == 0.0
    # without the support the line rests on the stem up to one bead width from it, then on nothing
    bare = measure(gcode(*[(0.2 * k, [stem]) for k in range(1, 7)], (1.4, [top])))
    assert bare["unsupported_mm"] == pytest.approx(20 - 5 - math.sqrt(W ** 2 - 0.35 ** 2), abs=0.2)


def test_support_laid_at_heights_of_its_own_carries_what_lies_on_it():
    """PrusaSlicer lays support in layers of its own height when they are not
    synchronized with the object's (here 0.3 mm against the object's
    0.2 mm).  Each support bead lies 0.3 mm over the one below at the same
    place and the overhang 0.1-0.2 mm over the top one: nothing is in mid-air,
    though some 0.2 mm slabs hold no support at all."""
    stem, support, top = [(0, 0), (5, 0)], [(5, 0.7), (20, 0.7)], [(0, 0.35), (20, 0.35)]
    part = [(round(0.2 * k, 3), [stem]) for k in range(1, 10)]                   # to z = 1.8
    sup = [(round(0.2 + 0.3 * k, 3), [support]) for k in range(6)]               # 0.2, 0.5, ... 1.7
    text = gcode(*sorted(part + sup, key=lambda l: l[0]), (2.0, [stem, top]))
    r = measure(text)
    assert r["layer_height_mm"] == pytest.approx(0.2)
    assert r["unsupported_mm"] == 0.0, r["unsupported_layers"]
    # the same support 0.4 mm apart (two object layers) leaves every support bead but the lowest in mid-air
    sparse = [(round(0.2 + 0.4 * k, 3), [support]) for k in range(5)]          # 0.2, 0.6, ... 1.8
    r = measure(gcode(*sorted(part + sparse, key=lambda l: l[0]), (2.0, [stem, top])))
    assert r["unsupported_mm"] == pytest.approx(4 * 15.0, abs=0.5)


def test_a_line_cut_into_pieces_is_one_path_for_the_bridge_rule():
    """Coordination cuts lines where two arms' (or two bands') work meets; the
    pieces meet end to end, are printed apart (here one of them backwards,
    by the other program) and still span the gap as one bridge."""
    pillars = [[(0, 0), (5, 0)], [(13, 0), (18, 0)]]
    whole = measure(gcode((0.2, pillars), (0.4, [[(0, 0), (18, 0)]])))
    cut = measure(gcode((0.2, pillars), (0.4, [[(0, 0), (9, 0)], [(0, 5), (18, 5)]])),
                  gcode((0.4, [[(18, 0), (9, 0)]])))
    assert whole["unsupported_mm"] == 0.0 and cut["bridged_mm"] == pytest.approx(whole["bridged_mm"], abs=0.3)
    # the line at y = 5 lies over nothing: it is counted, joined or not
    assert cut["unsupported_mm"] == pytest.approx(18.0, abs=1e-6)
    # a gap too long to bridge stays unsupported when cut as well
    far = [[(0, 0), (5, 0)], [(25, 0), (30, 0)]]
    long_cut = measure(gcode((0.2, far), (0.4, [[(0, 0), (15, 0)], [(15, 0), (30, 0)]])))
    assert long_cut["unsupported_mm"] == pytest.approx(20 - 2 * W, abs=0.3)


def test_a_piece_ending_where_the_rest_of_its_line_turns_is_one_path_for_the_bridge_rule():
    """Where a band edge cuts a line and one band's path turns along the edge
    at the cut (a link, ``ambots.coordinate.banded``), the other band's
    piece ends on a vertex of that path, not on its end: the piece and the
    line running on in line beyond the vertex still span the gap as one
    bridge; the other path's samples are not counted twice."""
    below = [[(0, 0), (5, 0)], [(13, 0), (18, 0)], [(0, 3), (5, 3)]]
    # one program: the line y = 0 from x = 0 to the edge x = 8, along the edge, back along y = 3;
    # the other: the rest of the line y = 0, from x = 18 back to the edge
    turned = measure(gcode((0.2, below), (0.4, [[(0, 0), (8, 0), (8, 3), (0, 3)]])),
                     gcode((0.4, [[(18, 0), (8, 0)]])))
    assert turned["extruded_mm"] == pytest.approx(15.0 + 18.0 + 3.0 + 8.0, abs=1e-6)      # the pillars on the bed too
    assert turned["unsupported_mm"] == 0.0
    # in the air: x = 5 + W .. 13 - W on y = 0, the link, x = 8 .. 5 + W on y = 3
    air = (13 - 5 - 2 * W) + 3.0 + (8 - 5 - W)
    assert turned["bridged_mm"] == pytest.approx(air, abs=0.3)
    # not in line (the piece meets the vertex at a right angle): its 4.55 mm from the pillar
    # at x = 13 to its end are not a bridge
    corner = measure(gcode((0.2, below), (0.4, [[(0, 0), (8, 0), (8, 3), (0, 3)]])),
                     gcode((0.4, [[(8, 10), (8, 0)]])))
    assert corner["unsupported_mm"] == pytest.approx(10.0, abs=0.3)
    apart = measure(gcode((0.2, below), (0.4, [[(0, 0), (8, 0), (8, 3), (0, 3)]])),
                    gcode((0.4, [[(18, 0), (8.5, 0)]])))            # ends short of the vertex: no bridge
    assert apart["unsupported_mm"] == pytest.approx(13 - W - 8.5, abs=0.3)
    # a gap too long to bridge stays unsupported in line too
    far = [[(0, 0), (5, 0)], [(25, 0), (30, 0)], [(0, 3), (5, 3)]]
    long_cut = measure(gcode((0.2, far), (0.4, [[(0, 0), (15, 0), (15, 3), (0, 3)]])),
                       gcode((0.4, [[(30, 0), (15, 0)]])))
    assert long_cut["unsupported_mm"] == pytest.approx((25 - W - 15) + (15 - 5 - W) + 3.0 + (15 - 5 - W), abs=0.3)


def test_layer_ranges():
    assert layer_ranges([9, 3, 4, 5]) == "3-5, 9"
    assert layer_ranges(range(1, 40, 2), limit=3) == "1, 3, 5, ... (17 more)"


def test_bad_rule_figures_are_refused():
    with pytest.raises(ValueError):
        unsupported_extrusion([], bead_width_mm=0)


@pytest.fixture(scope="module")
def t_shape(tmp_path_factory):
    """A T: a 10 x 10 x 10 mm stem under a 60 x 10 x 4 mm bar; 2 x 25 mm of the
    bar's underside overhangs, 10 mm above the bed."""
    stem = trimesh.creation.box((10, 10, 10))
    stem.apply_translation((0, 0, 5))
    bar = trimesh.creation.box((60, 10, 4))
    bar.apply_translation((0, 0, 12))
    path = tmp_path_factory.mktemp("t") / "t_shape.stl"
    trimesh.boolean.union([stem, bar], engine="manifold").export(str(path))
    return path


def test_slice_reports_the_T_bars_first_layer_as_unsupported(t_shape, tmp_path):
    """``slice`` prints the share and a warning naming the layer, and job.json
    holds it.  The bar's first layer prints at z = 10.2 mm: layer 10.2 / 0.2 = 51
    (0.2 mm layers from the bed).  Its unsupported length is the overhanging
    area's beads: at least the two overhangs' perimeters (2 x 2 loops of about
    2 x (25 - 2 W) + 2 x (10 - 2 W) mm, less the part within a bead width of the stem)."""
    out = tmp_path / "job"
    res = subprocess.run([sys.executable, "-m", "ambots", "slice", str(t_shape), "--arms", "ur10", "--support", "off",
                          "--out", str(out)], capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr
    assert "warning:" in res.stdout and "on layer 51 (z 10.20 mm); support is off" in res.stdout, res.stdout
    job = json.loads((out / "job.json").read_text())
    o = job["overhang"]
    assert [l["layer"] for l in o["unsupported_layers"]] == [51]
    # the overhang is 2 x 24.55 x 10 mm (past a bead width from the stem); its first layer is laid solid:
    # area / bead spacing of 0.2 mm layers (w - h (1 - pi/4)) is the length of bead over air
    spacing = W - 0.2 * (1 - math.pi / 4)
    solid = 2 * (25 - W) * 10 / spacing
    assert 0.8 * solid < o["unsupported_mm"] < 1.2 * solid
    assert o["unsupported_share"] == pytest.approx(o["unsupported_mm"] / o["extruded_mm"])
    info = subprocess.run([sys.executable, "-m", "ambots", "info", "--json", str(out / "ur10.gcode")],
                          capture_output=True, text=True, timeout=300)
    assert info.returncode == 0, info.stderr
    per_file = json.loads(info.stdout)
    assert per_file["unsupported_mm"] == pytest.approx(o["unsupported_mm"], rel=1e-6)
    assert [l["layer"] for l in per_file["unsupported_layers"]] == [51]
    # with support (the default) the bar rests on it: no warning, the share by this rule within 0.1 %
    res = subprocess.run([sys.executable, "-m", "ambots", "slice", str(t_shape), "--arms", "ur10",
                          "--out", str(tmp_path / "supported")], capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr
    assert "warning:" not in res.stdout, res.stdout
    o = json.loads((tmp_path / "supported" / "job.json").read_text())["overhang"]
    assert o["support"] is True and o["unsupported_share"] <= 0.001, o


def test_the_demo_block_has_nothing_unsupported(tmp_path):
    from ambots import data_path
    from ambots.mesh import load_model
    from ambots.slicer import slice_mesh
    m = load_model(data_path("config", "models", "demo_block.stl"))
    m.apply_translation((0, 0, -m.bounds[0][2]))
    r = unsupported_extrusion([list(parse_gcode_text(slice_mesh(m), "demo.gcode"))])
    assert r["unsupported_mm"] == 0.0 and r["extruded_mm"] > 1e5


def _brute_force_within(segs, pts, reach):
    """Whether each point lies within ``reach`` of some segment, by its
    distance to every segment (numpy, no tree)."""
    import numpy as np
    a, ab = segs[None, :, 0], (segs[:, 1] - segs[:, 0])[None]
    p = pts[:, None, :]
    L2 = (ab ** 2).sum(-1)
    t = np.clip(((p - a) * ab).sum(-1) / np.where(L2 > 0, L2, 1.0), 0.0, 1.0)
    return (np.hypot(*np.moveaxis(a + ab * t[..., None] - p, -1, 0)).min(axis=1) <= reach)


@pytest.mark.parametrize("dense", [False, True])
def test_which_points_the_layer_below_reaches_is_the_exact_distance(dense):
    """The layer-below test (:class:`ambots.overhang._Below`: a tree asked
    about every other point, neighbours settled by the gap between points,
    the few in between measured to nearby segments, the rest by GEOS)
    against the distance to every segment: random segments, and paths
    sampled as the rule samples them (0.2 mm apart) and random points,
    many of them within 0.1 mm of the reach.  ``dense``: segments so close
    together that more tree points than are measured lie near a point."""
    import numpy as np
    from ambots.overhang import _Below
    rng = np.random.default_rng(7)
    n = 60 if dense else 300
    start = rng.uniform(-20, 20, (n, 2)) if not dense else rng.uniform(-1, 1, (n, 2))
    end = start + rng.normal(0, 1.0 if dense else 6.0, (n, 2))
    segs = np.stack([start, end], axis=1)
    below = _Below(segs, W)
    # paths: lines across the area, points 0.2 mm apart (odd points settled by their neighbours)
    lines = []
    for _ in range(40):
        p0, d = rng.uniform(-22, 22, 2), rng.normal(0, 1, 2)
        d /= np.hypot(*d)
        lines.append(p0 + np.outer(np.arange(0, 30, 0.2), d))
    # points at the reach of a segment, give or take 0.1 mm and a hair
    k = rng.integers(0, n, 3000)
    t = rng.uniform(0, 1, 3000)
    normal = np.stack([-(end - start)[k, 1], (end - start)[k, 0]], axis=1)
    normal /= np.maximum(np.hypot(*normal.T), 1e-12)[:, None]
    off = W + rng.choice([-0.1, -0.05, -1e-6, 1e-6, 0.05, 0.1], 3000) * rng.uniform(0.0, 1.0, 3000)
    rim = start[k] + (end - start)[k] * t[:, None] + normal * off[:, None]
    pts = np.concatenate(lines + [rim, rng.uniform(-25, 25, (3000, 2))])
    got = below.near(pts)
    want = _brute_force_within(segs, pts, W)
    assert got.sum() > 0.2 * len(pts) and (~got).sum() > 0.2 * len(pts)
    assert (got == want).all(), np.flatnonzero(got != want)[:10]


def test_the_layer_below_is_measured_exactly_where_its_tree_points_are_farthest():
    """The worst cases of :class:`ambots.overhang._Below`'s shortcuts,
    against the distance to every segment: paths 0.2 mm apart heading
    straight at a line below, half-way between two of its tree points (where
    they are farthest from the line: 0.1 mm along it), at every phase of the
    samples against the reach; and a point within reach of a line whose
    tree points are all farther than ten tiny beads' just beyond reach (the
    nearest tree points are not enough: the line must still be found)."""
    import numpy as np
    from ambots.overhang import _Below
    line = np.array([[[0.0, 0.0], [20.0, 0.0]]])
    paths = [np.stack([np.full(40, x), phase + W + 0.2 * np.arange(-20, 20)], axis=1)
             for x in (10.1, 10.05, 10.0) for phase in np.arange(0.0, 0.2, 0.005)]
    pts = np.concatenate(paths + [p[::-1] for p in paths])
    below = _Below(line, W)
    assert (below.near(pts) == _brute_force_within(line, pts, W)).all()
    # a point 0.449 mm from a line, half-way between its tree points (0.460 mm away), and ten
    # 0.01 mm beads 0.455 mm away (20 tree points nearer than the line's)
    p = np.array([[10.1, 0.449]])
    ang = np.linspace(0.2, 1.3, 10)
    centre = p[0] + 0.455 * np.stack([np.cos(ang), np.sin(ang)], axis=1)
    beads = np.stack([centre, centre + [0.0, 0.01]], axis=1)
    segs = np.concatenate([line, beads])
    assert _brute_force_within(segs, p, W)[0]
    assert _Below(segs, W).near(p)[0]


def test_a_plan_made_in_a_worker_process_reports_what_its_written_program_holds(t_shape, tmp_path, monkeypatch):
    """The planner's choice for the T is the UR10 alone, planned in the job's
    worker process (:mod:`ambots.parallel`), which sends back the program's
    figures and extrusion paths instead of its 7,000 G-code events
    (``Candidate.__getstate__``; the 60 mm sphere's 116,000 took 0.45 s to
    send).  job.json holds what the written program holds: its figures and
    its unsupported extrusion, measured again from the file as read by the
    parser, equal."""
    from ambots.config import default_cell_path, load_cell
    from ambots.gcode import read_gcode, summarize_file
    from ambots.job import run_job, write_job
    from ambots.parallel import JOBS_ENV
    from ambots.slicer import SliceSettings
    monkeypatch.setenv(JOBS_ENV, "2")
    job = run_job(str(t_shape), load_cell(default_cell_path()), settings=SliceSettings(support=False))
    assert job.chosen.arms == ["ur10"] and job.chosen.events is None and set(job.chosen.figures) == {"ur10"}
    assert job.programs["ur10"].events is None                 # sent without them too
    summary = write_job(job, str(tmp_path))
    written = str(tmp_path / "ur10.gcode")
    figures = summarize_file(written)
    for key in ("layers", "moves", "extrude_path_mm", "travel_path_mm", "extruded_filament_mm", "print_time_s"):
        assert summary["arms"]["ur10"][key] == figures[key], key
    again = unsupported_extrusion([list(read_gcode(written))], layer_height_mm=0.2)
    assert summary["overhang"]["unsupported_mm"] == again["unsupported_mm"] > 1000
    assert summary["overhang"]["unsupported_layers"] == again["unsupported_layers"]
    for key in ("extruded_mm", "bridged_mm", "unsupported_share", "layers"):
        assert summary["overhang"][key] == again[key], key
