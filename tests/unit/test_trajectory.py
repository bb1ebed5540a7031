"""Trajectories for a real controller (ambots.trajectory, no ROS): the
driver's figures from the profile, blocks timed as cubic splines within the
joint limits (checked exactly and by finite differences of samples), the
nozzle kept on the G-code lines, and the firmware's runner streamed into
chunks: continuous, on the controller's sample grid, the extruder in step,
a pause braking to rest at the end of a line, A4 braking at once."""
import dataclasses
import math

import numpy as np
import pytest

from test_runner import PROGRAM
from ambots.config import default_cell_path, load_cell
from ambots.motion import MotionPlanner, read_program
from ambots.protocol import ArmState, ClearChunk, LoadChunk, Pause, Resume, Start
from ambots.runner import ArmRunner
from ambots.trajectory import (DEFAULT_SAMPLE_PERIOD, ACCEL_SHARE, SplineTiming, Stream, driver_spec,
                               finite_differences, joint_limits, retime, smooth)

MM = 1e-3


@pytest.fixture(scope="module")
def cell():
    return load_cell(default_cell_path())


def square(x0, y0, side, z=0.2, layers=1, feed=1200):
    lines = ["G21", "G90", "M83"]
    corners = [(x0, y0), (x0 + side, y0), (x0 + side, y0 + side), (x0, y0 + side), (x0, y0)]
    for k in range(layers):
        zz = z + 0.2 * k
        lines += [";LAYER_CHANGE", ";Z:%.1f" % zz, "G0 X%.3f Y%.3f Z%.3f F6000" % (x0, y0, zz)]
        lines += ["G1 X%.3f Y%.3f E%.5f F%d" % (x, y, side * 0.033, feed) for x, y in corners[1:]]
    return "\n".join(lines) + "\n", np.array(corners, float)


def planner(cell, name):
    pl = MotionPlanner(cell.arm(name), cell)
    pl.timing = SplineTiming.for_planner(pl)
    return pl


# ------------------------------------------------------------------ the profile's driver section
def test_driver_figures_come_from_the_profile(cell):
    kin, ur = cell.arm("kinova").profile, cell.arm("ur10").profile
    k = driver_spec(kin)
    assert (k.sample_period, k.max_joint_speed) == (0.001, 0.8727)          # the Kortex interface
    assert k.command_topic == "joint_trajectory_controller/command"
    assert k.joint_names == kin.driver_joint_names
    u = driver_spec(ur)
    assert (u.sample_period, u.max_joint_speed) == (DEFAULT_SAMPLE_PERIOD, None)
    assert (u.joint_states_topic, u.extruder_topic, u.extruder_joint) == \
        ("joint_states", "extruder_controller/command", "extruder")
    # the limits the arm uses: x velocity_scaling, speeds capped by the interface's
    v, a = joint_limits(kin)
    np.testing.assert_allclose(v, [j.velocity * 0.5 for j in kin.joints])
    np.testing.assert_allclose(a, [j.acceleration * 0.5 for j in kin.joints])
    full = dataclasses.replace(kin, velocity_scaling=1.0)
    np.testing.assert_allclose(joint_limits(full)[0], 0.8727)              # 1.3963 and 1.2218 capped
    assert MotionPlanner(cell.arm("kinova"), cell).vmax.tolist() == v.tolist()


# ------------------------------------------------------------------ timing one block
def sampled(block, dt):
    t = np.arange(0.0, block.duration + dt, dt)
    return t, block.motion.eval(np.minimum(t, block.duration))


@pytest.mark.parametrize("name", ["kinova", "ur10"])
def test_a_square_is_timed_within_the_limits_and_stays_on_its_lines(cell, name):
    arm = cell.arm(name)
    text, corners = square(-10.0, -10.0, 20.0)
    item = read_program(text)[0][0]
    plain = MotionPlanner(arm, cell).plan_moves(item.segments, arm.profile.home)
    pl = planner(cell, name)
    b = pl.plan_moves(item.segments, arm.profile.home)
    vmax, amax = joint_limits(arm.profile)
    # the same waypoints, never faster than planned (to 1e-5 of a duration: the two runs' waypoints
    # may differ in the last bits, and the law's stretch decides limit by limit whether a segment is
    # over; one clean-clone run saw 1.5e-6 s on a 0.58 s segment)
    np.testing.assert_allclose(b.Q, plain.Q, atol=1e-12)
    assert np.all(np.diff(b.t) >= np.diff(plain.t) * (1.0 - 1e-5) - 1e-12)
    sp = b.motion.pieces[0].spline
    # the spline passes through every waypoint at its time, at rest at both ends
    q, v, a, e, de = b.motion.eval(b.t)
    np.testing.assert_allclose(q, b.Q, atol=1e-12)
    assert not v[0].any() and not v[-1].any()
    # exact bounds per segment, and the finite differences of 1 ms samples
    assert (sp.vseg / vmax).max() <= 1 + 1e-9 and (sp.aseg / amax).max() <= ACCEL_SHARE + 1e-9
    t, (q, v, a, e, de) = sampled(b, 0.001)
    V, A = finite_differences(t, q)
    assert (np.abs(V) / vmax).max() <= 1 + 1e-9
    assert (np.abs(A) / amax).max() <= ACCEL_SHARE + 1e-6
    # the velocities and accelerations given are the derivatives of the positions
    np.testing.assert_allclose(V, 0.5 * (v[1:] + v[:-1]), atol=2e-3 * np.abs(v).max())
    # the extruder: the program's filament, only while extruding
    assert e[-1] == pytest.approx(4 * 0.66 * MM, abs=1e-12)
    assert np.diff(e).min() >= -1e-15
    # the nozzle stays within the planner's 0.1 mm of the square while extruding; rests at the corners
    P = pl.world_to_bed_mm(pl.tip_world(q))
    ext = np.concatenate([[False], np.diff(e) > 0])
    A0 = np.c_[corners[:-1], np.full(4, 0.2)]
    B0 = np.c_[corners[1:], np.full(4, 0.2)]
    d = B0 - A0
    u = np.clip(np.einsum("nij,ij->ni", P[ext][:, None] - A0[None], d) / np.einsum("ij,ij->i", d, d), 0, 1)
    dist = np.linalg.norm(P[ext][:, None] - (A0[None] + u[..., None] * d[None]), axis=2).min(axis=1)
    assert dist.max() < 0.1
    tips = pl.world_to_bed_mm(b.tip)
    # at a corner the arm rests or rounds it within the 0.1 mm above (short ramp
    # pieces near the corners: RAMP_MM); away from the corners it never rests
    near_corner = np.all(np.abs(np.abs(tips[:, :2]) - 10.0) <= 3.0 + 1e-6, axis=1)
    rest = np.all(sp.V == 0, axis=1)
    assert not rest[1:-1][~near_corner[sp.idx][1:-1]].any()


def test_retractions_and_hops_rest_and_push_filament_in_time(cell):
    pl = planner(cell, "kinova")
    items = [it for it in read_program(PROGRAM)[0] if hasattr(it, "segments")]
    q = np.array(cell.arm("kinova").profile.home)
    total = 0.0
    for it in items:
        b = pl.plan_moves(it.segments, q)
        t, (Q, v, a, e, de) = sampled(b, 0.001)
        e_mm = sum(s.e for s in it.segments)
        assert e[-1] / MM == pytest.approx(e_mm, abs=1e-9)
        assert e.min() / MM >= -0.8 - 1e-9          # the retraction pulls back 0.8 mm
        V, A = finite_differences(t, Q)
        vmax, amax = joint_limits(cell.arm("kinova").profile)
        assert (np.abs(A) / amax).max() <= ACCEL_SHARE + 1e-6
        total += e_mm
        q = b.Q[-1]
    assert total == pytest.approx(9.2, abs=1e-9)             # 2 + 0.4 + 2 - 0.8 + 0.8 + 2 + 2 + 0.8


def test_smooth_never_shortens_and_respects_any_limits():
    rng = np.random.default_rng(3)
    Q = np.cumsum(rng.normal(0, 0.05, (40, 3)), axis=0)
    Q[10] = Q[9]                                          # a pause in the motion
    t = np.concatenate([[0.0], np.cumsum(rng.uniform(0.01, 0.2, 39))])
    vmax, amax = np.array([0.5, 0.3, 1.0]), np.array([2.0, 1.0, 3.0])
    tn, sp = smooth(t, Q, vmax, amax)
    assert np.all(np.diff(tn) >= np.diff(t) - 1e-12)
    assert (sp.vseg / vmax).max() <= 1 + 1e-9 and (sp.aseg / amax).max() <= 1 + 1e-9
    assert not sp.V[[0, 9, 10, 11, -1]].any()             # at rest at the ends and around the pause
    # sampled to its end (the measure takes the motion to be at rest after the last sample)
    ts = np.append(np.arange(0, tn[-1], 0.0007), tn[-1])
    V, A = finite_differences(ts, sp.eval(ts)[0])
    assert (np.abs(V) / vmax).max() <= 1 + 1e-9 and (np.abs(A) / amax).max() <= 1 + 1e-6
    # and the finite differences at the waypoints themselves (as the export measures them)
    assert (np.abs(finite_differences(tn, Q)[1]) / amax).max() <= 1 + 1e-6
    # retime alone meets the waypoint measure only
    tr = retime(t, Q, amax)
    assert (np.abs(finite_differences(tr, Q)[1]) / amax).max() <= 1 + 1e-6


def zigzag(turn_deg, n=6, step=0.05):
    """Joint-space waypoints (n + 1, 2): ``n`` steps of ``step`` rad, the path
    turning by ``turn_deg`` at every inner waypoint."""
    pts, d, th = [np.zeros(2)], np.array([1.0, 0.0]), math.radians(turn_deg)
    for _ in range(n):
        pts.append(pts[-1] + step * d)
        d = np.array([d[0] * math.cos(th) - d[1] * math.sin(th), d[0] * math.sin(th) + d[1] * math.cos(th)])
    return np.array(pts)


@pytest.mark.parametrize("turn", [0, 30, 60, 90, 120, 135, 170])
def test_a_corner_is_never_passed_slower_than_stopping_there(turn):
    """Stopping at every waypoint, a cubic from rest to rest over a joint
    change L at acceleration limit a takes sqrt(6 L / a) (its acceleration
    peaks at 6 L / T^2 at its ends), unless the speed limit binds (not
    here): the sum over the steps, on the joint that needs longest, is what
    the path takes stopping at each corner.  Passing a corner may only be
    faster; straight on, much faster.  (Before the corner rule, passing 135
    deg turns took 2.42 s against 2.14 s stopping.)"""
    Q = zigzag(turn)
    vmax, amax = np.array([1.0, 1.0]), np.array([2.0, 2.0])
    tn, sp = smooth(np.linspace(0.0, 1e-3, len(Q)), Q, vmax, amax, joint_tolerance=1e9)
    stopping = sum(max(math.sqrt(6.0 * abs(dq) / a) for dq, a in zip(step, amax)) for step in np.diff(Q, axis=0))
    assert tn[-1] <= stopping * (1 + 1e-6)
    assert (sp.aseg / amax).max() <= 1 + 1e-9 and (sp.vseg / vmax).max() <= 1 + 1e-9
    if turn >= 90:                         # nothing of the speed carries on: the arm rests there
        assert not sp.V[1:-1].any()
    if turn <= 30:
        assert tn[-1] < 0.6 * stopping


# ------------------------------------------------------------------ the runner, streamed
def stream_run(cell, name, text, events=(), until=600.0, tick=0.02, q0=None):
    """Run ``text`` on the firmware's runner with the trajectory timing, a
    tick at a time; ``events``: (time, message) handed to it (A2 with the
    driver's pause plan, A4 with its stop).  Returns (runner, timing, chunks, log)."""
    arm = cell.arm(name)
    pl = planner(cell, name)
    r = ArmRunner(arm, cell, planner=pl, q0=q0)
    st = Stream(driver_spec(arm.profile).sample_period, 0.5)
    r.on_motion = st.started
    r.handle(LoadChunk(arm.id, text, chunk_id=1))
    r.handle(Start(arm.id), now=0.0)
    chunks, log, pending = [], [], sorted(events, key=lambda e: e[0])
    now = 0.0
    while now < until and (r.state not in (ArmState.DONE, ArmState.ERROR, ArmState.IDLE) or pending):
        now += tick
        while pending and pending[0][0] <= now:
            msg = pending.pop(0)[1]
            stop_q = st.abort(r, now, pl.timing.amax) if isinstance(msg, ClearChunk) else None
            r.handle(msg, now=now)
            if stop_q is not None:
                r.q = stop_q
            if isinstance(msg, Pause):
                j = st.pause(r, now, pl.timing)
                if j is not None:
                    r.pause_at = (r.block, j)
                    log.append(("pause_at", r.block, j))
            log.append((type(msg).__name__, now, r.state))
        r.advance(now)
        chunks += st.update(now)
    while True:
        more = st.update(now + 1e6)
        if not more:
            break
        chunks += more
    return r, pl.timing, st, chunks, log


def joined(chunks, dt):
    """(t, Q, E, V) of the chunks, checked: on the grid, each starting where the last one ended."""
    T, Q, E, V = [], [], [], []
    for c in chunks:
        t = c.segment.start_time + (c.first + np.arange(len(c.q))) * dt
        if T:
            assert t[0] >= T[-1][-1] - 1e-9
            np.testing.assert_array_equal(c.q[0], Q[-1][-1])
            if c.first > 0:
                assert t[0] == pytest.approx(T[-1][-1], abs=1e-9)
                t, c_q, c_e, c_v = t[1:], c.q[1:], c.e[1:], c.v[1:]
            else:
                assert not Q[-1][-1].any() or not np.abs(V[-1][-1]).max() > 1e-9   # a new stretch after rest
                c_q, c_e, c_v = c.q, c.e, c.v
        else:
            c_q, c_e, c_v = c.q, c.e, c.v
        T.append(t)
        Q.append(c_q)
        E.append(c_e)
        V.append(c_v)
    return np.concatenate(T), np.concatenate(Q), np.concatenate(E), np.concatenate(V)


def within_limits(arm, t, Q, share=1.0):
    vmax, amax = joint_limits(arm.profile)
    V, A = finite_differences(t - t[0], Q)
    return (np.abs(V) / vmax).max(), (np.abs(A) / amax).max()


def test_the_runner_streams_chunks_on_the_controllers_grid(cell):
    arm = cell.arm("kinova")
    r, timing, st, chunks, _ = stream_run(cell, "kinova", PROGRAM)
    assert r.state is ArmState.DONE
    t, Q, E, V = joined(chunks, 0.001)
    assert len(chunks) > 10 and max(len(c.q) for c in chunks) == 501       # 0.5 s chunks of 1 ms samples
    np.testing.assert_array_equal(Q[0], arm.profile.home)                   # from the current joint state
    np.testing.assert_allclose(Q[-1], r.q, atol=1e-12)
    assert not V[-1].any()
    rv, ra = within_limits(arm, t, Q)
    assert rv <= 1 + 1e-9 and ra <= ACCEL_SHARE + 1e-6
    assert E[-1] / MM == pytest.approx(9.2, abs=1e-9)                       # every E of the program
    # the stream keeps to the runner's clock: it ends when the runner's last block did, to the sample
    assert t[-1] == pytest.approx(r.stats.done_s, abs=2 * 0.001 * len(r.stats.plans) + 1e-6)


SQUARES = square(-15.0, -15.0, 30.0, layers=3)[0]     # one block of 13 moves: the pause brakes inside it


@pytest.mark.parametrize("program, times", [(PROGRAM, (1.3, 2.9, 4.4)), (SQUARES, None)],
                         ids=["short blocks", "one long block"])
def test_a_pause_brakes_to_rest_at_a_line_end_and_resume_lays_the_same(cell, program, times):
    arm = cell.arm("kinova")
    r0, _, _, chunks0, _ = stream_run(cell, "kinova", program)
    t0, Q0, E0, V0 = joined(chunks0, 0.001)
    if times is None:       # in the long block, at full speed along a line: after 15, 55 and 80 % of it
        speed = np.abs(V0).max(axis=1)
        late = t0 >= 0.15 * t0[-1]                         # after the joint move from home
        fast = late & (speed >= 0.9 * speed[late].max())
        times = tuple(float(t0[np.argmax(fast & (t0 >= f * t0[-1]))]) for f in (0.15, 0.55, 0.8))
    braked = 0
    for when in times:
        r, timing, st, chunks, log = stream_run(cell, "kinova", program,
                                                [(when, Pause(arm.id)), (when + 6.0, Resume(arm.id))])
        assert r.state is ArmState.DONE
        t, Q, E, V = joined(chunks, 0.001)
        rv, ra = within_limits(arm, t, Q)
        assert rv <= 1 + 1e-9 and ra <= 1 + 1e-6
        # the same path and filament as without the pause
        assert E[-1] == pytest.approx(E0[-1], abs=1e-12)
        np.testing.assert_allclose(Q[-1], Q0[-1], atol=1e-12)
        # it came to rest (a pause in the commands) at a waypoint ending a G-code line
        gap = np.nonzero(np.diff(t) > 0.5)[0]
        assert len(gap) == 1
        k = gap[0]
        assert not V[k].any() or np.abs(V[k]).max() < 1e-9
        plans = [e for e in log if e[0] == "pause_at"]
        if plans:
            _, block, j = plans[0]
            assert block.line_end[j]
            np.testing.assert_array_equal(Q[k], block.Q[j])
            braked += any(p.c is not None for p in block.motion.pieces)
            assert t[k] > when                     # after what was committed when A2 came
    if program is SQUARES:
        assert braked == len(times)                # it braked in the middle of the block every time


def test_a4_while_moving_brakes_at_once_and_stops_the_extruder(cell):
    arm = cell.arm("kinova")
    for when in (1.0, 3.1):
        r, timing, st, chunks, log = stream_run(cell, "kinova", PROGRAM, [(when, ClearChunk(arm.id))])
        assert r.state is ArmState.IDLE
        t, Q, E, V = joined(chunks, 0.001)
        rv, ra = within_limits(arm, t, Q)
        assert rv <= 1 + 1e-9 and ra <= 1 + 1e-6
        assert not np.abs(V[-1]).max() > 1e-9
        np.testing.assert_allclose(r.q, Q[-1], atol=1e-12)        # the runner knows where the arm stopped
        assert t[-1] < when + 0.5 + 0.5 + 1.0                     # committed (<= 2 chunks ahead), then braking
        moving = np.nonzero(np.any(np.diff(Q, axis=0) != 0, axis=1))[0]
        assert np.ptp(E[moving[-10]:]) == 0.0
