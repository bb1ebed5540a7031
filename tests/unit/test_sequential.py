"""Sequential mode (the original's hand-over, in rounds): the programs read
as the protocol says, independently of the coordinator and the firmware
(a small interpreter of the hand-over directives below), then run by the
firmware's own runners offline.

What must hold (issue 16):

* the first move of each turn goes over everything printed so far, then
  straight down to the first point (never ``G0 X0 Y0 Z0``: the bed's
  centre, the first arm's seam face);
* exactly one retraction before each park, none doubled anywhere;
* the original's order: the other arms parked first (A7), each arm prints,
  parks, then starts (A1) or resumes (A6) the next arm and pauses itself
  (A2) until its next turn; one arm moves at a time;
* more than one turn per arm when a part is taller than the print head
  can pass over: while an arm prints at height z, nothing within its head's
  reach stands higher than z + (the head's gap behind the tip - 1 mm)."""
from collections import deque

import numpy as np
import pytest
import trimesh

from ambots.config import default_cell_path, load_cell
from ambots.gcode import Segment, parse_gcode_text
from ambots.protocol import MoveTo, Pause, Resume, Start, decode

#: the profiles' print heads: the nearest body 5 mm behind the tip, the widest 32 mm
#: across its axis (config/arms/*.yaml tool.head: fan duct, mount plate)
HEAD_GAP_MM = 5.0
HEAD_RADIUS_MM = 32.0
#: what the head keeps over the other arms' slabs
MARGIN_MM = 1.0


@pytest.fixture(scope="module")
def cell():
    return load_cell(default_cell_path())


def box_model(tmp_path_factory, dims):
    path = str(tmp_path_factory.mktemp("seq") / ("box_%dx%dx%d.stl" % dims))
    trimesh.creation.box(extents=dims).export(path)
    return path


@pytest.fixture(scope="module")
def tall_job(cell, tmp_path_factory):
    """Both arms, a block 9 mm tall: too tall for one round (45 layers)."""
    from ambots.job import run_job
    return run_job(box_model(tmp_path_factory, (100, 30, 9)), cell, list(cell.arms), mode="sequential")


# ------------------------------------------------------------------ the interpreter

def hand_over(programs):
    """Run the programs' hand-over directives as the protocol defines them:
    the front end starts the arms with ``start_first``; an arm runs its
    lines until it pauses itself (A2) or ends; an A1/A6 to another arm makes
    that arm run next.  Returns the turns in execution order, each
    ``(arm name, [(kind, payload)])`` with kind "move" (a Segment),
    "park" (an A7 to itself), "to" (an A1/A6/A7 sent to another arm).
    Fails if an arm moves after handing over before it pauses, or if a
    program never ends (paused for ever)."""
    by_id = {p.arm.id: n for n, p in programs.items()}
    segs = {}
    for n, p in programs.items():
        by_line = {}
        for s in parse_gcode_text(p.text, n + ".gcode"):
            if type(s) is Segment:
                by_line.setdefault(s.line, []).append(s)
        segs[n] = by_line
    pc = {n: 0 for n in programs}
    queue = deque(n for n, p in programs.items() if p.start_first)
    assert len(queue) == 1, "sequential: the front end starts one arm"
    turns = []
    while queue:
        n = queue.popleft()
        lines, me = programs[n].lines, programs[n].arm.id
        turn, handed = [], False
        while pc[n] < len(lines):
            text = lines[pc[n]]
            pc[n] += 1
            if text.startswith(";@"):
                msg = decode(text[2:])
                if msg.robot == me and isinstance(msg, Pause):
                    break
                if msg.robot == me and isinstance(msg, MoveTo):
                    turn.append(("park", msg))
                elif msg.robot != me:
                    turn.append(("to", msg))
                    if isinstance(msg, (Start, Resume)):
                        queue.append(by_id[msg.robot])
                        handed = True
                continue
            for s in segs[n].get(pc[n], ()):
                assert not handed, "%s moves after handing over (line %d)" % (n, pc[n])
                turn.append(("move", s))
        turns.append((n, turn))
    for n, p in programs.items():
        assert pc[n] == len(p.lines), "%s paused for ever at line %d" % (n, pc[n])
    return turns


class Heights:
    """The deposit so far as a height map (1 mm cells, bed frame), and the
    highest deposit within the print head's reach of a point."""

    def __init__(self, lo=(-160.0, -60.0), hi=(160.0, 60.0), cell_mm=1.0):
        self.lo, self.c = np.asarray(lo), cell_mm
        self.top = np.zeros((int((hi[0] - lo[0]) / cell_mm) + 1, int((hi[1] - lo[1]) / cell_mm) + 1))
        self.near = None

    def _ij(self, xy):
        return np.clip(np.round((np.asarray(xy) - self.lo) / self.c).astype(int), 0,
                       np.array(self.top.shape) - 1)

    def lay(self, seg):
        a, b = np.asarray(seg.start), np.asarray(seg.end)
        n = max(2, int(np.ceil(np.linalg.norm(b[:2] - a[:2]) / (0.5 * self.c))) + 1)
        P = a[None] + np.linspace(0, 1, n)[:, None] * (b - a)[None]
        ij = self._ij(P[:, :2])
        np.maximum.at(self.top, (ij[:, 0], ij[:, 1]), P[:, 2])
        self.near = None

    def highest_near(self, p, radius=HEAD_RADIUS_MM):
        """Highest deposit (mm) within ``radius`` of p's x, y (cells whose
        centre is within radius + one cell)."""
        if self.near is None:        # a disc maximum filter of the map, by shifts
            r = int(np.ceil(radius / self.c)) + 1
            pad = np.pad(self.top, r)
            out = np.zeros_like(self.top)
            nx, ny = self.top.shape
            for dx in range(-r, r + 1):
                for dy in range(-r, r + 1):
                    if dx * dx + dy * dy <= r * r:
                        np.maximum(out, pad[r + dx:r + dx + nx, r + dy:r + dy + ny], out=out)
            self.near = out
        i, j = self._ij(p[:2])
        return float(self.near[i, j])

    @property
    def highest(self):
        return float(self.top.max())


# ------------------------------------------------------------------ the checks

def test_the_rounds_keep_the_head_clear_of_the_other_arms_slabs():
    from ambots.coordinate.sequential import slab_rounds
    tops = [round(0.2 * (k + 1), 3) for k in range(50)]            # the demo block: 50 layers of 0.2 mm
    bounds = slab_rounds(tops, 4.0)
    assert bounds[-1] == 10.0 and len(bounds) == 3                  # 4.2 mm per round at most: 3 rounds
    lo = 0.0
    for hi in bounds:
        mine = [z for z in tops if lo < z <= hi]
        assert mine[-1] - mine[0] <= 4.0 + 1e-9
        lo = hi
    assert len(slab_rounds(tops[:20], 4.0)) == 1                     # 4 mm: one round
    uneven = [0.3, 0.5, 0.7, 1.0, 1.3, 1.6, 2.0, 2.4, 2.8, 3.2, 3.6]
    b = slab_rounds(uneven, 1.0)
    lo, prev = 0.0, None
    for hi in b:
        mine = [z for z in uneven if lo < z <= hi]
        assert mine and mine[-1] - mine[0] <= 1.0 + 1e-9
        lo = hi
    assert sorted(b) == b and b[-1] == 3.6


def test_turns_alternate_in_the_original_order(cell, tall_job):
    programs = tall_job.programs
    names = [a.name for a in cell.arms]
    first, second = programs[names[0]], programs[names[1]]
    turns = hand_over(programs)
    # the first arm parks every other arm before it moves at all
    kind, msg = turns[0][1][0]
    assert turns[0][0] == names[0] and kind == "to" and isinstance(msg, MoveTo) and msg.robot == second.arm.id
    assert [n for n, _ in turns] == names * 3                       # 9 mm: three rounds, alternating
    started = set()
    for k, (n, turn) in enumerate(turns):
        me = programs[n].arm.id
        kinds = [kd for kd, _ in turn]
        moves = [i for i, kd in enumerate(kinds) if kd == "move"]
        park = kinds.index("park")
        assert park > moves[-1]                                      # prints, then parks
        tail = [m for kd, m in turn[park + 1:]]
        if k + 1 < len(turns):                                       # then hands over: A1 once, A6 after
            nxt = programs[turns[k + 1][0]].arm.id
            want = Resume(nxt) if nxt in started else Start(nxt)
            assert tail == [want], (n, tail)
            started.add(nxt)
        else:
            assert tail == []
        started.add(me)
    # a pause for every turn but the arm's last, in the program: the A2 right after the hand-over
    for n, p in programs.items():
        dirs = [decode(l[2:]) for l in p.lines if l.startswith(";@")]
        pauses = [d for d in dirs if isinstance(d, Pause)]
        assert all(d.robot == p.arm.id for d in pauses)
        assert len(pauses) == sum(1 for m, _ in turns if m == n) - 1
    # the last arm ends rounds 1 and 2 as the original's UR10: park, resume the first, pause itself
    dirs = [decode(l[2:]) for l in second.lines if l.startswith(";@")]
    assert isinstance(dirs[0], MoveTo) and dirs[0].robot == second.arm.id
    assert dirs[1:3] == [Resume(first.arm.id), Pause(second.arm.id)]


def test_first_moves_come_from_above_and_the_head_never_meets_a_slab(tall_job):
    """Replays the turns on a height map of the deposit: each turn's first
    move (a joint move from wherever the arm stands) ends at least 5 mm over
    everything printed so far, then the nozzle goes straight down; at every
    point the nozzle visits, nothing within the head's reach stands higher
    than the head's gap (less the margin) over the nozzle."""
    heights = Heights()
    checked = 0
    for n, turn in hand_over(tall_job.programs):
        moves = [s for kd, s in turn if kd == "move"]
        first = moves[0]
        assert first.end[2] >= heights.highest + 5.0, (n, first, heights.highest)
        assert first.end[2] > 0.0 and abs(first.end[0]) + abs(first.end[1]) > 0.0   # never G0 X0 Y0 Z0
        k = 1
        while not moves[k].extrude:                                   # straight down to the first point
            assert moves[k].end[:2] == first.end[:2] and moves[k].end[2] < moves[k].start[2]
            k += 1
        assert moves[k].start[:2] == first.end[:2]
        for s in moves[1:]:
            for p in (s.start, s.end):
                assert heights.highest_near(p) <= p[2] + HEAD_GAP_MM - MARGIN_MM + 1e-6, (n, s, heights.highest_near(p))
                checked += 1
        for s in moves:
            if s.extrude:
                heights.lay(s)
        # the lift before the park: straight up, over everything printed
        lift = [s for s in moves if not s.extrude and s.end[2] > s.start[2]][-1]
        assert lift.end[:2] == lift.start[:2] and lift.end[2] >= heights.highest + 5.0
    assert checked > 1000


def test_one_retraction_before_each_park_and_none_doubled(tall_job, cell):
    """E-only moves: the filament is retracted by at most one retraction
    length at any time, exactly one at each park, and primed again before
    the next extrusion; every extrusion of the slicer's G-code is kept."""
    from ambots.slicer import SliceSettings
    retract = SliceSettings().retract_length_mm
    for n, p in tall_job.programs.items():
        state, parks = 0.0, 0
        segs = {s.line: s for s in parse_gcode_text(p.text) if type(s) is Segment}
        for number, line in enumerate(p.lines, 1):
            if line.startswith(";@") and isinstance(decode(line[2:]), MoveTo) and decode(line[2:]).robot == p.arm.id:
                assert abs(state + retract) < 1e-9, (n, number, state)       # one retraction length
                parks += 1
            s = segs.get(number)
            if s is None:
                continue
            if s.start == s.end and s.e:
                state += s.e
                assert -retract - 1e-9 <= state <= 1e-9, (n, number, line, state)
            elif s.extrude:
                assert abs(state) < 1e-9, (n, number, state)
        assert parks == sum(1 for l in p.lines if l.startswith(";@A2")) + 1
        tail = [l for l in p.lines[-6:] if l.startswith("G1 E-")]
        assert len(tail) == 1, (n, p.lines[-6:])
    # every extrusion of the slicer's output, once
    from ambots.coordinate.steps import read_sliced
    for n, p in tall_job.programs.items():
        want = sorted((s.start, s.end, round(s.e, 5)) for segs in read_sliced(tall_job.sliced[n], n).layers.values()
                      for s in segs if s.extrude and s.start != s.end)
        got = sorted((s.start, s.end, round(s.e, 5)) for s in parse_gcode_text(p.text)
                     if type(s) is Segment and s.extrude and s.start != s.end)
        assert got == want


def test_an_arm_pauses_itself_until_another_resumes_it(cell):
    """The firmware's runner: ``;@A2`` to itself pauses the arm (A10
    PAUSED), an A6 from the hub resumes it where it stopped; ``;@A6`` to
    another arm goes out through the hub."""
    from ambots.protocol import ArmState, LoadChunk, Status
    from ambots.runner import ArmRunner
    a, b = cell.arms[0], cell.arms[1]
    side = -1.0 if np.asarray(a.base_xyz)[0] < np.asarray(b.base_xyz)[0] else 1.0
    x = side * 60.0
    text = "\n".join(["G21", "G90", "M83", "G0 X%.1f Y0 Z20 F6000" % x, "G0 Z0.2",
                      "G1 X%.1f Y10 Z0.2 E0.5 F1200" % x, ";@A6 R%d" % b.id, ";@A2 R%d" % a.id,
                      "G1 X%.1f Y20 Z0.2 E0.5 F1200" % x]) + "\n"
    r = ArmRunner(a, cell)
    r.handle(LoadChunk(a.id, text, chunk_id=1))
    r.handle(Start(a.id))
    r.advance(200.0)
    assert r.state is ArmState.PAUSED and r.done_line == 8
    sent = [m for _, m in r.outbox]
    assert Resume(b.id) in sent
    assert [m.state for m in sent if isinstance(m, Status)][-1] is ArmState.PAUSED
    beads = sum(len(bd.e_mm) for bd in r.beads)
    r.advance(400.0)
    assert r.state is ArmState.PAUSED and sum(len(bd.e_mm) for bd in r.beads) == beads   # stays paused
    r.handle(Resume(a.id), now=400.0)
    r.advance(600.0)
    assert r.state is ArmState.DONE and sum(len(bd.e_mm) for bd in r.beads) > beads


def test_the_estimate_runs_the_turns_one_after_the_other(tall_job, cell):
    """The planner's estimate (ambots.estimate) holds a paused arm until
    the A6 that resumes it: the arms' busy times add up, nothing overlaps."""
    from ambots.estimate import estimate_programs
    est = estimate_programs(tall_job.programs, cell)
    busy = sum(a["busy_s"] for a in est["arms"].values())
    assert est["makespan_s"] == pytest.approx(busy, rel=0.02)


# ------------------------------------------------------------------ run offline

@pytest.fixture(scope="module")
def small_run(cell, tmp_path_factory):
    """A 60 x 20 x 5 mm block in sequential mode, run by the firmware's
    runners on one simulated clock (``python -m ambots plan``'s run)."""
    from ambots.job import run_job
    from ambots.sim import check_motion, simulate
    job = run_job(box_model(tmp_path_factory, (60, 20, 5)), cell, list(cell.arms), mode="sequential")
    result = simulate(job.programs, cell)
    return job, result, check_motion(result, cell)


def _executed(result):
    traces = {n: (np.concatenate(r.trace_t), np.concatenate(r.trace_q), np.concatenate(r.trace_v))
              for n, r in result.runners.items()}
    beads = {n: tuple(np.concatenate([getattr(b, k) for b in r.beads]) for k in ("p0", "p1", "t"))
             for n, r in result.runners.items()}
    return traces, beads


def _checks():
    import os
    import sys
    sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "ros"))
    import sequential_checks
    return sequential_checks


def test_offline_the_second_arm_keeps_off_the_first_half(cell, small_run):
    """0 contacts (the report's check), and from the executed motion and the
    actual beads (tests/ros/sequential_checks.py): the second arm's bodies
    stay more than the sampling slack away from the first arm's beads, each
    arm prints in two turns, and neither moves while the other prints."""
    from ambots.collision import ArmBody
    sc = _checks()
    job, result, motion = small_run
    assert result.finished and motion["collisions"] == {"arm_arm": 0, "arm_bed": 0, "arm_part": 0}
    traces, beads = _executed(result)
    first, second = (a.name for a in cell.arms)
    closest, _ = sc.closest_to_beads(ArmBody.from_arm(cell.arm(second)), traces[second], beads[first])
    assert closest - sc.SLACK_MM > 0.0, closest                    # 2.38 mm measured (5 mm head gap, 2.2 mm slab)
    turns = {n: sc.bursts(beads[n][2]) for n in (first, second)}
    assert len(turns[first]) == len(turns[second]) == 2
    order = sorted((t0, t1, n) for n in turns for t0, t1 in turns[n])
    assert [n for _, _, n in order] == [first, second, first, second]
    assert all(a[1] < b[0] for a, b in zip(order, order[1:]))
    assert sc.moves_during(traces[second], turns[first]) < 1e-9
    assert sc.moves_during(traces[first], turns[second]) < 1e-9


def test_offline_one_round_would_bring_the_head_down_onto_the_first_half(cell, small_run):
    """The control: the same job in one round (the issue's hand-over: the
    first half whole, then the second) -- the check above sees the second
    head come within the slack of the first half (its 5 mm half against the
    head's 5 mm gap)."""
    from ambots.collision import ArmBody
    from ambots.coordinate import build_programs
    from ambots.sim import simulate
    sc = _checks()
    job = small_run[0]
    result = simulate(build_programs(job.sliced, job.parts, cell, mode="sequential", slab_mm=100.0), cell)
    assert result.finished
    traces, beads = _executed(result)
    first, second = (a.name for a in cell.arms)
    closest, _ = sc.closest_to_beads(ArmBody.from_arm(cell.arm(second)), traces[second], beads[first])
    assert closest < sc.SLACK_MM, closest


def _layers(x0, x1, y0, y1, layers, h=0.2, step=5.0):
    """Hand-made slicer output: per layer, lines across the part every ``step`` mm."""
    out = ["; test slicer", "G21", "G90", "M83"]
    for k in range(layers):
        z = h * (k + 1)
        out += [";LAYER_CHANGE", ";Z:%.1f" % z, "G0 X%.1f Y%.1f Z%.1f F9000" % (x0, y0, z)]
        for x in np.arange(x0, x1 + 1e-9, step):
            out += ["G0 X%.1f Y%.1f F9000" % (x, y0), "G1 X%.1f Y%.1f E0.5 F1800" % (x, y1), "G1 E-0.8 F2100",
                    "G1 E0.8 F2100"]
    return "\n".join(out) + "\n"


def test_a_shorter_part_ends_its_turns_early(cell):
    """The second part is 2 mm tall, the first 6 mm: round 1 both arms,
    round 2 the first arm alone (it is resumed by the second, which ends
    there); the slab rule holds and no arm pauses for ever."""
    import manifold3d as m3
    from ambots.coordinate import build_programs
    from ambots.partition import partition
    parts = partition(m3.Manifold.cube([160, 40, 6]).translate([-80, -20, 0]), cell)
    first, second = (a.name for a in cell.arms)
    side = {p.arm.name: np.sign(np.mean(np.asarray(p.manifold.bounding_box())[[0, 3]])) for p in parts}
    sliced = {n: _layers(*(sorted((0.0, side[n] * 80.0))), -20, 20, layers=30 if n == first else 10)
              for n in (first, second)}
    programs = build_programs(sliced, parts, cell, mode="sequential")
    turns = hand_over(programs)
    assert [n for n, _ in turns] == [first, second, first]
    heights = Heights()
    for n, turn in turns:
        for kd, s in turn:
            if kd == "move" and s.extrude:
                assert heights.highest_near(s.end) <= s.end[2] + HEAD_GAP_MM - MARGIN_MM + 1e-6
        for kd, s in turn:
            if kd == "move" and s.extrude:
                heights.lay(s)
    dirs = {n: [decode(l[2:]) for l in p.lines if l.startswith(";@")] for n, p in programs.items()}
    assert dirs[second][-1] == Resume(programs[first].arm.id)          # it resumes the first arm and ends
    assert sum(isinstance(d, Pause) for d in dirs[first]) == 1 and not any(isinstance(d, Pause) for d in dirs[second])
    # the slicer's own retractions are gone: the writer's, one per travel or park
    for p in programs.values():
        text = p.lines
        assert not any(a.startswith("G1 E-") and b.startswith("G1 E-") for a, b in zip(text, text[1:]))


def test_arms_alone_on_one_gcode_share_what_the_first_wrote(cell, tmp_path_factory, monkeypatch):
    """Each arm alone prints the same G-code (the planner's alone plans):
    the second arm's program copies the moves the first one wrote
    (``written``) and must be, line for line and event for event, the
    program written in full; the events it carries are the parser's reading
    of its text.  Given a record of another G-code, nothing is copied and
    the program is still the one written in full."""
    import ambots.coordinate.emit as emit
    from ambots.coordinate import build_programs, read_sliced
    from ambots.partition import partition
    from ambots.mesh import to_manifold
    from ambots.slicer import SliceSettings, slice_mesh
    mesh = trimesh.creation.box(extents=(60, 30, 4))
    mesh.apply_translation([0, 0, 2])
    text = slice_mesh(mesh, SliceSettings(), backend="builtin")
    read = read_sliced(text, "box.gcode")
    calls = []
    real = emit._Writer.segments
    monkeypatch.setattr(emit._Writer, "segments", lambda self, segs: (calls.append(1), real(self, segs))[1])

    def alone(arm, written=None):
        idle = [a for a in cell.arms if a.name != arm.name]
        parts = partition(to_manifold(mesh), cell, [arm])
        return build_programs({arm.name: read}, parts, cell, idle=idle, written=written)[arm.name]

    first, second = cell.arms
    written = []
    alone(first, written)
    written_by_first = len(calls)
    assert written_by_first > 10 and len(written) == written_by_first
    del calls[:]
    copied = alone(second, written)
    assert not calls                            # every layer's moves copied
    full = alone(second)
    assert copied.lines == full.lines and copied.lines[0] != alone(first).lines[0]
    assert copied.parse() == full.parse() == list(parse_gcode_text(full.text, "%s.gcode" % second.name))
    # a record of other segments (the text parsed again: equal segments, other objects): written in
    # full, the same program
    other = []
    alone(first, other)
    read = read_sliced(str(text), "again.gcode")
    del calls[:]
    again = alone(second, other)
    assert len(calls) == written_by_first and again.lines == full.lines and again.parse() == full.parse()
