"""One arm's firmware, without ROS: A-series commands in, motion and
deposit out, on a clock the caller drives.

:class:`ArmRunner` is the state machine of ``nodes/firmware`` and of the
offline simulator (``python -m ambots plan``), so both execute programs the
same way.  The caller

* hands it every message addressed to the arm, and the status reports
  (A10) and error reports (A11) of the other arms: :meth:`handle`;
* advances its clock: :meth:`advance` (simulated seconds; the caller
  chooses how they relate to wall time);
* drains what it produced: :attr:`outbox` ((simulated time, protocol
  message) pairs for the hub, without S/Q -- the caller's
  :class:`~ambots.reliable.Sender` numbers them), :attr:`beads` (deposited
  beads), and reads :meth:`joints`.

Waiting costs no computation: a waiting arm resumes at the simulated time
the awaited report was made (or its own clock, if later), so the offline
simulator's step size does not inflate idle time.  That holds also when the
report is already there when the arm reaches the barrier: the arms' clocks
are independent, and a report made at a later simulated time than this
arm's clock holds the arm until then.

States (:class:`~ambots.protocol.ArmState`): IDLE (no chunk or not
started), PRINTING, PAUSED, WAITING (at an A9 barrier), DONE, ERROR.

Directives of the program (``;@...`` lines) are executed when reached:
``A9`` waits for another arm's line/layer (its A10 reports); ``A3``
reports this arm's line and position (A10) to the others; ``A7`` addressed
to this arm moves it, ``A2`` pauses it there (until an A6 or A1 from
another arm resumes it: sequential mode's hand-over); other commands
addressed to another arm (``A1``, ``A6``, ``A7``) are sent through the hub.  Before the first A9 of a barrier the arm reports
A10 with the last completed line, which is what the other arms' A9
barriers wait for.

Pause (A2) stops at the end of the G-code line being executed (a clean
point: never in the middle of a bead) and A6 resumes from there, so a
paused print deposits exactly what an uninterrupted one does.
"""
from collections import deque
from dataclasses import asdict, dataclass, field
from typing import Dict, List, Optional

import numpy as np

from ambots.errors import GCodeError
from ambots.motion import Directive, MotionError, MotionPlanner, Pause as Dwell, read_program
from ambots.protocol import (Ack, ArmState, ClearChunk, ErrorReport, LoadChunk, MoveTo, Pause, Resume,
                             SendPosition, Start, Status, Stop, WaitFor, MAX_TEXT, decode, encode)

__all__ = ["ArmRunner", "Bead", "RunStats"]


@dataclass
class Bead:
    """Deposited beads of one step, world frame: ``p0``, ``p1`` (K, 3) m,
    ``e_mm`` (K,) filament, ``line``/``layer`` (K,), ``t`` (K,) sim time at
    the end of each bead."""
    p0: np.ndarray
    p1: np.ndarray
    e_mm: np.ndarray
    line: np.ndarray
    layer: np.ndarray
    t: np.ndarray

    @property
    def area_m2(self):
        """Cross-section of each bead (K,) m^2 from the filament pushed."""
        from ambots.deposit import bead_area_m2
        return bead_area_m2(self.p0, self.p1, self.e_mm)


#: a clock within this of a waypoint's time has reached it (s); the one clock
#: (ambots.clock) steps to block ends in whole nanoseconds
TIME_TOLERANCE_S = 1e-6


@dataclass
class RunStats:
    moves: int = 0                 #: G-code moves executed
    extrude_m: float = 0.0
    travel_m: float = 0.0
    print_time_s: float = 0.0      #: simulated time in motion
    idle_time_s: float = 0.0       #: simulated time waiting or paused while a job runs
    ik_failures: int = 0
    max_path_error_mm: float = 0.0
    plans: Dict[str, int] = field(default_factory=dict)   #: blocks by planning kind
    first_motion_s: Optional[float] = None
    done_s: Optional[float] = None


class ArmRunner:
    """Firmware state machine of one arm (see the module docstring).

    Parameters
    ----------
    arm, cell : the arm (:class:`~ambots.config.ArmInstance`) and its cell
    planner : a :class:`~ambots.motion.MotionPlanner` (default: built here)
    q0 : initial joint vector (default: the profile's home)
    now : initial simulated time (s)
    record : keep every executed waypoint (``trace``) for offline analysis

    A move that only the other arms' current poses block (``Block.blocked``,
    see :class:`~ambots.motion.MotionPlanner`) is waited for and planned
    again, for at most :attr:`max_blocked_s` simulated s in a row; then it
    is an error like an unreachable point.
    """

    max_blocked_s = 60.0

    def __init__(self, arm, cell, planner=None, q0=None, now=0.0, record=False):
        self.arm, self.cell = arm, cell
        self.id = arm.id
        self.planner = planner or MotionPlanner(arm, cell)
        self.q = np.array(arm.profile.home if q0 is None else q0, dtype=float)
        self.clock = float(now)
        self.state = ArmState.IDLE
        self.outbox: List[object] = []
        self.beads: List[Bead] = []
        self.stats = RunStats()
        self.peers: Dict[int, Status] = {}
        self.peer_time: Dict[int, float] = {}
        self.peer_log: Dict[int, deque] = {}     #: recent reports per arm: (done, line, layer, clock)
        self.record = record
        self.trace_t: List[np.ndarray] = []
        self.trace_q: List[np.ndarray] = []
        self.trace_v: List[np.ndarray] = []      #: joint speeds at the trace's knots (rad/s)
        self._trace_end = -np.inf    #: simulated time of the last waypoint recorded
        #: optional ``f(block, t0, k)``: told of every block the arm starts (k = 0) or resumes (at
        #: waypoint k) at simulated time ``t0`` (a driver streaming the motion to a controller)
        self.on_motion = None
        #: A4 while moving (simulated): the brake the arm is still on after its block was dropped,
        #: ``(motion, t0, tau_from, tau_rest)`` in block times of ``motion`` (started at ``t0``);
        #: kept out of :meth:`_clear` (a chunk loaded meanwhile does not stop the arm)
        self.coast = None
        self._clear()

    # ----------------------------------------------------------- program
    def starts_run(self, msg):
        """True if the A1 ``msg`` (to this arm) begins a run of the loaded
        chunk: an IDLE or DONE arm, and not a repeated start (with C) of a
        chunk that has already started."""
        return bool(self.items) and self.state in (ArmState.IDLE, ArmState.DONE) and (
            msg.chunk_id is None or (not self.started and self.chunk is not None
                                     and msg.chunk_id == self.chunk[0]))

    def _clear(self):
        self.chunk = None            #: identity of the loaded chunk
        self.started = False         #: an A1 has started this chunk (a later A1 C<chunk> is ignored)
        self.items = []
        self.n_lines = 0
        self.layer_of_line = np.zeros(1, dtype=int)
        self.idx = 0                 #: next item
        self.block = None
        self.block_t0 = 0.0
        self.k = 0                   #: last waypoint reached in the block
        self.done_line = 0           #: last completed program line
        self.layer = 0
        self.wait = None             #: the WaitFor being waited on
        self.pause_requested = False
        #: the pause requested is an operator's stop (A12): rest on the first waypoint reachable
        self.stop_requested = False
        self.after_block = None      #: state after a manual (A7) move
        self.reported_line = -1
        self._ahead = {}             #: item index -> (start joints, block) planned ahead
        self._block_src = None       #: where the current block came from (for checkpoints)
        self.blocked_s = 0.0         #: s waited so far for other arms to clear the way
        #: (block, waypoint): a pause stops there, not at the end of the line being executed
        #: (set by a driver that has sent the motion up to later than that line's end)
        self.pause_at = None

    @property
    def percent(self):
        return 100.0 * min(1.0, self.done_line / self.n_lines) if self.n_lines else 0.0

    def joints(self, now=None):
        """Joint vector (n,) at ``now`` (default: the runner's clock): while
        moving, the block's commanded motion (the one timing law) at that
        instant, never past the next waypoint the runner has not reached."""
        c = self.coast
        if c is not None and now is not None and now < c[1] + c[3]:
            return c[0].eval(np.array([max(now - c[1], c[2])]))[0][0]
        b = self.block
        if b is None or now is None or self.state not in (ArmState.PRINTING,) or self.k + 1 >= len(b.t):
            return self.q.copy()
        t = min(max(now - self.block_t0, b.t[self.k]), b.t[self.k + 1])
        if b.motion is not None:
            return b.motion.eval(np.array([t]))[0][0]
        span = b.t[self.k + 1] - b.t[self.k]
        u = 0.0 if span <= 0 else (t - b.t[self.k]) / span
        return b.Q[self.k] + u * (b.Q[self.k + 1] - b.Q[self.k])

    def nozzle_mm(self):
        """Nozzle position (3,) in the bed frame, mm."""
        return self.planner.world_to_bed_mm(self.planner.tip_world(self.q[None]))[0]

    def status(self, with_position=False):
        """The arm's A10 report now."""
        x = y = z = None
        if with_position:
            x, y, z = (round(float(v), 3) for v in self.nozzle_mm())
        return Status(self.id, self.state, int(self.layer), int(self.done_line),
                      round(float(self.percent), 2), x, y, z, clock=round(float(self.clock), 6))

    def _report(self, with_position=False):
        self.outbox.append((self.clock, self.status(with_position)))
        self.reported_line = self.done_line

    def _error(self, line, text):
        self.outbox.append((self.clock, ErrorReport(self.id, int(line), str(text)[:MAX_TEXT])))

    def _begin(self, block, t0):
        """``block`` starts at simulated time ``t0``."""
        self.block, self.block_t0, self.k = block, float(t0), 0
        if block is not None and self.stats.first_motion_s is None:
            self.stats.first_motion_s = float(t0)     # any block: a program's moves, a MoveTo, an A7
        if self.on_motion is not None and block is not None:
            self.on_motion(block, self.block_t0, 0)

    # ----------------------------------------------------------- commands
    def handle(self, msg, now=None):
        """Execute one message (its S/Q already handled by the caller's
        :class:`~ambots.reliable.Receiver`).  Messages about other arms
        (A10/A11 with R != this arm) update what this arm knows of them."""
        now = self.clock if now is None else now
        if isinstance(msg, Status):
            if msg.robot != self.id:
                last = self.peers.get(msg.robot)
                if last is not None and last.clock is not None and msg.clock is not None \
                        and msg.clock < last.clock:
                    return                    # an older report overtaken by a newer one: stale
                self.peers[msg.robot] = msg
                self.peer_time[msg.robot] = msg.clock if msg.clock is not None else now
                log = self.peer_log.setdefault(msg.robot, deque(maxlen=256))
                if log and msg.line < log[-1][1]:
                    log.clear()               # the other arm began a new run
                log.append((msg.state is ArmState.DONE, msg.line, msg.layer, self.peer_time[msg.robot]))
                if msg.state is ArmState.ERROR and self.state is ArmState.WAITING \
                        and self.wait is not None and self.wait.other == msg.robot:
                    # the arm this one waits for failed: hold here (A6 resumes the wait)
                    self.state = ArmState.PAUSED
                    self._error(self.done_line, "holding at line %d: arm R%d, which this arm waits "
                                                "for, stopped with an error" % (self.done_line, msg.robot))
                    self._report()
            return
        if isinstance(msg, ErrorReport):
            if msg.robot != self.id:
                self.peers.setdefault(msg.robot, None)
            return
        if isinstance(msg, Ack):
            return
        if getattr(msg, "robot", None) != self.id:
            if isinstance(msg, SendPosition):       # A3 R<to>: a report with our position, for arm <to>
                self._report(with_position=True)
                return
            self._error(0, "A%d for R%d delivered to arm R%d: ignored" % (msg.CODE, msg.robot, self.id))
            return
        kind = type(msg)
        if kind is LoadChunk:
            self._load(msg)
        elif kind is ClearChunk:
            was = self.state
            self._coast_out(now)
            self._clear()
            self.state = ArmState.IDLE
            if was in (ArmState.PRINTING, ArmState.WAITING, ArmState.PAUSED):
                self._error(0, "chunk cleared while %s: stopped" % was.name)
            self._report()
        elif kind is Start:
            loaded = self.chunk[0] if self.chunk is not None else None
            if not self.items:
                self._error(0, "A1: no chunk loaded")
            elif msg.chunk_id is not None and msg.chunk_id != loaded:
                self._error(0, "A1 C%d refused: the chunk loaded is %s" % (
                    msg.chunk_id, "C%d" % loaded if loaded is not None else "one without a C"))
            elif msg.chunk_id is not None and self.started:
                self._report()                         # a repeated start of this chunk: nothing to do
            elif self.starts_run(msg):
                if self.state is ArmState.DONE:        # run the same chunk again from the top
                    self.idx, self.done_line, self.block = 0, 0, None
                self.started = True
                self.state = ArmState.PRINTING
                self.clock = max(now, self.rest_at())
                self._report()
            elif self.state is ArmState.PAUSED:
                self._resume(now)
        elif kind is Pause:
            if self.state is ArmState.PRINTING:
                self.pause_requested = True
                self._brake(now)
            elif self.state is ArmState.WAITING:
                self.state = ArmState.PAUSED
                self._report()
        elif kind is Stop:
            if self.state is ArmState.PRINTING:
                self.pause_requested = self.stop_requested = True
                self.pause_at = None
                self._brake(now)
            elif self.state is ArmState.WAITING:
                self.state = ArmState.PAUSED
                self._report()
        elif kind is Resume:
            if self.state is ArmState.PAUSED:
                self._resume(now)
        elif kind is SendPosition:
            self._report(with_position=True)
        elif kind is MoveTo:
            self._manual_move(msg, now)
        elif kind is WaitFor:
            if self.state in (ArmState.PRINTING, ArmState.IDLE):
                self.wait = msg
                self.state = ArmState.WAITING
                self._report()

    def _brake(self, now):
        """A pause while moving: brake within the acceleration limits to rest
        on the first waypoint ending a G-code line that the arm can reach so
        (:func:`ambots.trajectory.stop_at_line_end`, the one timing law; a
        stop, A12: on the first waypoint it can reach);
        the block's times after ``now`` change accordingly.  A driver that
        streams the motion (:attr:`on_motion`) plans the stop itself, after
        what it has sent (:attr:`pause_at`)."""
        b = self.block
        if b is None or b.motion is None or self.on_motion is not None:
            return
        from ambots.trajectory import stop_at_line_end
        H = max(now, self.clock) - self.block_t0
        self.pause_at = (b, stop_at_line_end(b, max(H, float(b.t[self.k])), self.planner.timing,
                                             line_ends_only=not self.stop_requested))

    def _coast_out(self, now):
        """A4 while the simulated arm moves: it brakes to rest as soon as the
        acceleration limits allow after ``now``, the extruder stopped there
        (:func:`ambots.trajectory.stop_now`, as a streaming driver's abort
        brakes a real arm: :meth:`ambots.trajectory.Stream.abort`), and goes
        on moving on that brake while the runner is already idle: its joints
        (:meth:`joints`) and trace follow the brake, and the next motion
        (A1, A7) starts where and when the arm has come to rest
        (:meth:`rest_at`).  The extrusion between the last waypoint reached
        and ``now`` is not recorded as a bead (at most one waypoint interval)."""
        b = self.block
        if b is None or b.motion is None or self.on_motion is not None or self.state is not ArmState.PRINTING:
            return
        from ambots.trajectory import stop_now
        H = max(max(now, self.clock) - self.block_t0, float(b.t[self.k]))
        T = stop_now(b.motion, H, self.planner.timing.amax)
        self.coast = (b.motion, self.block_t0, float(b.t[self.k]), float(T))
        self.q = b.motion.eval(np.array([T]))[0][0]
        self._coast_run(self.clock)

    def rest_at(self):
        """Simulated time at which the arm comes to rest from a brake after
        A4 (:meth:`_coast_out`); -inf when it is not braking."""
        return self.coast[1] + self.coast[3] if self.coast is not None else -np.inf

    def _coast_run(self, now):
        """Record the brake after A4 up to simulated time ``now`` (trace
        knots every :data:`BRAKE_KNOT_S` s); forget it once at rest."""
        m, t0, tau, T = self.coast
        end = min(now - t0, T)
        if end > tau + 1e-9 and self.record:
            ts = np.union1d(np.arange(tau, end, BRAKE_KNOT_S), [tau, end])
            q, v = m.eval(ts)[:2]
            if t0 + ts[0] <= self._trace_end:
                ts, q, v = ts[1:], q[1:], v[1:]
            self.trace_t.append(t0 + ts)
            self.trace_q.append(q)
            self.trace_v.append(v)
            self._trace_end = t0 + end
        if end >= T - 1e-12:
            self.coast = None
        else:
            self.coast = (m, t0, max(tau, end), T)

    def _resume(self, now):
        self.pause_requested = self.stop_requested = False
        self.state = ArmState.WAITING if self.wait is not None else ArmState.PRINTING
        if self.block is not None:       # continue the block where it stopped
            self.block_t0 = now - self.block.t[self.k]
            if self.on_motion is not None:
                self.on_motion(self.block, self.block_t0, self.k)
        self.clock = now
        self._report()

    def _load(self, msg):
        if self.state in (ArmState.PRINTING, ArmState.WAITING, ArmState.PAUSED):
            self._error(0, "A5 refused: arm is %s; clear (A4) or let it finish first" % self.state.name)
            return
        if msg.identity == self.chunk:
            return                       # the same chunk again
        try:
            items, n_lines, layer_of_line = read_program(msg.gcode, "chunk %s" % msg.chunk_id)
        except GCodeError as exc:
            self._error(exc.line or 0, "A5 refused: %s" % exc)
            return
        self._clear()
        self.chunk = msg.identity
        self.items, self.n_lines, self.layer_of_line = items, n_lines, layer_of_line
        self.state = ArmState.IDLE
        self._report()

    def _manual_move(self, msg, now):
        if self.state in (ArmState.PRINTING, ArmState.WAITING) or self.block is not None:
            self._error(0, "A7 refused while %s%s" % (self.state.name, " in the middle of a move"
                                                       if self.block is not None else ""))
            return
        target = self.planner.bed_mm_to_base(np.array([[msg.x, msg.y, msg.z]]))[0]
        block = self.planner.move_to(target, self.q, line=self.done_line, layer=self.layer)
        if block.error is not None:
            self.stats.ik_failures += 1
            self._error(0, "A7 X%g Y%g Z%g: %s" % (msg.x, msg.y, msg.z, block.error.message))
            return
        self.after_block = self.state
        self._block_src = ["manual", float(msg.x), float(msg.y), float(msg.z)]
        self.state = ArmState.PRINTING
        self._begin(block, max(now, self.rest_at()))

    # ----------------------------------------------------------- checkpoints
    def checkpoint(self):
        """Everything needed to resume this run after a crash, as a
        JSON-able dict (the chunk's text is not in it: the caller keeps it).
        Progress is recorded to the waypoint: the current block's source
        (program item or manual move), the line it is executing and whether
        that line is complete; :meth:`restore` re-plans the rest of that
        item from the joints ``q`` the arm had reached."""
        cur = None
        b = self.block
        if b is not None and self._block_src is not None:
            k = self.k
            cur = {"src": list(self._block_src), "line": int(b.line[k]) if k > 0 else None,
                   "line_done": bool(b.line_end[k]) if k > 0 else False, "t": float(b.t[k]),
                   "after": self.after_block.name if self.after_block is not None else None}
        return {
            "chunk": list(self.chunk) if self.chunk is not None else None, "started": self.started,
            "state": self.state.name, "clock": self.clock, "idx": self.idx, "q": self.q.tolist(),
            "done_line": int(self.done_line), "layer": int(self.layer),
            "wait": encode(self.wait) if self.wait is not None else None,
            "pause_requested": self.pause_requested, "stop_requested": self.stop_requested,
            "reported_line": int(self.reported_line),
            "peers": {str(i): encode(st) for i, st in self.peers.items() if st is not None},
            "peer_time": {str(i): t for i, t in self.peer_time.items()},
            "peer_log": {str(i): [list(e) for e in log] for i, log in self.peer_log.items()},
            "stats": asdict(self.stats), "block": cur,
        }

    def restore(self, cp, text):
        """Resume from :meth:`checkpoint` ``cp`` with the chunk's G-code
        ``text``.  The block in progress is re-planned from the joints
        reached: a line cut short continues from the nozzle's position to
        its end (its filament in proportion), so no bead is laid twice and
        none is missing."""
        items, n_lines, layer_of_line = read_program(text, "chunk %s" % (cp["chunk"] or ["?"])[0])
        self._clear()
        self.chunk = tuple(cp["chunk"]) if cp["chunk"] is not None else None
        self.items, self.n_lines, self.layer_of_line = items, n_lines, layer_of_line
        self.state = ArmState[cp["state"]]
        self.started = bool(cp.get("started", self.state is not ArmState.IDLE))
        self.clock, self.idx = float(cp["clock"]), int(cp["idx"])
        self.q = np.array(cp["q"], dtype=float)
        self.done_line, self.layer = int(cp["done_line"]), int(cp["layer"])
        self.wait = decode(cp["wait"]) if cp["wait"] else None
        self.pause_requested, self.reported_line = bool(cp["pause_requested"]), int(cp["reported_line"])
        self.stop_requested = bool(cp.get("stop_requested", False))
        self.peers = {int(i): decode(t) for i, t in cp["peers"].items()}
        self.peer_time = {int(i): float(t) for i, t in cp["peer_time"].items()}
        self.peer_log = {int(i): deque([tuple(e) for e in log], maxlen=256)
                         for i, log in cp.get("peer_log", {}).items()}
        self.stats = RunStats(**cp["stats"])
        cur = cp["block"]
        if cur is None:
            return
        src = cur["src"]
        if src[0] == "manual":
            target = self.planner.bed_mm_to_base(np.array([src[1:4]], dtype=float))[0]
            self.block = self.planner.move_to(target, self.q, line=self.done_line, layer=self.layer)
            self.after_block = ArmState[cur["after"]] if cur["after"] else None
        else:
            item = self.items[int(src[1])]
            if isinstance(item, Dwell):
                self.block = self.planner.dwell(self.q, max(0.0, item.seconds - cur["t"]), item.line,
                                                self.layer_of_line[item.line])
            elif isinstance(item, Directive):          # a MoveTo of the program
                msg = item.message
                target = self.planner.bed_mm_to_base(np.array([[msg.x, msg.y, msg.z]]))[0]
                self.block = self.planner.move_to(target, self.q, line=item.line,
                                                  layer=self.layer_of_line[item.line])
            else:
                rest = _remaining(item.segments, cur["line"], cur["line_done"], self.nozzle_mm())
                self.block = self.planner.plan_moves(rest, self.q) if rest else None
        self._block_src = list(src)
        self._begin(self.block, self.clock)

    # ----------------------------------------------------------- time
    def _wait_satisfied(self):
        w = self.wait
        st = self.peers.get(w.other)
        if st is None:
            return False
        if st.state is ArmState.DONE:
            return True
        if w.line is not None:
            return st.line >= w.line
        return st.layer >= w.layer

    def advance(self, now):
        """Run until simulated time ``now`` (s) or until the arm stops
        (waits, pauses, finishes or fails)."""
        if self.coast is not None:
            self._coast_run(now)
        while True:
            if self.state is ArmState.WAITING:
                wake = self.release_time()
                if wake is not None:
                    if wake > now:           # released later: by the other arm's clock it is not there yet
                        self._idle_until(now)
                        return
                    self._idle_until(wake)
                    self.wait = None
                    self.state = ArmState.PRINTING
                    continue
                return                   # the clock stays where the wait began
            if self.state is ArmState.PAUSED:
                self._idle_until(now)
                return
            if self.state is not ArmState.PRINTING:
                self.clock = max(self.clock, now)
                return
            if self.block is None and not self._next_block():
                continue
            if not self._run_block(now):
                return

    def release_time(self):
        """When the barrier being waited on releases this arm (simulated s):
        the other arm's clock when it reported the awaited line, never before
        this arm's own clock; None while the wait is not satisfied."""
        if self.state is not ArmState.WAITING or self.wait is None or not self._wait_satisfied():
            return None
        w = self.wait
        t = self.peer_time.get(w.other, self.clock)
        for done, line, layer, clock in self.peer_log.get(w.other, ()):    # the first report that satisfied it
            if done or (line >= w.line if w.line is not None else layer >= w.layer):
                t = clock
                break
        return max(self.clock, t)

    def _idle_until(self, now):
        if now > self.clock:
            if self.stats.first_motion_s is not None:
                self.stats.idle_time_s += now - self.clock
            self.clock = now

    def _next_block(self):
        """Take the next item.  Returns True if a block is ready to run."""
        if self.pause_requested:          # between two items is a clean point
            self.pause_requested = self.stop_requested = False
            self.state = ArmState.PAUSED
            self._report()
            return False
        if self.idx >= len(self.items):
            self.done_line = self.n_lines
            self.state = ArmState.DONE
            self.stats.done_s = self.clock
            self._report(with_position=True)
            return False
        item = self.items[self.idx]
        self.idx += 1
        if isinstance(item, Directive):
            self.done_line = max(self.done_line, item.line - 1)
            if isinstance(item.message, WaitFor) and self.reported_line != self.done_line:
                self._report()        # what the other arms' barriers wait for (also a line before
                #                       a chain of barriers: another arm may wait for exactly it)
            self._directive(item)
            return False
        self._block_src = ["item", self.idx - 1]
        if isinstance(item, Dwell):
            self.block = self.planner.dwell(self.q, item.seconds, item.line, self.layer_of_line[item.line])
        else:
            ahead = self._ahead.pop(self.idx - 1, None)
            if ahead is not None and np.array_equal(ahead[0], self.q):
                self.block = ahead[1]
            else:
                self.block = self.planner.plan_moves(item.segments, self.q)
            self.stats.moves += len(item.segments)
        b = self.block
        self.stats.plans[b.planned] = self.stats.plans.get(b.planned, 0) + 1
        self.stats.max_path_error_mm = max(self.stats.max_path_error_mm, b.max_deviation_mm)
        self._begin(b, self.clock)
        return True

    def prefetch(self, max_items=4):
        """Plan one more of the next moves ahead of time (while the arm
        waits at a barrier, or in spare time between ticks), so that the
        plan is ready when the arm gets there.  Looks at most ``max_items``
        items ahead and not past a barrier, a manual move or the end.
        Returns True if it planned something (call again while there is
        time), False if there is nothing more to plan ahead."""
        if self.state not in (ArmState.PRINTING, ArmState.WAITING, ArmState.PAUSED):
            return False
        q = self.block.Q[-1] if self.block is not None else self.q
        for i in range(self.idx, min(self.idx + max_items, len(self.items))):
            item = self.items[i]
            if isinstance(item, Directive):
                msg = item.message
                if getattr(msg, "robot", None) == self.id and isinstance(msg, (WaitFor, MoveTo)):
                    return False
                continue
            if isinstance(item, Dwell):
                continue
            ahead = self._ahead.get(i)
            if ahead is not None and np.array_equal(ahead[0], q):
                q = ahead[1].Q[-1]
                continue
            block = self.planner.plan_moves(item.segments, q)
            self._ahead[i] = (np.array(q, dtype=float), block)
            return True
        return False

    def _directive(self, item):
        msg = item.message
        target = getattr(msg, "robot", None)
        if isinstance(msg, WaitFor) and target == self.id:
            # wait even if the awaited report is already here: advance()
            # releases the arm at the reporter's clock when it reported
            # (release_time), at once if that is not later than this arm's
            # own clock.  Clocks of arms are independent (speed max, the
            # offline simulator): a report from an arm whose clock is ahead
            # must not let this arm into the region the other arm left only
            # at that later moment
            self.done_line = item.line
            self.wait = msg
            self.state = ArmState.WAITING
            return
        if isinstance(msg, SendPosition):      # ;@A3 R<to>: report (A10 with position) now
            self.done_line = item.line
            self._report(with_position=True)
            return
        if target == self.id and isinstance(msg, MoveTo):
            target_base = self.planner.bed_mm_to_base(np.array([[msg.x, msg.y, msg.z]]))[0]
            self._block_src = ["item", self.idx - 1]
            self._begin(self.planner.move_to(target_base, self.q, line=item.line,
                                             layer=self.layer_of_line[item.line]), self.clock)
            self.stats.plans[self.block.planned] = self.stats.plans.get(self.block.planned, 0) + 1
            return
        if target == self.id and isinstance(msg, Pause):
            # ;@A2 to itself (sequential mode: until the arm it handed over to resumes it, A6)
            self.done_line = item.line
            self.state = ArmState.PAUSED
            self._report()
            return
        if target == self.id:
            self.done_line = item.line
            return
        # addressed to another arm: send it through the hub
        self.outbox.append((self.clock, msg))
        self.done_line = item.line

    def _run_block(self, now):
        """Advance in the current block.  Returns False when time is used up
        (or the arm stopped), True when the block finished."""
        b = self.block
        K = len(b.t)
        t_rel = now - self.block_t0 + TIME_TOLERANCE_S     # a clock step to an event lands on it
        kk = int(np.searchsorted(b.t, t_rel, side="right")) - 1
        kk = min(max(kk, self.k), K - 1)
        stop = None
        if self.pause_requested:
            j = self._pause_point(b)
            if j <= kk:
                kk, stop = j, True
        if kk > self.k:
            self._execute(b, self.k, kk)
            self.k = kk
        if stop:
            self.pause_requested = self.stop_requested = False
            self.pause_at = None
            self.clock = self.block_t0 + b.t[self.k]
            if self.k == K - 1:
                self._end_block()
            self.state = ArmState.PAUSED
            self._report()
            return False
        if self.k == K - 1:
            self.clock = self.block_t0 + b.duration
            self._end_block()
            return self.state is ArmState.PRINTING
        self.clock = now
        return False

    def next_event(self):
        """When this arm next reports or reaches a barrier by itself (s): the
        end of the block it executes, or where a requested pause stops it;
        None when it is not printing (it waits, pauses, is idle or done)."""
        if self.state is not ArmState.PRINTING:
            return None
        b = self.block
        if b is None:
            return self.clock
        j = self._pause_point(b) if self.pause_requested else len(b.t) - 1
        return self.block_t0 + float(b.t[j])

    def _pause_point(self, b):
        """The waypoint where a pause requested now stops the block ``b``:
        :attr:`pause_at` if set for it, else the end of the line being executed."""
        if self.pause_at is not None and self.pause_at[0] is b and self.pause_at[1] > self.k:
            return int(self.pause_at[1])
        if self.stop_requested:
            return min(self.k + 1, len(b.t) - 1)
        ends = np.nonzero(b.line_end[self.k + 1:])[0]
        return self.k + 1 + int(ends[0]) if len(ends) else len(b.t) - 1

    def _execute(self, b, k0, k1):
        """Waypoints k0 -> k1 of block ``b`` are reached."""
        sl = slice(k0 + 1, k1 + 1)
        self.q = b.Q[k1].copy()
        self.stats.print_time_s += float(b.t[k1] - b.t[k0])
        done = np.nonzero(b.line_end[sl])[0]
        if len(done):
            self.done_line = max(self.done_line, int(b.line[sl][done[-1]]))
        lay = int(b.layer[k1])
        if lay != self.layer:
            self.layer = lay
        ex = b.extrude[sl]
        if ex.any():
            idx = np.arange(k0 + 1, k1 + 1)[ex]
            self.beads.append(Bead(b.tip[idx - 1], b.tip[idx], b.e_mm[idx], b.line[idx], b.layer[idx],
                                   self.block_t0 + b.t[idx]))
        if self.record:
            # from waypoint k0 when the arm reaches it later than the last
            # knot recorded: it stood there until then, at rest (a block
            # starting after a barrier; a block resumed, A6, after a pause or
            # a stop braked it to rest on k0).  Without this knot the trace,
            # interpolated, would move the arm all through the wait, towards
            # the next waypoint -- and, a Hermite cubic over the whole wait
            # with that waypoint's speed, far off the path
            t0 = self.block_t0 + b.t[k0]
            sl_rec = slice(k0, k1 + 1) if t0 > self._trace_end + TIME_TOLERANCE_S else sl
            self._trace_end = self.block_t0 + b.t[k1]
            tau, Q, V = _knots(b, b.t[sl_rec], b.Q[sl_rec], after=b.t[k0])
            self.trace_t.append(self.block_t0 + tau)
            self.trace_q.append(Q)
            self.trace_v.append(V)

    def _end_block(self):
        b = self.block
        self.stats.extrude_m += b.extrude_m
        self.stats.travel_m += b.travel_m
        self.block = None
        if b.blocked is not None and self._block_src is not None and self._block_src[0] == "item":
            # only other arms were in the way: plan the same item again, up to max_blocked_s
            self.blocked_s += b.duration
            self.stats.print_time_s -= b.duration      # a wait, not motion
            self.stats.idle_time_s += b.duration
            if self.blocked_s <= self.max_blocked_s:
                self.idx = self._block_src[1]
                self._ahead.pop(self.idx, None)
                return
            b.error = MotionError(int(b.line[0]), "other arms blocked the way for %.0f s: %s"
                                  % (self.blocked_s, b.blocked))
        self.blocked_s = 0.0
        if b.error is not None:
            self.stats.ik_failures += 1
            self.state = ArmState.ERROR
            self._error(b.error.line, b.error.message)
            self._report(with_position=True)
            return
        if self.after_block is not None:        # a manual A7 move
            self.state, self.after_block = self.after_block, None
            self._report(with_position=True)


#: s between the knots recorded while an arm brakes (the warp of a pause is
#: not a cubic between waypoints; at this spacing the recorded Hermite knots
#: follow it to well under a micrometre)
BRAKE_KNOT_S = 0.01


def _knots(block, tau, Q, after=None):
    """The executed motion of ``block`` at block times ``tau`` (the
    waypoints reached) as Hermite knots ``(tau, Q, V)``: positions and speeds
    of the commanded motion, plus knots every :data:`BRAKE_KNOT_S` s where
    the motion brakes after ``after`` (the block time of the knot recorded
    last; default ``tau[0]``): a brake begun between that knot and
    ``tau[0]`` is no cubic through the two; without a motion (a block of
    one waypoint), at rest."""
    m = block.motion
    if m is None or len(tau) == 0:
        return tau, Q, np.zeros_like(Q)
    lo = tau[0] if after is None else after
    extra = [np.arange(max(p.t_b, lo), min(p.end, tau[-1]), BRAKE_KNOT_S)
             for p in m.pieces if p.c is not None and p.t_b < tau[-1] and p.end > lo]
    if extra:
        extra = np.concatenate(extra)
        tau = np.union1d(tau, extra if after is None else extra[extra > after + TIME_TOLERANCE_S])
    q, v = m.eval(tau)[:2]
    return tau, q, v


def _remaining(segments, line, line_done, nozzle_mm):
    """The segments of a Moves item still to execute when the nozzle is at
    ``nozzle_mm`` (bed frame, mm) in line ``line`` (None: nothing done yet),
    complete or not: the rest of a cut line starts at the nozzle, with the
    remaining share of its filament."""
    if line is None:
        return list(segments)
    idx = [i for i, s in enumerate(segments) if s.line == line]
    if not idx:
        return list(segments)
    if line_done:
        return list(segments[idx[-1] + 1:])
    p = np.asarray(nozzle_mm, dtype=float)

    def dist(s):
        a, b = np.asarray(s.start, dtype=float), np.asarray(s.end, dtype=float)
        ab = b - a
        u = 0.0 if not ab.any() else float(np.clip((p - a) @ ab / (ab @ ab), 0.0, 1.0))
        return float(np.linalg.norm(a + u * ab - p)), u

    j = min(idx, key=lambda i: dist(segments[i])[0])
    (off, u), s = dist(segments[j]), segments[j]
    if off > 0.5:                 # not on the line yet (a joint move leading to it): all of it
        return list(segments[j:])
    head = []
    if u < 1.0 - 1e-9:
        head = [s._replace(start=tuple(float(v) for v in p), e=s.e * (1.0 - u))]
    return head + list(segments[j + 1:])
