"""ROS side of the firmware's real-controller output (``driver:=trajectory``):
the arm's motion as ``trajectory_msgs/JointTrajectory`` chunks for a
ros_control joint trajectory controller, the extruder's in step with it,
and the controller's joint states read back.

* The planner times every block for the controller
  (:class:`ambots.trajectory.SplineTiming`: within the arm's joint speed and
  acceleration limits, the driver's ``max_joint_speed``; a block starts and
  ends at rest) and the runner tells a :class:`ambots.trajectory.Stream`
  of every block it starts or resumes.
* Commands: ``<arm ns>/<driver.command_topic>`` (JointTrajectory, the
  driver's ``joint_names``): each chunk holds up to ``chunk_duration`` s of
  motion sampled every ``driver.sample_period`` s (positions, velocities,
  accelerations); its first point is the previous chunk's last one (the
  state the arm is commanded to be in at that instant, ``time_from_start``
  0 at ``header.stamp``), or -- after a rest -- the joints the arm rests at.
  A trajectory controller given a new trajectory from a future
  ``header.stamp`` keeps what it has up to then: the chunks join into one
  motion.  The firmware's clock leads the controller by ``delay`` s: motion
  the runner executes at simulated time t is stamped t + ``delay`` (in ROS
  time), so every chunk arrives before it is due (a chunk is sent about
  ``chunk_duration`` s before its start, the first chunk after a rest
  ``delay`` s before).
* Extruder: ``<arm ns>/<driver.extruder_topic>`` (JointTrajectory, one
  joint ``driver.extruder_joint``; position = metres of filament pushed
  since the node started, velocity = feed in m/s) with the same stamps and
  times as the arm's chunk: an extruder on a position-controlled joint of
  its own controller (e.g. a stepper behind ros_control) follows it.
* Joint states: ``<arm ns>/<driver.joint_states_topic>`` (sensor_msgs/
  JointState) from anyone but this node, carrying every driver joint name,
  is the controller's.  When the commanded motion has come to rest (and
  the arm has reached its end) the runner takes the measured joints once
  as where the arm is, so the next motion starts there.  The firmware's
  own ``/<arm>/joint_states`` then carry the measured joints (fresh ones,
  else what it commanded for now).
* Progress (:class:`ambots.pacing.Pacer`): once the controller's joint
  states come, they tie the firmware to what the arm has really executed:
  the runner's clock (:meth:`TrajectoryDriver.clock`) stays within
  ``delay`` s of the arm's progress along the commanded samples, chunks
  are stamped anew from the measured lag when the controller falls behind
  (a scaled or stopped controller), and the firmware holds the messages
  the runner produced until the arm has got there
  (:meth:`TrajectoryDriver.released_until`).  The stamps of a chunk follow
  from its runner times: ``c + shift`` (``shift`` = ``delay`` plus how far
  the runner's clock is behind ROS time, while nothing lags).
"""
import threading
import time
from collections import deque

import numpy as np
import rospy
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from ambots.pacing import Pacer
from ambots.trajectory import SplineTiming, Stream, driver_spec

__all__ = ["DRIVERS", "TrajectoryDriver", "arm_topic"]

#: what ``~driver`` accepts
DRIVERS = ("sim", "trajectory")
NS = 1000000000


def arm_topic(arm_name, topic):
    """A driver topic of the profile (relative) in the arm's namespace; an absolute one as it is."""
    return topic if topic.startswith("/") else "/%s/%s" % (arm_name, topic)


def _time(ns):
    return rospy.Time(int(ns // NS), int(ns % NS))


def _duration(ns):
    return rospy.Duration(int(ns // NS), int(ns % NS))


class TrajectoryDriver:
    """The controller output of one arm's firmware (see the module docstring).

    Parameters
    ----------
    arm : :class:`~ambots.config.ArmInstance`
    planner : the firmware's :class:`~ambots.motion.MotionPlanner` (gets its ``timing``)
    chunk_duration : s of motion per JointTrajectory
    delay : s from the firmware's clock to the controller's execution
    max_age : s a controller joint state stays fresh
    settle : s after the commanded motion ends before the measured joints are taken
    progress_tie : False: the runner on the wall clock and the plan's timeline
        whatever the controller does (the firmware before :mod:`ambots.pacing`;
        for comparisons only: it lets the arm fall behind its reports)
    """

    def __init__(self, arm, planner, chunk_duration=0.5, delay=0.3, max_age=0.5, settle=0.1,
                 progress_tie=True):
        self.arm = arm
        self.spec = driver_spec(arm.profile)
        self.timing = SplineTiming.for_planner(planner)
        planner.timing = self.timing
        self.stream = Stream(self.spec.sample_period, chunk_duration)
        self.delay, self.max_age, self.settle = float(delay), float(max_age), float(settle)
        self.pacer = Pacer(self.spec.sample_period, lead=self.delay, tie=progress_tie)
        self._lock = threading.Lock()         # the measurements and the pacer
        self._measured = None             # (q, monotonic time)
        self._history = deque(maxlen=16)  # (ns (M,), Q (M, n)) of recent chunks
        self._synced = False
        self.chunks = self.points = 0
        self.min_lead = None              # s: least time between sending a chunk and its start
        self.send_s = 0.0                 # s from stamping a chunk to its being sent (mean of the recent ones)
        self._stamped_at = None           # ROS time the chunks to publish were stamped for

    # ------------------------------------------------------------- ROS
    def start(self, runner):
        spec, name = self.spec, self.arm.name
        self.command_topic = arm_topic(name, spec.command_topic)
        self.extruder_topic = arm_topic(name, spec.extruder_topic)
        self.joint_states_topic = arm_topic(name, spec.joint_states_topic)
        self._cmd = rospy.Publisher(self.command_topic, JointTrajectory, queue_size=100)
        self._ext = rospy.Publisher(self.extruder_topic, JointTrajectory, queue_size=100)
        self._index = None
        rospy.Subscriber(self.joint_states_topic, JointState, self._on_joint_states, queue_size=10)
        runner.on_motion = self.stream.started
        rospy.loginfo("%s firmware: driver trajectory: %s (%d joints, %g ms samples, %g s chunks, %g s ahead), "
                      "extruder %s, joint states from %s, progress %s", name, self.command_topic,
                      len(spec.joint_names), spec.sample_period * 1e3, self.stream.chunk_n * spec.sample_period,
                      self.delay, self.extruder_topic, self.joint_states_topic,
                      "tied to them" if self.pacer.tie else "NOT tied to them (progress_tie false)")

    def _on_joint_states(self, msg):
        header = getattr(msg, "_connection_header", None) or {}
        if header.get("callerid") == rospy.get_name():
            return                        # this firmware's own joint states (same topic by default)
        try:
            index = {n: i for i, n in enumerate(msg.name)}
            q = np.array([msg.position[index[j]] for j in self.spec.joint_names], dtype=float)
        except (KeyError, IndexError):
            return
        if np.all(np.isfinite(q)):
            stamp = msg.header.stamp
            t = stamp.to_sec() if (stamp.secs or stamp.nsecs) else rospy.get_time()
            with self._lock:
                self._measured = (q, time.monotonic())
                self.pacer.measured(t, q)

    def measured(self):
        """The controller's latest joint vector if fresh, else None."""
        with self._lock:
            m = self._measured
        if m is None or time.monotonic() - m[1] > self.max_age:
            return None
        return m[0].copy()

    # ------------------------------------------------------------- the firmware's loop
    def clock(self, ros_now):
        """The runner's time now (ROS time ``ros_now``): within ``delay`` of
        what the controller has executed (:class:`~ambots.pacing.Pacer`)."""
        with self._lock:
            return self.pacer.clock(ros_now)

    def released_until(self):
        """Messages the runner produced up to this runner time may leave."""
        with self._lock:
            return self.pacer.released_until()

    def rest_joints(self, runner, ros_now):
        """With the runner between blocks, the commanded motion at rest for
        ``settle`` s and the arm at its end: the measured joints, once per
        rest (None otherwise)."""
        if self._synced or runner.block is not None:
            return None
        with self._lock:
            last_ns = self.pacer.last_ns
            resting = not (last_ns and ros_now * NS < last_ns + self.settle * NS)
            if not resting or (self.pacer.closed and self.pacer.pending()):     # the arm is not there yet
                return None
        q = self.measured()
        if q is not None:
            self._synced = True
        return q

    def pause(self, runner, now):
        """The runner was asked to pause (A2): brake after the committed motion."""
        if runner.pause_requested and runner.block is not None:
            j = self.stream.pause(runner, now, self.timing)
            if j is not None:
                runner.pause_at = (runner.block, j)

    def abort(self, runner, now):
        """Before the runner drops its block (A4): brake; returns the joints where the arm stops, or None."""
        return self.stream.abort(runner, now, self.timing.amax)

    def update(self, now, ros_now):
        """The chunks due at the runner's time ``now`` (lock held by the
        caller; ``ros_now``: the same instant in ROS time), each with the
        stamps of its points (ns): ``[(chunk, t_ns (M,))]`` for :meth:`publish`."""
        out = []
        for c in self.stream.update(now):
            with self._lock:        # the stamps as of when the chunk will be out (the lag grows meanwhile)
                out.append((c, self.pacer.stamps(c, ros_now + self.send_s)))
        self._stamped_at = ros_now
        return out

    def publish(self, chunks):
        """Send ``chunks`` (from :meth:`update`)."""
        for c, t_ns in chunks:
            traj = JointTrajectory()
            traj.header.stamp = _time(int(t_ns[0]))
            traj.joint_names = list(self.spec.joint_names)
            ext = JointTrajectory()
            ext.header.stamp = traj.header.stamp
            ext.joint_names = [self.spec.extruder_joint]
            # one conversion of each array to Python floats, then one point per sample
            for d, q, v, a, e, de in zip((t_ns - t_ns[0]).tolist(), c.q.tolist(), c.v.tolist(), c.a.tolist(),
                                         np.asarray(c.e, float).tolist(), np.asarray(c.de, float).tolist()):
                tfs = _duration(d)
                traj.points.append(JointTrajectoryPoint(positions=q, velocities=v, accelerations=a,
                                                        time_from_start=tfs))
                ext.points.append(JointTrajectoryPoint(positions=[e], velocities=[de], time_from_start=tfs))
            lead = t_ns[0] / NS - rospy.get_time()
            self.min_lead = lead if self.min_lead is None else min(self.min_lead, lead)
            self._cmd.publish(traj)
            self._ext.publish(ext)
            if self._stamped_at is not None:         # the rest of the step, building, sending
                self.send_s += 0.3 * (rospy.get_time() - self._stamped_at - self.send_s)
            self._history.append((t_ns, c.q))
            self._synced = False
            self.chunks += 1
            self.points += len(c.q)

    def commanded(self, ros_now):
        """The joints the controller is commanded to have at ``ros_now`` (s), or None before any command."""
        if not self._history:
            return None
        t = int(ros_now * NS)
        for t_ns, Q in reversed(self._history):
            if t >= t_ns[0]:
                if t >= t_ns[-1]:
                    return Q[-1].copy()
                k = int(np.searchsorted(t_ns, t, side="right")) - 1
                u = (t - t_ns[k]) / float(t_ns[k + 1] - t_ns[k])
                return Q[k] + u * (Q[k + 1] - Q[k])
        return self._history[0][1][0].copy()

    def stats(self):
        with self._lock:
            pacing = self.pacer.stats()
        return {"driver": "trajectory", "command_topic": self.command_topic, "chunks": self.chunks,
                "points": self.points, "sample_period": self.spec.sample_period,
                "min_lead_s": None if self.min_lead is None else round(self.min_lead, 4),
                "progress_tie": self.pacer.tie, **pacing}
