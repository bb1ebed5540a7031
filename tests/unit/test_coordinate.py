"""Per-arm programs: sequential (the original) and concurrent (layers in
lock-step, seam zones taken in turns), checked by executing them."""
import random

import manifold3d as m3
import numpy as np
import pytest

from ambots.config import default_cell_path, load_cell
from ambots.coordinate import build_programs, home_positions_mm, park_positions_mm, seam_planes
from ambots.gcode import Segment, parse_gcode_text
from ambots.partition import partition
from ambots.protocol import MoveTo, SendPosition, Start, WaitFor, decode


@pytest.fixture(scope="module")
def cell():
    return load_cell(default_cell_path())


def square_layers(x0, x1, y0, y1, layers=4, h=0.2, step=5.0):
    """Hand-made slicer output: per layer, lines across the part every `step` mm."""
    out = ["; test slicer", "G21", "G90", "M83", "A1 R2 ; must be stripped"]
    for k in range(layers):
        z = h * (k + 1)
        out += [";LAYER_CHANGE", ";Z:%.1f" % z, "G0 X%.1f Y%.1f Z%.1f F9000" % (x0, y0, z)]
        for x in np.arange(x0, x1 + 1e-9, step):
            out += ["G0 X%.1f Y%.1f F9000" % (x, y0), "G1 X%.1f Y%.1f E0.5 F1800" % (x, y1)]
    return "\n".join(out) + "\n"


@pytest.fixture(scope="module")
def job(cell):
    model = m3.Manifold.cube([160, 40, 0.8]).translate([-80, -20, 0])
    parts = partition(model, cell)
    sliced = {"kinova": square_layers(-80, 0, -20, 20), "ur10": square_layers(0, 80, -20, 20)}
    return parts, sliced


def extrusions(text):
    """Sorted (start, end, E) of the moves that lay filament (unretractions excluded)."""
    return sorted((s.start, s.end, round(s.e, 5)) for s in parse_gcode_text(text)
                  if type(s) is Segment and s.extrude and s.start != s.end)


def totals(text):
    """(filament pushed, extruded path length) of a program."""
    segs = [s for s in parse_gcode_text(text) if type(s) is Segment and s.extrude and s.start != s.end]
    return (sum(s.e for s in segs), sum(float(np.linalg.norm(np.subtract(s.end, s.start))) for s in segs))


def test_concurrent_programs_keep_every_extrusion_and_strip_a_series(cell, job):
    parts, sliced = job
    programs = build_programs(sliced, parts, cell, mode="concurrent", zone_mm=20.0)
    for name, prog in programs.items():
        want = totals(sliced[name].replace("A1 R2 ; must be stripped", ""))
        assert totals(prog.text) == pytest.approx(want, rel=1e-9)
        assert prog.removed and prog.removed[0][1].startswith("A1 R2")
        assert "A1 R2" not in prog.text


def test_bands_split_moves_that_cross_them(cell):
    """A diagonal slicer line across the bands is cut where it crosses each
    band boundary; the pieces keep the line's filament."""
    model = m3.Manifold.cube([160, 40, 0.4]).translate([-80, -20, 0])
    parts = partition(model, cell)
    diag = ["G21", "G90", "M83", ";LAYER_CHANGE", ";Z:0.2", "G0 X-5 Y-20 Z0.2 F9000", "G1 X-75 Y20 E3 F1800"]
    other = ["G21", "G90", "M83", ";LAYER_CHANGE", ";Z:0.2", "G0 X5 Y-20 Z0.2 F9000", "G1 X75 Y20 E3 F1800"]
    sliced = {"kinova": "\n".join(diag) + "\n", "ur10": "\n".join(other) + "\n"}
    programs = build_programs(sliced, parts, cell, mode="concurrent", zone_mm=30.0)
    for name, prog in programs.items():
        k = prog.phases
        pieces = [s for s in parse_gcode_text(prog.text) if type(s) is Segment and s.extrude and s.start != s.end]
        assert len(pieces) > 1 and sum(s.e for s in pieces) == pytest.approx(3.0)
        (n, off), = [(np.asarray(n), o) for n, o in next(p.planes for p in parts if p.arm.name == name)]
        # the band boundaries, from the header: "... k band(s) per layer from t0 t1 ... mm"
        t = [float(v) for v in prog.lines[2].split(" from ")[1].split(" mm")[0].split()]
        assert len(t) == k and t[0] == 0.0 and all(t[i] + t[k - 1 - i] >= 30.0 - 1e-6 for i in range(k))
        for s in pieces:       # every piece lies inside one band
            d = sorted((float(n @ np.array(s.start) - off), float(n @ np.array(s.end) - off)))
            band = int(np.searchsorted(t, (d[0] + d[1]) / 2, side="right")) - 1
            assert d[0] >= t[band] - 2e-3 and (band == k - 1 or d[1] <= t[band + 1] + 2e-3)


def execute(programs, rng, home=None):
    """Execute programs line by line with random durations (0.1-3 s per
    moving line or A7 park move, so any arm may run far slower than
    planned), as the firmware does: ``;@A9 R W N`` blocks until the other
    arm has *reported* line N or more, or is done; an arm reports its last
    completed line only when it reaches the first of a run of A9 lines after
    a move (the line before the run), at an ``;@A3`` line (that line), and
    when it finishes, never while it waits.  ``home``: {arm: (x, y, z) mm}
    where each nozzle starts (default: where its first move ends).

    Returns {arm: [(t0, t1, p0, p1, kind)]}: the arm's whole time, in order,
    as straight moves of the nozzle from p0 to p1 (mm, bed frame); kind
    "move" (a G-code line), "park" (an A7 to the park position), "leave"
    (an A7 from home, before the first move), "wait" (standing still at an
    A9), "home" (waiting before the first move) or "end" (done)."""
    ids = {p.arm.id: name for name, p in programs.items()}
    lines = {n: p.lines for n, p in programs.items()}
    segs = {n: {s.line: s for s in parse_gcode_text(p.text) if type(s) is Segment} for n, p in programs.items()}
    pos = {n: tuple(home[n]) if home else segs[n][min(segs[n])].end for n in lines}
    done = {n: 0 for n in lines}
    reported = {n: 0 for n in lines}
    clock = {n: 0.0 for n in lines}
    spans = {n: [] for n in lines}
    after_move = {n: False for n in lines}
    started = {n: False for n in lines}
    for _ in range(10 ** 7):
        active = [n for n in lines if done[n] < len(lines[n])]
        if not active:
            end = max(clock.values()) + 1.0
            for n in lines:
                spans[n].append((clock[n], end, pos[n], pos[n], "end"))
            return spans
        progressed = False
        for n in sorted(active, key=lambda n: clock[n]):
            text, i = lines[n][done[n]], done[n] + 1
            if text.startswith(";@"):
                cmd = decode(text[2:])
                if isinstance(cmd, WaitFor):
                    if after_move[n]:
                        reported[n] = i - 1
                    after_move[n] = False
                    other = ids[cmd.other]
                    finished = done[other] >= len(lines[other])
                    if not finished and reported[other] < cmd.line:
                        continue
                    if clock[other] > clock[n]:
                        spans[n].append((clock[n], clock[other], pos[n], pos[n], "wait" if started[n] else "home"))
                        clock[n] = clock[other]
                elif isinstance(cmd, MoveTo) and cmd.robot == programs[n].arm.id:
                    t0 = clock[n]
                    clock[n] += rng.uniform(0.1, 3.0)
                    target = (cmd.x, cmd.y, cmd.z)
                    spans[n].append((t0, clock[n], pos[n], target, "park" if started[n] else "leave"))
                    pos[n] = target
                    after_move[n] = False
                else:
                    if isinstance(cmd, SendPosition):
                        reported[n] = i
                    after_move[n] = False
            elif not text.startswith(";") and text.strip():
                t0 = clock[n]
                clock[n] += rng.uniform(0.1, 3.0)
                if i in segs[n]:
                    spans[n].append((t0, clock[n], pos[n], segs[n][i].end, "move"))
                    pos[n] = segs[n][i].end
                    started[n] = True
                after_move[n] = True
            done[n] += 1
            progressed = True
            break
        assert progressed, "deadlock: %s" % {n: (done[n] + 1, lines[n][done[n]]) for n in active}
    raise AssertionError("did not finish")


def closest_across(spans, planes, zones, park, skip=("leave",)):
    """For every two arms with a plane between them: every two spans that
    overlap in time, the sum of the two nozzles' distances to the plane
    (closest points of each span; a park position counts as clear).
    Returns ({(a, b): number of overlapping spans}, {(a, b): smallest sum - zone})."""
    counts, slack = {}, {}
    names = list(spans)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            if (a, b) not in planes:
                continue
            n, o = planes[a, b]

            def dist(arm, sign, p0, p1):
                d = [sign * (float(np.dot(n, p)) - o) for p in (p0, p1) if not np.allclose(p, park[arm], atol=1e-3)]
                return min(d) if d else np.inf

            A = [(t0, t1, dist(a, 1.0, p0, p1)) for t0, t1, p0, p1, k in spans[a] if t1 > t0 and k not in skip]
            B = [(t0, t1, dist(b, -1.0, p0, p1)) for t0, t1, p0, p1, k in spans[b] if t1 > t0 and k not in skip]
            count, worst, ia, ib = 0, np.inf, 0, 0
            while ia < len(A) and ib < len(B):          # each arm's spans follow each other in time
                if max(A[ia][0], B[ib][0]) < min(A[ia][1], B[ib][1]):
                    count += 1
                    worst = min(worst, A[ia][2] + B[ib][2] - zones[a, b])
                if A[ia][1] <= B[ib][1]:
                    ia += 1
                else:
                    ib += 1
            counts[a, b], slack[a, b] = count, worst
    return counts, slack


@pytest.mark.parametrize("seed", range(5))
def test_concurrent_nozzles_across_a_seam_stay_a_zone_apart(cell, job, seed):
    """Whatever the timing, two moves that run at the same time are at least
    the zone apart across the seam (sum of their distances to it)."""
    parts, sliced = job
    zone = 20.0
    programs = build_programs(sliced, parts, cell, mode="concurrent", zone_mm=zone)
    assert {p.phases for p in programs.values()} == {programs["kinova"].phases} and programs["kinova"].phases >= 2
    arms = [p.arm for p in parts]
    spans = execute(programs, random.Random(seed), home_positions_mm(cell, arms))
    planes = seam_planes(parts)
    counts, slack = closest_across(spans, planes, {k: zone for k in planes}, park_positions_mm(cell, arms))
    assert counts["kinova", "ur10"] > 100                 # the arms do work at the same time
    assert slack["kinova", "ur10"] >= -1e-6, "nozzles %.1f mm nearer than the zone" % -slack["kinova", "ur10"]


def zigzag_layers(sign, layers=4, h=0.2, s=2.5, span=20.0):
    """Hand-made slicer output of a part on one side of the seam x = 0
    (``sign`` +1 or -1): per layer one zig-zag lane of infill, lines at 45
    deg spanning ``span`` mm across the strip, ``s`` mm apart, joined along
    its edges (what the built-in slicer makes of sparse infill)."""
    out = ["G21", "G90", "M83"]
    for k in range(layers):
        z = h * (k + 1)
        pts = []
        for i, a in enumerate(np.arange(0.0, 80.0 - span + 1e-9, s)):
            bottom, top = (a, -20.0), (a + span, 20.0)
            pts += [bottom, top] if i % 2 == 0 else [top, bottom]
        out += [";LAYER_CHANGE", ";Z:%.1f" % z, "G0 X%.3f Y%.3f Z%.1f F9000" % (sign * pts[0][0], pts[0][1], z)]
        for p, q in zip(pts, pts[1:]):
            out.append("G1 X%.3f Y%.3f E%.5f F1800" % (sign * q[0], q[1], 0.03 * np.hypot(q[0] - p[0], q[1] - p[1])))
    return "\n".join(out) + "\n"


@pytest.mark.parametrize("seed", range(3))
def test_zigzag_lanes_are_cut_between_lines_and_keep_the_zone(cell, seed):
    """A lane whose every line crosses the band edges is divided between its
    lines, not at every crossing: far fewer runs of extrusion than
    crossings, the same filament, and -- executed with random durations --
    two nozzles are never nearer than the zone across the seam."""
    model = m3.Manifold.cube([160, 40, 0.8]).translate([-80, -20, 0])
    parts = partition(model, cell)
    sliced = {"kinova": zigzag_layers(-1), "ur10": zigzag_layers(1)}
    zone = 30.0
    programs = build_programs(sliced, parts, cell, mode="concurrent", zone_mm=zone)
    planes = seam_planes(parts)
    for name, prog in programs.items():
        assert totals(prog.text) == pytest.approx(totals(sliced[name]), rel=1e-9)
        t = [float(v) for v in prog.lines[2].split(" from ")[1].split(" mm")[0].split()]
        segs = [x for x in parse_gcode_text(sliced[name]) if type(x) is Segment and x.extrude]
        d = lambda p: abs(p[0])                                 # distance to the seam x = 0
        crossings = sum(1 for x in segs for edge in t[1:] if min(d(x.start), d(x.end)) < edge < max(d(x.start), d(x.end)))
        out = [x for x in parse_gcode_text(prog.text) if type(x) is Segment and x.start != x.end]
        runs = sum(1 for i, x in enumerate(out) if x.extrude and (i == 0 or not out[i - 1].extrude))
        # cut at every crossing, a lane made crossings + 1 runs a layer (53 for 44 with 30 mm lines)
        assert crossings >= 30 and runs <= 0.4 * crossings, (runs, crossings)
    spans = execute(programs, random.Random(seed), home_positions_mm(cell, [p.arm for p in parts]))
    counts, slack = closest_across(spans, planes, {k: zone for k in planes},
                                   park_positions_mm(cell, [p.arm for p in parts]))
    assert counts["kinova", "ur10"] > 50
    assert slack["kinova", "ur10"] >= -1e-6, "nozzles %.1f mm nearer than the zone" % -slack["kinova", "ur10"]


@pytest.mark.parametrize("seed", range(3))
def test_concurrent_programs_never_deadlock_and_barriers_hold(cell, job, seed):
    parts, sliced = job
    programs = build_programs(sliced, parts, cell, mode="concurrent", zone_mm=20.0)
    execute(programs, random.Random(seed))
    by_id = {p.arm.id: p for p in programs.values()}
    for prog in programs.values():
        waits = [decode(l[2:]) for l in prog.lines if l.startswith(";@A9")]
        k = prog.phases
        # the arm that ends the last layer away from the seam parks once the other is done
        done = [w for w in waits if w.line == len(by_id[w.other].lines)]
        assert len(done) <= 1
        if done:      # after its last bead, before it parks (the last line)
            at = max(i for i, l in enumerate(prog.lines) if l.startswith(";@A9") and decode(l[2:]) == done[0])
            assert at > max(i for i, l in enumerate(prog.lines) if l.startswith("G1 X"))
            assert prog.lines[-1].startswith(";@A7") and not any(l.startswith(";@A9") for l in prog.lines[at + 1:])
        waits = [w for w in waits if w not in done]
        # an arm waits (for its neighbour's approach) before every phase that moves it
        # towards the seam: k - 1 phases in each of the 2 layers of 4 it sweeps towards it
        assert len(waits) == 2 * (k - 1) and all(isinstance(w, WaitFor) and w.robot == prog.arm.id for w in waits)
        assert [w.line for w in waits] == sorted(w.line for w in waits)
    assert sum(1 for p in programs.values() for l in p.lines
               if l.startswith(";@A9") and decode(l[2:]).line == len(by_id[decode(l[2:]).other].lines)) == 1


def test_sequential_is_the_original_hand_over(cell, job):
    parts, sliced = job
    programs = build_programs(sliced, parts, cell, mode="sequential")
    kinova, ur10 = programs["kinova"], programs["ur10"]
    assert kinova.start_first and not ur10.start_first
    a_lines = [decode(l[2:]) for l in kinova.lines if l.startswith(";@")]
    assert isinstance(a_lines[0], MoveTo) and a_lines[0].robot == ur10.arm.id    # park the UR10 first
    assert isinstance(a_lines[-2], MoveTo) and a_lines[-2].robot == kinova.arm.id  # then park itself
    assert a_lines[-1] == Start(ur10.arm.id)                                    # and start the UR10
    assert [type(decode(l[2:])) for l in ur10.lines if l.startswith(";@")] == [MoveTo]
    assert extrusions(ur10.text) == extrusions(sliced["ur10"].replace("A1 R2 ; must be stripped", ""))


def _travel_mm(segs, pos):
    total = 0.0
    for s in segs:
        total += float(np.linalg.norm(np.subtract(s.start, pos)))
        pos = s.end
    return total


def test_run_order_keeps_every_bead_and_shortens_travel():
    """Band pieces of perimeter loops: the slicer's order hops across the part
    between the two sides of each loop; the greedy order visits each side's
    pieces together, reversing runs where that is shorter."""
    from ambots.coordinate import _order_runs
    segs, line = [], 1
    for i in range(3):                       # three loops cut to the band x in [20, 40]
        y0, y1 = -20.0 + i, 20.0 - i
        for a, b in (((20, y0, .2), (40, y0, .2)), ((40, y1, .2), (20, y1, .2))):
            segs.append(Segment(a, b, 0.7, 1800.0, True, line, 0))
            segs.append(Segment(b, b, -0.8, 2100.0, False, line + 1, 0))     # slicer's retraction
            line += 2
    ordered = _order_runs(segs, (20.0, -20.0, 0.2))
    beads = lambda ss: sorted(tuple(sorted((s.start, s.end))) + (s.e,) for ss_ in [ss] for s in ss_
                              if s.extrude and s.start != s.end)
    assert beads(ordered) == beads(segs)
    assert all(s.extrude for s in ordered)          # travels and retractions are the writer's job
    assert _travel_mm(ordered, (20.0, -20.0, 0.2)) < 0.3 * _travel_mm(
        [s for s in segs if s.extrude], (20.0, -20.0, 0.2))


def test_short_travels_are_not_retracted():
    from ambots.coordinate import _Writer
    w = _Writer()
    w.travel_to((0.0, 0.0, 0.2))
    w.travel_to((0.5, 0.5, 0.2))            # 0.7 mm, same layer: a plain move
    assert w.lines[-1].startswith("G0 X0.500 Y0.500") and len(w.lines) == 2
    w.travel_to((10.0, 0.5, 0.2))           # longer: retract, move, unretract (no lift by default)
    assert w.lines[2].startswith("G1 E-0.8") and w.lines[-1].startswith("G1 E0.8") and len(w.lines) == 5
    assert w.lines[3] == "G0 X10.000 Y0.500 F9000"
    w.travel_to((0.0, 0.5, 0.4))            # to the next layer: up first, then across
    assert w.lines[-3:-1] == ["G0 Z0.400 F9000", "G0 X0.000 Y0.500 F9000"]
    h = _Writer(hop_mm=0.4)                 # with a lift: retract, lift, move, lower, unretract
    h.travel_to((0.0, 0.0, 0.2))
    h.travel_to((10.0, 0.5, 0.2))
    assert [ln.split()[1][0] for ln in h.lines[1:]] == ["E", "Z", "X", "Z", "E"]


# ------------------------------------------------------------ N arms
def _box(tmp_path_factory, name, dims):
    import trimesh
    path = tmp_path_factory.mktemp("models") / ("%s.stl" % name)
    m = trimesh.creation.box(dims)
    m.apply_translation((0.0, 0.0, dims[2] / 2))
    m.export(str(path))
    return str(path)


#: layouts of 3, 4 and 4-of-8 arms: cell, arms (None: all), model box (mm)
LAYOUTS = {
    # three around a point; wide enough that two print at once beyond their zones (154-240 mm)
    "three_arms": ("config/cells/three_arms.yaml", None, (240.0, 120.0, 0.6)),
    "four_arms": ("config/cells/four_arms.yaml", None, (140.0, 120.0, 0.4)),       # 2 x 2, diagonals meet
    "beam_row": ("config/cells/eight_arms_beam.yaml",                              # a row, alternate sides
                 ["kinova_3", "ur10_4", "ur10_5", "kinova_6"], (1300.0, 30.0, 0.4)),
}


@pytest.fixture(scope="module")
def n_arm_jobs(tmp_path_factory):
    from ambots.coordinate import seam_zones_for
    from ambots.job import prepare_model, slice_parts, split
    out = {}
    for key, (path, names, dims) in LAYOUTS.items():
        c = load_cell(path)
        arms = [c.arm(n) for n in names] if names else list(c.arms)
        mesh = prepare_model(_box(tmp_path_factory, key, dims), c)
        parts = split(mesh, c, arms)
        sliced = slice_parts(parts)
        parts = [p for p in parts if p.arm.name in sliced]
        arms = [p.arm for p in parts]
        programs = build_programs(sliced, parts, c)
        out[key] = (c, parts, sliced, programs, seam_zones_for(c, arms, parts))
    return out


@pytest.mark.parametrize("layout,seed", [(k, s) for k in LAYOUTS for s in range(2)])
def test_n_arm_programs_keep_every_pair_a_zone_apart_whatever_the_timing(n_arm_jobs, layout, seed):
    """Three arms around a point, four in the corners (diagonal neighbours
    meet only at the centre) and a row along a beam: executed with random
    durations and the firmware's reporting, no deadlock, and every two arms
    whose work comes within their zone of each other keep their nozzles the
    zone apart across the plane between them, waiting and parking included
    (only the simultaneous departure from the home poses is left out)."""
    from ambots.coordinate import read_sliced, adjacent_arms
    c, parts, sliced, programs, zones = n_arm_jobs[layout]
    arms = [p.arm for p in parts]
    planes = seam_planes(parts)
    read = {a.name: read_sliced(sliced[a.name], a.name) for a in arms}
    assert_zones_kept(programs, c, arms, planes, zones, adjacent_arms(arms, read, planes, zones), seed)


def assert_zones_kept(programs, cell, arms, planes, zones, adjacent, seed):
    """``programs`` executed with random durations (:func:`execute`, seeded):
    every two adjacent arms keep their nozzles the zone apart across their
    plane (and come near it at least once), and at the busiest moment more
    than one arm prints."""
    spans = execute(programs, random.Random(seed), home_positions_mm(cell, arms))
    counts, slack = closest_across(spans, planes, zones, park_positions_mm(cell, arms))
    pairs = [(a.name, b.name) for i, a in enumerate(arms) for b in arms[i + 1:] if b.name in adjacent[a.name]]
    assert pairs and all(counts[p] > 0 for p in pairs)
    for p in pairs:
        assert slack[p] >= -0.01, "%s and %s: nozzles %.2f mm nearer than the zone" % (p + (-slack[p],))
    # the arms do work at the same time: the busiest moment has more than one arm printing
    moves = sorted((t0, t1) for sp in spans.values() for t0, t1, _, _, k in sp if k == "move")
    ends, busiest = [], 0
    for t0, t1 in moves:
        ends = [e for e in ends if e > t0] + [t1]
        busiest = max(busiest, len(ends))
    assert busiest >= 2


def test_n_arm_layouts_use_the_schedule_their_adjacency_needs(n_arm_jobs):
    """Three around a point and four in the corners (diagonal pairs adjacent
    through the centre) are not two-colourable: a scheduled timeline.  A row
    is, and its middle arms, between two seams whose zones (58-60 mm: the
    print heads' bodies, the wrists trailing behind them) leave most of the
    330 mm between the seams free, keep clear of both neighbours at once:
    banded sweeps (with the wrists over the nozzles, zones of 157 and 170 mm
    made the row scheduled too)."""
    from ambots.coordinate import read_sliced, adjacent_arms
    for layout, scheduled in (("three_arms", True), ("four_arms", True), ("beam_row", False)):
        c, parts, sliced, programs, zones = n_arm_jobs[layout]
        arms = [p.arm for p in parts]
        read = {a.name: read_sliced(sliced[a.name], a.name) for a in arms}
        adjacent = adjacent_arms(arms, read, seam_planes(parts), zones)
        if layout == "four_arms":
            assert adjacent["kinova1"] >= {"kinova2", "ur10_1", "ur10_2"}       # the diagonal too
        if layout == "beam_row":
            assert adjacent == {"kinova_3": {"ur10_4"}, "ur10_4": {"kinova_3", "ur10_5"},
                                "ur10_5": {"ur10_4", "kinova_6"}, "kinova_6": {"ur10_5"}}
        assert all(("scheduled" in p.lines[2]) == scheduled for p in programs.values())


def test_every_wait_names_a_line_the_other_arm_reports(n_arm_jobs, job, cell):
    """A firmware reports its line at an ;@A3 (that line) or at the first of
    a run of ;@A9 lines after a move (the line before): a wait for any other
    line would last until some later report, and two arms could wait for
    each other (the deadlock of the first three-arm trial)."""
    sets = [programs for _, _, _, programs, _ in n_arm_jobs.values()]
    sets.append(build_programs(job[1], job[0], cell, zone_mm=20.0))
    for programs in sets:
        by_id = {p.arm.id: p for p in programs.values()}
        for prog in programs.values():
            for line in prog.lines:
                if not line.startswith(";@A9"):
                    continue
                w = decode(line[2:])
                other = by_id[w.other].lines
                target = other[w.line - 1]
                reported = target.startswith(";@A3") or w.line == len(other) or (     # (last line: when done)
                    not target.startswith(";@") and w.line < len(other) and other[w.line].startswith(";@A9"))
                assert reported, "R%d waits for line %d of R%d: %r" % (w.robot, w.line, w.other, target)


def test_seam_planes_name_the_arm_across_each_plane():
    """Each part's plane j bounds it against the arm ``neighbours[j]`` (its
    normal points from that arm's base to the part's own); with a part left
    out (an arm with nothing to print) the other planes keep their arms."""
    from ambots.partition import arm_sites_mm
    c = load_cell("config/cells/four_arms.yaml")
    model = m3.Manifold.cube([160, 120, 2]).translate([-80, -60, 0])
    parts = partition(model, c)
    sites = dict(zip([a.name for a in c.arms], arm_sites_mm(c, c.arms)))
    for part in parts:
        assert sorted(part.neighbours) == sorted(a.name for a in c.arms if a.name != part.arm.name)
        for (n, _), other in zip(part.planes, part.neighbours):
            u = sites[part.arm.name] - sites[other]
            assert np.allclose(np.asarray(n)[:2], u / np.linalg.norm(u))
    full = seam_planes(parts)
    some = seam_planes([p for p in parts if p.arm.name != "ur10_1"])
    assert len(full) == 12 and len(some) == 6 and not any("ur10_1" in k for k in some)
    for key, (n, o) in some.items():
        assert np.allclose(n, full[key][0]) and o == pytest.approx(full[key][1])


@pytest.mark.parametrize("path", ["config/cells/kinova_ur10.yaml", "config/cells/three_arms.yaml",
                                  "config/cells/four_arms.yaml", "config/cells/eight_arms_beam.yaml"])
def test_park_positions_are_clear_of_the_bed_and_reachable(path):
    """Every arm parks outside the bed, above the printable height, on its
    own side (nearer its base than the bed is), nozzle down within reach."""
    from ambots.model import arm_kinematics
    from ambots.partition import arm_sites_mm
    from ambots.workspace import down_in_base, world_to_base
    c = load_cell(path)
    park = park_positions_mm(c, c.arms)
    sx, sy = c.bed.size[0] * 500.0, c.bed.size[1] * 500.0
    for arm, site in zip(c.arms, arm_sites_mm(c, c.arms)):
        x, y, z = park[arm.name]
        assert abs(x) >= sx + 50.0 or abs(y) >= sy + 50.0, "%s parks over the bed" % arm.name
        assert z >= c.bed.max_height * 1000.0
        nearest = np.clip(site, [-sx, -sy], [sx, sy])
        assert np.linalg.norm(site - (x, y)) < np.linalg.norm(site - nearest)
        world = np.array([[x, y, z]]) / 1000.0 @ c.bed.pose[:3, :3].T + c.bed.pose[:3, 3]
        _, ok, _ = arm_kinematics(arm).ik_batch(world_to_base(arm, world), np.asarray(arm.profile.home),
                                                down_in_base(arm))
        assert ok[0]


def test_sequential_parks_the_waiting_arms_clear_of_the_bed():
    c = load_cell("config/cells/three_arms.yaml")
    model = m3.Manifold.cube([150, 40, 0.4]).translate([-75, -20, 0])
    parts = partition(model, c)
    sliced = {p.arm.name: square_layers(*np.asarray(p.manifold.bounding_box())[[0, 3, 1, 4]], layers=2)
              for p in parts}
    programs = build_programs(sliced, parts, c, mode="sequential")
    first = [decode(l[2:]) for l in programs["kinova"].lines if l.startswith(";@A7")]
    assert [m.robot for m in first[:2]] == [c.arm("ur10").id, c.arm("panda").id]
    sx, sy = c.bed.size[0] * 500.0, c.bed.size[1] * 500.0
    for m in first:
        assert abs(m.x) > sx or abs(m.y) > sy


def test_a_scheduled_step_waits_only_for_work_within_the_zone_of_it():
    """Worked out by hand: arms a and b across one plane, zone 50 mm.  Each
    step's footprint is its closest distance to the plane.  b's step waits
    for the last of a's steps that ended before it starts and comes within
    the zone of it, not for a step that keeps the zone; nor again for what
    an earlier step of b already waited for."""
    from types import SimpleNamespace
    from ambots.coordinate.schedule import Act
    from ambots.coordinate.timeline import _barriers
    act = lambda S, C, d: Act("chunk", 0, S, C, np.array([d]))
    acts = {"a": [act(0, 10, 0.0),       # at the seam
                  act(10, 20, 40.0),     # 40 mm off it
                  act(20, 30, 90.0)],    # far
            "b": [act(0, 10, 60.0),      # far while a is at the seam: no wait
                  act(20, 25, 20.0),     # a ended 0 and 1 by now; 20 + 40 >= 50, 20 + 0 < 50: waits for a's 0
                  act(30, 40, 5.0),      # a ended 2 (95: clear) and 1 (45 < 50): waits for a's 1
                  act(40, 50, 0.0)]}     # nothing new within the zone: no wait
    seams = SimpleNamespace(nbrs={"a": ["b"], "b": ["a"]}, where={"a": {"b": 0}, "b": {"a": 0}},
                            Z={"a": np.array([50.0]), "b": np.array([50.0])})
    _barriers(acts, seams, {"a": SimpleNamespace(id=1), "b": SimpleNamespace(id=2)})
    assert [x.waits for x in acts["b"]] == [{}, {"a": 0}, {"a": 1}, {}]
    assert [x.report for x in acts["a"]] == [2, 2, None]
    assert [x.waits for x in acts["a"]] == [{}, {}, {}]     # b's steps ended by then keep the zone from a's


def test_the_timeline_counts_the_joint_moves_to_and_from_the_park_position():
    """The firmware comes down from the park position in one joint move
    (straight in joint space): the nozzle bulges off the straight line, here
    (the Panda of the three-arm cell, towards its seam with the UR10) about
    20 mm nearer the seam than either end.  The timeline's estimate of the
    move (``JointMoves``, counted in the step's footprint) follows the
    firmware planner's own move."""
    from ambots.coordinate import JointMoves
    from ambots.motion import MotionPlanner
    c = load_cell("config/cells/three_arms.yaml")
    panda = c.arm("panda")
    park = park_positions_mm(c, c.arms)["panda"]
    target = np.array([-104.6, -57.5, 10.2])                  # 10 mm over a chunk's start near the seam
    planner = MotionPlanner(panda, c)
    q_park = planner.kin.ik(planner.bed_mm_to_base(park[None])[0], np.asarray(panda.profile.home), planner.down)
    tip = planner.world_to_bed_mm(planner.joint_move_to(planner.bed_mm_to_base(target[None])[0], q_park).tip)
    low = tip[tip[:, 2] <= c.bed.max_height * 1000.0]
    est = JointMoves(c, c.arms).path("panda", park, target)
    assert len(low) and len(est) and np.all(est[:, 2] <= c.bed.max_height * 1000.0)
    assert np.linalg.norm(low[:, None] - est[None], axis=2).min(axis=1).max() < 6.0     # 32 samples
    towards_ur10 = np.array([0.88, 0.47, 0.0]) / np.hypot(0.88, 0.47)
    ends = max(park @ towards_ur10, target @ towards_ur10)
    assert (low @ towards_ur10).max() > ends + 15.0
    assert abs((est @ towards_ur10).max() - (low @ towards_ur10).max()) < 1.0


def test_an_a7_parks_a_redundant_arm_in_the_same_joints_whatever_it_printed_before():
    """A Panda (seven joints for the nozzle's five constraints and its turn)
    drifts along its redundancy while it prints, as each IK starts from
    the joints before.  Measured in the three-arm cell on the 276 mm hex
    plate: at its park position after hours of printing, joints 1 and 3
    stood 2.6 rad from the park's joints reached from home, and the joint
    move from there back to 10 mm over the part went 10 mm into the bed.
    An A7 now solves its target from the home pose: the same joints at
    the park position every time, from which that move keeps clear of the
    bed, as the coordinator's estimate of the move said."""
    from ambots.collision import ArmBody, bed_clearance
    from ambots.coordinate import JointMoves
    from ambots.motion import MotionPlanner
    c = load_cell("config/cells/three_arms.yaml")
    panda = c.arm("panda")
    planner = MotionPlanner(panda, c)
    body = ArmBody.from_arm(panda)
    park = park_positions_mm(c, c.arms)["panda"]
    park_base = planner.bed_mm_to_base(park[None])[0]
    drifted = np.array([2.53, 1.23, -2.57, -2.95, 0.54, 1.74, -0.50])     # the simulation's, near the park
    home = np.asarray(panda.profile.home, dtype=float)
    q_park = planner.move_to(park_base, home).Q[-1]
    assert np.allclose(planner.move_to(park_base, drifted).Q[-1], q_park, atol=1e-9)
    assert np.linalg.norm(planner.world_to_bed_mm(planner.tip_world(q_park[None]))[0] - park) < 0.01
    # a joint move seeded with where the arm is keeps the drift (the old A7)
    kept = planner.joint_move_to(park_base, drifted).Q[-1]
    assert np.abs(kept - q_park).max() > 2.0
    over_part = (-54.902, -86.368, 11.0)                  # the hex plate's chunk start, 10 mm over layer 2
    down = lambda q: bed_clearance(body, planner.joint_move_to(planner.bed_mm_to_base(
        np.array([over_part]))[0], q).Q, c).min() * 1000.0
    assert down(kept) < -5.0                              # from the drifted joints: into the bed
    assert down(q_park) > 5.0                             # from the park's own joints: clear
    est = JointMoves(c, c.arms).clearance_mm("panda", park, over_part, (-138.0, -87.0, 0.0), (138.0, 87.0, 1.0))
    assert est == pytest.approx(down(q_park), abs=3.0)


def test_the_timeline_leaves_the_part_straight_up_and_comes_back_clear_of_the_bed(n_arm_jobs):
    """Three arms around a point: an arm leaving the part for its park
    position first lifts straight up, the Panda (seven joints) to the
    park's height (where it leaves, its joints are those of the print,
    which no estimate here follows), the others as high as their A7 needs
    to keep clear of the bed; the first move after a park comes down from
    the park's joints to a height the firmware's joint move reaches clear
    of the bed, then straight down."""
    from ambots.collision import ArmBody, bed_clearance
    from ambots.motion import MotionPlanner
    c, parts, sliced, programs, _ = n_arm_jobs["three_arms"]
    park = park_positions_mm(c, [p.arm for p in parts])
    checked = lifted = 0
    for name, prog in programs.items():
        arm = prog.arm
        planner = MotionPlanner(arm, c)
        body = ArmBody.from_arm(arm)
        q_park = planner.move_to(planner.bed_mm_to_base(park[name][None])[0], np.asarray(arm.profile.home)).Q[-1]
        lines = prog.lines
        own = [i for i, ln in enumerate(lines) if ln.startswith(";@A7 R%d " % arm.id)]
        assert own
        for i in own:
            before = [ln for ln in lines[:i] if ln.startswith("G")]
            if any(ln.startswith("G1") and " E" in ln and " X" in ln for ln in before):      # it printed before
                assert before[-1].startswith("G0 Z"), (name, i, before[-1])
                z = float(before[-1].split()[1][1:])
                if len(arm.profile.joint_names) > 6:                  # the Panda
                    assert z == pytest.approx(park[name][2], abs=1e-3), (name, i, before[-1])
                else:
                    last = next(ln for ln in reversed(before) if " X" in ln)
                    w = dict((t[0], float(t[1:])) for t in last.split()[1:] if t[0] in "XY")
                    q = planner.kin.ik(planner.bed_mm_to_base(np.array([[w["X"], w["Y"], z]]))[0],
                                       np.asarray(arm.profile.home), planner.down)
                    up = planner.move_to(planner.bed_mm_to_base(park[name][None])[0], q)
                    assert bed_clearance(body, up.Q, c).min() >= 0.0, (name, i)
                lifted += 1
            after = next((ln for ln in lines[i + 1:] if ln.startswith("G0 X")), None)
            if after is None:
                continue                                   # the end of the job
            w = dict((t[0], float(t[1:])) for t in after.split()[1:])
            move = planner.joint_move_to(planner.bed_mm_to_base(np.array([[w["X"], w["Y"], w["Z"]]]))[0], q_park)
            assert move.error is None
            assert bed_clearance(body, move.Q, c).min() >= 0.0, (name, after)
            checked += 1
    assert checked >= 1 and lifted >= 2, (checked, lifted)      # a retreat and back, and the last parks


def test_robot_id_0_is_an_id_like_any_other(cell, job):
    """The default cell numbers its arms from 0 (the original's ids): its
    programs are those of the same cell numbered from 1, id for id (an id 0
    once read as "no report" dropped the UR10's ;@A3 lines, and the other
    arm then waited for a later report)."""
    import dataclasses
    import re
    assert [a.id for a in cell.arms] == [0, 1]
    from_1 = dataclasses.replace(cell, arms=tuple(dataclasses.replace(a, id=a.id + 1) for a in cell.arms))
    model = m3.Manifold.cube([160, 40, 0.8]).translate([-80, -20, 0])       # the fixture's
    parts_1 = partition(model, from_1)
    for mode in ("concurrent", "sequential"):
        got = build_programs(job[1], job[0], cell, mode=mode)
        want = build_programs(job[1], parts_1, from_1, mode=mode)
        for name in got:
            shifted = [re.sub(r"\b([RW])(\d+)\b", lambda m: m.group(1) + str(int(m.group(2)) - 1), line)
                       if line.startswith((";@", "; ambots program")) else line for line in want[name].lines]
            assert got[name].lines == shifted, (mode, name)


def test_the_emitters_events_are_the_parsers(cell, job, n_arm_jobs):
    """A job times its programs on the events the emitter kept while it wrote
    them, not on a parse of the text: they must be the parser's, event for
    event (banded, sequential, one arm with the others parked, the timeline
    of three and four arms, a row along a beam)."""
    from ambots.coordinate.emit import Emitter
    parts, sliced = job
    plans = [build_programs(sliced, parts, cell), build_programs(sliced, parts, cell, mode="sequential"),
             build_programs({parts[0].arm.name: sliced[parts[0].arm.name]}, parts[:1], cell, idle=[parts[1].arm])]
    plans += [v[3] for v in n_arm_jobs.values()]
    checked = 0
    for programs in plans:
        for name, program in programs.items():
            assert program.events is not None
            parsed = list(parse_gcode_text(program.text, name + ".gcode"))
            assert program.parse() == parsed
            checked += len(parsed)
    assert checked > 5000
    # lines changed after the emitter wrote them: the text is parsed again
    program = plans[0][parts[0].arm.name]
    program.lines.append("G1 X1.000 Y2.000 Z3.000 E0.10000 F1200")
    again = program.parse()
    assert again == list(parse_gcode_text(program.text, "x.gcode"))
    assert again[-1].end == (1.0, 2.0, 3.0) and again[-1].line == len(program.lines)
    # a line the events cannot follow (a line break inside a header line): no events
    em = Emitter(parts[0].arm, "concurrent", ["; a\nG1 X5"])
    assert em.events() is None


def test_chains_written_at_once_are_written_as_one_by_one(cell, monkeypatch):
    """The emitter writes a chain of extrusions (each starting where the one
    before ended) with one format and reads its numbers back at once: the
    lines must be those it writes one by one, and its events the parser's
    (E added up in order: a 300-point spiral, so rounding shows)."""
    from ambots.coordinate import emit
    from ambots.coordinate.steps import Step
    arm = cell.arms[0]
    t = np.linspace(0.0, 12 * np.pi, 301)
    pts = [(float(30 * np.cos(a) * a / 40), float(30 * np.sin(a) * a / 40), 0.2 + 1e-4 * k)
           for k, a in enumerate(t)]
    spiral = [Segment(p, q, 0.0123456789 * (1 + k % 7), 1200.0 + k % 3, True, k + 10, 0)
              for k, (p, q) in enumerate(zip(pts[:-1], pts[1:]))]
    short = spiral[:5]
    steps = [Step(layers=[0.2], approach=5.0, pieces=spiral), Step(pieces=short), Step(layers=[0.4], pieces=spiral[7:])]

    def write():
        em = emit.Emitter(arm, "concurrent").steps(steps)
        return em.lines, em.events()

    calls = []
    real = emit._Events.run
    monkeypatch.setattr(emit._Events, "run", lambda self, *a: calls.append(a[2]) or real(self, *a))
    lines, events = write()
    assert calls and max(calls) == 300                  # the chains went the fast way
    monkeypatch.setattr(emit, "_RUN", 10 ** 9)
    one_by_one, events_1 = write()
    assert lines == one_by_one
    text = "\n".join(lines) + "\n"
    parsed = tuple(parse_gcode_text(text, "x.gcode"))
    assert events[0] == parsed == events_1[0]
    assert len([e for e in parsed if type(e) is Segment and e.extrude]) > 590
