"""The firmware's pace tied to the controller (ambots.pacing, no ROS): the
progress of the arm along the commanded samples from its joint states,
the runner's clock, the stamps and the gate of the outgoing messages; and
the whole loop -- the firmware's runner and stream, the pacer and a model
of a ros_control (scaled) joint trajectory controller -- with a controller
that keeps time, one 30 % slower and one that stops for 5 s: the runner is
never more than the lead ahead of the arm, no message leaves before the
arm got there, the arm's motion has no jumps; without the tie (the
firmware before) the same controllers leave the arm seconds behind its
reports."""
import math

import numpy as np
import pytest

from ambots.config import default_cell_path, load_cell
from ambots.motion import MotionPlanner
from ambots.pacing import ControllerModel, Pacer, Progress
from ambots.protocol import ArmState, LoadChunk, Start, Status
from ambots.runner import ArmRunner
from ambots.trajectory import SplineTiming, Stream, driver_spec

T0 = 1000.0          # ROS time of the start (s)


@pytest.fixture(scope="module")
def cell():
    return load_cell(default_cell_path())


def line(c0, n, dt, q0, v):
    """n samples from runner time c0, every dt, joints q0 + v t (2 joints)."""
    c = c0 + np.arange(n) * dt
    return c, np.asarray(q0, float) + np.outer(c - c0, v)


# ------------------------------------------------------------------ progress
def test_progress_is_the_nearest_point_of_the_commanded_path_and_never_goes_back():
    p = Progress(0.01, tolerance=0.01)
    c, Q = line(10.0, 51, 0.01, [0.0, 0.0], [1.0, -0.5])    # 0.5 s at 1 rad/s
    p.add(c, Q)
    assert p.measure(100.0, Q[0]) == pytest.approx(10.0)
    assert p.measure(100.1, [0.1234, -0.0617]) == pytest.approx(10.1234)      # between two samples
    assert p.lag == pytest.approx(100.1 - 10.1234)                              # in motion: ROS - runner time
    assert p.measure(100.2, [0.12, -0.06]) == pytest.approx(10.1234)          # a little behind: not back
    assert p.measure(100.25, [0.05, -0.025]) is None                            # far behind: no match
    assert p.measure(100.3, [0.2, 0.3]) is None and p.misses == 2             # off the path: held
    assert p.pi == pytest.approx(10.1234)
    assert p.measure(100.35, Q[-1]) is None                  # 0.38 s of motion in 0.15 s: not the arm
    assert p.measure(100.6, Q[-1]) == pytest.approx(10.5)
    assert p.pi == pytest.approx(p.end)


def test_progress_looks_only_as_far_as_the_arm_can_have_moved():
    # out and back: the same joints at 0.1 s and at 0.9 s
    p = Progress(0.01)
    c = 10.0 + np.arange(101) * 0.01
    Q = np.c_[0.5 - np.abs(c - 10.5), np.zeros(101)]
    p.add(c, Q)
    assert p.measure(100.0, Q[0]) == pytest.approx(10.0)
    assert p.measure(100.1, Q[10]) == pytest.approx(10.1)      # not 10.9, the same joints later on
    assert p.measure(100.2, Q[10]) == pytest.approx(10.1)      # standing there
    # a rest: every sample of it is where the arm is; of them the latest it can have got to
    p = Progress(0.01)
    p.add(10.0 + np.arange(200) * 0.01, np.zeros((200, 2)))
    assert p.measure(100.0, [0, 0]) == pytest.approx(10.05, abs=0.011)
    assert p.measure(100.1, [0, 0]) - p.first == pytest.approx(0.05 + 0.15, abs=0.021)    # 1.5 x 0.1 s on
    assert p.moving is False and p.lag is None                  # no lag from a rest


def test_a_rest_between_two_stretches_counts_as_no_motion():
    p = Progress(0.01)
    c1, Q1 = line(10.0, 11, 0.01, [0.0, 0.0], [1.0, 0.0])       # to 0.1 rad, at rest there
    c2, Q2 = line(40.0, 11, 0.01, [0.1, 0.0], [0.0, 1.0])       # 30 s later, on
    p.add(c1, Q1)
    p.add(c2, Q2)
    assert p.measure(100.0, Q1[0]) == pytest.approx(10.0)
    assert p.measure(100.1, Q1[-1]) == pytest.approx(40.0)     # at rest where the next stretch starts
    assert p.measure(100.15, [0.1, 0.05]) == pytest.approx(40.05)


# ------------------------------------------------------------------ the pacer
def test_the_clock_stays_within_the_lead_of_the_arm_and_follows_the_wall_at_rest():
    pc = Pacer(0.01, lead=0.3)
    assert pc.clock(T0) == T0 and pc.clock(T0 + 1.0) == T0 + 1.0      # no controller heard: the wall
    pc.measured(T0 + 1.0, [0.0, 0.0])
    c, Q = line(T0 + 1.0, 101, 0.01, [0.0, 0.0], [1.0, 0.0])         # 1 s of motion from runner time T0 + 1
    assert pc.stamp(c, Q, True, T0 + 1.0) == pytest.approx(0.3)
    assert pc.pending()
    R = [pc.clock(T0 + 1.0)]
    for k in range(1, 301):
        t = T0 + 1.0 + 0.01 * k
        # the arm stands still for 1 s (a controller that has not started), then keeps time
        pc.measured(t, Q[min(max(k - 100, 0), 100)])
        R.append(pc.clock(t))
        assert R[-1] - R[-2] <= 0.01 + 1e-9                            # never faster than the wall
        if pc.pending():
            assert R[-1] <= pc.progress.pi + 0.3 + 1e-9
        if k == 100:
            assert R[-1] == pytest.approx(T0 + 1.3)                    # held at progress + lead
            assert pc.released_until() == pytest.approx(T0 + 1.0, abs=0.011)
    assert not pc.pending() and pc.released_until() == math.inf      # the arm at the end
    # at rest the wall's rate, not the wall: the time the arm lost (it started 0.7 s after its
    # first sample's stamp) stays lost
    assert pc.clock(T0 + 5.0) == pytest.approx(R[-1] + 1.0)
    assert T0 + 5.0 - pc.R == pytest.approx(0.7, abs=0.02)


def test_stamps_follow_the_measured_lag_when_the_controller_falls_behind():
    pc = Pacer(0.01, lead=0.3, resync=0.005)
    pc.clock(T0)
    pc.measured(T0, [0.0, 0.0])
    c, Q = line(T0, 300, 0.01, [0.0, 0.0], [0.5, 0.0])
    assert pc.stamp(c[:50], Q[:50], True, T0) == pytest.approx(0.3)            # from rest: lead s ahead
    # the arm executes runner time T0 + 0.2 at T0 + 0.5: on time
    pc.measured(T0 + 0.5, Q[20])
    assert pc.stamp(c[49:100], Q[49:100], False, T0 + 0.5) == pytest.approx(0.3)
    # then at T0 + 1.2 only at T0 + 0.6 (lag 0.6 s): stamped anew, ``a + (c - pi)``
    pc.measured(T0 + 1.2, Q[60])
    assert pc.stamp(c[99:150], Q[99:150], False, T0 + 1.2) == pytest.approx(0.6)
    assert pc.resyncs == 1
    # within a stretch never earlier again (a controller does not run ahead of its commands)
    pc.measured(T0 + 1.5, Q[100])
    assert pc.stamp(c[149:200], Q[149:200], False, T0 + 1.5) == pytest.approx(0.6)


def test_chunk_stamps_are_on_the_sample_grid_of_their_stretch():
    from ambots.trajectory import Chunk, Segment
    pc = Pacer(0.01, lead=0.3)
    pc.clock(T0)
    seg = Segment(None, T0, 0.0, 1.0, 100, 0.0, True, -1, T0)
    c, Q = line(T0, 101, 0.01, [0.0, 0.0], [0.5, 0.0])
    z = np.zeros((51, 2))
    t1 = pc.stamps(Chunk(seg, 0, Q[:51], z, z, np.zeros(51), np.zeros(51)), T0)
    t2 = pc.stamps(Chunk(seg, 50, Q[50:], z, z, np.zeros(51), np.zeros(51)), T0 + 0.02)
    assert t1[0] == int(round((T0 + 0.3) * 1e9)) and t2[0] == t1[-1]
    assert set(np.diff(np.concatenate([t1, t2[1:]]))) == {10000000}


# ------------------------------------------------------------------ the controller model
def test_the_controller_model_maps_stamps_at_arrival_and_scales_its_time():
    ctl = ControllerModel([0.0], T0)
    ctl.command(T0, T0 + 0.5, [0.0, 1.0], [[0.0], [1.0]])
    assert ctl.advance(T0 + 0.5)[0] == 0.0 and ctl.advance(T0 + 1.0)[0] == pytest.approx(0.5)
    ctl.advance(T0 + 2.0, rate=0.0)                               # stopped for 1 s
    assert ctl.q[0] == pytest.approx(0.5)
    # a trajectory stamped 0.2 s after its arrival starts 0.2 s of the controller's time later
    ctl.command(T0 + 2.0, T0 + 2.2, [0.0, 1.0], [[0.7], [2.0]])
    assert ctl.advance(T0 + 2.2, rate=0.5)[0] == pytest.approx(0.6)        # still the first, at half speed
    assert ctl.advance(T0 + 2.4, rate=0.5)[0] == pytest.approx(0.7)        # the new one from its start
    assert ctl.advance(T0 + 3.4, rate=1.0)[0] == pytest.approx(0.7 + 1.3)


# ------------------------------------------------------------------ the whole loop
def square(x0, y0, side, layers=2):
    lines = ["G21", "G90", "M83"]
    corners = [(x0, y0), (x0 + side, y0), (x0 + side, y0 + side), (x0, y0 + side), (x0, y0)]
    for k in range(layers):
        z = 0.2 + 0.2 * k
        lines += [";LAYER_CHANGE", ";Z:%.1f" % z, "G0 X%.3f Y%.3f Z%.3f F6000" % (x0, y0, z)]
        lines += ["G1 X%.3f Y%.3f E%.5f F1200" % (x, y, side * 0.033) for x, y in corners[1:]]
        lines += [";@A3 R1"]                # a report of this arm's line and position
    return "\n".join(lines) + "\n"


class Loop:
    """One arm's firmware as nodes/firmware runs it with driver:=trajectory
    (runner, stream, pacer: clock every 20 ms, stamps, gate) and its
    controller (:class:`ControllerModel`, joint states every 10 ms),
    ``rate(t)``: the controller's speed at ROS time t.  Records what the
    arm did, when messages left, and the truth: the runner time of the
    commanded point the controller is at."""

    def __init__(self, cell, name, text, rate, tie=True, lead=0.3):
        arm = cell.arm(name)
        pl = MotionPlanner(arm, cell)
        pl.timing = SplineTiming.for_planner(pl)
        self.dt = driver_spec(arm.profile).sample_period
        self.runner = ArmRunner(arm, cell, planner=pl, now=T0)
        self.stream = Stream(self.dt, 0.5)
        self.runner.on_motion = self.stream.started
        self.pacer = Pacer(self.dt, lead=lead, tie=tie)
        self.ctl = ControllerModel(arm.profile.home, T0)
        self.rate, self.t = rate, T0
        self.held, self.sent, self.stamps = [], [], []
        self.tau, self.c = np.zeros(0), np.zeros(0)          # controller time -> runner time, as queued
        self.q, self.ahead = [], []
        self.runner.handle(LoadChunk(arm.id, text, chunk_id=1), now=T0)
        self.runner.handle(Start(arm.id), now=T0)

    def truth(self):
        return float(np.interp(self.ctl.uptime, self.tau, self.c)) if len(self.tau) else -math.inf

    def run(self, limit=120.0):
        k = 0
        while self.t < T0 + limit:
            k += 1
            self.t = T0 + 0.01 * k
            q = self.ctl.advance(self.t, self.rate(self.t))
            self.pacer.measured(self.t, q)
            self.q.append(q)
            if k % 2:
                continue
            R = self.pacer.clock(self.t)
            self.runner.advance(R)
            for ch in self.stream.update(R):
                S = self.pacer.stamps(ch, self.t) / 1e9
                self.stamps.append(S)
                self.ctl.command(self.t, S[0], S - S[0], ch.q)
                tau = self.ctl.uptime + (S - self.t)
                keep = self.tau < tau[0]
                c = ch.segment.start_time + (ch.first + np.arange(len(S))) * self.dt
                self.tau, self.c = np.concatenate([self.tau[keep], tau]), np.concatenate([self.c[keep], c])
            self.held += self.runner.outbox
            self.runner.outbox.clear()
            until = self.pacer.released_until()
            while self.held and self.held[0][0] <= until + 1e-6:
                T, m = self.held.pop(0)
                self.sent.append((T, m, self.truth()))
            self.ahead.append(R - self.truth())
            if self.runner.state is ArmState.DONE and not self.held and self.ctl.uptime >= self.ctl.t[-1]:
                break                     # done, and the controller has executed everything
        self.q = np.array(self.q)
        return self

    def jump(self):
        """Largest joint step between two joint states (rad)."""
        return float(np.abs(np.diff(self.q, axis=0)).max())

    def early(self):
        """Most a message left before the arm got to the runner time it was produced at (s)."""
        return max(T - truth for T, _, truth in self.sent)


def stalled(t0, t1):
    return lambda t: 0.0 if t0 < t <= t1 else 1.0


@pytest.fixture(scope="module")
def runs(cell):
    text = square(80.0, -10.0, 20.0)
    out = {}
    for tie in (True, False):
        for name, rate in (("nominal", lambda t: 1.0), ("slow", lambda t: 0.7),
                           ("stall", stalled(T0 + 3.0, T0 + 8.0))):
            out[name, tie] = Loop(cell, "ur10", text, rate, tie).run()
    return out


@pytest.mark.parametrize("name", ["nominal", "slow", "stall"])
def test_tied_to_the_controller_the_runner_never_runs_ahead_of_the_arm(runs, name):
    run, nominal = runs[name, True], runs["nominal", True]
    assert run.runner.state is ArmState.DONE
    # the runner's clock: at most the lead ahead of the arm (+ one joint state period, + the
    # last samples of a stretch, which the grid rounds up: the arm rests there already)
    assert max(run.ahead) <= 0.3 + 0.035
    # every message left when the arm had got there, to the commanded samples' resolution
    # (a block ends between two samples of the 10 ms grid; the arm rests in its last
    # sample): the reports of the square's corners too
    assert run.early() <= run.dt
    assert sum(isinstance(m, Status) for _, m, _ in run.sent) >= 4
    # the arm's motion has no jumps: no step between joint states much larger than keeping
    # time gives.  A re-stamped chunk still cuts a little motion at its splice (docs/firmware.md:
    # up to 29 ms in the rostests); with the faster timing of short moves the slow controller's
    # largest step is 1.29 x the nominal's (one splice in the move from home), without the tie
    # over 2 x (test_without_the_tie_the_reports_run_ahead_of_the_arm)
    assert run.jump() <= 1.5 * nominal.jump()
    # the same deposit: every line done
    assert run.runner.done_line == nominal.runner.done_line


def test_a_controller_that_keeps_time_gets_the_plans_stamps(runs):
    a, b = runs["nominal", True], runs["nominal", False]
    assert len(a.stamps) == len(b.stamps) and a.pacer.resyncs == 0
    for x, y in zip(a.stamps, b.stamps):
        assert np.abs(x - y).max() < 2e-7


def test_slower_or_stopped_controllers_take_longer_and_get_stamped_anew(runs):
    nominal, slow, stall = (runs[n, True] for n in ("nominal", "slow", "stall"))
    d = {k: v.t - T0 for k, v in (("nominal", nominal), ("slow", slow), ("stall", stall))}
    assert d["slow"] > 1.25 * d["nominal"] and d["stall"] > d["nominal"] + 4.5
    assert slow.pacer.resyncs > 5 and stall.pacer.resyncs >= 1


@pytest.mark.parametrize("name, early", [("slow", 0.5), ("stall", 3.0)])
def test_without_the_tie_the_reports_run_ahead_of_the_arm(runs, name, early):
    """The firmware before: the same controllers leave the arm behind its
    reports (a 5 s stop: by seconds) and the arm jumps where the controller
    takes up chunks stamped for a timeline it did not keep."""
    run = runs[name, False]
    assert run.early() > early
    assert run.jump() > 2 * runs["nominal", True].jump()
