"""A stepped seam (ambots.seam_steps): per-layer offsets worked out by hand
on layers of known extent, the parts cut by the stepped prism checked
section by section, the clipped toolpaths checked against the per-layer planes, and
the programs (bands about each layer's seam) checked move by move."""
import manifold3d as m3
import numpy as np
import pytest

from ambots.config import default_cell_path, load_cell
from ambots.partition import partition
from ambots.seam_steps import STEP_MM, largest_step, layer_segments, plan_offsets, stepped_parts, timed_offsets
from ambots.slicer import Path, SliceSettings, WholeModel, layer_heights


@pytest.fixture(scope="module")
def cell():
    return load_cell(default_cell_path())


def lines_layers(spans):
    """Per layer one line along x from a to b (y = 0): (starts, ends)."""
    return [(np.array([[a, 0.0]]), np.array([[b, 0.0]])) for a, b in spans]


def by_length(spans, seam=0.0, rate_a=1.0, rate_b=1.0):
    """Busy times (2, L) of lines ``spans`` cut at x = ``seam``: the first
    arm (x >= seam) at ``rate_a`` s a mm, the second at ``rate_b``."""
    return np.array([[rate_a * max(b - max(a, seam), 0.0) for a, b in spans],
                     [rate_b * max(min(b, seam) - a, 0.0) for a, b in spans]])


def test_each_layer_is_cut_where_its_halves_take_equally_long():
    """Lines from a to b along the normal; the first arm takes 3 s a mm,
    the second 1 s: equal times give the first a quarter of each line, so
    the seam goes to b - (b - a) / 4, whatever the seam they were timed at."""
    spans = [(-100.0, 100.0), (-90.0, 100.0), (-80.0, 100.0), (-70.0, 100.0)]
    want = [b - (b - a) / 4.0 for a, b in spans]
    for seam in (0.0, -30.0, 60.0):
        got = timed_offsets(lines_layers(spans), (1.0, 0.0), seam, np.zeros(4), by_length(spans, seam, 3.0, 1.0),
                            step_mm=50.0, quantum_mm=1e-3)
        assert got + seam == pytest.approx(want, abs=2e-3)
    # timed at offsets already moved: the same answer
    moved = np.array([10.0, -5.0, 0.0, 20.0])
    got = timed_offsets(lines_layers(spans), (1.0, 0.0), 0.0, moved,
                        np.column_stack([by_length([s], m, 3.0, 1.0)[:, 0] for s, m in zip(spans, moved)]),
                        step_mm=50.0, quantum_mm=1e-3)
    assert got == pytest.approx(want, abs=2e-3)


def test_the_seam_moves_at_most_a_step_a_layer_and_short_layers_stay():
    """Layers whose middles jump 60 mm (the arms alike): the offsets go
    there a step a layer; a layer narrower than twice ``keep_mm`` keeps
    the seam it had."""
    spans = [(-100.0, 100.0)] * 3 + [(-40.0, 160.0)] * 150
    for step in (STEP_MM, 2.0):
        got = timed_offsets(lines_layers(spans), (1.0, 0.0), 0.0, np.zeros(len(spans)), by_length(spans),
                            step_mm=step)
        assert largest_step(got) <= step + 1e-9
        assert got[0] == 0.0 and got[-1] == pytest.approx(60.0)
        assert np.all(np.diff(got) >= -1e-9)                 # straight there, no overshoot
        # from the layer where the layers move on, a step a layer
        assert got[2] == 0.0 and got[3] == pytest.approx(step) and got[4] == pytest.approx(2 * step)
    short = [(-100.0, 100.0), (50.0, 90.0), (-100.0, 100.0)]
    busy = by_length(short, 0.0, 1.0, 1.0)                  # the 40 mm layer all the first arm's
    kept = timed_offsets(lines_layers(short), (1.0, 0.0), 0.0, np.zeros(3), busy, step_mm=1e3, keep_mm=25.0)
    free = timed_offsets(lines_layers(short), (1.0, 0.0), 0.0, np.zeros(3), busy, step_mm=1e3)
    assert kept[1] == 0.0 and free[1] == pytest.approx(70.0, abs=0.1)


def test_a_layer_is_shared_by_the_arms_times():
    """The first arm took 3 s for its 100 mm of a 200 mm line, the second
    1 s for its 100 mm: at 30 and 10 ms a mm, equal times need 50 mm and
    150 mm (3 x 50 = 150 = 1 x 150); the first part is x >= seam, so the
    seam moves from 0 to +50.  A layer one arm has nothing on takes the
    layer's mean rate for it."""
    segs = lines_layers([(-100.0, 100.0), (-100.0, 100.0)])
    busy = np.array([[3.0, 2.0], [1.0, 2.0]])
    got = timed_offsets(segs, (1.0, 0.0), 0.0, np.zeros(2), busy, step_mm=1e3, quantum_mm=1e-3)
    assert got == pytest.approx([50.0, 0.0], abs=2e-3)
    # all on the second arm's side (seam at +100, nothing >= it): 4 s for 200 mm; half each
    got = timed_offsets(segs, (1.0, 0.0), 100.0, np.zeros(2), np.array([[0.0, 0.0], [4.0, 4.0]]),
                        step_mm=1e3, quantum_mm=1e-3)
    assert got == pytest.approx([-100.0, -100.0], abs=2e-3)


def test_the_seam_does_not_creep_across_a_gap_between_islands():
    """Two towers, 20 mm each, 200 mm apart (x in [-110, -90] and [90, 110]),
    the first arm's at 3 s a mm, the second's at 1 s: the balance asks for
    some of the first tower, but the seam keeps 25 mm inside the layer's
    ends, and any seam it may take splits the same work, so it stays (it
    used to creep towards the first tower a step a layer, 78.6 mm over 150
    layers, moving no work); where a cut can move work (one line across),
    it still moves."""
    towers = [(np.array([[-110.0, 0.0], [90.0, 0.0]]), np.array([[-90.0, 0.0], [110.0, 0.0]]))] * 150
    busy = np.array([[3.0 * 20.0] * 150, [1.0 * 20.0] * 150])
    got = timed_offsets(towers, (1.0, 0.0), 0.0, np.zeros(150), busy, keep_mm=25.0)
    assert np.all(got == 0.0)
    line = lines_layers([(-110.0, 110.0)] * 150)
    moved = timed_offsets(line, (1.0, 0.0), 0.0, np.zeros(150), by_length([(-110.0, 110.0)] * 150, 0.0, 3.0, 1.0),
                          keep_mm=25.0)
    assert moved[-1] == pytest.approx(55.0) and largest_step(moved) <= STEP_MM + 1e-9


def ramp_manifold():
    """120 x 30 mm, rising from 2 to 8 mm along +x (the top layers only at one end)."""
    box = m3.Manifold.cube([120.0, 30.0, 8.0]).translate([-60.0, -15.0, 0.0])
    cut = m3.Manifold.cube([200.0, 60.0, 40.0]).translate([-100.0, -30.0, 0.0])
    # the slope: keep below z = 2 + (x + 60) / 20
    n = np.array([-1.0 / 20.0, 0.0, 1.0])
    n /= np.linalg.norm(n)
    return box.trim_by_plane((-n).tolist(), float(-(2.0 + 60.0 / 20.0) * n[2])) ^ cut


def test_stepped_parts_tile_the_model_and_each_layer_is_cut_at_its_own_seam(cell):
    model = ramp_manifold()
    parts = partition(model, cell)
    (n, off), = parts[0].planes
    s = SliceSettings()
    z, h = layer_heights(float(model.bounding_box()[5]), s)
    offsets = np.round(np.linspace(-10.0, 14.0, len(z)), 1)
    a, b = stepped_parts(model, parts, offsets, z, h)
    assert a.volume + b.volume == pytest.approx(model.volume(), rel=1e-6)
    assert (a.manifold ^ b.manifold).volume() == pytest.approx(0.0, abs=1e-6 * model.volume())
    assert list(a.layer_offsets) == list(offsets) and list(b.layer_offsets) == list(-offsets)
    shared = 0
    for i in range(len(z)):                     # each layer's section: on its side of that layer's seam
        mid = float(z[i] - h[i] / 2)
        near = []
        for part, sign in ((a, 1.0), (b, -1.0)):
            polygons = part.manifold.slice(mid).to_polygons()
            if not polygons:                    # the ramp's top: the UR10's end only
                continue
            pts = np.concatenate([np.asarray(p) for p in polygons])
            d = sign * (pts @ np.asarray(n[:2]) - (off + offsets[i]))
            assert d.min() >= -1e-6, (part.arm.name, i)
            near.append(d.min())
        if len(near) == 2:                      # a layer of both: they meet at that layer's seam
            assert max(near) <= 1e-6, i
            shared += 1
    assert shared >= 10


def test_a_seam_at_an_angle_stepped_on_every_layer_cuts_each_section_at_its_own_offset():
    # a seam plane turned 40 deg from x, its offset different on every layer (the prism's
    # staircase has a step per layer), on a box 60 x 40 x 6 mm: each layer's section
    # lies on its side of that layer's line, and the two parts tile the box
    from ambots.partition import Part
    model = m3.Manifold.cube([60.0, 40.0, 6.0]).translate([-30.0, -20.0, 0.0])
    n = np.array([np.cos(0.7), np.sin(0.7), 0.0])
    z, h = layer_heights(6.0, SliceSettings())
    offsets = np.round(np.random.default_rng(3).uniform(-8.0, 8.0, len(z)), 1)
    a, b = stepped_parts(model, [Part(None, model, [(n, 1.0)]), Part(None, model, [(-n, -1.0)])], offsets, z, h)
    assert a.volume + b.volume == pytest.approx(model.volume(), rel=1e-9)
    for i in range(len(z)):
        mid = float(z[i] - h[i] / 2)
        sides = []
        for part, sign in ((a, 1.0), (b, -1.0)):
            pts = np.concatenate([np.asarray(p) for p in part.manifold.slice(mid).to_polygons()])
            d = sign * (pts @ n[:2] - (1.0 + offsets[i]))
            sides.append(d.min())
        # each part's section reaches that layer's line and no further
        assert min(sides) >= -1e-6 and max(sides) <= 1e-6, (i, sides)
    # the same plane written with a normal twice as long (n . p >= o): the same parts
    a2, _ = stepped_parts(model, [Part(None, model, [(2 * n, 2.0)]), Part(None, model, [(-2 * n, -2.0)])],
                          2 * offsets, z, h)
    assert (a.manifold - a2.manifold).volume() + (a2.manifold - a.manifold).volume() < 1e-6 * model.volume()
    with pytest.raises(ValueError, match="upright"):
        stepped_parts(model, [Part(None, model, [(np.array([0.0, 0.6, 0.8]), 0.0)]),
                              Part(None, model, [(np.array([0.0, -0.6, -0.8]), 0.0)])], offsets, z, h)


def test_the_zone_is_sampled_at_the_seams_two_extremes(cell):
    """extremes(): the stepped parts as straight pairs at the least and the
    most offset, each pair's two planes the same plane seen from both sides."""
    from ambots.seam_steps import extremes
    model = ramp_manifold()
    parts = partition(model, cell)
    z, h = layer_heights(float(model.bounding_box()[5]), SliceSettings())
    offsets = np.round(np.linspace(-10.0, 14.0, len(z)), 1)
    (n, off), = parts[0].planes
    for pair, d in zip(extremes(stepped_parts(model, parts, offsets, z, h)), (-10.0, 14.0)):
        (na, oa), = pair[0].planes
        (nb, ob), = pair[1].planes
        assert oa == pytest.approx(off + d) and ob == pytest.approx(-oa) and np.allclose(nb, -na)
        assert pair[0].layer_offsets is None and pair[1].layer_offsets is None


def test_the_clipped_toolpaths_follow_each_layers_seam_and_lose_nothing(cell):
    """The whole model's toolpaths clipped to the two stepped prisms: every
    extrusion of a part on its side of its layer's seam, and the two parts'
    extruded lengths add up to the whole model's on every layer."""
    import trimesh
    from ambots.coordinate import read_sliced
    from ambots.job import slice_parts
    model = ramp_manifold()
    m = model.to_mesh()
    mesh = trimesh.Trimesh(np.asarray(m.vert_properties)[:, :3], np.asarray(m.tri_verts), process=False)
    whole = WholeModel(mesh, SliceSettings())
    parts = partition(model, cell)
    (n, off), = parts[0].planes
    tp = whole.toolpaths()
    offsets = np.round(np.linspace(-10.0, 14.0, len(tp)), 1)
    stepped = stepped_parts(model, parts, offsets, *layer_heights(float(model.bounding_box()[5]), SliceSettings()))
    sliced = slice_parts(stepped, "builtin", None, whole)
    whole_len = [float(np.linalg.norm(b - a, axis=1).sum()) for a, b in layer_segments(tp)]
    got = np.zeros(len(tp))
    for part, sign in zip(stepped, (1.0, -1.0)):
        read = read_sliced(sliced[part.arm.name], part.arm.name)
        zs = sorted({round(lp.z, 3) for lp in tp})
        for layer, segs in read.layers.items():
            ext = [s for s in segs if s.extrude and s.start[:2] != s.end[:2]]
            if not ext:
                continue
            i = zs.index(round(ext[0].end[2], 3))
            P = np.array([s.end[:2] for s in ext] + [s.start[:2] for s in ext])
            assert (sign * (P @ np.asarray(n[:2]) - (off + offsets[i]))).min() >= -1e-3, (part.arm.name, i)
            got[i] += sum(float(np.hypot(s.end[0] - s.start[0], s.end[1] - s.start[1])) for s in ext)
    # the G-code (to 1 um) adds no extrusion but the links that join cut infill along the seam
    assert np.all(got >= np.array(whole_len) - 0.1)
    assert got.sum() <= 1.02 * sum(whole_len)


def test_plan_offsets_reads_each_programs_layers_by_height():
    """Layer busy times of programs whose G-code starts higher (a part
    with nothing on the lowest layers) go to the whole model's layers of
    the same Z."""
    class P:
        def __init__(self, name, planes):
            self.arm = type("A", (), {"name": name})()
            self.planes = planes

    class L:
        def __init__(self, z, index, a, b):
            self.z, self.index = z, index
            self.islands = [[[Path("perimeter", np.array([[a, 0.0], [b, 0.0]]), False)]]]
            self.support = self.contact = None

    tp = [L(0.2 * (i + 1), i, -100.0, 100.0) for i in range(4)]
    parts = [P("a", [(np.array([1.0, 0.0, 0.0]), 0.0)]), P("b", [(np.array([-1.0, 0.0, 0.0]), 0.0)])]
    sliced = {"a": ";Z:0.200\n;Z:0.400\n;Z:0.600\n;Z:0.800\n", "b": ";Z:0.600\n;Z:0.800\n"}
    # b: 4 s on its program's layers 0, 1 = the model's layers 2, 3; a: 1 s on each of its four
    busy = {"a": np.array([1.0, 1.0, 1.0, 1.0]), "b": np.array([4.0, 4.0])}
    by_hand = np.array([[1.0, 1.0, 1.0, 1.0], [0.0, 0.0, 4.0, 4.0]])
    want = timed_offsets(layer_segments(tp), (1.0, 0.0), 0.0, np.zeros(4), by_hand)
    assert plan_offsets(parts, sliced, busy, tp, keep_mm=0.0) == pytest.approx(want)
    assert want[3] < want[0]                 # b slower on the top layers: a's side grows there
    # balanced layers: the seam would not move, no stepped plan
    assert plan_offsets(parts, sliced, {"a": np.ones(4), "b": np.array([1.0, 1.0])}, tp[2:], 0.0) is None


def leaning_block(length=160.0, width=20.0, height=12.0, lean=12.0):
    """A block whose layers move ``lean`` mm along x from the bed to its top (45 deg)."""
    import trimesh
    x0, x1, w = -length / 2 - lean / 2, length / 2 - lean / 2, width / 2
    v = [[x0, -w, 0], [x1, -w, 0], [x1, w, 0], [x0, w, 0],
         [x0 + lean, -w, height], [x1 + lean, -w, height], [x1 + lean, w, height], [x0 + lean, w, height]]
    f = [[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4], [1, 2, 6], [1, 6, 5], [2, 3, 7],
         [2, 7, 6], [3, 0, 4], [3, 4, 7]]
    m = trimesh.Trimesh(v, f)
    m.fix_normals()
    return m


def test_a_leaning_block_is_printed_with_the_seam_stepped_when_that_is_faster(cell, tmp_path):
    """The layers of a block leaning along the arms' line move 12 mm from
    the bed to its top, so a straight seam gives one arm more of the low
    layers and the other more of the high ones, and the layers go in step;
    cooperating pays, so the planner also makes the plan with the seam
    moved layer by layer and keeps the fastest.  Every extrusion of each
    program is on its side of its own layer's seam, the zone grew by the
    largest step, and the simulation on one clock agrees that the stepped
    plan is faster than the straight one and finds no contact, as planned
    and with every move of each arm 0.5-2x slower at random."""
    import re
    from ambots.gcode import Segment
    from ambots.job import VARIANT_SHARE, plan_lines, run_job, write_job
    from ambots.sim import check_motion, simulate
    path = str(tmp_path / "lean.stl")
    leaning_block().export(path)
    job = run_job(path, cell)
    chosen = job.chosen
    straight = next(c for c in job.candidates if len(c.arms) == 2 and not c.seam_turn_deg and not c.seam_steps_mm)
    assert chosen.seam_steps_mm is not None and len(chosen.arms) == 2
    assert chosen.makespan_s == min(c.makespan_s for c in job.candidates if c.makespan_s is not None)
    assert chosen.makespan_s < straight.makespan_s * (1.0 - VARIANT_SHARE)        # clearly faster, so kept
    offsets = chosen.seam_offsets
    assert [p.arm.name for p in job.parts] == ["kinova", "ur10"]
    assert list(job.parts[0].layer_offsets) == list(offsets) and list(job.parts[1].layer_offsets) == list(-offsets)
    assert largest_step(offsets) <= STEP_MM + 1e-9 and np.ptp(offsets) > 5.0
    (n, off), = job.parts[0].planes
    seam_x = (off + offsets) / n[0]                  # where each layer's seam crosses the x axis
    assert seam_x[-1] > seam_x[0] + 5.0              # it follows the lean (+x going up)
    zone = lambda c: {float(re.search(r"; seam zone ([0-9.]+) mm", p.text).group(1))      # noqa: E731
                      for p in c.programs.values()}
    assert sorted(zone(chosen)) == pytest.approx([max(zone(straight)) + largest_step(offsets)])
    zs = sorted({round(float(lp.z), 3) for lp in WholeModel(job.mesh, SliceSettings()).toolpaths()})
    for part, sign in zip(job.parts, (1.0, -1.0)):
        ext = [s for s in job.events()[part.arm.name] if type(s) is Segment and s.extrude and s.start != s.end]
        ends = np.array([s.end for s in ext])
        layer = np.searchsorted(zs, np.round(ends[:, 2], 3))
        d = sign * (ends[:, :2] @ np.asarray(n[:2]) - (off + offsets[layer]))
        assert d.min() > -0.5 * 0.45, part.arm.name                      # within half a bead of its side
    assert job.plan_summary()["seam_steps_mm"] == chosen.seam_steps_mm
    # the seam figures are measured on each layer's seam (job.json's "seams")
    from ambots.mesh import to_manifold
    from ambots.seams import seam_samples
    setup = job.seam_setup()
    planes = {tuple(k.split("/")): (np.asarray(v["normal"]), v["offset_mm"] + np.asarray(v["layer_offsets_mm"]))
              for k, v in setup["planes"].items()}
    assert setup["planes"]["kinova/ur10"]["layer_offsets_mm"] == pytest.approx(list(offsets))
    P, normal = seam_samples(to_manifold(job.mesh), planes, np.asarray(setup["z_tops_mm"]),
                             np.asarray(setup["heights_mm"]))["kinova", "ur10"]
    layer = np.searchsorted(setup["z_tops_mm"], P[:, 2])
    assert len(P) > 1000 and P @ normal == pytest.approx(off + offsets[layer], abs=1e-6)
    assert "seam stepped per layer (%+.1f to %+.1f mm)" % tuple(chosen.seam_steps_mm) in plan_lines(
        job.plan_summary())[0]
    out = tmp_path / "job"
    write_job(job, str(out))                                             # the stepped parts' STLs too
    assert (out / "kinova.stl").stat().st_size > 0
    stepped = simulate(job.programs, cell)
    flat = simulate(straight.programs, cell)
    assert stepped.finished and stepped.makespan_s < flat.makespan_s
    assert chosen.makespan_s == pytest.approx(stepped.makespan_s, rel=0.03)
    for res in (stepped, simulate(job.programs, cell, slow={k: (0.5, 2.0) for k in job.programs}, seed=1)):
        motion = check_motion(res, cell)
        assert res.finished and sum(motion["collisions"].values()) == 0, motion
