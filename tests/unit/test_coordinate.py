"""Per-arm programs: sequential (the original) and concurrent (layers in
lock-step, seam zones taken in turns), checked by executing them."""
import random

import manifold3d as m3
import numpy as np
import pytest

from ambots.config import default_cell_path, load_cell
from ambots.coordinate import build_programs
from ambots.gcode import Segment, parse_gcode_text
from ambots.partition import partition
from ambots.protocol import MoveTo, Start, WaitFor, decode


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
        w = 30.0 / (k - 1)
        for s in pieces:       # every piece lies inside one band
            d = sorted((float(n @ np.array(s.start) - off), float(n @ np.array(s.end) - off)))
            band = min(int(np.floor((d[0] + d[1]) / 2 / w)), k - 1)
            assert d[0] >= band * w - 1e-6 and (band == k - 1 or d[1] <= (band + 1) * w + 1e-6)


def execute(programs, rng):
    """Execute programs line by line with random durations (0.1-3 s per line,
    so any arm may run far slower than planned); ;@A9 blocks until the other
    arm has completed line N.  Returns {arm: [(t0, t1, segment)]} for every
    moving G-code line."""
    ids = {p.arm.id: name for name, p in programs.items()}
    parsed = {}
    for n, p in programs.items():
        segs = [s for s in parse_gcode_text(p.text) if type(s) is Segment and s.start != s.end]
        segs[0] = segs[0]._replace(start=segs[0].end)     # the first move comes from the park pose
        parsed[n] = {s.line: s for s in segs}
    lines = {n: p.lines for n, p in programs.items()}
    done = {n: 0 for n in lines}
    clock = {n: 0.0 for n in lines}
    spans = {n: [] for n in lines}
    for _ in range(10 ** 7):
        active = [n for n in lines if done[n] < len(lines[n])]
        if not active:
            return spans
        progressed = False
        for n in sorted(active, key=lambda n: clock[n]):
            text = lines[n][done[n]]
            if text.startswith(";@A9"):
                cmd = decode(text[2:])
                other = ids[cmd.other]
                if done[other] < cmd.line:
                    continue
                clock[n] = max(clock[n], clock[other])
            elif not text.startswith(";"):
                t0 = clock[n]
                clock[n] += rng.uniform(0.1, 3.0)
                if done[n] + 1 in parsed[n]:
                    spans[n].append((t0, clock[n], parsed[n][done[n] + 1]))
            done[n] += 1
            progressed = True
            break
        assert progressed, "deadlock: %s" % {n: lines[n][done[n]] for n in active}
    raise AssertionError("did not finish")


@pytest.mark.parametrize("seed", range(5))
def test_concurrent_nozzles_across_a_seam_stay_a_zone_apart(cell, job, seed):
    """Whatever the timing, two moves that run at the same time are at least
    the zone apart across the seam (sum of their distances to it)."""
    parts, sliced = job
    zone = 20.0
    programs = build_programs(sliced, parts, cell, mode="concurrent", zone_mm=zone)
    assert {p.phases for p in programs.values()} == {programs["kinova"].phases} and programs["kinova"].phases >= 2
    spans = execute(programs, random.Random(seed))
    planes = {p.arm.name: p.planes for p in parts}

    def dist(name, seg):
        pts = np.array([seg.start, seg.end])
        return float(min((pts @ np.asarray(n) - off).min() for n, off in planes[name]))

    a = [(t0, t1, dist("kinova", s)) for t0, t1, s in spans["kinova"]]
    b = [(t0, t1, dist("ur10", s)) for t0, t1, s in spans["ur10"]]
    b.sort()
    starts = np.array([x[0] for x in b])
    overlaps = 0
    for t0, t1, da in a:
        for j in range(int(np.searchsorted(starts, t1)) - 1, -1, -1):
            u0, u1, db = b[j]
            if u1 <= t0:
                if u0 < t0 - 10.0:
                    break
                continue
            overlaps += 1
            assert da + db >= zone - 1e-6, "moves %.1f and %.1f mm from the seam at the same time" % (da, db)
    assert overlaps > 0            # the arms do work at the same time


@pytest.mark.parametrize("seed", range(3))
def test_concurrent_programs_never_deadlock_and_barriers_hold(cell, job, seed):
    parts, sliced = job
    programs = build_programs(sliced, parts, cell, mode="concurrent", zone_mm=20.0)
    execute(programs, random.Random(seed))
    for prog in programs.values():
        waits = [decode(l[2:]) for l in prog.lines if l.startswith(";@A9")]
        k = prog.phases
        assert len(waits) >= 4 * k and all(isinstance(w, WaitFor) and w.robot == prog.arm.id for w in waits)
        assert [w.line for w in waits] == sorted(w.line for w in waits)


def test_sequential_is_the_original_hand_over(cell, job):
    parts, sliced = job
    programs = build_programs(sliced, parts, cell, mode="sequential")
    kinova, ur10 = programs["kinova"], programs["ur10"]
    assert kinova.start_first and not ur10.start_first
    a_lines = [decode(l[2:]) for l in kinova.lines if l.startswith(";@")]
    assert isinstance(a_lines[0], MoveTo) and a_lines[0].robot == 2          # park the UR10 first
    assert isinstance(a_lines[-2], MoveTo) and a_lines[-2].robot == 1        # then park itself
    assert a_lines[-1] == Start(2)                                            # and start the UR10
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
    w.travel_to((10.0, 0.5, 0.2))           # longer: retract, lift, move, lower, unretract
    assert w.lines[2].startswith("G1 E-0.8") and w.lines[-1].startswith("G1 E0.8") and len(w.lines) == 7
