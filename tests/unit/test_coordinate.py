"""Per-arm programs: sequential (the original) and concurrent (layers in
lock-step, seam zones taken in turns), checked by executing them."""
import random
import re

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


def run(programs, rng, zone_check=None):
    """Execute the programs with random line durations; A9 blocks until the
    other arm has completed line N.  Returns the finish order of content lines
    as (time, arm, step) and checks that no two arms ever print different steps."""
    ids = {p.arm.id: name for name, p in programs.items()}
    lines = {n: p.lines for n, p in programs.items()}
    done = {n: 0 for n in lines}         # completed lines
    clock = {n: 0.0 for n in lines}
    for _ in range(10 ** 6):
        active = [n for n in lines if done[n] < len(lines[n])]
        if not active:
            return clock
        progressed = False
        for n in sorted(active, key=lambda n: clock[n]):
            text = lines[n][done[n]]
            if text.startswith(";@A9"):
                cmd = decode(text[2:])
                other = ids[cmd.other]
                if done[other] < cmd.line:
                    continue
                clock[n] = max(clock[n], clock[other])
            else:
                clock[n] += rng.uniform(0.1, 3.0)
            done[n] += 1
            progressed = True
            break
        assert progressed, "deadlock: %s" % {n: lines[n][done[n]] for n in active}
    raise AssertionError("did not finish")


def test_concurrent_programs_keep_every_extrusion_and_strip_a_series(cell, job):
    parts, sliced = job
    programs = build_programs(sliced, parts, cell, mode="concurrent", zone_mm=20.0)
    for name, prog in programs.items():
        assert extrusions(prog.text) == extrusions(sliced[name].replace("A1 R2 ; must be stripped", ""))
        assert prog.removed and prog.removed[0][1].startswith("A1 R2")
        assert "A1 R2" not in prog.text


def test_concurrent_seam_zone_is_taken_in_turns(cell, job):
    parts, sliced = job
    zone = 20.0
    programs = build_programs(sliced, parts, cell, mode="concurrent", zone_mm=zone)
    assert {p.phases for p in programs.values()} == {2}
    for name, prog in programs.items():
        # step of every line: layer k phase p = step 2k + p (counted by barrier groups)
        step_of, step, prev_a9 = {}, 0, False
        for i, line in enumerate(prog.lines, start=1):
            is_a9 = line.startswith(";@A9")
            if prev_a9 and not is_a9:
                step += 1
            step_of[i], prev_a9 = step, is_a9
        assert step == 4 * 2                     # 4 layers x 2 phases, then the end
        colour = int(re.search(r"colour (\d)", prog.text).group(1))
        for e in parse_gcode_text(prog.text):
            if type(e) is not Segment or not e.extrude or e.start == e.end:
                continue
            near = min(abs(e.start[0]), abs(e.end[0])) < zone
            s = step_of[e.line]
            assert near == (s % 2 == colour), "%s line %d (step %d): seam-zone work only in its turn" % (
                name, e.line, s)


@pytest.mark.parametrize("seed", range(5))
def test_concurrent_programs_never_deadlock_and_barriers_hold(cell, job, seed):
    parts, sliced = job
    programs = build_programs(sliced, parts, cell, mode="concurrent", zone_mm=20.0)
    run(programs, random.Random(seed))
    for prog in programs.values():     # one barrier per other arm after each of 8 steps
        waits = [decode(l[2:]) for l in prog.lines if l.startswith(";@A9")]
        assert len(waits) == 8 and all(isinstance(w, WaitFor) and w.robot == prog.arm.id for w in waits)
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
