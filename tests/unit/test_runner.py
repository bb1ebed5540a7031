"""One arm's firmware state machine (ambots.runner.ArmRunner) on a clock the
test drives: A5 + A1 run a program to DONE, beads are laid where the joints
really put the nozzle, A2/A6 pause at a line end and resume with the same
deposit, A9 barriers wait for the other arm's A10 reports, bad input and
unreachable lines are reported (A11) with their line."""
import numpy as np
import pytest

from ambots.config import default_cell_path, load_cell
from ambots.gcode import Segment, parse_gcode_text
from ambots.motion import MotionPlanner
from ambots.protocol import (ArmState, ClearChunk, ErrorReport, LoadChunk, Pause, Resume, SendPosition, Start,
                             Status, Stop, WaitFor)
from ambots.runner import ArmRunner

MM = 1e-3

# arm R0 (the Kinova); lines 1-based
PROGRAM = """\
G21
G90
M83
;LAYER_CHANGE
;Z:0.2
G0 X-30 Y-10 Z0.2 F9000
G1 X30 Y-10 E2.0 F1800
G1 X30 Y0 E0.4
G1 X-30 Y0 E2.0
G1 E-0.8 F2100
G0 Z0.6 F9000
G0 X-30 Y10
G0 Z0.2
G1 E0.8 F2100
G1 X30 Y10 E2.0 F1800
;LAYER_CHANGE
;Z:0.4
G0 Z0.4 F9000
G1 X-30 Y10 E2.0 F1800
G1 X-30 Y-10 E0.8
"""
N_LINES = len(PROGRAM.splitlines())
BARRIER_LINE = 10          # where test_barrier puts its ;@A9
STEP = 0.5                 # simulated seconds per advance


@pytest.fixture(scope="module")
def cell():
    return load_cell(default_cell_path())


@pytest.fixture(scope="module")
def arm(cell):
    return cell.arm("kinova")


@pytest.fixture(scope="module")
def planner(arm, cell):
    return MotionPlanner(arm, cell)


def new_runner(arm, cell, planner, **kw):
    return ArmRunner(arm, cell, planner=planner, record=True, **kw)


def load_and_start(r, text=PROGRAM, now=0.0):
    r.handle(LoadChunk(r.id, text, chunk_id=1), now=now)
    r.handle(Start(r.id), now=now)


def run(r, until=None, t_max=2000.0):
    """Advance in STEP steps while the arm prints (or until ``until``)."""
    t = r.clock
    while r.state is ArmState.PRINTING and t < t_max:
        if until is not None and t >= until:
            break
        t += STEP
        r.advance(t)
    return r


def messages(r, kind):
    return [m for _, m in r.outbox if isinstance(m, kind)]


def concat(beads, name):
    return np.concatenate([getattr(b, name) for b in beads]) if beads else np.zeros(0)


def same_beads(a, b):
    """The same bead sequence (positions to floating-point rounding)."""
    for name in ("line", "layer"):
        np.testing.assert_array_equal(concat(a.beads, name), concat(b.beads, name), err_msg=name)
    for name in ("p0", "p1", "e_mm"):
        np.testing.assert_allclose(concat(a.beads, name), concat(b.beads, name), rtol=0, atol=1e-12,
                                   err_msg=name)


def moving_extrusion(text):
    """{line: filament} of the lines that lay a bead (moving, E > 0)."""
    return {s.line: s.e for s in parse_gcode_text(text) if type(s) is Segment and s.extrude and s.start != s.end}


def bead_filament_by_line(beads):
    out = {}
    for line, e in zip(concat(beads, "line"), concat(beads, "e_mm")):
        out[int(line)] = out.get(int(line), 0.0) + float(e)
    return out


@pytest.fixture(scope="module")
def reference(arm, cell, planner):
    """The uninterrupted run."""
    r = new_runner(arm, cell, planner)
    load_and_start(r)
    run(r)
    return r


# ------------------------------------------------------------ a plain run
def test_load_start_run_to_done(reference):
    r = reference
    assert r.state is ArmState.DONE
    assert r.done_line == N_LINES and r.percent == 100.0
    states = [m.state for m in messages(r, Status)]
    assert states[0] is ArmState.IDLE                 # after A5
    assert states[1] is ArmState.PRINTING             # after A1
    last = messages(r, Status)[-1]
    assert last.state is ArmState.DONE and last.line == N_LINES and last.percent == 100.0
    assert last.position is not None
    np.testing.assert_allclose(last.position, (-30, -10, 0.4), atol=2e-3)
    assert not messages(r, ErrorReport)
    assert r.stats.moves == len([s for s in parse_gcode_text(PROGRAM) if type(s) is Segment])
    assert r.stats.ik_failures == 0
    assert 0.0 < r.stats.max_path_error_mm <= 0.1
    assert r.stats.done_s == pytest.approx(r.stats.print_time_s)
    assert r.stats.idle_time_s == 0.0
    assert r.layer == 1


def test_beads_are_where_the_joints_put_the_nozzle(reference, arm, planner):
    """Each bead runs from the FK of one executed waypoint to the FK of the
    next (world = base pose x KDL FK), at that waypoint's time."""
    r = reference
    tt, tq = np.concatenate(r.trace_t), np.concatenate(r.trace_q)
    assert np.all(np.diff(tt) >= 0)
    p0, p1, bt = concat(r.beads, "p0"), concat(r.beads, "p1"), concat(r.beads, "t")
    assert len(bt) >= 10
    for j in range(len(bt)):
        i = int(np.searchsorted(tt, bt[j], side="right")) - 1
        assert tt[i] == bt[j]
        assert i >= 1
        for p, q in ((p1[j], tq[i]), (p0[j], tq[i - 1])):
            T = arm.base_pose @ planner.kin.fk(q)
            np.testing.assert_allclose(p, T[:3, 3], atol=1e-9)


def test_bead_filament_is_the_programs_extrusion(reference):
    r = reference
    want = moving_extrusion(PROGRAM)
    got = bead_filament_by_line(r.beads)
    assert set(got) == set(want)
    for line in want:
        assert got[line] == pytest.approx(want[line], abs=1e-9)
    assert sum(got.values()) == pytest.approx(9.2, abs=1e-9)
    assert np.all(concat(r.beads, "e_mm") > 0)
    assert set(concat(r.beads, "layer").astype(int)) == {0, 1}


class OffsetIK:
    """A solver whose answers are off by a fixed joint offset (a badly
    calibrated arm): the nozzle really goes somewhere else than commanded."""

    def __init__(self, kin, offset):
        self._kin, self._offset = kin, np.asarray(offset, float)

    def __getattr__(self, name):
        return getattr(self._kin, name)

    def ik(self, *a, **kw):
        return self._kin.ik(*a, **kw) + self._offset

    def ik_batch(self, *a, **kw):
        Q, ok, err = self._kin.ik_batch(*a, **kw)
        return Q + self._offset, ok, err

    def ik_path(self, *a, **kw):
        Q, ok = self._kin.ik_path(*a, **kw)
        return Q + self._offset, ok


def test_beads_follow_forward_kinematics_not_the_commanded_points(arm, cell, planner):
    """With joints that do not reach the commanded points, the deposit is
    where the nozzle really is (FK of the joints), not on the G-code line."""
    offset = np.zeros(planner.kin.dof)
    offset[1] = 2e-3                                           # shoulder: ~1 mm at the nozzle
    bad = MotionPlanner(arm, cell, kin=OffsetIK(planner.kin, offset), tolerance_mm=50.0)
    r = new_runner(arm, cell, bad)
    load_and_start(r)
    run(r)
    assert r.state is ArmState.DONE
    tt, tq = np.concatenate(r.trace_t), np.concatenate(r.trace_q)
    p1, bt, lines = concat(r.beads, "p1"), concat(r.beads, "t"), concat(r.beads, "line")
    T_bed = cell.bed.pose
    segs = {s.line: s for s in parse_gcode_text(PROGRAM) if type(s) is Segment}
    off_line = []
    for j in range(len(bt)):
        i = int(np.searchsorted(tt, bt[j], side="right")) - 1
        fk = (arm.base_pose @ planner.kin.fk(tq[i]))[:3, 3]
        np.testing.assert_allclose(p1[j], fk, atol=1e-9)
        s = segs[int(lines[j])]
        A, B = (np.asarray(p, float) * MM @ T_bed[:3, :3].T + T_bed[:3, 3] for p in (s.start, s.end))
        d = B - A
        u = np.clip((p1[j] - A) @ d / (d @ d), 0, 1)
        off_line.append(np.linalg.norm(p1[j] - (A + u * d)))
    assert min(off_line) > 0.2 * MM       # the test can tell FK from the commanded line


def test_joints_between_waypoints_follow_the_timed_trajectory(reference, arm, cell, planner):
    """joints(now) is the commanded motion at that time: the cubic Hermite
    motion through the executed knots (positions and speeds) the runner
    recorded, evaluated here by the textbook Hermite basis."""
    ref = reference
    tt = np.concatenate([[0.0], np.concatenate(ref.trace_t)])
    tq = np.concatenate([np.asarray(arm.profile.home, float)[None], np.concatenate(ref.trace_q)])
    tv = np.concatenate([np.zeros((1, tq.shape[1])), np.concatenate(ref.trace_v)])
    keep = np.concatenate([np.diff(tt) > 0, [True]])
    tt, tq, tv = tt[keep], tq[keep], tv[keep]
    r = new_runner(arm, cell, planner)
    load_and_start(r)
    for t in np.arange(0.37, ref.stats.done_s - 0.5, 1.13):
        r.advance(t)
        assert r.state is ArmState.PRINTING and r.clock == t
        k = int(np.searchsorted(tt, t, side="right")) - 1
        h = tt[k + 1] - tt[k]
        s = (t - tt[k]) / h
        want = ((2 * s**3 - 3 * s**2 + 1) * tq[k] + (s**3 - 2 * s**2 + s) * h * tv[k]
                + (-2 * s**3 + 3 * s**2) * tq[k + 1] + (s**3 - s**2) * h * tv[k + 1])
        np.testing.assert_allclose(r.joints(t), want, atol=1e-9)


# ------------------------------------------------------------ pause / resume
def test_pause_lands_on_a_line_end_and_resume_gives_the_same_deposit(reference, arm, cell, planner):
    ref = reference
    # pause in the middle of line 9 (a 60 mm bead)
    t9 = concat(ref.beads, "t")[concat(ref.beads, "line") == 9]
    t_pause = 0.5 * (t9.min() + t9.max())
    r = new_runner(arm, cell, planner)
    load_and_start(r)
    r.advance(t_pause)
    assert r.state is ArmState.PRINTING
    r.handle(Pause(r.id))
    r.advance(t_pause + 20.0)
    assert r.state is ArmState.PAUSED
    st = messages(r, Status)[-1]
    assert st.state is ArmState.PAUSED and st.line == 9 == r.done_line
    # no partial line: every line up to 9 is complete, nothing after it
    got, want = bead_filament_by_line(r.beads), moving_extrusion(PROGRAM)
    assert set(got) == {line for line in want if line <= 9}
    for line in got:
        assert got[line] == pytest.approx(want[line], abs=1e-9)
    np.testing.assert_allclose(r.nozzle_mm(), (-30, 0, 0.2), atol=1e-3)
    # it braked within the acceleration limits: rests on the line's end later than
    # the unpaused run passed it, within a few seconds
    t_stop = concat(r.beads, "t").max()
    assert t9.max() - 1e-9 <= t_stop < t9.max() + 5.0
    # paused: nothing moves while time passes
    q, n = r.q.copy(), len(r.beads)
    r.advance(t_pause + 60.0)
    assert r.state is ArmState.PAUSED and len(r.beads) == n
    np.testing.assert_array_equal(r.q, q)
    np.testing.assert_array_equal(r.joints(t_pause + 60.0), q)
    # resume: same beads as the uninterrupted run, later by the pause
    r.handle(Resume(r.id))
    assert r.state is ArmState.PRINTING
    assert messages(r, Status)[-1].state is ArmState.PRINTING
    run(r)
    assert r.state is ArmState.DONE
    same_beads(r, ref)
    # times: unchanged up to the pause request; braking to rest and starting
    # again from rest cost a little more motion time than the uninterrupted run
    shift = (t_pause + 60.0) - t_stop
    t_ref, t_got = concat(ref.beads, "t"), concat(r.beads, "t")
    before = t_ref <= t_pause
    np.testing.assert_allclose(t_got[before], t_ref[before])
    assert np.all(t_got[t_ref > t_stop] >= t_pause + 60.0)
    assert r.stats.idle_time_s == pytest.approx(shift)
    extra = r.stats.print_time_s - ref.stats.print_time_s
    assert 0.0 <= extra < 5.0
    assert r.stats.done_s == pytest.approx(ref.stats.done_s + shift + extra)


def test_pause_in_the_travel_from_home_stops_at_its_end(arm, cell, planner):
    r = new_runner(arm, cell, planner)
    load_and_start(r)
    r.advance(0.3)                              # in the joint move to line 6's end
    r.handle(Pause(r.id))
    r.advance(100.0)
    assert r.state is ArmState.PAUSED and r.done_line == 6
    assert not r.beads
    np.testing.assert_allclose(r.nozzle_mm(), (-30, -10, 0.2), atol=1e-3)
    r.handle(Start(r.id))                        # A1 on a paused arm resumes too
    assert r.state is ArmState.PRINTING
    run(r)
    assert r.state is ArmState.DONE


# ------------------------------------------------------------ A1 C<chunk>: a start sent again
def test_a_start_naming_the_chunk_starts_it_once(arm, cell, planner, reference):
    """A1 R<id> C<chunk>, sent again (by a front end replacing a crashed
    one), does nothing once that chunk has started: a DONE arm does not
    print again, a PAUSED one is not resumed; the deposit is the
    uninterrupted run's.  A plain A1 keeps the original's meaning."""
    r = new_runner(arm, cell, planner)
    r.handle(LoadChunk(r.id, PROGRAM, chunk_id=41), now=0.0)
    assert r.starts_run(Start(r.id, chunk_id=41)) and not r.starts_run(Start(r.id, chunk_id=40))
    r.handle(Start(r.id, chunk_id=41), now=0.0)
    assert r.state is ArmState.PRINTING
    r.outbox.clear()
    r.handle(Start(r.id, chunk_id=41), now=r.clock)               # while printing: nothing
    run(r, until=3.0)
    r.handle(Pause(r.id), now=r.clock)
    run(r)
    assert r.state is ArmState.PAUSED
    paused_at = r.done_line
    r.handle(Start(r.id, chunk_id=41), now=r.clock)               # not a resume
    assert r.state is ArmState.PAUSED and r.done_line == paused_at
    assert not r.starts_run(Start(r.id, chunk_id=41))
    r.handle(Resume(r.id), now=r.clock)
    run(r)
    assert r.state is ArmState.DONE
    r.handle(Start(r.id, chunk_id=41), now=r.clock)               # DONE: not again
    assert r.state is ArmState.DONE and r.done_line == N_LINES
    assert not messages(r, ErrorReport)
    assert messages(r, Status)[-1].state is ArmState.DONE         # it says where it is
    same_beads(r, reference)
    r.handle(Start(r.id), now=r.clock)                            # plain A1: again from the top
    assert r.state is ArmState.PRINTING and r.done_line == 0


def test_a_start_naming_another_chunk_is_refused(arm, cell, planner):
    r = new_runner(arm, cell, planner)
    r.handle(LoadChunk(r.id, PROGRAM, chunk_id=7), now=0.0)
    r.handle(Start(r.id, chunk_id=8), now=0.0)
    assert r.state is ArmState.IDLE and not r.starts_run(Start(r.id, chunk_id=8))
    errs = messages(r, ErrorReport)
    assert len(errs) == 1 and errs[0].message == "A1 C8 refused: the chunk loaded is C7"
    r.handle(LoadChunk(r.id, PROGRAM), now=0.0)                   # a chunk without C: a new identity
    r.handle(Start(r.id, chunk_id=7), now=0.0)
    assert r.state is ArmState.IDLE and messages(r, ErrorReport)[-1].message.endswith("one without a C")


def test_a_new_chunk_can_be_started_and_a_restored_arm_remembers_its_start(arm, cell, planner):
    import json
    a = new_runner(arm, cell, planner)
    a.handle(LoadChunk(a.id, PROGRAM, chunk_id=1), now=0.0)
    a.handle(Start(a.id, chunk_id=1), now=0.0)
    run(a)
    a.handle(LoadChunk(a.id, PROGRAM + "G1 X-30 Y0 E0.8\n", chunk_id=2), now=a.clock)
    assert a.state is ArmState.IDLE and a.starts_run(Start(a.id, chunk_id=2))
    a.handle(Start(a.id, chunk_id=2), now=a.clock)
    assert a.state is ArmState.PRINTING
    a.advance(a.clock + 2.0)
    b = new_runner(arm, cell, planner)                            # the firmware crashed and came back
    b.restore(json.loads(json.dumps(a.checkpoint())), PROGRAM + "G1 X-30 Y0 E0.8\n")
    assert b.started and not b.starts_run(Start(b.id, chunk_id=2))
    done_line = b.done_line
    b.handle(Start(b.id, chunk_id=2), now=b.clock)
    assert b.done_line == done_line and not messages(b, ErrorReport)
    old = a.checkpoint()
    del old["started"]                                            # a checkpoint written before C existed
    c = new_runner(arm, cell, planner)
    c.restore(old, PROGRAM + "G1 X-30 Y0 E0.8\n")
    assert c.started


# ------------------------------------------------------------ refusals
def test_start_without_a_chunk_is_an_error(arm, cell, planner):
    r = new_runner(arm, cell, planner)
    r.handle(Start(r.id))
    assert r.state is ArmState.IDLE
    errs = messages(r, ErrorReport)
    assert len(errs) == 1 and errs[0].robot == r.id and "no chunk" in errs[0].message


def test_load_while_printing_is_refused(arm, cell, planner, reference):
    r = new_runner(arm, cell, planner)
    load_and_start(r)
    r.advance(5.0)
    assert r.state is ArmState.PRINTING
    chunk = r.chunk
    r.handle(LoadChunk(r.id, "G1 X0 Y0 Z5 F600\n", chunk_id=2))
    errs = messages(r, ErrorReport)
    assert len(errs) == 1 and "A5 refused" in errs[0].message and "PRINTING" in errs[0].message
    assert r.state is ArmState.PRINTING and r.chunk == chunk
    run(r)
    assert r.state is ArmState.DONE
    same_beads(r, reference)


@pytest.mark.parametrize("line, bad", [(8, "G1 X30 Y0 E0.4 Q5"), (8, "G1 X30 Y0 Enan"), (8, ";@A9 R1 W1 N3")])
def test_a_chunk_with_a_bad_line_is_refused_naming_it(arm, cell, planner, line, bad):
    lines = PROGRAM.split("\n")
    lines[line - 1] = bad
    r = new_runner(arm, cell, planner)
    r.handle(LoadChunk(r.id, "\n".join(lines), chunk_id=3))
    errs = messages(r, ErrorReport)
    assert len(errs) == 1 and errs[0].line == line
    assert ":%d" % line in errs[0].message
    assert r.state is ArmState.IDLE and r.chunk is None and not r.items
    r.handle(Start(r.id))
    assert r.state is ArmState.IDLE and len(messages(r, ErrorReport)) == 2


def test_clear_chunk_stops_the_arm(arm, cell, planner):
    r = new_runner(arm, cell, planner)
    load_and_start(r)
    r.advance(5.0)
    r.handle(ClearChunk(r.id))
    assert r.state is ArmState.IDLE and r.chunk is None
    assert messages(r, ErrorReport) and messages(r, Status)[-1].state is ArmState.IDLE


# ------------------------------------------------------------ barriers
def with_barrier(n):
    lines = PROGRAM.split("\n")
    lines.insert(BARRIER_LINE - 1, ";@A9 R0 W1 N%d" % n)
    return "\n".join(lines)


def test_barrier_waits_for_the_other_arms_line_and_resumes_at_its_report(arm, cell, planner):
    text = with_barrier(40)
    # the same program with the barrier already satisfied: no wait
    free = new_runner(arm, cell, planner)
    free.handle(Status(1, ArmState.PRINTING, 0, 40, 50.0), now=0.0)
    load_and_start(free, text)
    run(free)
    assert free.state is ArmState.DONE and free.stats.idle_time_s == 0.0

    r = new_runner(arm, cell, planner)
    load_and_start(r, text)
    run(r, t_max=100.0)
    assert r.state is ArmState.WAITING
    t_wait = r.clock
    # it told the others where it is before waiting: the last line before the barrier
    st = messages(r, Status)[-1]
    assert st.line == BARRIER_LINE - 1 and st.state is ArmState.PRINTING
    assert set(bead_filament_by_line(r.beads)) == {7, 8, 9}
    n_beads = len(r.beads)
    r.advance(200.0)
    assert r.state is ArmState.WAITING and r.clock == t_wait and len(r.beads) == n_beads
    # a report of an earlier line, or about itself, does not release it
    r.handle(Status(1, ArmState.PRINTING, 0, 39, 40.0), now=150.0)
    r.handle(Status(0, ArmState.DONE, 5, 99, 100.0), now=150.0)
    r.advance(250.0)
    assert r.state is ArmState.WAITING and len(r.beads) == n_beads
    # line 40 reported at t = 260 (the arm's clock is already at 300)
    r.handle(Status(1, ArmState.PRINTING, 0, 40, 41.0), now=260.0)
    r.advance(300.0)
    assert r.state is not ArmState.WAITING
    run(r)
    assert r.state is ArmState.DONE
    assert r.stats.idle_time_s == pytest.approx(260.0 - t_wait)
    assert r.stats.done_s == pytest.approx(free.stats.done_s + 260.0 - t_wait)
    first_after = concat(r.beads, "t")[n_beads_t(r, n_beads)]
    first_free = concat(free.beads, "t")[n_beads_t(free, n_beads)]
    assert first_after == pytest.approx(first_free + 260.0 - t_wait)
    same_beads(r, free)


def n_beads_t(r, n_blocks):
    """Index (in the concatenated beads) of the first bead after ``n_blocks`` bead blocks."""
    return sum(len(b.t) for b in r.beads[:n_blocks])


def test_barrier_released_by_the_other_arm_done(arm, cell, planner):
    r = new_runner(arm, cell, planner)
    load_and_start(r, with_barrier(10 ** 6))
    run(r, t_max=100.0)
    assert r.state is ArmState.WAITING
    r.handle(Status(1, ArmState.DONE, 3, 12, 100.0), now=r.clock + 1.0)
    r.advance(r.clock + 2.0)
    run(r)
    assert r.state is ArmState.DONE


def test_pause_while_waiting_then_resume_keeps_waiting(arm, cell, planner):
    r = new_runner(arm, cell, planner)
    load_and_start(r, with_barrier(40))
    run(r, t_max=100.0)
    assert r.state is ArmState.WAITING
    r.handle(Pause(r.id))
    assert r.state is ArmState.PAUSED and messages(r, Status)[-1].state is ArmState.PAUSED
    r.handle(Resume(r.id))
    assert r.state is ArmState.WAITING
    r.handle(Status(1, ArmState.PRINTING, 0, 40, 41.0), now=r.clock + 1.0)
    r.advance(r.clock + 2.0)
    run(r)
    assert r.state is ArmState.DONE


def test_a9_command_makes_an_idle_arm_wait(arm, cell, planner):
    r = new_runner(arm, cell, planner)
    r.handle(LoadChunk(r.id, PROGRAM, chunk_id=1))
    r.handle(WaitFor(r.id, 1, layer=1))
    assert r.state is ArmState.WAITING
    r.handle(Status(1, ArmState.PRINTING, 1, 30, 50.0), now=4.0)
    r.advance(5.0)
    assert r.state is not ArmState.WAITING


# ------------------------------------------------------------ A3, errors
def test_send_position_reports_the_nozzle(arm, cell, planner):
    r = new_runner(arm, cell, planner)
    r.handle(SendPosition(r.id))
    st = messages(r, Status)[-1]
    T = arm.base_pose @ planner.kin.fk(np.asarray(arm.profile.home, float))
    inv = np.linalg.inv(cell.bed.pose)
    want = (inv[:3, :3] @ T[:3, 3] + inv[:3, 3]) / MM
    np.testing.assert_allclose(st.position, want, atol=1e-3)
    assert st.state is ArmState.IDLE and st.robot == r.id
    # mid-print: where the last reached waypoint is
    ref = new_runner(arm, cell, planner)       # how long the program takes
    load_and_start(ref)
    run(ref)
    load_and_start(r)
    r.advance(0.6 * ref.stats.done_s)
    r.handle(SendPosition(1))                  # A3 R1 reaching this arm: report for arm 1
    st = messages(r, Status)[-1]
    np.testing.assert_allclose(st.position, r.nozzle_mm(), atol=1e-3)
    assert st.state is ArmState.PRINTING and st.line == r.done_line


UNREACHABLE = PROGRAM.replace("G1 X30 Y0 E0.4", "G1 X3000 Y0 E0.4")       # line 8


def test_unreachable_line_stops_the_arm_with_an_error_naming_it(arm, cell, planner):
    r = new_runner(arm, cell, planner)
    load_and_start(r, UNREACHABLE)
    run(r)
    assert r.state is ArmState.ERROR
    errs = messages(r, ErrorReport)
    assert len(errs) == 1 and errs[0].line == 8 and errs[0].robot == r.id
    assert "unreachable" in errs[0].message
    st = messages(r, Status)[-1]
    assert st.state is ArmState.ERROR and st.line == 7 and st.position is not None
    np.testing.assert_allclose(st.position, (30, -10, 0.2), atol=1e-3)
    assert set(bead_filament_by_line(r.beads)) == {7}
    assert r.stats.ik_failures == 1
    t = r.clock
    r.advance(t + 100.0)                        # stays stopped
    assert r.state is ArmState.ERROR and set(bead_filament_by_line(r.beads)) == {7}


def test_an_arm_waiting_for_a_failed_arm_holds_and_says_why(cell):
    from ambots.protocol import ArmState, ErrorReport, LoadChunk, Start, Status
    from ambots.runner import ArmRunner
    arm = cell.arm("kinova")
    text = "G21\nG90\nM83\nG0 X0 Y0 Z5 F3000\n;@A9 R0 W1 N50\nG0 X5 Y0 Z5\n"
    r = ArmRunner(arm, cell)
    r.handle(LoadChunk(arm.id, text, chunk_id=1))
    r.handle(Start(arm.id))
    r.advance(100.0)
    assert r.state is ArmState.WAITING
    r.handle(Status(1, ArmState.ERROR, 0, 10, 5.0), now=100.0)
    assert r.state is ArmState.PAUSED
    errors = [m for _, m in r.outbox if isinstance(m, ErrorReport)]
    assert errors and "R1" in errors[-1].message and errors[-1].line == 5


def test_planning_ahead_while_waiting_gives_the_same_motion(arm, cell, planner):
    """Moves planned ahead at a barrier (prefetch) are the ones executed:
    the same beads as the reference run, and no move is planned twice."""
    calls = []

    class Counting:
        def __init__(self, inner):
            self.inner = inner

        def __getattr__(self, name):
            return getattr(self.inner, name)

        def plan_moves(self, segments, q0):
            calls.append(segments[0].line)
            return self.inner.plan_moves(segments, q0)

    r = ArmRunner(arm, cell, planner=Counting(planner), record=True)
    load_and_start(r, with_barrier(40))
    run(r, t_max=100.0)
    assert r.state is ArmState.WAITING
    n_before = len(calls)
    while r.prefetch():
        pass
    assert len(calls) > n_before               # the moves after the barrier are planned now
    r.handle(Status(1, ArmState.PRINTING, 0, 40, 41.0), now=r.clock)
    r.advance(r.clock)
    run(r)
    assert r.state is ArmState.DONE
    assert len(calls) == len(set(calls))       # ... and not again when the arm gets there
    free = new_runner(arm, cell, planner)      # the same program, the barrier satisfied from the start
    free.handle(Status(1, ArmState.PRINTING, 0, 40, 50.0), now=0.0)
    load_and_start(free, with_barrier(40))
    run(free)
    same_beads(r, free)


@pytest.mark.parametrize("stop_at", [1.1, 3.0, 4.2, 5.5, 6.3, 8.0, 9.72, 10.5, 12.0, 21.0])
def test_checkpoint_restore_continues_without_gap_or_repeat(arm, cell, planner, reference, stop_at):
    """A run stopped at any moment (a crash: the runner object is lost) and
    restored from its JSON checkpoint into a new runner lays, per program
    line, the same filament along the same path as the uninterrupted run."""
    import json
    a = new_runner(arm, cell, planner)
    load_and_start(a)
    t = 0.0
    while a.state is ArmState.PRINTING and t < stop_at:
        t = min(stop_at, t + 0.37)
        a.advance(t)
    cp = json.loads(json.dumps(a.checkpoint()))
    b = new_runner(arm, cell, planner)
    b.restore(cp, PROGRAM)
    assert b.state is a.state and b.done_line == a.done_line and np.allclose(b.q, a.q)
    run(b)
    assert b.state is ArmState.DONE
    got = bead_filament_by_line(a.beads + b.beads)
    want = bead_filament_by_line(reference.beads)
    assert set(got) == set(want)
    for line in want:
        assert got[line] == pytest.approx(want[line], rel=1e-6), line      # nozzle vs plan: < 1e-6

    def length_by_line(beads):
        out = {}
        for p0, p1, line in zip(concat(beads, "p0"), concat(beads, "p1"), concat(beads, "line")):
            out[int(line)] = out.get(int(line), 0.0) + float(np.linalg.norm(p1 - p0))
        return out
    la, lr = length_by_line(a.beads + b.beads), length_by_line(reference.beads)
    for line in lr:
        assert la[line] == pytest.approx(lr[line], abs=2e-5), line      # 0.02 mm
    # contiguous: each bead starts where the previous bead of its line ended
    beads = a.beads + b.beads
    p0, p1, ln = concat(beads, "p0"), concat(beads, "p1"), concat(beads, "line")
    same = ln[1:] == ln[:-1]
    assert np.abs(p0[1:][same] - p1[:-1][same]).max() < 1e-6


def test_a_report_overtaken_by_a_newer_one_is_ignored(arm, cell, planner):
    """Reordered delivery: the older A10 (earlier clock) arriving last must
    not take the other arm's progress back (a barrier it satisfied would
    close again)."""
    r = new_runner(arm, cell, planner)
    load_and_start(r, with_barrier(40))
    run(r, t_max=100.0)
    assert r.state is ArmState.WAITING
    r.handle(Status(1, ArmState.PRINTING, 0, 41, 50.0, clock=30.0), now=r.clock)
    r.handle(Status(1, ArmState.PRINTING, 0, 12, 10.0, clock=5.0), now=r.clock)     # late, older
    assert r.peers[1].line == 41
    r.advance(r.clock + 40.0)
    assert r.state is not ArmState.WAITING


def test_a_barrier_already_satisfied_by_a_later_report_holds_the_arm_until_then(arm, cell, planner):
    """Clocks of arms are independent (speed max, the offline simulator): the
    awaited report may be there before the arm reaches its barrier, made at a
    later simulated time than the arm's own clock.  The arm then waits until
    that time, as if it had been waiting when the report came: the other arm
    left the region at that moment, not before."""
    text = with_barrier(40)
    free = new_runner(arm, cell, planner)
    load_and_start(free, text)
    free.handle(Status(1, ArmState.PRINTING, 0, 40, 50.0, clock=0.0), now=0.0)
    run(free)
    assert free.state is ArmState.DONE and free.stats.idle_time_s == 0.0

    r = new_runner(arm, cell, planner)
    load_and_start(r, text)
    # line 40 reported by an arm whose clock is at 500 s, long before this arm gets to the barrier
    r.handle(Status(1, ArmState.PRINTING, 0, 40, 50.0, clock=500.0), now=0.0)
    t = 0.0
    while r.state in (ArmState.PRINTING, ArmState.WAITING) and t < 2000.0:
        t += STEP
        r.advance(t)
    assert r.state is ArmState.DONE
    assert r.stats.idle_time_s == pytest.approx(500.0 - bead_end_before_barrier(free))
    assert r.stats.done_s == pytest.approx(free.stats.done_s + r.stats.idle_time_s)
    # nothing after the barrier happened before 500 s
    t, lines = concat(r.beads, "t"), concat(r.beads, "line")
    assert t[lines > BARRIER_LINE].min() > 500.0
    same_beads(r, free)
    # the executed trace stands still through the wait: it has the pose the arm
    # waited in at 500 s too, so interpolating it does not move the arm early
    tt, tq = np.concatenate(r.trace_t), np.concatenate(r.trace_q)
    assert np.all(np.diff(tt) > 0)
    t_wait = bead_end_before_barrier(r)
    i = int(np.searchsorted(tt, t_wait))
    assert tt[i] == pytest.approx(t_wait) and tt[i + 1] == pytest.approx(500.0)
    np.testing.assert_array_equal(tq[i + 1], tq[i])
    for t_mid in (t_wait + 1.0, 250.0, 499.9):
        q = [np.interp(t_mid, tt, tq[:, j]) for j in range(tq.shape[1])]
        np.testing.assert_allclose(q, tq[i], atol=1e-12)


def bead_end_before_barrier(r):
    """Time the arm completed the last line before the barrier."""
    t, lines = concat(r.beads, "t"), concat(r.beads, "line")
    return float(t[lines < BARRIER_LINE].max())


# ------------------------------------------------- another arm in the way (real-time planning)
class OtherArmInTheWay:
    """is_valid for a planner: while ``blocked``, every joint vector farther
    than 0.3 rad from ``free`` is taken by another arm; ``static`` (no other
    arms) is always clear."""

    def __init__(self, free):
        self.free, self.blocked, self.calls = np.asarray(free, float), True, 0

    def __call__(self, Q):
        Q = np.atleast_2d(Q)
        self.calls += 1
        if not self.blocked:
            return np.ones(len(Q), dtype=bool)
        return np.linalg.norm(Q - self.free, axis=1) <= 0.3

    def static(self, Q):
        return np.ones(len(np.atleast_2d(Q)), dtype=bool)


def test_a_move_blocked_only_by_another_arm_waits_and_goes_on(arm, cell, reference):
    check = OtherArmInTheWay(arm.profile.home)
    r = new_runner(arm, cell, MotionPlanner(arm, cell, is_valid=check))
    load_and_start(r)
    run(r, until=3.0)
    assert r.state is ArmState.PRINTING and not r.beads and r.q.tolist() == list(arm.profile.home)
    assert r.stats.idle_time_s >= 2.0 and r.blocked_s >= 2.0       # waited in place
    check.blocked = False                                            # the other arm moved on
    run(r)
    assert r.state is ArmState.DONE and not messages(r, ErrorReport)
    assert r.blocked_s == 0.0
    assert bead_filament_by_line(r.beads) == pytest.approx(bead_filament_by_line(reference.beads))
    np.testing.assert_allclose(concat(r.beads, "p1"), concat(reference.beads, "p1"), atol=1e-9)


def test_a_move_blocked_for_too_long_is_an_error_naming_its_line(arm, cell):
    r = new_runner(arm, cell, MotionPlanner(arm, cell, is_valid=OtherArmInTheWay(arm.profile.home)))
    r.max_blocked_s = 2.0
    load_and_start(r)
    run(r, t_max=20.0)
    assert r.state is ArmState.ERROR
    [err] = messages(r, ErrorReport)
    assert err.line == 6 and "other arms blocked the way for 2 s" in err.message


def test_a_blocked_move_says_what_its_end_is_too_close_to(arm, cell):
    check = OtherArmInTheWay(arm.profile.home)
    check.explain = lambda q: "ur10 -3.00 mm (needs >= 5 mm): bracelet_link / wrist_2_link"
    r = new_runner(arm, cell, MotionPlanner(arm, cell, is_valid=check))
    r.max_blocked_s = 1.0
    load_and_start(r)
    run(r, until=0.1)
    assert r.block.blocked.startswith("goal configuration ")
    assert r.block.blocked.endswith("is in collision (is_valid is False): ur10 -3.00 mm (needs >= 5 mm): "
                                    "bracelet_link / wrist_2_link")
    run(r, t_max=20.0)
    assert "(needs >= 5 mm): bracelet_link / wrist_2_link" in messages(r, ErrorReport)[0].message

def test_a_move_blocked_by_the_bed_itself_is_an_error_at_once(arm, cell):
    check = OtherArmInTheWay(arm.profile.home)
    check.static = check.__call__                       # no other arm: the obstacle is static
    r = new_runner(arm, cell, MotionPlanner(arm, cell, is_valid=check))
    load_and_start(r)
    run(r, t_max=20.0)
    assert r.state is ArmState.ERROR and r.clock < 1.0
    assert "no collision-free path" in messages(r, ErrorReport)[0].message


def test_stop_brakes_at_once_mid_line_and_resume_gives_the_same_deposit(reference, arm, cell, planner):
    """A12 (an operator's stop): rest mid-line on the first waypoint the arm
    can brake to, PAUSED; A6 goes on from there to the same deposit."""
    ref = reference
    t9 = concat(ref.beads, "t")[concat(ref.beads, "line") == 9]       # X30 -> X-30 at Y0, 60 mm
    t_cmd = t9.min() + 0.3 * (t9.max() - t9.min())
    r = new_runner(arm, cell, planner)
    load_and_start(r)
    r.advance(t_cmd)
    x_cmd = r.nozzle_mm()[0]
    r.handle(Stop(r.id))
    r.advance(t_cmd + 20.0)
    assert r.state is ArmState.PAUSED and messages(r, Status)[-1].state is ArmState.PAUSED
    x_rest = r.nozzle_mm()[0]
    # mid-line, well before the line's end (a pause goes on to X-30)
    assert -30.0 + 5.0 < x_rest <= x_cmd
    t_rest = concat(r.beads, "t").max()
    assert t_rest < t9.max() - 1.0
    # paused: nothing moves while time passes
    q = r.q.copy()
    r.advance(t_cmd + 60.0)
    np.testing.assert_array_equal(r.q, q)
    r.handle(Resume(r.id))
    run(r)
    assert r.state is ArmState.DONE
    same_beads(r, ref)
    got, want = bead_filament_by_line(r.beads), moving_extrusion(PROGRAM)
    assert set(got) == set(want)
    for line in got:
        assert got[line] == pytest.approx(want[line], abs=1e-9)


def _hermite(tt, tq, tv, t):
    """The textbook cubic Hermite through knots (tt, tq, tv) at time t."""
    k = min(int(np.searchsorted(tt, t, side="right")) - 1, len(tt) - 2)
    h = tt[k + 1] - tt[k]
    s = (t - tt[k]) / h
    return ((2 * s**3 - 3 * s**2 + 1) * tq[k] + (s**3 - 2 * s**2 + s) * h * tv[k]
            + (-2 * s**3 + 3 * s**2) * tq[k + 1] + (s**3 - s**2) * h * tv[k + 1])


@pytest.mark.parametrize("command", [Pause, Stop])
def test_the_recorded_trace_holds_the_arm_still_through_a_pause_mid_block(reference, arm, cell, planner, command):
    """The executed motion the contact check reads (the trace knots,
    Hermite-interpolated) is the motion the arm made through an A2 / A12
    mid-block, 60 s at rest and A6: at every instant the joints the runner
    commanded (joints(now)), standing still through the pause.  A live
    print's report once showed 48,958 arm-arm contact samples, 126 mm deep,
    because the knot before the pause and the first after it were joined by
    one cubic over the whole pause."""
    ref = reference
    t7 = concat(ref.beads, "t")[concat(ref.beads, "line") == 7]       # X-30 -> X30 at Y-10, 60 mm
    t_cmd = t7.min() + 0.3 * (t7.max() - t7.min())
    r = new_runner(arm, cell, planner)
    load_and_start(r)
    seen = []

    def go(t_end, dt=0.23):
        t = r.clock
        while t < t_end - 1e-9:
            t = min(t + dt, t_end)
            r.advance(t)
            seen.append((t, r.joints(t)))

    go(t_cmd)
    r.handle(command(r.id))
    go(t_cmd + 60.0)
    assert r.state is ArmState.PAUSED
    q_rest, t_rest = r.q.copy(), r.block_t0 + r.block.t[r.k]
    assert t_rest < t_cmd + 10.0                                # it came to rest early in the pause
    r.handle(Resume(r.id))
    go(ref.stats.done_s + 80.0)
    assert r.state is ArmState.DONE
    tt = np.concatenate([[0.0], np.concatenate(r.trace_t)])
    tq = np.concatenate([np.asarray(arm.profile.home, float)[None], np.concatenate(r.trace_q)])
    tv = np.concatenate([np.zeros((1, tq.shape[1])), np.concatenate(r.trace_v)])
    keep = np.concatenate([np.diff(tt) > 0, [True]])
    tt, tq, tv = tt[keep], tq[keep], tv[keep]
    assert (np.diff(tt) > 0).all()
    still = 0
    for t, q in seen:
        if t > tt[-1]:
            break
        np.testing.assert_allclose(_hermite(tt, tq, tv, t), q, atol=1e-9, err_msg="t = %.3f" % t)
        if t_rest <= t <= t_cmd + 60.0:
            np.testing.assert_allclose(q, q_rest, atol=1e-12)
            still += 1
    assert still > 100                                          # the pause was sampled


def test_clear_chunk_while_moving_brakes_within_the_limits_and_the_next_run_starts_at_rest(arm, cell, planner):
    """A4 in the middle of a line (simulated arm): idle at once, but the arm
    brakes as a real one would, its speed continuous and its acceleration
    within the profile's limits (finite differences of the joints it shows,
    not the brake's own figures); a new chunk then starts from where and
    when it came to rest."""
    r = new_runner(arm, cell, planner)
    load_and_start(r)
    t = 0.0
    while r.block is None or not r.block.extrude[min(r.k + 1, len(r.block.t) - 1)] or t < 2.0:
        t += 0.05
        r.advance(t)
    h = 1e-3
    v_before = (r.joints(t) - r.joints(t - h)) / h
    tip = r.planner.tip_world(np.array([r.joints(t - h), r.joints(t)]))
    assert np.linalg.norm(tip[1] - tip[0]) / h > 0.01     # the nozzle moves (> 10 mm/s) when the A4 comes
    r.handle(ClearChunk(r.id), now=t)
    assert r.state is ArmState.IDLE and r.chunk is None
    rest = r.rest_at()
    assert t < rest < t + 2.0
    v_after = (r.joints(t + h) - r.joints(t)) / h
    assert np.allclose(v_after, v_before, atol=0.02 * np.abs(v_before).max() + 1e-3)   # no jump in speed
    ts = np.arange(t, rest + 0.05, 0.002)
    Q = np.array([r.joints(x) for x in ts])
    a = np.diff(Q, 2, axis=0) / 0.002 ** 2
    amax = np.asarray(r.planner.timing.amax, dtype=float)
    assert (np.abs(a) <= 1.05 * amax + 1e-6).all()
    assert np.allclose(Q[-1], r.q) and np.allclose(Q[-2], Q[-1])           # at rest at its end
    assert np.linalg.norm(Q[-1] - Q[0]) > 1e-4                              # it did coast on
    # a new chunk at once: accepted, and its motion starts from the rest pose, after the brake
    r.handle(LoadChunk(r.id, PROGRAM, chunk_id=2), now=t)
    r.handle(Start(r.id), now=t)
    assert r.state is ArmState.PRINTING and r.clock >= rest
    r.advance(rest + 0.5)
    assert r.block is None or r.block_t0 >= rest - 1e-9
    tt = np.concatenate(r.trace_t)
    assert (np.diff(tt) > 0).all()                                          # one timeline, in order
    run(r)
    assert r.state is ArmState.DONE
