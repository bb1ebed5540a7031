"""ROS side of one arm's firmware: :class:`ambots.runner.ArmRunner` (the
state machine, no ROS) on a simulated clock, talking to the communication
hub, publishing joint states, the deposit and run statistics.

* Inbox ``topics.arm_topic(arm)`` (std_msgs/String, from the hub): every
  numbered message is acknowledged (``A8 R<sender> Q<q> S<arm id>``) and,
  the first time only (:class:`~ambots.reliable.Receiver`,
  ``Verdict.NEW``), queued for the runner; an A8 settles one of our
  messages.  Text that cannot be decoded is logged and ignored (the hub has
  validated it; a corrupt copy is not acknowledged, so it comes again).
* Outbox: the runner's A10/A11 (and directives for other arms) go to
  ``topics.HUB_TOPIC`` numbered by a :class:`~ambots.reliable.Sender`
  (``S<arm id>``, Q from the wall clock) and are sent again until the hub
  acknowledges them.  While printing, an A10 with the position is also sent
  every ``report_period`` s when the line, layer or percentage changed.
* The clock: one loop thread owns the runner (every access holds
  ``self.lock``; the subscriber callbacks only queue commands, so an ack is
  never held up behind a long planning step).  The runner runs on ROS time,
  the one clock of the cell: in simulation ``/clock`` (``use_sim_time``;
  ``nodes/clock``, :mod:`ambots.clock`), with a real arm the wall.  Each
  iteration executes the commands that arrived at the current instant and
  advances the runner to it; in simulation the node then tells the clock
  (``topics.CLOCK_READY_TOPIC``) where it stands: its instant, its next
  event (the end of the block it executes), its messages in flight and the
  hub's messages it executed, so that the clock moves on only when every
  arm has done its step and every message is delivered.
* ``topics.joint_states_topic(arm)``: sensor_msgs/JointState at every
  new instant of the simulated clock, stamped with it (with the wall clock,
  at ``rate`` Hz), names ``<arm>/<joint>``, positions ``runner.joints(now)``;
  robot_state_publisher of the cell turns them into TF (start cell.launch
  with ``publish_home:=false``).
* :data:`ambots.rviz.DEPOSIT_TOPIC`: visualization_msgs/MarkerArray of
  TRIANGLE_LIST markers (ns = arm name, world frame, the arm's filament
  colour, one colour per triangle: :class:`DepositMarkers`), one marker
  per layer of a run (a new marker id after ``max_beads`` beads); beads are
  the nozzle positions reached (forward kinematics of the executed joint
  waypoints), drawn as shaded tubes (:mod:`ambots.tubes`).  Only changed
  markers are republished, at most ``marker_rate`` Hz, built outside the
  loop's lock; a new subscriber gets them all.
* ``~stats`` (``/<arm>/firmware/stats``, std_msgs/String, latched): JSON
  with the state, line, layer, percent, the runner's :class:`RunStats` and
  what the arm knows of the others, whenever its state or another arm's
  state changes.
* Joint moves (to a program's first point, after a park, A7) are planned
  around obstacles: the bed, and with a real arm (``driver`` trajectory)
  the other arms of the cell at their latest joint states (subscribed),
  with ``clearance_mm`` of margin; the G-code's own moves follow the
  program (the coordinator's barriers keep them apart)
  (:mod:`ambots.collision`).  A move that only the other arms block waits
  for them (:class:`~ambots.runner.ArmRunner`); the wait is logged once,
  with what the refused pose is too close to (obstacle, clearance in mm,
  closest links: :meth:`CollisionCheck.explain`).
* ``driver``: ``"sim"`` (the above: the arm is simulated, joint states are
  the runner's) or ``"trajectory"`` (real time only): the motion also goes
  to the arm's joint trajectory controller as JointTrajectory chunks, the
  extruder's in step, and the controller's joint states are read back
  (:mod:`ambots.ros.driver`); pause (A2) brakes after what was sent, to
  rest at the end of a G-code line, a stop (A12) to rest on the first
  waypoint it can, resumable; A4 while moving brakes at once.  Once
  the controller's joint states come, the runner's clock follows what the
  arm has really executed (:mod:`ambots.pacing`): it runs at most
  ``command_delay`` s ahead of the arm's progress along the commanded
  motion, and the messages the runner produces (A10/A11, directives for
  other arms) leave only when the arm has got as far as the runner was
  when it produced them, so a barrier of another arm is never released
  by progress this arm has not made.  The other arms' reports count from
  when they arrive (their M word is their own arm's time).
"""
import dataclasses
import json
import math
import queue
import threading
import time
from dataclasses import asdict

import numpy as np
import rosgraph
import rospy
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, MultiArrayDimension, String
from visualization_msgs.msg import Marker, MarkerArray

from ambots import topics
from ambots.checkpoint import StateStore
from ambots.clock import ArmReady
from ambots.collision import CollisionCheck
from ambots.deposit import bead_area_m2
from ambots.errors import ProtocolError
from ambots.motion import MotionPlanner
from ambots.protocol import (HUB, Ack, ArmState, ClearChunk, LoadChunk, Pause, SendPosition, Start, Status, Stop,
                             decode, encode)
from ambots.reliable import Receiver, Sender, Verdict, seq_seed
from ambots.ros import ASeriesLog, debug_param, going_down
from ambots.ros.driver import DRIVERS, TrajectoryDriver
from ambots.ros.markers import ArrayMarker, ArrayMarkers
from ambots.runner import ArmRunner, Bead, RunStats
from ambots.rviz import DEPOSIT_TOPIC
from ambots.tubes import SIDES, exposed, face_normals, merge_beads, shade, tube_triangles
from ambots.units import MM

__all__ = ["parse_speed", "DepositMarkers", "CollisionCheck", "FirmwareNode"]

_BARRIER = {ArmState.PRINTING, ArmState.WAITING}


def parse_speed(value):
    """``~speed`` -> float factor (> 0), or None for ``max``."""
    if isinstance(value, str) and value.strip().lower() in ("max", "inf", "fast"):
        return None
    try:
        speed = float(value)
    except (TypeError, ValueError):
        raise ValueError("speed must be a number > 0 or 'max', got %r" % (value,)) from None
    if not np.isfinite(speed) or speed <= 0:
        raise ValueError("speed must be a number > 0 or 'max', got %r" % (value,))
    return speed


class DepositMarkers:
    """Batches an arm's beads into shaded ``TRIANGLE_LIST`` markers
    (:mod:`ambots.tubes`: the beads merged into straight segments, each a
    tube of ``sides`` faces ``height_m`` tall with the bead's cross-section,
    one colour per face lit by a fixed light): one marker per layer of a
    run, a new one every ``max_beads`` beads.  Marker ids count up over the
    node's life (a new run never overwrites an earlier deposit).

    Segments buried in the deposit (:func:`ambots.tubes.exposed` over all
    of the arm's beads, the bed's top ``floor_z`` closing it from below)
    are left out: :meth:`update_exposure` finds them again at most every
    ``exposure_period`` s, and the markers whose set changed are sent
    again.  Until then (and for segments laid since) everything is drawn.

    Thread-safe: :meth:`add` and :meth:`take_changed` only copy arrays
    under an internal lock; :meth:`build` (the triangles and the message)
    and :meth:`update_exposure` run outside it; the newest build of every
    marker is kept for :meth:`all`."""

    def __init__(self, ns, frame, colour, height_m, max_beads=2000, sides=SIDES, floor_z=None,
                 exposure_period=10.0, cell_m=4e-4):
        self.ns, self.frame, self.colour, self.height = ns, frame, tuple(colour), float(height_m)
        self.max_beads, self.sides = int(max_beads), int(sides)
        self.floor_z, self.exposure_period, self.cell = floor_z, float(exposure_period), float(cell_m)
        self._lock = threading.Lock()
        self._beads = {}          # id -> [(K, 8) rows of p0 xyz, p1 xyz, area m^2, G-code line]
        self._count = {}          # id -> beads in the marker
        self._version = {}        # id -> changes of the marker's look so far (beads, exposure)
        self._shown = {}          # id -> (beads, (M,) bool over the merge of those beads), or None: all
        self._merged = {}         # id -> (beads, starts, ends, area): the merge of its first beads
        self._built = {}          # id -> (version, Marker), the newest built
        self._open = {}           # layer -> id of the marker still being filled
        self._dirty = set()
        self._next_id = 0
        self._exposure_at = -math.inf
        self._exposure_of = None  # the bead counts the last exposure was found for

    def new_run(self):
        """Beads from now on go to new markers."""
        with self._lock:
            self._open.clear()

    def _marker_id(self, layer):
        mid = self._open.get(layer)
        if mid is not None and self._count[mid] < self.max_beads:
            return mid
        mid = self._next_id
        self._next_id += 1
        self._beads[mid], self._count[mid], self._version[mid], self._shown[mid] = [], 0, 0, None
        self._open[layer] = mid
        return mid

    def add(self, bead):
        """One :class:`~ambots.runner.Bead` (K beads, world frame, m)."""
        p0, p1 = np.asarray(bead.p0, dtype=float).reshape(-1, 3), np.asarray(bead.p1, dtype=float).reshape(-1, 3)
        rows = np.column_stack([p0, p1, bead_area_m2(p0, p1, bead.e_mm), np.asarray(bead.line, dtype=float)])
        layers = np.asarray(bead.layer).reshape(-1)
        bounds = np.r_[0, np.nonzero(layers[1:] != layers[:-1])[0] + 1, len(layers)]
        with self._lock:
            for i, j in zip(bounds[:-1].tolist(), bounds[1:].tolist()):      # runs of one layer
                while i < j:
                    mid = self._marker_id(int(layers[i]))
                    take = min(j - i, self.max_beads - self._count[mid])
                    self._beads[mid].append(rows[i:i + take])
                    self._count[mid] += take
                    self._version[mid] += 1
                    self._dirty.add(mid)
                    i += take

    def _snapshot(self, ids):
        """[(id, version, rows, shown)] of markers ``ids``; the caller holds the lock."""
        out = []
        for mid in ids:
            chunks = self._beads[mid]
            if len(chunks) > 1:
                chunks[:] = [np.concatenate(chunks)]
            out.append((mid, self._version[mid], chunks[0] if chunks else np.zeros((0, 8)), self._shown[mid]))
        return out

    def take_changed(self):
        """What changed since the last call, for :meth:`build`."""
        with self._lock:
            ids = sorted(self._dirty)
            self._dirty.clear()
            return self._snapshot(ids)

    def _segments(self, mid, rows):
        """The marker's beads merged into segments (cached for the same beads)."""
        with self._lock:
            done = self._merged.get(mid)
        if done is None or done[0] != len(rows):
            s, e, a, _ = merge_beads(rows[:, 0:3], rows[:, 3:6], rows[:, 6], keys=(rows[:, 7],))
            keep = a > 0
            done = (len(rows), s[keep], e[keep], a[keep])
            with self._lock:
                if mid not in self._merged or self._merged[mid][0] < len(rows):
                    self._merged[mid] = done
        return done[1:]

    def update_exposure(self, now=None, force=False):
        """Find the buried segments again (every ``exposure_period`` s of
        ``now``, wall clock, when beads came since; ``force``: now).  Returns
        whether it ran."""
        now = time.monotonic() if now is None else now
        with self._lock:
            counts = dict(self._count)
            if counts == self._exposure_of or (not force and now - self._exposure_at < self.exposure_period):
                return False
            self._exposure_at, self._exposure_of = now, counts
            snap = self._snapshot(sorted(self._beads))
        parts = [(mid, len(rows), self._segments(mid, rows)) for mid, _, rows, _ in snap]
        if not parts:
            return True
        starts, ends, area = (np.concatenate([p[k] for _, _, p in parts]) for k in range(3))
        shown = exposed(starts, ends, area, self.height, cell=self.cell, floor_z=self.floor_z, sides=self.sides)
        cut = np.cumsum([len(p[0]) for _, _, p in parts])[:-1]
        with self._lock:
            for (mid, n, _), mask in zip(parts, np.split(shown, cut)):
                new = None if mask.all() else (n, mask)
                old = self._shown.get(mid)
                if (old is None and new is None) or (old is not None and new is not None and old[0] == n
                                                     and np.array_equal(old[1], mask)):
                    continue
                self._shown[mid] = new
                self._version[mid] += 1
                self._dirty.add(mid)
        return True

    def build(self, snapshot, stamp=None):
        """MarkerArray of a :meth:`take_changed` (or None if empty)."""
        if not snapshot:
            return None
        markers = []
        for mid, version, rows, shown in snapshot:
            with self._lock:
                done = self._built.get(mid)
            if done is None or done[0] != version:
                done = (version, self._make(mid, rows, shown))
                with self._lock:
                    if mid not in self._built or self._built[mid][0] < version:
                        self._built[mid] = done
            markers.append(done[1])
        if stamp is not None:
            for m in markers:
                m.header.stamp = stamp
        return ArrayMarkers(markers=markers)

    def _make(self, mid, rows, shown):
        s, e, a = self._segments(mid, rows)
        if shown is not None:             # buried segments out
            n_beads, mask = shown
            keep = np.ones(len(s), dtype=bool)
            # beads laid since: the segments they made and the last one they may have extended stay in
            n = min(len(mask) if n_beads == len(rows) else len(mask) - 1, len(s))
            keep[:n] = mask[:n]
            s, e, a = s[keep], e[keep], a[keep]
        tris = tube_triangles(s, e, a, self.height, self.sides)
        # one colour per triangle (RViz draws them unlit, see ambots.tubes)
        m = ArrayMarker(xyz=tris.reshape(-1, 3), rgba=shade(face_normals(tris), self.colour))
        m.header.frame_id = self.frame
        # nothing left to draw (all buried): RViz drops the marker (an empty one is an error there)
        m.ns, m.id, m.type = self.ns, mid, Marker.TRIANGLE_LIST
        m.action = Marker.ADD if len(tris) else Marker.DELETE
        m.pose.orientation.w = 1.0
        m.scale.x = m.scale.y = m.scale.z = 1.0
        m.color.r, m.color.g, m.color.b, m.color.a = (float(c) for c in self.colour)
        return m

    def changed(self, stamp=None):
        """MarkerArray of the markers changed since the last call (or None)."""
        return self.build(self.take_changed(), stamp)

    def all(self):
        """MarkerArray of every marker so far (or None)."""
        with self._lock:
            snap = self._snapshot(sorted(self._beads))
        return self.build(snap)

    @property
    def n_beads(self):
        with self._lock:
            return sum(self._count.values())


class FirmwareNode:
    """One arm's firmware on ROS (see the module docstring).

    Parameters
    ----------
    arm, cell : the arm (:class:`~ambots.config.ArmInstance`) and its cell
    rate : ticks per wall second (joint states with a wall clock)
    driver : ``"sim"`` or ``"trajectory"`` (:mod:`ambots.ros.driver`; a real arm: the wall clock)
    chunk_duration, command_delay : s of motion per JointTrajectory; s the
        controller executes after the firmware's clock (``trajectory``)
    progress_tie : ``trajectory``: tie the clock and the reports to the
        controller's joint states (False: the plan's timeline, for comparisons)
    """

    def __init__(self, arm, cell, rate=50.0, report_period=1.0,
                 marker_rate=4.0, bead_height_mm=None, clearance_mm=5.0, max_beads=2000,
                 retry_period=0.05, max_tries=None, state_dir=None, run_id="", slowdown=1.0,
                 driver="sim", chunk_duration=0.5, command_delay=0.3, progress_tie=True):
        self.arm, self.cell = arm, cell
        self.rate = float(rate)
        #: the one clock is simulated (/clock, use_sim_time) rather than the wall
        self.sim_clock = bool(rospy.get_param("/use_sim_time", False))
        self.log = ASeriesLog("%s firmware" % arm.name, debug_param())
        self.report_period, self.marker_period = report_period, 1.0 / marker_rate
        self.retry_period = retry_period
        self.collision = CollisionCheck(arm, cell, clearance_mm * MM)
        self.runner = ArmRunner(arm, cell, planner=MotionPlanner(arm, cell, is_valid=self.collision),
                                record=True)
        self.lock = threading.Lock()          # the runner, the markers, the sim clock
        self._io = threading.Lock()           # sender and receiver
        self.sender = Sender(arm.id, first_seq=seq_seed(time.time()), max_tries=max_tries)
        self.receiver = Receiver(arm.id)
        self._commands = queue.Queue()
        self._wake = threading.Event()        # a command arrived: the loop need not finish its tick
        if bead_height_mm is None:             # the layer height the deposit (ambots.deposit) is built with
            from ambots.slicer import SliceSettings
            bead_height_mm = SliceSettings().layer_height_mm
        # nothing is seen from under the bed: its top closes the deposit from below
        self.markers = DepositMarkers(arm.name, cell.world_frame, arm.profile.colour, bead_height_mm * MM,
                                      max_beads, floor_z=float(cell.bed.pose[2, 3]))
        self.sim_now = 0.0
        self._clock_now = 0.0                 #: the latest instant received on /clock
        self.slowdown = float(slowdown)       # > 1: this arm's motion takes that much longer (fault tests)
        if self.slowdown != 1.0:
            self.runner.planner.time_scale = self.slowdown
        self.store = StateStore(state_dir, arm.name, dof=len(arm.profile.joint_names)) if state_dir else None
        self.checkpoint_period = 0.1          # wall s between checkpoints while printing (at least)
        self.run_id = run_id
        self.resumed = None                   # the checkpoint this node resumed from
        self.peers = {}                       # robot id -> last A10 state name
        self._names = {a.id: a.name for a in cell.arms}
        self._thread = None
        self._traced = (None, None)
        self._late = False
        self._blocked = False                 # the runner waits for other arms to clear the way (logged)
        self.driver = None
        if driver not in DRIVERS:
            raise ValueError("driver must be one of %s, got %r" % (", ".join(DRIVERS), driver))
        if driver == "trajectory":
            if self.sim_clock:
                raise ValueError("driver trajectory drives a real arm: its clock is the wall, not a "
                                 "simulated /clock (use_sim_time must be false)")
            self.driver = TrajectoryDriver(arm, self.runner.planner, chunk_duration, command_delay,
                                           progress_tie=progress_tie)
        self._chunks = []
        #: (runner time, message) produced but held until the arm got there (driver trajectory)
        self._held = []

    # ------------------------------------------------------------- ROS
    def start(self):
        arm = self.arm
        if rospy.get_name() != topics.arm_node(arm.name):
            rospy.logwarn("firmware of %s runs as %s, not %s: the hub will refuse its messages",
                          arm.name, rospy.get_name(), topics.arm_node(arm.name))
        self._to_hub = rospy.Publisher(topics.HUB_TOPIC, String, queue_size=1000)
        self._joints = rospy.Publisher(topics.joint_states_topic(arm.name), JointState, queue_size=10)
        self._deposit = rospy.Publisher(DEPOSIT_TOPIC, MarkerArray, queue_size=100,
                                        subscriber_listener=_NewSubscriber(self))
        self._stats = rospy.Publisher("~stats", String, queue_size=10, latch=True)
        self._trace = rospy.Publisher("~trace", Float64MultiArray, queue_size=100000)
        self._bead_times = rospy.Publisher("~beads", Float64MultiArray, queue_size=100000)
        self._row_seq = {"trace": 0, "beads": 0}
        self._clock_ready = rospy.Publisher(topics.CLOCK_READY_TOPIC, String, queue_size=1000)
        self._ready = None
        if self.sim_clock:                    # wake up at each step of the one clock
            rospy.Subscriber("/clock", Clock, self._on_clock, queue_size=1)
        self._js = JointState(name=[arm.prefix + j for j in arm.profile.joint_names])
        # a real arm (driver trajectory) plans around the other arms' current poses; a
        # simulated one, like the offline run, around the bed only (the barriers keep the
        # arms apart, and the same plan runs offline and live)
        for other in self.cell.arms if self.driver is not None else ():
            if other.name != arm.name:
                rospy.Subscriber(topics.joint_states_topic(other.name), JointState,
                                 self._on_other_joints, callback_args=other, queue_size=1)
        if self.driver is not None:
            self.driver.start(self.runner)
        rospy.Subscriber(topics.arm_topic(arm), String, self._on_inbox, queue_size=1000)
        replay = None
        with self.lock:
            self._outgoing = [self.runner.status(with_position=True)]   # here I am
            if self.store is not None:
                replay = self._resume_from_checkpoint()
        if replay is not None:
            self._publish_replay(*replay)
        self._thread = threading.Thread(target=self._loop, name="firmware-%s" % arm.name, daemon=True)
        self._thread.start()

    def join(self):
        if self._thread is not None:
            self._thread.join()

    def _on_clock(self, msg):
        # the instant itself: rospy's own clock may not have taken it yet
        self._clock_now = max(self._clock_now, msg.clock.to_sec())
        self._wake.set()

    def _on_other_joints(self, msg, other):
        try:
            index = {n: i for i, n in enumerate(msg.name)}
            q = [msg.position[index[other.prefix + j]] for j in other.profile.joint_names]
        except (KeyError, IndexError):
            return
        self.collision.update(other.name, q)

    def _send(self, text):
        """Publish ``text`` to the hub (logged with ``~debug``)."""
        self.log.sent(topics.HUB_TOPIC, text)
        self._to_hub.publish(String(text))

    def _on_inbox(self, msg):
        self.log.received("hub via " + self.arm.inbox, msg.data)
        try:
            message = decode(msg.data)
        except ProtocolError as exc:
            rospy.logwarn("%s firmware: ignored malformed message %r: %s", self.arm.name, msg.data[:80],
                          exc.message)
            return
        if isinstance(message, Ack):
            with self._io:
                self.sender.acknowledge(message)
            return
        # deduplicated, executed and checkpointed by the loop before it is acknowledged
        self._commands.put((message, msg.data))
        self._wake.set()

    def _receive(self, message, data):
        """One numbered command from the inbox (loop thread, lock held), and
        the commands it releases (held behind it for order): returns the
        A8s to send once the step is checkpointed."""
        with self._io:
            deliveries = self.receiver.deliver(message)
        for m, delivery in deliveries:
            if delivery.verdict is Verdict.NEW:
                self._apply(m)
            elif delivery.verdict is Verdict.STALE:
                rospy.logwarn("%s firmware: Q%d of node %d is older than the window: not executed",
                              self.arm.name, m.seq, HUB if m.sender is None else m.sender)
            elif delivery.verdict is Verdict.UNNUMBERED:
                rospy.logwarn("%s firmware: ignored unnumbered %r (everything comes numbered through the hub)",
                              self.arm.name, data[:80])
        return [d.ack for _, d in deliveries if d.ack is not None]

    # ------------------------------------------------------------- the loop
    def _apply(self, message):
        """Hand one command to the runner (lock held)."""
        r = self.runner
        if isinstance(message, (LoadChunk, ClearChunk)):
            self._new_run()
        elif isinstance(message, Start) and message.robot == self.arm.id and r.starts_run(message):
            self._new_run()                   # a new run: new markers, its own statistics
            r.stats = RunStats()
        stop_q = None
        if self.driver is not None and isinstance(message, ClearChunk) and message.robot == self.arm.id:
            stop_q = self.driver.abort(r, self.sim_now)       # the arm was moving: it brakes
        if isinstance(message, Status) and message.robot != self.arm.id and self.driver is not None \
                and message.clock is not None:
            # each arm's time follows its own controller: a report counts from when it arrives
            message = dataclasses.replace(message, clock=None)
        if isinstance(message, Status) and message.robot != self.arm.id:
            name = message.state.name
            if self.peers.get(message.robot) != name:
                self.peers[message.robot] = name
                self._peers_changed = True
                if message.state is ArmState.ERROR:
                    rospy.logwarn("%s firmware: arm %s (R%d) stopped with an error", self.arm.name,
                                  self._names.get(message.robot, "?"), message.robot)
        r.handle(message, now=self.sim_now)
        if stop_q is not None:
            r.q = stop_q
        if self.driver is not None and isinstance(message, (Pause, Stop)) and message.robot == self.arm.id:
            self.driver.pause(r, self.sim_now)
        if isinstance(message, LoadChunk) and self.store is not None and r.chunk == message.identity:
            self.store.save_chunk(message.identity, message.gcode)

    def _step(self, dt):
        """One iteration (lock held): commands, the clock, what to publish."""
        r = self.runner
        self._peers_changed = False
        # the one clock: ROS time (/clock in simulation, the wall with a real arm,
        # held back to what its controller has executed); commands that arrived
        # are executed at this instant
        if self.driver is not None:
            self.sim_now = max(self.sim_now, self.driver.clock(rospy.get_time()))
        else:
            self.sim_now = max(self.sim_now, rospy.get_time(), self._clock_now)
        acks = []
        while True:
            try:
                acks += self._receive(*self._commands.get_nowait())
            except queue.Empty:
                break
        if self.driver is not None and r.block is None:
            q = self.driver.rest_joints(r, rospy.get_time())    # where the controller says the arm rests
            if q is not None:
                r.q = q
        r.advance(self.sim_now)
        blocked = r.block.blocked if r.block is not None else None
        if blocked is not None and not self._blocked:       # once per wait: the move is tried every 0.5 s
            rospy.logwarn("%s firmware: line %d waits for the other arms to clear the way: %s", self.arm.name,
                          int(r.block.line[0]), blocked)
        self._blocked = blocked is not None
        if self.driver is not None:
            self._chunks = self.driver.update(self.sim_now, rospy.get_time())
        out = list(r.outbox)              # (runner time, message)
        r.outbox.clear()
        trace = beads = None
        if r.trace_t:             # the executed motion as Hermite knots, ROS time: rows (t, q..., v...)
            trace = np.column_stack([np.concatenate(r.trace_t), np.concatenate(r.trace_q),
                                     np.concatenate(r.trace_v)])
            r.trace_t.clear()
            r.trace_q.clear()
            r.trace_v.clear()
        if trace is not None and self.store is not None:
            self.store.append_trace(trace)
        if r.beads:               # the beads with their times: rows (p0 xyz, p1 xyz, t, e_mm)
            beads = np.concatenate([bead_rows(b.p0, b.p1, b.t, b.e_mm) for b in r.beads])
        for bead in r.beads:
            if self.store is not None:
                self.store.append(bead.p0, bead.p1, bead.e_mm, bead.line, bead.layer, bead.t)
            self.markers.add(bead)
        changed = bool(acks or out or r.beads or r.state is ArmState.PRINTING)
        r.beads.clear()
        self._traced = (trace, beads)
        return out, acks, changed, r.joints(self.sim_now), self._peers_changed

    def _loop(self):
        period = 1.0 / self.rate
        last = time.monotonic()
        next_joints = next_markers = next_retry = next_report = next_checkpoint = last
        last_state, last_status = None, None
        js_time = None
        while not rospy.is_shutdown():
            wall = time.monotonic()
            self._wake.clear()                # before the queue is drained: no command is missed
            try:
                with self.lock:
                    out, acks, changed, q, peers_changed = self._step(wall - last)
                    state = self.runner.state
                    if self._outgoing:
                        out = [(-math.inf, m) for m in self._outgoing] + out
                        self._outgoing = []
                    if state is ArmState.PRINTING and wall >= next_report:
                        next_report = wall + self.report_period
                        st = self.runner.status(with_position=True)
                        if last_status is None or (st.layer, st.line, st.percent) != \
                                (last_status.layer, last_status.line, last_status.percent):
                            out.append((self.runner.clock, st))
                    for _, m in out:
                        if isinstance(m, Status) and m.robot == self.arm.id:
                            last_status = m
                    out = self._release(out)
                    # number what goes out, then checkpoint, then publish: a crash
                    # anywhere in between is undone by the restart
                    numbered = self._number(out)
                    # (before any ack or message goes out; otherwise at most every
                    # checkpoint_period s while printing: a crash redoes at most that)
                    if self.store is not None and (acks or numbered or state != last_state or
                                                   (changed and wall >= next_checkpoint)):
                        self._checkpoint()
                        next_checkpoint = wall + self.checkpoint_period
                    stats = self._stats_json() if (state != last_state or peers_changed or
                                                   (state is ArmState.PRINTING and out)) else None
            except Exception as exc:          # noqa: BLE001 -- a bug: say why, and stop the node
                rospy.logerr("%s firmware: %s: %s", self.arm.name, type(exc).__name__, exc)
                rospy.signal_shutdown("firmware loop failed: %s" % exc)
                raise
            last = wall
            try:
                if self._chunks:
                    self.driver.publish(self._chunks)
                    self._chunks = []
                    if self.driver.min_lead is not None and self.driver.min_lead < 0 and not self._late:
                        self._late = True
                        rospy.logwarn("%s firmware: a trajectory chunk was sent %.3f s after its start: raise "
                                      "~command_delay", self.arm.name, -self.driver.min_lead)
                for a in acks:
                    self._send(encode(a))
                for o in numbered:
                    self._send(encode(o.message))
                for key, pub, rows in zip(("trace", "beads"), (self._trace, self._bead_times), self._traced):
                    if rows is not None:          # numbered (data_offset): a subscriber can tell a gap
                        self._row_seq[key] += 1
                        pub.publish(_rows(rows, self._row_seq[key]))
                if wall >= next_retry:
                    next_retry = wall + self.retry_period
                    with self._io:
                        due = self.sender.due(wall)
                    for o in due:
                        self._send(encode(o.message))
                # joint states at every new instant of the one clock, stamped with it (with
                # the wall as the clock, at most at the tick rate; with a controller, at
                # the tick rate stamped with ROS time: its joints, which move on even
                # while the runner's time waits for them)
                if (self.sim_now != js_time or self.driver is not None) and (self.sim_clock or wall >= next_joints):
                    next_joints = max(next_joints + period, wall)
                    js_time = self.sim_now
                    self._js.header.stamp = rospy.Time.from_sec(js_time if self.driver is None else rospy.get_time())
                    if self.driver is not None:          # the controller's joints, else what it was told
                        measured = self.driver.measured()
                        if measured is None:
                            measured = self.driver.commanded(self._js.header.stamp.to_sec())
                        if measured is not None:
                            q = measured
                    self._js.position = [float(v) for v in q]
                    self._joints.publish(self._js)
                if wall >= next_markers:      # out of the loop's lock: the markers lock themselves
                    self.markers.update_exposure(wall)
                    markers = self.markers.changed(rospy.Time.now())
                    if markers is not None:
                        next_markers = wall + self.marker_period
                        self._deposit.publish(markers)
                if stats is not None:
                    self._stats.publish(String(stats))
                    if state is not last_state:      # barriers come and go: not worth a line each
                        log = rospy.logdebug if {state, last_state} == _BARRIER else rospy.loginfo
                        log("%s firmware: %s", self.arm.name, state.name)
                    last_state = state
                self._publish_ready()
            except rospy.ROSException as exc:
                # a topic closed under us: the node is going down
                if going_down() or "closed topic" in str(exc):
                    break
                raise
            # spare time until the next tick: plan the next moves ahead (one
            # item at a time), then sleep until the tick, a command (a
            # barrier's report) or the clock's next step arrives
            tick_end = wall + period
            while not self._wake.is_set() and time.monotonic() < tick_end - 0.002:
                with self.lock:
                    if not self.runner.prefetch():
                        break
                time.sleep(0)             # let the callbacks run
            self._wake.wait(max(0.0, tick_end - time.monotonic()))

    def _release(self, out):
        """The messages of ``out`` ((runner time, message) pairs, in order)
        that may leave now: all of them, or with a controller, those the
        arm has got to (the rest are held, in order, for a later step)."""
        if self.driver is None:
            return [m for _, m in out]
        self._held += out
        until = self.driver.released_until()
        n = 0
        while n < len(self._held) and self._held[n][0] <= until + 1e-6:
            n += 1
        ready = [m for _, m in self._held[:n]]
        del self._held[:n]
        return ready

    def _publish_ready(self):
        """Tell the clock (:mod:`ambots.clock`) where this arm is: its step, its
        next event, its messages in flight, what it executed of the hub's."""
        if not self.sim_clock:
            return
        with self.lock:
            r = self.runner
            ready = ArmReady(self.sim_now, r.next_event(), r.state is ArmState.PRINTING, 0, None, None)
        with self._io:
            ready = ArmReady(ready.t, ready.next_event, ready.active, len(self.sender.pending),
                             self.sender.last_seq, self.receiver.top(HUB))
        if ready != self._ready:
            self._ready = ready
            doc = ready.as_dict()
            doc["arm"] = self.arm.name
            self._clock_ready.publish(String(json.dumps(doc)))

    def _number(self, messages):
        out = []
        with self._io:
            for m in messages:
                out.append(self.sender.send(m, HUB, time.monotonic()))
        return out

    # ------------------------------------------------------------- persistence
    def _new_run(self):
        self.markers.new_run()
        if self.store is not None:
            self.store.new_journal()

    def _checkpoint(self):
        with self._io:
            rx, tx = self.receiver.snapshot(), self.sender.snapshot()
        self.store.save({"run_id": self.run_id, "arm": self.arm.name, "runner": self.runner.checkpoint(),
                         "receiver": rx, "sender": tx, "sim_now": self.sim_now,
                         "peers": {str(k): v for k, v in self.peers.items()},
                         "held": [encode(m) for _, m in self._held]})

    def _resume_from_checkpoint(self):
        """After a crash (same ROS run): the runner, the duplicate filter,
        the unacknowledged messages and the deposit so far, from the state
        directory; the other arms are asked where they are (A3).  Returns
        what to publish again, (knots, bead rows) from the journals (what
        the killed node published last may never have left its publisher's
        queue), or None when starting clean."""
        cp = self.store.load()
        if cp is None or cp.get("run_id") != self.run_id or cp.get("arm") != self.arm.name:
            self.store.start_clean()           # another run's state: start clean
            return
        rcp = cp["runner"]
        if rcp["chunk"] is not None:
            identity, text = self.store.load_chunk()
            if list(identity) != list(rcp["chunk"]):
                rospy.logerr("%s firmware: checkpoint and saved chunk differ: starting clean", self.arm.name)
                self.store.start_clean()
                return
            self.runner.restore(rcp, text)
        with self._io:
            self.receiver.restore(cp["receiver"])
            self.sender.restore(cp["sender"], time.monotonic())
        self.sim_now = max(float(cp["sim_now"]), self.runner.clock)
        self.peers = {int(k): v for k, v in cp["peers"].items()}
        trace_records = int(cp.get("trace_records", 0))
        self.store.reopen(int(cp["records"]), trace_records)
        journal = self.store.read_journal(int(cp["records"]))
        if len(journal):
            self.markers.add(Bead(journal[:, 0:3], journal[:, 3:6], journal[:, 6], journal[:, 7].astype(int),
                                  journal[:, 8].astype(int), journal[:, 9]))
        self.resumed = cp
        # messages held for the arm's progress when it stopped: the arm has stopped too
        self._outgoing = [decode(text) for text in cp.get("held", [])] + [self.runner.status(with_position=True)] \
            + [SendPosition(a.id) for a in self.cell.arms if a.id != self.arm.id]
        rospy.logwarn("%s firmware: resumed from its checkpoint: %s at line %d, %d beads kept",
                      self.arm.name, self.runner.state.name, self.runner.done_line, len(journal))
        return self.store.read_trace(trace_records), bead_rows(journal[:, 0:3], journal[:, 3:6], journal[:, 9],
                                                               journal[:, 6])

    def _publish_replay(self, knots, beads, wait_s=5.0, rows_per_message=20000):
        """After a resume: publish again, from the journals, the motion this
        node executed in this ROS run and the run's beads, before anything
        new, once every subscriber the master knows of has connected (at
        most ``wait_s`` wall s).  A recorder keeps the later copy of rows it
        had (:func:`ambots.ros.capture._latest_copy`) and gets what the
        killed node's publisher queue lost."""
        pubs = [(key, p, rows) for key, p, rows in (("trace", self._trace, knots), ("beads", self._bead_times, beads))
                if len(rows)]
        if not pubs:
            return
        try:
            _, subscribed, _ = rosgraph.Master(rospy.get_name()).getSystemState()
            wanted = {topic: len(nodes) for topic, nodes in subscribed}
        except Exception as exc:          # noqa: BLE001 -- the master is there: a node just registered with it
            rospy.logwarn("%s firmware: subscribers of the trace not known (%s): replaying at once", self.arm.name,
                          exc)
            wanted = {}

        def late():
            return [p.resolved_name for _, p, _ in pubs if p.get_num_connections() < wanted.get(p.resolved_name, 0)]

        t_end = time.monotonic() + wait_s
        while late() and time.monotonic() < t_end and not rospy.is_shutdown():
            time.sleep(0.01)
        if late():
            rospy.logwarn("%s firmware: not every subscriber of %s connected within %.0f s: they miss the replay",
                          self.arm.name, ", ".join(late()), wait_s)
        for key, p, rows in pubs:
            for k in range(0, len(rows), rows_per_message):
                self._row_seq[key] += 1
                p.publish(_rows(np.ascontiguousarray(rows[k:k + rows_per_message]), self._row_seq[key]))
        rospy.loginfo("%s firmware: published again the run so far: %d knots, %d beads", self.arm.name,
                      len(knots), len(beads))

    def _stats_json(self):
        r = self.runner
        return json.dumps({
            "arm": self.arm.name, "id": self.arm.id, "state": r.state.name, "layer": int(r.layer),
            "line": int(r.done_line), "percent": round(float(r.percent), 2), "sim_time": round(r.clock, 6),
            "clock": "sim" if self.sim_clock else "wall", "beads": self.markers.n_beads,
            "stats": asdict(r.stats),
            "peers": {self._names.get(i, str(i)): s for i, s in sorted(self.peers.items())},
            "driver": dict(self.driver.stats(), held=len(self._held)) if self.driver is not None
            else {"driver": "sim"},
        })

    def publish_all_markers(self, publish):
        """Every marker so far, through ``publish(MarkerArray)`` (the markers
        lock themselves; the loop goes on meanwhile)."""
        markers = self.markers.all()
        if markers is not None:
            publish(markers)


def bead_rows(p0, p1, t, e_mm):
    """The ``~beads`` rows (K, 8): p0 xyz, p1 xyz (m), time (s), filament (mm)."""
    return np.column_stack([p0, p1, t, e_mm])


def _rows(a, seq=0):
    """(N, M) array -> Float64MultiArray (dims rows, cols; ``seq`` in data_offset)."""
    msg = Float64MultiArray()
    msg.layout.data_offset = int(seq)
    msg.layout.dim = [MultiArrayDimension("rows", a.shape[0], a.size), MultiArrayDimension("cols", a.shape[1],
                                                                                        a.shape[1])]
    msg.data = a.ravel().tolist()
    return msg


def rows_of(msg):
    """Float64MultiArray from :func:`_rows` -> (N, M) array."""
    cols = msg.layout.dim[1].size if len(msg.layout.dim) > 1 else 1
    return np.asarray(msg.data, dtype=float).reshape(-1, cols)


class _NewSubscriber(rospy.SubscribeListener):
    """A new subscriber of the deposit topic gets every marker so far."""

    def __init__(self, node):
        super().__init__()
        self.node = node

    def peer_subscribe(self, topic_name, topic_publish, peer_publish):
        self.node.publish_all_markers(peer_publish)
