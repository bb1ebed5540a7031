"""Links along a band edge (``ambots.coordinate.links.edge_links``): where
a two-arm plan's bands cut a zig-zag of infill, the pieces on each side of
an edge are joined along it, as the slicer joins its lines at an outline.
Checked on a real job (built-in slicer, the default cell) against its
sliced parts: every bead of the parts printed once, plus links that lie on
an edge, between two infill lines, the two bands' links meeting end to end;
the programs then take less time by the one timing law, and executed with
random durations keep the zone.  Hand-made layers check that no link is
made along a perimeter (round a hole) or across a wall."""
import math
import random
from types import SimpleNamespace

import numpy as np
import pytest
import trimesh

from ambots.config import default_cell_path, load_cell
from ambots.coordinate import banded, home_positions_mm, park_positions_mm, read_sliced, seam_planes
from ambots.coordinate import links as linking
from ambots.coordinate.steps import Features
from ambots.estimate import estimate_programs
from ambots.gcode import Segment, parse_gcode_text
from ambots.job import run_job
from test_coordinate import closest_across, execute  # tests/unit/test_coordinate.py


@pytest.fixture(scope="module")
def cell():
    return load_cell(default_cell_path())


@pytest.fixture(scope="module")
def block(tmp_path_factory):
    path = str(tmp_path_factory.mktemp("edge") / "block_200x40x3.stl")
    trimesh.creation.box((200.0, 40.0, 3.0)).apply_translation((0.0, 0.0, 1.5)).export(path)
    return path


def _edges(program):
    """The band edges (mm from the seam) a banded program's header states."""
    line = next(ln for ln in program.lines if "band(s) per layer from" in ln)
    return [float(v) for v in line.split(" from ")[1].split(" mm")[0].split()][1:]


def _moves(text):
    """The extruding moves of a G-code text, in order: (start, end, E)."""
    return [(s.start, s.end, s.e) for s in parse_gcode_text(text)
            if type(s) is Segment and s.extrude and s.start != s.end]


def test_features_name_the_lines_as_a_plain_scan_does(cell, block):
    """Each line's feature is the last ``;TYPE:`` above it, counted as
    ``str.splitlines`` counts lines (the parser's), whatever the line breaks."""
    job = run_job(block, cell, [cell.arms[0]])
    text = str(job.sliced[cell.arms[0].name])
    for t in (text, text.replace("\n", "\r\n"), text.replace("\n", "\r")):
        f = Features(t)
        want, cur = [], None
        for ln in t.splitlines():
            if ln.startswith(";TYPE:"):
                cur = ln[6:]
            want.append(cur)
        assert len(f.names) > 20
        assert [f.of(i) for i in range(1, len(want) + 1)] == want


@pytest.fixture(scope="module")
def plans(cell, block):
    """The block by both arms, with links and without (the limit 0)."""
    both = list(cell.arms)
    job = run_job(block, cell, both)
    keep = linking.EDGE_LINK_MAX_MM
    linking.EDGE_LINK_MAX_MM = 0.0
    try:
        bare = run_job(block, cell, both)
    finally:
        linking.EDGE_LINK_MAX_MM = keep
    return job, bare


def _infill_segments(text):
    """(S, 2, 3) the extruding segments of a sliced G-code text that its
    ``;TYPE:`` comments call infill (read line by line here)."""
    out, feature, pos = [], None, None
    for ln in str(text).splitlines():
        if ln.startswith(";TYPE:"):
            feature = ln[6:]
        if ln.startswith(("G0 ", "G1 ")):
            w = {t[0]: float(t[1:]) for t in ln.split(";")[0].split()[1:]}
            new = (w.get("X", pos[0] if pos else 0.0), w.get("Y", pos[1] if pos else 0.0),
                   w.get("Z", pos[2] if pos else 0.0))
            if pos is not None and w.get("E", 0.0) > 0 and new != pos and feature and "infill" in feature.lower():
                out.append((pos, new))
            pos = new
    return np.array(out, dtype=float)


def _on_any(p, q, segs, tol=2e-3):
    """Whether the move p -> q lies on one of ``segs`` ((S, 2, 3))."""
    a, b = segs[:, 0], segs[:, 1]
    ab = b - a
    L2 = np.maximum((ab * ab).sum(axis=1), 1e-12)

    def dist(x):
        u = np.clip(((np.asarray(x) - a) * ab).sum(axis=1) / L2, 0.0, 1.0)
        return np.linalg.norm(a + u[:, None] * ab - np.asarray(x), axis=1)
    return bool(np.any((dist(p) <= tol) & (dist(q) <= tol)))


def test_links_lie_on_an_edge_between_infill_lines_and_add_only_themselves(plans):
    job, _ = plans
    planes = seam_planes(job.parts)
    links_in_all = 0
    for part in job.parts:
        name = part.arm.name
        program = job.programs[name]
        (n, off), = [v for (a, _), v in planes.items() if a == name]
        n = np.asarray(n, dtype=float)
        edges = _edges(program)
        assert edges and all(e > 0 for e in edges)
        dist = lambda p: float(np.dot(n[:2], p[:2]) - off)
        moves = _moves(program.text)
        on_edge = lambda p: min(abs(dist(p) - e) for e in edges) < 1e-6
        links = [i for i, (a, b, _) in enumerate(moves) if on_edge(a) and on_edge(b) and abs(dist(a) - dist(b)) < 1e-9]
        assert len(links) > 50, "the bands cut the zig-zags: links expected"
        links_in_all += len(links)
        infill = _infill_segments(job.sliced[name])
        by_layer = {}
        for i in links:
            a, b, _ = moves[i]
            assert math.dist(a, b) <= linking.EDGE_LINK_MAX_MM + 1e-9
            for j in (i - 1, i + 1):             # between two moves of the part's infill, end to end
                assert moves[j][1] == a if j < i else moves[j][0] == b
                assert _on_any(moves[j][0], moves[j][1], infill), (moves[j], moves[i])
            along = sorted((float(np.cross(n[:2], a[:2])), float(np.cross(n[:2], b[:2]))))
            by_layer.setdefault((round(a[2], 4), round(dist(a), 4)), []).append(along)
        # links of the two bands along one edge of a layer meet end to end: no two overlap
        for spans in by_layer.values():
            spans.sort()
            for (_, hi), (lo, _) in zip(spans, spans[1:]):
                assert lo >= hi - 1e-6, spans
        # every bead of the sliced part printed once, plus the links
        parts_moves = _moves(str(job.sliced[name]))
        length = lambda ms: sum(math.dist(a, b) for a, b, _ in ms)
        link_moves = [moves[i] for i in links]
        assert length(moves) == pytest.approx(length(parts_moves) + length(link_moves), rel=1e-9)
        assert sum(e for _, _, e in moves) == pytest.approx(
            sum(e for _, _, e in parts_moves) + sum(e for _, _, e in link_moves), rel=1e-6)
        # a link lays as much filament a millimetre as the line it follows on from
        for i in links:
            a, b, e = moves[i]
            p, q, e0 = moves[i - 1]
            assert e / math.dist(a, b) == pytest.approx(e0 / math.dist(p, q), rel=1e-3)
    assert links_in_all > 100


def test_links_save_time_and_retractions(cell, plans):
    """By the one timing law, every move planned, the linked programs take
    less time (about 0.1 % here: less than the sampled estimate's own error,
    so not that); they retract less (a link replaces a retracted travel)."""
    job, bare = plans
    fast = estimate_programs(job.programs, cell, sample_moves=10 ** 9)
    slow = estimate_programs(bare.programs, cell, sample_moves=10 ** 9)
    assert fast["makespan_s"] < slow["makespan_s"]
    for name in job.programs:
        assert fast["arms"][name]["busy_s"] < slow["arms"][name]["busy_s"]
        retracts = lambda text: sum(1 for s in parse_gcode_text(text) if type(s) is Segment and s.e < 0)
        assert retracts(job.programs[name].text) < 0.8 * retracts(bare.programs[name].text)


@pytest.mark.parametrize("seed", range(2))
def test_linked_programs_keep_the_zone_whatever_the_timing(cell, plans, seed):
    job, _ = plans
    arms = [p.arm for p in job.parts]
    zone = float(job.programs[arms[0].name].lines[2].split("seam zone ")[1].split(" mm")[0])
    spans = execute(job.programs, random.Random(seed), home_positions_mm(cell, arms))
    planes = seam_planes(job.parts)
    counts, slack = closest_across(spans, planes, {k: zone for k in planes}, park_positions_mm(cell, arms))
    pair = tuple(a.name for a in arms)
    assert counts[pair] > 100
    assert slack[pair] >= -1e-6, "nozzles %.1f mm nearer than the zone" % -slack[pair]


def _layer(moves, typed=True):
    """Hand-made sliced G-code of one layer, read: ``moves`` [(feature,
    [(x, y), ...])] paths, each extruded point to point, a travel before
    each; ``typed``: with the ``;TYPE:`` comments."""
    out = ["G21", "G90", "M83", ";LAYER_CHANGE", ";Z:0.2", "G0 Z0.2 F9000"]
    for feature, pts in moves:
        out += [";TYPE:%s" % feature] if typed else []
        out += ["G0 X%.3f Y%.3f F9000" % pts[0]] + ["G1 X%.3f Y%.3f E0.10000 F1800" % p for p in pts[1:]]
    return read_sliced("\n".join(out) + "\n", "layer.gcode")


def _banded(read, t=(0.0, 10.0)):
    """The pieces {band: [Segment]} of one arm on the side x >= 0 of a seam
    x = 0, its band edge at ``t[1]`` mm."""
    arm = SimpleNamespace(name="a")
    planes = {"a": [(np.array([1.0, 0.0, 0.0]), 0.0)]}
    lo = {"a": np.array([0.0, t[1]])}
    ph = banded._phases([arm], {("a", 0): read.layers[0]}, planes, {"a": np.array(t)}, 2, {"a": 0}, 1, lo,
                        {"a": read.features})
    return {b: pieces for b, pieces in ph.values()}


def _links(pieces, edge=10.0):
    """The y spans of the moves along the edge x = ``edge``."""
    return sorted(tuple(sorted((s.start[1], s.end[1]))) for s in pieces
                  if s.extrude and s.start != s.end and abs(s.start[0] - edge) < 1e-9 and abs(s.end[0] - edge) < 1e-9)


#: a zig-zag of three 45 deg lines joined at y = +-5, crossing the edge x = 10
#: at y = 1, -1 and -3
ZIGZAG = [(4.0, -5.0), (14.0, 5.0), (16.0, 5.0), (6.0, -5.0), (8.0, -5.0), (18.0, 5.0)]


@pytest.fixture
def cut_at_every_crossing(monkeypatch):
    """Lanes cut at every crossing (not divided between their lines), so
    that the pieces are the ones worked out by hand here."""
    monkeypatch.setattr(banded, "ZIGZAG_CROSSINGS", 10 ** 6)


def test_a_zigzag_of_infill_cut_at_an_edge_is_linked_on_both_sides(cut_at_every_crossing):
    bands = _banded(_layer([("Internal infill", ZIGZAG)]))
    # the near band leaves at y = 1 and comes back at y = -1; the far band leaves
    # at y = -1 (the end of its V) and comes back at y = -3: the links meet at y = -1
    assert _links(bands[0]) == [(-1.0, 1.0)]
    assert _links(bands[1]) == [(-3.0, -1.0)]
    # each band's pieces are now one run of extrusion
    for pieces in bands.values():
        assert all(p.end == q.start for p, q in zip(pieces, pieces[1:]))


def test_no_link_along_a_perimeter_without_features_or_across_a_wall(cut_at_every_crossing):
    # the same path as a perimeter (a loop round a hole, say): never linked
    bands = _banded(_layer([("Perimeter", ZIGZAG)]))
    assert not _links(bands[0]) and not _links(bands[1])
    # bridge infill spans a gap: a link between its lines would too
    bands = _banded(_layer([("Bridge infill", ZIGZAG)]))
    assert not _links(bands[0]) and not _links(bands[1])
    # solid infill is linked as sparse infill is
    assert _links(_banded(_layer([("Solid infill", ZIGZAG)]))[0]) == [(-1.0, 1.0)]
    # no feature comments: nothing known, no link
    bands = _banded(_layer([("Internal infill", ZIGZAG)], typed=False))
    assert not _links(bands[0]) and not _links(bands[1])
    # walls across the edge between the ends of each would-be link
    walls = [("Perimeter", [(9.0, 0.0), (11.0, 0.0)]), ("Perimeter", [(9.0, -2.0), (11.0, -2.0)])]
    bands = _banded(_layer([("Internal infill", ZIGZAG)] + walls))
    assert not _links(bands[0]) and not _links(bands[1])
    # one wall: only the link it crosses is left out
    bands = _banded(_layer([("Internal infill", ZIGZAG)] + walls[1:]))
    assert _links(bands[0]) == [(-1.0, 1.0)] and not _links(bands[1])


def test_a_wall_leaves_out_only_the_link_it_crosses_among_a_bands_links(cut_at_every_crossing):
    """A band with two links (all of a band's links are tested against the
    layer's walls at once): a wall across the second leaves the first."""
    longer = ZIGZAG + [(20.0, 5.0), (8.0, -7.0)]          # a fourth line, crossing the edge at y = -5
    bands = _banded(_layer([("Internal infill", longer)]))
    assert _links(bands[0]) == [(-5.0, -3.0), (-1.0, 1.0)]
    assert _links(bands[1]) == [(-3.0, -1.0)]
    wall = [("Perimeter", [(9.0, -4.0), (11.0, -4.0)])]   # across the edge between y = -5 and -3
    bands = _banded(_layer([("Internal infill", longer)] + wall))
    assert _links(bands[0]) == [(-1.0, 1.0)]
    assert _links(bands[1]) == [(-3.0, -1.0)]


def _chunked(read, bands=2, zone=20.0, links=True):
    """The chunks of one arm's layer by the scheduled timeline
    (``timeline._chunks``) on the side x >= 0 of a seam x = 0 whose zone is
    ``zone`` mm: ``bands`` chunk bands, edges every zone / bands mm;
    ``links``: the infill linked along the chunk edges or as cut."""
    from ambots.coordinate import timeline
    N, O = np.array([[1.0, 0.0, 0.0]]), np.array([0.0])
    seams = SimpleNamespace(names=["a"], useful={"a": np.array([True])}, Z={"a": np.array([zone])},
                            N={"a": N}, O={"a": O}, dist=lambda n, pts: np.asarray(pts, float).reshape(-1, 3) @ N.T - O)
    return timeline._chunks(seams, {"a": read}, 1, bands, links)[("a", 0)]


def test_the_scheduled_timeline_links_its_chunks_along_their_edges(cut_at_every_crossing):
    """Four arms in the corners (a scheduled timeline) cut a layer into
    chunks by band; the zig-zag is linked along the chunk edge as the banded
    sweeps link it, and a link moves nothing of a chunk nearer the seam (its
    footprint, the closest distance to the plane, is the pieces')."""
    chunks = _chunked(_layer([("Internal infill", ZIGZAG)]))
    assert len(chunks) == 2                          # [0, 10) mm from the seam and [10, 20)
    near, far = (pieces for pieces, _, _ in chunks)
    assert _links(near) == [(-1.0, 1.0)] and _links(far) == [(-3.0, -1.0)]
    for pieces, dmin, _ in chunks:
        assert all(p.end == q.start for p, q in zip(pieces, pieces[1:]))     # one run each
        ends = [p.start[0] for p in pieces if not _links([p])] + [p.end[0] for p in pieces if not _links([p])]
        assert dmin[0] == pytest.approx(min(ends), abs=1e-9)
    # a perimeter (or no features known) is never linked: each line a run of its own
    for read in (_layer([("Perimeter", ZIGZAG)]), _layer([("Internal infill", ZIGZAG)], typed=False)):
        assert not any(_links(pieces) for pieces, _, _ in _chunked(read))


def test_the_timeline_chunks_as_cut_keep_each_line_a_run_of_its_own(cut_at_every_crossing):
    """The other kind of chunks the timeline schedules (``links=False``):
    the same pieces without the links, so the zig-zag cut at the chunk edge
    is two runs in each chunk (one when linked: the lines joined at the
    outline on the chunk's side stay joined), and the footprints are the
    linked chunks' (a link lies between two ends of pieces on the edge)."""
    read = _layer([("Internal infill", ZIGZAG)])
    linked, cut = _chunked(read), _chunked(read, links=False)
    runs = lambda ps: 1 + sum(p.end != q.start for p, q in zip(ps, ps[1:]))
    assert [runs(ps) for ps, _, _ in cut] == [2, 2] and [runs(ps) for ps, _, _ in linked] == [1, 1]
    assert not any(_links(ps) for ps, _, _ in cut)
    for (ps_l, d_l, level_l), (ps_c, d_c, level_c) in zip(linked, cut):
        assert [p for p in ps_l if not _links([p])] == ps_c
        assert d_l.tolist() == d_c.tolist() and level_l == level_c

