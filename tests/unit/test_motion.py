"""The firmware's planner (ambots.motion): programs read into items, straight
nozzle lines turned into time-stamped joint waypoints that stay within
0.1 mm of the line, at the programmed feedrate within the joint speed
limits, without joint jumps; unreachable points named by their line.

Everything is checked independently of the planner: nozzle positions by
forward kinematics of the returned joints (KDL for a few, the vectorised FK
for dense samples of the joint-linear interpolation), G-code lines mapped
to the world with the cell's bed pose."""
import numpy as np
import pytest

from ambots.config import default_cell_path, load_cell
from ambots.errors import GCodeError
from ambots.gcode import Dwell, Segment, parse_gcode_text
from ambots.motion import Directive, Moves, MotionPlanner, Pause, read_program
from ambots.protocol import SendPosition, WaitFor

MM = 1e-3
TOL_MM = 0.1              # the limit on the nozzle leaving a straight line
DENSE = 20                # samples per interval of the joint-linear interpolation

# A square, both diagonals, a retract / fast travel / unretract and a long
# line, at z = 0.2 mm, bed frame mm, with feedrates.  Lines are 1-based.
SQUARE = """\
G21
G90
M83
;LAYER_CHANGE
;Z:0.2
G0 X-40 Y-40 Z0.2 F9000
G1 X40 Y-40 E2.0 F1200
G1 X40 Y40 E2.0
G1 X-40 Y40 E2.0 F2400
G1 X-40 Y-40 E2.0
G1 X40 Y40 E3.0 F1800
G1 E-0.8 F2100
G0 X-40 Y40 F120000
G1 E0.8 F2100
G1 X40 Y-40 E3.0 F600
G1 X-100 Y-40 E5.0 F3000
"""
FIRST_CARTESIAN_LINE = 7      # line 6 is the travel from the home pose: a joint move


@pytest.fixture(scope="module")
def cell():
    return load_cell(default_cell_path())


@pytest.fixture(scope="module", params=["kinova", "ur10"])
def arm(request, cell):
    return cell.arm(request.param)


@pytest.fixture(scope="module")
def planner(arm, cell):
    return MotionPlanner(arm, cell)


def segments_by_line(text):
    return {s.line: s for s in parse_gcode_text(text) if type(s) is Segment}


def bed_to_world(cell, P_mm):
    """Bed-frame mm -> world m, straight from the cell's bed pose."""
    T = cell.bed.pose
    return np.asarray(P_mm, float) * MM @ T[:3, :3].T + T[:3, 3]


def world_tips(arm, kin, Q):
    """Nozzle positions (N, 3), world frame, by the vectorised FK."""
    T = arm.base_pose @ kin.fk_batch(np.atleast_2d(Q))
    return T[:, :3, 3]


def seg_distance(X, A, B):
    """Distance of points X (N, 3) from the segment A-B (3,)."""
    d = B - A
    L2 = float(d @ d)
    u = np.clip((X - A) @ d / L2, 0.0, 1.0) if L2 > 0 else np.zeros(len(X))
    return np.linalg.norm(X - (A + u[:, None] * d), axis=1)


def plan_program(planner, text, q0):
    """Plan every Moves item of a program in turn -> list of blocks."""
    items, _, _ = read_program(text)
    blocks, q = [], np.asarray(q0, float)
    for it in items:
        if isinstance(it, Moves):
            b = planner.plan_moves(it.segments, q)
            blocks.append(b)
            if b.error is not None:
                break
            q = b.Q[-1]
    return blocks


@pytest.fixture(scope="module")
def square(planner, arm):
    blocks = plan_program(planner, SQUARE, arm.profile.home)
    assert len(blocks) == 1, "one layer, no directive: one Moves item"
    b = blocks[0]
    assert b.error is None
    return b


def cartesian_intervals(b):
    """Interval indices k (waypoint k-1 -> k) that follow a G-code line."""
    return [k for k in range(1, len(b.t)) if b.line[k] >= FIRST_CARTESIAN_LINE]


# ------------------------------------------------------------ read_program
PROGRAM = """\
G21
G90
M83
;LAYER_CHANGE
;Z:0.2
G0 X0 Y0 Z0.2 F9000
G1 X10 Y0 E0.5 F1200
;@A9 R1 W2 N5
G1 X10 Y10 E0.5
G4 P500
G1 X0 Y10 E0.5
;LAYER_CHANGE
;Z:0.4
G4 S1
G0 Z0.4
G1 X0 Y0 E0.5
;@A3 R2
"""


def test_read_program_splits_at_directives_dwells_and_layers():
    items, n_lines, layer_of_line = read_program(PROGRAM)
    kinds = [(type(it).__name__, it.line) for it in items]
    assert kinds == [("Moves", 6), ("Directive", 8), ("Moves", 9), ("Pause", 10), ("Moves", 11),
                     ("Pause", 14), ("Moves", 15), ("Directive", 17)]
    assert [s.line for s in items[0].segments] == [6, 7]
    assert [s.line for s in items[6].segments] == [15, 16]
    assert items[1].message == WaitFor(1, 2, line=5)
    assert items[7].message == SendPosition(2)
    assert isinstance(items[3], Pause) and items[3].seconds == pytest.approx(0.5)
    assert items[5].seconds == pytest.approx(1.0)
    # a run never mixes layers
    for it in items:
        if isinstance(it, Moves):
            assert len({s.layer for s in it.segments}) == 1
    assert n_lines == len(PROGRAM.splitlines())          # a final line break starts no line
    assert layer_of_line.shape == (n_lines + 1,)


def test_layer_of_line_matches_every_event():
    """Each G-code event's line gets that event's own layer (a dwell opening
    a layer belongs to the new layer)."""
    _, _, layer_of_line = read_program(PROGRAM)
    for ev in parse_gcode_text(PROGRAM):
        if type(ev) in (Segment, Dwell):
            assert layer_of_line[ev.line] == max(ev.layer, 0), ev
    assert layer_of_line[14] == 1          # G4 S1 right after the second ;LAYER_CHANGE
    assert layer_of_line[-1] == 1


def test_read_program_cuts_long_runs():
    text = ";LAYER_CHANGE\nG0 X0 Y0 Z0.2 F6000\n" + "".join("G1 X%d Y0 E0.1 F1200\n" % (i + 1)
                                                             for i in range(25))
    items, _, _ = read_program(text, max_run=10)
    assert [len(it.segments) for it in items] == [10, 10, 6]
    assert [s.line for it in items for s in it.segments] == list(range(2, 28))


@pytest.mark.parametrize("bad", [";@A9 R1 W1 N5", ";@A9 R1 W2", ";@A5 R1", ";@A9 R1 W2 N5 X3", ";@hello"])
def test_malformed_directive_names_its_line(bad):
    text = PROGRAM.replace(";@A9 R1 W2 N5", bad)
    with pytest.raises(GCodeError) as exc:
        read_program(text, "arm.gcode")
    assert exc.value.line == 8
    assert "arm.gcode:8" in str(exc.value)


def test_malformed_gcode_names_its_line():
    text = PROGRAM.replace("G1 X10 Y10 E0.5", "G1 X10 Y10 E0.5 Q7")
    with pytest.raises(GCodeError) as exc:
        read_program(text, "arm.gcode")
    assert exc.value.line == 9


# ------------------------------------------------------------ geometry
def test_waypoints_lie_on_the_commanded_lines(square, planner, arm, cell):
    segs = segments_by_line(SQUARE)
    b = square
    tips = world_tips(arm, planner.kin, b.Q)
    np.testing.assert_allclose(b.tip, tips, atol=1e-12)
    ks = cartesian_intervals(b)
    assert len(ks) >= 12
    for k in ks:
        s = segs[int(b.line[k])]
        A, B = bed_to_world(cell, [s.start, s.end])
        # both ends of the interval are on that G-code line
        d = seg_distance(tips[[k - 1, k]], A, B)
        assert d.max() <= 1e-6, (k, int(b.line[k]), d)
    # the last waypoint of every line is its end point
    for k in np.nonzero(b.line_end)[0]:
        s = segs[int(b.line[k])]
        assert np.linalg.norm(tips[k] - bed_to_world(cell, [s.end])[0]) <= 1e-6
    # a few by KDL, independently of the vectorised FK
    for k in (ks[0], ks[len(ks) // 2], len(b.t) - 1):
        T = arm.base_pose @ planner.kin.fk(b.Q[k])
        np.testing.assert_allclose(T[:3, 3], b.tip[k], atol=1e-9)
        np.testing.assert_allclose(T[:3, 2], [0.0, 0.0, -1.0], atol=1e-5)   # nozzle points down
    assert np.all(planner.kin.within_limits(b.Q))


def dense_deviation_mm(b, arm, kin, ks):
    """Largest distance (mm) between the joint-linearly interpolated nozzle
    and the chord of each interval in ``ks`` (chord ends = FK of the waypoints)."""
    u = np.linspace(0.0, 1.0, DENSE + 1)[1:-1]
    worst = np.zeros(len(ks))
    tips = world_tips(arm, kin, b.Q)
    for i, k in enumerate(ks):
        Qs = b.Q[k - 1] + u[:, None] * (b.Q[k] - b.Q[k - 1])
        worst[i] = seg_distance(world_tips(arm, kin, Qs), tips[k - 1], tips[k]).max() / MM
    return worst


@pytest.mark.parametrize("sample_mm", [10.0, 60.0])
def test_joint_interpolation_stays_within_a_tenth_of_a_millimetre(arm, cell, sample_mm):
    """Between waypoints the controller interpolates the joints linearly; the
    nozzle must not leave the commanded line by more than 0.1 mm.  With
    60 mm first samples the planner has to refine (more waypoints than
    samples)."""
    planner = MotionPlanner(arm, cell, sample_mm=sample_mm)
    b = plan_program(planner, SQUARE, arm.profile.home)[0]
    segs = segments_by_line(SQUARE)
    ext = [k for k in cartesian_intervals(b) if b.extrude[k]]
    assert len(ext) >= 8
    dev = dense_deviation_mm(b, arm, planner.kin, ext)
    assert dev.max() <= TOL_MM, dev.max()
    # also against the G-code line itself (not only the chord)
    u = np.linspace(0.0, 1.0, DENSE + 1)
    for k in ext:
        s = segs[int(b.line[k])]
        A, B = bed_to_world(cell, [s.start, s.end])
        Qs = b.Q[k - 1] + u[:, None] * (b.Q[k] - b.Q[k - 1])
        assert seg_distance(world_tips(arm, planner.kin, Qs), A, B).max() <= TOL_MM * MM + 1e-6
    # the figure the block reports is that measurement (midpoints are among the samples)
    assert b.max_deviation_mm <= dev.max() + 1e-3
    assert dev.max() <= 1.05 * b.max_deviation_mm + 1e-3
    assert 0.0 < b.max_deviation_mm <= TOL_MM
    if sample_mm == 60.0:
        n_samples = sum(int(np.ceil(np.linalg.norm(np.subtract(s.end, s.start)) / sample_mm)) or 1
                        for line, s in segs.items() if line >= FIRST_CARTESIAN_LINE)
        assert len(b.t) - 1 > n_samples, "the 0.1 mm limit needs refined waypoints here"


def test_an_extrusion_interval_never_has_zero_length(square):
    """An unretraction (E only) lays no bead."""
    b = square
    L = np.linalg.norm(np.diff(b.tip, axis=0), axis=1)
    assert np.all(L[b.extrude[1:]] > 1e-6)
    assert not b.extrude[0]
    retract = [k for k in range(1, len(b.t)) if b.line[k] in (12, 14)]
    assert len(retract) == 2 and not b.extrude[retract].any()
    np.testing.assert_allclose(b.e_mm[retract], [-0.8, 0.8])


HOP = """\
M83
;LAYER_CHANGE
G0 X-20 Y0 Z0.2 F9000
G1 X0 Y0 E1.0 F1200
G1 E-0.8 F2100
G0 Z0.8 F9000
G0 X20 Y10
G0 Z0.2
G1 E0.8 F2100
G1 X30 Y10 E0.5 F1200
"""


def test_unretraction_after_a_z_hop_lays_no_bead(planner, arm):
    """The program builder's travel (retract, lift, move, lower, unretract):
    the unretraction at the lowered point is E only, even though 0.8 +
    (0.2 - 0.8) is not exactly 0.2 in floating point.  It must neither count
    as a bead nor be timed as a zero-length move."""
    b = plan_program(MotionPlanner(arm, planner.cell), HOP, arm.profile.home)[-1]
    assert b.error is None
    k = [k for k in range(1, len(b.t)) if b.line[k] == 9]
    assert len(k) == 1
    k = k[0]
    assert not b.extrude[k]
    assert b.e_mm[k] == pytest.approx(0.8)
    assert b.t[k] - b.t[k - 1] == pytest.approx(0.8 / (2100 / 60.0), rel=1e-9)
    segs = segments_by_line(HOP)
    assert b.e_mm[b.extrude].sum() == pytest.approx(segs[4].e + segs[10].e, abs=1e-9)


# ------------------------------------------------------------ timing
def test_feedrate_and_joint_limits_on_the_commanded_motion(square, planner, arm):
    """The one timing law, checked on dense samples of the commanded motion
    (``block.motion``) by finite differences, independent of the spline's
    own bounds: no joint exceeds its speed (velocity x velocity_scaling) or
    the planned share of its acceleration; over every interval of a G-code
    line the nozzle's mean speed is at most the feedrate (the law never
    shortens the feedrate's time); along the long lines the nozzle runs at
    the feedrate away from the corners, where it rests; and the F120000
    travel is limited by the joints."""
    from ambots.trajectory import ACCEL_SHARE
    segs = segments_by_line(SQUARE)
    prof = arm.profile
    vmax = np.array([j.velocity for j in prof.joints]) * prof.velocity_scaling
    amax = np.array([j.acceleration for j in prof.joints]) * prof.velocity_scaling * ACCEL_SHARE
    b = square
    assert b.t[0] == 0.0 and np.all(np.diff(b.t) >= 0)
    h = 0.002
    ts = np.arange(0.0, b.t[-1], h)
    Q = b.motion.eval(ts)[0]
    V = np.diff(Q, axis=0) / h
    A = np.diff(V, axis=0) / h
    assert np.all(np.abs(V) <= vmax * (1 + 1e-3))
    assert np.all(np.abs(A) <= amax * (1 + 1e-3) + 1e-6)
    # the waypoints are on the motion at their times
    assert np.allclose(b.motion.eval(b.t)[0], b.Q, atol=1e-9)
    tips = world_tips(arm, planner.kin, b.Q)
    dt = np.diff(b.t)
    for k in cartesian_intervals(b):
        s = segs[int(b.line[k])]
        dist = np.linalg.norm(tips[k] - tips[k - 1]) / MM
        assert dist <= s.feedrate / 60.0 * dt[k - 1] + 1e-3, (k, dist)     # 1 um: the IK tolerance
    # nozzle speed along the motion
    X = world_tips(arm, planner.kin, Q) / MM
    speed = np.linalg.norm(np.diff(X, axis=0), axis=1) / h
    mid_t = ts[:-1] + h / 2
    line_at = b.line[np.clip(np.searchsorted(b.t, mid_t, side="right"), 1, len(b.t) - 1)]
    for line in (7, 8, 9, 10, 15, 16):
        feed = segs[line].feedrate / 60.0
        on = speed[line_at == line]
        assert on.max() <= feed * 1.01          # never above the feedrate (1 %: the chord vs the arc)
        assert np.median(on) == pytest.approx(feed, rel=0.02), (line, np.median(on), feed)
    travel = speed[line_at == 12]
    assert travel.max() < 0.5 * 120000.0 / 60.0, "the F120000 travel is faster than the joints allow"


def test_filament_of_each_line_is_shared_along_it(square):
    segs = segments_by_line(SQUARE)
    b = square
    for line, s in segs.items():
        if line < FIRST_CARTESIAN_LINE:
            continue
        ks = [k for k in range(1, len(b.t)) if b.line[k] == line]
        assert b.e_mm[ks].sum() == pytest.approx(s.e, abs=1e-9)
    net_on_moving = sum(s.e for s in segs.values() if s.extrude and s.start != s.end)
    assert b.e_mm[b.extrude].sum() == pytest.approx(net_on_moving, abs=1e-9)


def test_no_joint_jump(square, planner, arm):
    """Consecutive waypoints are close in joint space; the joint change per
    interval follows the nozzle's displacement (no configuration flip)."""
    b = square
    dq = np.max(np.abs(np.diff(b.Q, axis=0)), axis=1)
    assert dq.max() <= 0.35
    tips = world_tips(arm, planner.kin, b.Q)
    for k in cartesian_intervals(b):
        dist = np.linalg.norm(tips[k] - tips[k - 1])
        assert dq[k - 1] <= 0.02 + 20.0 * dist, (k, dq[k - 1], dist)   # <= 0.22 rad per 10 mm


# ------------------------------------------------------------ joint moves, errors
def test_first_move_away_from_the_nozzle_is_a_joint_move(planner, arm, cell):
    segments = [s for s in parse_gcode_text("G0 X20 Y-30 Z5 F9000\nG1 X30 Y-30 Z5 E0.4 F1200\n")]
    home = np.asarray(arm.profile.home, float)
    travel = planner.plan_moves(segments[:1], home)
    assert travel.planned == "joint" and travel.error is None
    np.testing.assert_allclose(travel.Q[0], home)
    np.testing.assert_allclose(travel.tip[-1], bed_to_world(cell, [(20, -30, 5)])[0], atol=1e-6)
    assert not travel.extrude.any()
    prof = arm.profile
    vmax = np.array([j.velocity for j in prof.joints]) * prof.velocity_scaling
    dt = np.diff(travel.t)
    assert np.all(dt > 0)
    assert np.all(np.abs(np.diff(travel.Q, axis=0)) / dt[:, None] <= vmax * (1 + 1e-9))
    # a run that starts with an extrusion elsewhere: a joint move to its start first
    both = planner.plan_moves(segments[1:], home)
    assert set(both.planned.split("+")) == {"joint", "cartesian"}
    k0 = int(np.argmax(both.extrude))
    np.testing.assert_allclose(both.tip[k0 - 1], bed_to_world(cell, [(20, -30, 5)])[0], atol=1e-6)
    assert not both.extrude[:k0].any()


UNREACHABLE = """\
G0 X0 Y0 Z0.2 F9000
G1 X40 Y0 E1.0 F1200
G1 X40 Y20 E0.5
G1 X3000 Y20 E50 F1200
G1 X0 Y0 E1.0
"""


def test_unreachable_point_ends_the_block_before_its_line(planner, arm, cell):
    b = plan_program(planner, UNREACHABLE, arm.profile.home)[-1]
    assert b.error is not None
    assert b.error.line == 4
    assert "unreachable" in b.error.message and "line 4" in str(b.error)
    assert b.line.max() <= 3
    # stops at the end of the last line it can complete
    np.testing.assert_allclose(b.tip[-1], bed_to_world(cell, [(40, 20, 0.2)])[0], atol=1e-6)
    assert b.line_end[-1] and b.line[-1] == 3


def test_unreachable_first_move(planner, arm):
    home = np.asarray(arm.profile.home, float)
    items, _, _ = read_program("G21\nG0 X3000 Y0 Z0.2 F9000\nG1 X3010 Y0 E1 F1200\n")
    b = planner.plan_moves(items[0].segments, home)
    assert b.error is not None and b.error.line == 2
    assert len(b.t) == 1 and b.duration == 0.0
    np.testing.assert_allclose(b.Q[0], home)
