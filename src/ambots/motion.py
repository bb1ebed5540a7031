"""From an arm's program to joint motion: the firmware's planner.

A program (G-code plus ``;@`` directive lines, see :mod:`ambots.program`)
is read into a list of *items*, in line order:

* :class:`Moves` -- a run of consecutive G-code segments (bed frame, mm);
* :class:`Directive` -- an A-series command to execute at that line;
* :class:`Pause` -- a ``G4`` dwell.

:class:`MotionPlanner` turns one :class:`Moves` item into a :class:`Block`
of time-stamped joint waypoints, steps a real controller could follow:

1. every straight G-code move is sampled (``sample_mm`` apart), converted
   once to metres in the arm's base frame and solved by
   :meth:`~ambots.kinematics.ArmKinematics.ik_path` (each point seeded by
   the previous, nozzle pointing down, joint continuity checked);
2. between two waypoints a controller interpolates the *joints* linearly;
   the nozzle then leaves the straight line a little.  That deviation is
   measured by forward kinematics at the middle of every interval and the
   interval is halved until it is at most ``tolerance_mm`` (0.1 mm);
3. each interval gets the duration of its programmed feedrate, stretched
   where a joint would exceed its speed limit (``velocity`` x the profile's
   ``velocity_scaling``);
4. a move that does not start where the nozzle is (the first move of a
   program, or after a park) is a joint-space move to the end of that move,
   checked against obstacles and planned around them with OMPL when a
   straight joint move is blocked (:mod:`ambots.planning`), against a
   caller-supplied obstacle check (``is_valid``) when there is one.  The
   G-code's own moves (extrusion and travel) follow the program's path and
   are not checked here: their safety from other arms comes from the
   coordinator's barriers (:mod:`ambots.coordinate`).

Units: metres, radians and seconds inside; mm only where G-code is read
(:mod:`ambots.units`).  World frame = the cell's; bed frame = G-code frame.
"""
import re
from dataclasses import dataclass
from typing import List, Optional

import numpy as np

from ambots.errors import AmbotsError, UnreachableError
from ambots.gcode import Dwell, Segment, parse_gcode_text
from ambots.program import DIRECTIVE, parse_directive
from ambots.trajectory import SplineTiming, joint_limits
from ambots.units import MM
from ambots.workspace import down_in_base

__all__ = ["Moves", "Directive", "Pause", "read_program", "Block", "MotionPlanner",
           "MotionError", "DEFAULT_TOLERANCE_MM"]

#: largest distance (mm) between the nozzle and the programmed straight line
DEFAULT_TOLERANCE_MM = 0.1
#: distances (mm) from both ends of a straight move at which extra waypoints
#: are placed (where the piece at that end is long enough): the ramps of the
#: timing law at a corner happen over these
RAMP_MM = (0.3, 1.0, 3.0)


class MotionError(AmbotsError):
    """The arm cannot execute a line of its program.  Attributes: ``line``
    (1-based line of the program), ``message``."""

    def __init__(self, line, message):
        self.line, self.message = line, message
        super().__init__("line %d: %s" % (line, message))


# ------------------------------------------------------------- the program
@dataclass
class Moves:
    segments: List[Segment]

    @property
    def line(self):
        return self.segments[0].line


@dataclass
class Directive:
    line: int
    message: object          #: a protocol dataclass (WaitFor, MoveTo, Start...)


@dataclass
class Pause:
    line: int
    seconds: float


def read_program(text, path="<chunk>", max_run=400, events=None):
    """Program text -> (items, n_lines, layer_of_line).

    ``items`` in line order; moves are split at every directive, dwell and
    layer change, and into runs of at most ``max_run`` segments (so that a
    firmware plans a little ahead of the nozzle, never the whole print
    before it moves).
    ``layer_of_line`` (n_lines + 1,) gives the layer of each line (index 0
    unused).  Malformed G-code or directives raise
    :class:`~ambots.errors.GCodeError` naming ``path`` and the line.
    ``events``: the text's G-code events when the caller has parsed it
    already (:meth:`ambots.coordinate.ArmProgram.parse`), else it is parsed here."""
    n_lines = text.count("\n")
    if not text.endswith("\n"):
        n_lines += 1               # a final line break ends the last line, it starts none
    # directive lines: found in the text (a few hundred among 100,000s of lines)
    directives = {}
    number, at = 1, 0
    for m in _DIRECTIVE_LINE.finditer(text):
        number += text.count("\n", at, m.start())
        at = m.start()
        end = text.find("\n", at)
        directives[number] = parse_directive(text[at:] if end < 0 else text[at:end], path, number)
    items = []
    append = items.append
    marks = sorted(directives)
    n_marks = len(marks)
    mi = 0
    next_mark = marks[0] if marks else n_lines + 2
    ev_lines, ev_layers = [], []
    run, run_layer = [], None
    for ev in parse_gcode_text(text, path) if events is None else events:
        kind = type(ev)
        if kind is not Segment and kind is not Dwell:
            continue
        line = ev.line
        while next_mark < line:        # the directives before this line, in order
            if run:
                append(Moves(run))
                run = []
            append(Directive(next_mark, directives[next_mark]))
            mi += 1
            next_mark = marks[mi] if mi < n_marks else n_lines + 2
        ev_lines.append(line)
        ev_layers.append(ev.layer)
        if kind is Segment:
            if run and (ev.layer != run_layer or len(run) >= max_run):
                append(Moves(run))
                run = []
            run.append(ev)
            run_layer = ev.layer
        else:
            if run:
                append(Moves(run))
                run = []
            append(Pause(line, ev.seconds))
    if run:
        append(Moves(run))
    for m in marks[mi:]:
        append(Directive(m, directives[m]))
    # each line's layer: that of the last event on or before it (0 before the first)
    layer_of_line = np.zeros(n_lines + 1, dtype=int)
    if ev_lines:
        at_line = np.asarray(ev_lines)
        which = np.searchsorted(at_line, np.arange(n_lines + 1), side="right") - 1
        layer_of_line = np.where(which >= 0, np.maximum(np.asarray(ev_layers), 0)[np.maximum(which, 0)], 0)
    return items, n_lines, layer_of_line


#: the start of a directive line (:func:`ambots.program.is_directive`)
_DIRECTIVE_LINE = re.compile(r"^[ \t]*" + re.escape(DIRECTIVE), re.M)


# ------------------------------------------------------------- the motion
@dataclass
class Block:
    """Planned motion of one item: K time-stamped waypoints.

    ``t`` (K,) s from the block's start (t[0] = 0); ``Q`` (K, n) rad;
    ``tip`` (K, 3) nozzle positions in the world frame (m), by forward
    kinematics of ``Q``.  Interval k is waypoint k-1 -> k (k >= 1); per
    interval (index k, entry 0 unused): ``line`` the program line it executes,
    ``layer``, ``extrude`` whether it deposits, ``e_mm`` filament pushed.
    ``line_end`` (K,): waypoint k completes line ``line[k]``.
    ``max_deviation_mm``: largest measured distance between the nozzle and
    the programmed line over extrusion intervals.
    """
    t: np.ndarray
    Q: np.ndarray
    tip: np.ndarray
    line: np.ndarray
    layer: np.ndarray
    extrude: np.ndarray
    e_mm: np.ndarray
    line_end: np.ndarray = None
    max_deviation_mm: float = 0.0
    travel_m: float = 0.0
    extrude_m: float = 0.0
    error: Optional[MotionError] = None      #: set if the arm cannot go past the block's end
    planned: str = "cartesian"               #: or "joint" / "ompl" for joint-space moves
    motion: Optional[object] = None          #: a :class:`~ambots.trajectory.Motion` (planner ``timing``)
    cartesian: Optional[np.ndarray] = None   #: (K,) interval k is part of a straight G-code move
    #: set on a wait in place because only other arms' current poses block the
    #: way (the runner plans the move again after it): why, e.g. "goal in collision"
    blocked: Optional[str] = None

    def __post_init__(self):
        if self.cartesian is None:
            self.cartesian = np.zeros(len(self.t), dtype=bool)
        if self.line_end is None:
            le = np.zeros(len(self.t), dtype=bool)
            if len(self.t) > 1:
                le[1:-1] = self.line[1:-1] != self.line[2:]
                le[-1] = True
            self.line_end = le

    @property
    def duration(self):
        return float(self.t[-1]) if len(self.t) else 0.0


def _concat(blocks):
    """Join blocks that follow each other (each starts where the previous ends)."""
    blocks = [b for b in blocks if b is not None and len(b.t)]
    if len(blocks) == 1:
        return blocks[0]
    t, parts = [], []
    offset = 0.0
    for i, b in enumerate(blocks):
        s = slice(0 if i == 0 else 1, None)
        t.append(b.t[s] + offset)
        offset += b.duration
        parts.append(b)
    cat = lambda name: np.concatenate([getattr(b, name)[0 if i == 0 else 1:] for i, b in enumerate(parts)])
    return Block(np.concatenate(t), cat("Q"), cat("tip"), cat("line"), cat("layer"), cat("extrude"),
                 cat("e_mm"), cat("line_end"), max(b.max_deviation_mm for b in parts),
                 sum(b.travel_m for b in parts), sum(b.extrude_m for b in parts),
                 next((b.error for b in parts if b.error is not None), None),
                 "+".join(sorted({b.planned for b in parts})), cartesian=cat("cartesian"))


def _point_line_distance(X, A, B):
    """Distance of points X from segments A-B, all (N, 3) -> (N,)."""
    d = B - A
    L2 = np.einsum("ij,ij->i", d, d)
    u = np.where(L2 > 0, np.einsum("ij,ij->i", X - A, d) / np.where(L2 > 0, L2, 1.0), 0.0)
    u = np.clip(u, 0.0, 1.0)
    return np.linalg.norm(X - (A + u[:, None] * d), axis=1)


class MotionPlanner:
    """Plans one arm's motion.

    Parameters
    ----------
    arm : :class:`~ambots.config.ArmInstance`
    cell : :class:`~ambots.config.Cell` (its bed pose maps G-code to world)
    kin : :class:`~ambots.kinematics.ArmKinematics` (default: built from the arm)
    tolerance_mm : largest nozzle deviation from a programmed straight line
    sample_mm : first sampling step along a move (refined where needed)
    is_valid : optional ``f(Q (N, n)) -> bool (N,)`` saying which joint
        vectors are free of collisions right now (bed, part, other arms);
        travel and joint moves are checked with it and re-planned by OMPL.
        If it has an attribute ``static`` (the same check without the
        other arms), a move that only the other arms' current poses block
        becomes a wait in place of ``blocked_wait_s`` s (``Block.blocked``)
        after which the runner plans it again, instead of an error.  If
        it has ``explain(q)`` (what ``q`` is too close to), a start or goal
        in collision says so in ``Block.blocked`` and in the error.
    timing : the timing law applied to every block the planner returns
        (default and only law in use: :class:`ambots.trajectory.SplineTiming`
        for this planner -- the programmed feedrates as the wanted nozzle
        speed, every joint within its speed and acceleration limits; the
        block carries the commanded motion in ``block.motion``)
    """

    def __init__(self, arm, cell, kin=None, tolerance_mm=DEFAULT_TOLERANCE_MM, sample_mm=10.0,
                 is_valid=None, plan_timeout=2.0, timing=None):
        from ambots.kinematics import shared_arm_kinematics
        self.arm, self.cell = arm, cell
        self.kin = kin or shared_arm_kinematics(arm)
        self.tolerance = tolerance_mm * MM
        self.sample = sample_mm * MM
        self.is_valid = is_valid
        self.plan_timeout = plan_timeout
        self.blocked_wait_s = 0.5         #: s to wait before planning a blocked move again
        #: > 1 stretches every planned duration (an arm slower than planned)
        self.time_scale = 1.0
        #: optional (rng, lo, hi): each planned block is stretched by a further
        #: factor drawn uniformly from [lo, hi] (an arm whose speed varies
        #: from move to move; timing-robustness tests, ``plan --slow ARM=LO:HI``)
        self.time_jitter = None
        prof = arm.profile
        self.vmax, self.amax = joint_limits(prof)
        self.down = down_in_base(arm)
        #: no nozzle position is farther from the base (m): a loose bound
        #: (twice the published reach, plus the tool) used to cut a run of moves
        #: at the first move that leaves it (see :meth:`_cartesian`)
        self.max_reach = 2.0 * (prof.reach + float(np.linalg.norm(prof.tool_xyz)))
        T_bed = cell.bed.pose
        # bed mm -> base m in one affine map
        Tb = np.linalg.inv(arm.base_pose) @ T_bed
        self._bed_R, self._bed_t = Tb[:3, :3] * MM, Tb[:3, 3]
        self._world = arm.base_pose
        self.timing = timing if timing is not None else SplineTiming.for_planner(self)

    # -------------------------------------------------------- frames
    def bed_mm_to_base(self, P):
        """(N, 3) bed-frame mm -> (N, 3) base-frame m."""
        return np.asarray(P, dtype=float) @ self._bed_R.T + self._bed_t

    def base_to_world(self, P):
        T = self._world
        return P @ T[:3, :3].T + T[:3, 3]

    def tip_world(self, Q):
        """Nozzle positions (N, 3) in the world frame for joint vectors (N, n)."""
        return self.base_to_world(self.kin.fk_batch(Q)[:, :3, 3])

    def world_to_bed_mm(self, P):
        T = np.linalg.inv(self.cell.bed.pose)
        return (np.asarray(P, dtype=float) @ T[:3, :3].T + T[:3, 3]) / MM

    def _scale(self):
        """The factor stretching the block being planned."""
        if self.time_jitter is None:
            return self.time_scale
        rng, lo, hi = self.time_jitter
        return self.time_scale * float(rng.uniform(lo, hi))

    # -------------------------------------------------------- segments
    def _timed(self, block, scaled=True):
        """``block`` timed by the one timing law, stretched by :meth:`_scale`
        (``scaled``) when the arm is set to run slower than planned."""
        f = self._scale() if scaled else 1.0
        return self.timing(block, scale=f) if f != 1.0 else self.timing(block)

    def plan_moves(self, segments, q0):
        """A run of G-code segments starting at joint vector ``q0`` -> Block.

        If the first segment does not start where the nozzle is, the nozzle
        first makes a joint-space move there.  An unreachable point ends the
        block at the last reachable waypoint with ``error`` set."""
        return self._timed(self._plan_moves(segments, q0))

    def _plan_moves(self, segments, q0):
        q0 = np.asarray(q0, dtype=float)
        here = self.kin.fk_batch(q0[None])[0, :3, 3]
        first = segments[0]
        start = self.bed_mm_to_base(np.array([first.start]))[0]
        lead = None
        if np.linalg.norm(start - here) > 0.5 * MM:
            # a travel to somewhere else: joint move straight to the end of
            # the first travel (no point following a fictitious start)
            if not first.extrude:
                target = self.bed_mm_to_base(np.array([first.end]))[0]
                lead = self._joint_move_to(target, q0, line=first.line, layer=max(first.layer, 0))
                segments = segments[1:]
            else:
                lead = self._joint_move_to(start, q0, line=first.line, layer=max(first.layer, 0))
            if lead.error is not None or lead.blocked is not None or not segments:
                return lead
            q0 = lead.Q[-1]
        body = self._cartesian(segments, q0)
        return _concat([lead, body]) if lead is not None else body

    def _cartesian(self, segments, q0):
        # a move ending out of reach fails anyway: drop the moves after it, so
        # that absurd coordinates (+-1e6 mm) cost one move's samples, not GBs
        # of samples for the whole run
        E_base = self.bed_mm_to_base(np.array([s.end for s in segments], dtype=float))
        far = np.linalg.norm(E_base, axis=1) > self.max_reach
        if far.any():
            segments = segments[:int(np.argmax(far)) + 1]
        n = len(segments)
        S = np.array([s.start for s in segments], dtype=float)
        E = np.array([s.end for s in segments], dtype=float)
        Lmm = np.linalg.norm(E - S, axis=1)
        pieces = np.maximum(1, np.ceil(Lmm * MM / self.sample)).astype(int)
        pieces[Lmm == 0] = 1
        # sample points: the start, then each segment's interior points and end
        seg_of = np.repeat(np.arange(n), pieces)                      # per interval
        frac = (np.arange(len(seg_of)) - np.repeat(np.cumsum(pieces) - pieces, pieces) + 1) / np.repeat(pieces, pieces)
        # near both ends of a move, points at RAMP_MM from the end: where the arm
        # rests at a corner, the timing law's cubics ramp the nozzle up to the
        # feedrate (and down) over these short pieces, not over a whole sample
        ramp = np.asarray(RAMP_MM)
        near = ramp[None, :] < 0.45 * Lmm[:, None] / pieces[:, None]      # inside the end pieces
        if near.any():
            si, ri = np.nonzero(near)
            f_extra = ramp[ri] / Lmm[si]
            seg_of = np.concatenate([seg_of, si, si])
            frac = np.concatenate([frac, f_extra, 1.0 - f_extra])
            order = np.lexsort((frac, seg_of))
            seg_of, frac = seg_of[order], frac[order]
        # (1 - f) S + f E puts a segment's last sample exactly on its end (S + (E - S) f
        # need not: 0.8 + (0.2 - 0.8) != 0.2), so a following E-only move has zero length
        P_mm = np.concatenate([S[:1], (1.0 - frac[:, None]) * S[seg_of] + frac[:, None] * E[seg_of]])
        seg_of = np.concatenate([[seg_of[0]], seg_of])                 # waypoint k ends interval of segment seg_of[k]
        P = self.bed_mm_to_base(P_mm)
        Q, ok = self.kin.ik_path(P, q0, self.down, max_joint_step=0.35)
        error = None
        if not ok.all():
            bad = int(np.argmin(ok))
            seg = segments[seg_of[bad]]
            error = MotionError(seg.line, "unreachable: no joint configuration within limits puts the "
                                "nozzle at (%.2f, %.2f, %.2f) mm (bed frame) pointing down without a joint "
                                "jump" % tuple(P_mm[bad]))
            # stop after the last segment completed before the failing one
            keep = max(1, int(np.sum(seg_of[1:] < seg_of[bad])) + 1)
            P, Q, seg_of, P_mm = P[:keep], Q[:keep], seg_of[:keep], P_mm[:keep]
        # refine until joint interpolation stays within tolerance of the line
        for _ in range(8):
            if len(P) < 2:
                break
            Qm = 0.5 * (Q[:-1] + Q[1:])
            Xm = self.kin.fk_batch(Qm)[:, :3, 3]
            dev = _point_line_distance(Xm, P[:-1], P[1:])
            moving = np.linalg.norm(P[1:] - P[:-1], axis=1) > 1e-9
            bad = np.where((dev > self.tolerance) & moving)[0]
            if not len(bad):
                break
            Pm = 0.5 * (P[bad] + P[bad + 1])
            Qn, okn, _ = self.kin.ik_batch(Pm, Qm[bad], self.down)
            Qn[~okn] = Qm[bad][~okn]
            ins = bad + 1
            P = np.insert(P, ins, Pm, axis=0)
            Q = np.insert(Q, ins, Qn, axis=0)
            P_mm = np.insert(P_mm, ins, 0.5 * (P_mm[bad] + P_mm[bad + 1]), axis=0)
            seg_of = np.insert(seg_of, ins, seg_of[bad + 1])
        # measured deviation (after refinement) over extruding intervals
        K = len(P)
        seg_of_iv = seg_of.copy()
        extr = np.array([s.extrude for s in segments])[seg_of_iv]
        extr[0] = False
        extr[1:] &= np.linalg.norm(np.diff(P, axis=0), axis=1) > 0    # an unretraction lays no bead
        dev_max = 0.0
        if K >= 2:
            Qm = 0.5 * (Q[:-1] + Q[1:])
            Xm = self.kin.fk_batch(Qm)[:, :3, 3]
            dev = _point_line_distance(Xm, P[:-1], P[1:])
            if extr[1:].any():
                dev_max = float(dev[extr[1:]].max()) / MM
        # per-interval figures
        seg_L = np.maximum(Lmm, 1e-12)
        L_iv = np.zeros(K)
        L_iv[1:] = np.linalg.norm(np.diff(P_mm, axis=0), axis=1)
        e_seg = np.array([s.e for s in segments])
        e_iv = np.where(Lmm[seg_of_iv] > 0, e_seg[seg_of_iv] * L_iv / seg_L[seg_of_iv], e_seg[seg_of_iv])
        e_iv[0] = 0.0
        feed = np.array([s.feedrate for s in segments])[seg_of_iv]
        feed = np.where(feed > 0, feed, 1800.0) / 60.0                   # mm/s
        dt = np.zeros(K)
        dt[1:] = np.where(L_iv[1:] > 0, L_iv[1:] / feed[1:], np.abs(e_iv[1:]) / feed[1:])
        if K >= 2:
            dq = np.abs(np.diff(Q, axis=0))
            dt[1:] = np.maximum(dt[1:], np.max(dq / self.vmax, axis=1))
        t = np.cumsum(dt)
        lines = np.array([s.line for s in segments])[seg_of_iv]
        layers = np.maximum(np.array([s.layer for s in segments]), 0)[seg_of_iv]
        travel = float(L_iv[~extr].sum()) * MM
        extrude = float(L_iv[extr].sum()) * MM
        cart = np.ones(K, dtype=bool)
        cart[0] = False
        return Block(t, Q, self.base_to_world(self.kin.fk_batch(Q)[:, :3, 3]), lines, layers, extr, e_iv,
                     max_deviation_mm=dev_max, travel_m=travel, extrude_m=extrude, error=error, cartesian=cart)

    # -------------------------------------------------------- joint moves
    def joint_move_to(self, target_base, q0, line=0, layer=0):
        """Joint-space move of the nozzle to ``target_base`` (3,) base-frame m,
        pointing down: straight in joint space when clear, else OMPL."""
        return self._timed(self._joint_move_to(target_base, q0, line, layer))

    def move_to(self, target_base, q0, line=0, layer=0):
        """An A7: joint-space move of the nozzle to ``target_base`` (3,)
        base-frame m, pointing down, in the arm's reference posture: the
        target's IK starts from the home pose (from ``q0`` if it fails), so
        the arm stands at a park position with the same joints every time,
        whatever it printed before.  Along a print the IK starts from the
        joints before (a redundant arm turning back towards its home posture
        along its self-motion, :data:`ambots.kinematics.POSTURE_RAD_PER_M`;
        before session 22 the Panda of the three-arm cell drifted 2.6 rad on
        joints 1 and 3 after hours); the joint moves from the park position
        down to the part
        (:class:`~ambots.coordinate.parking.JointMoves`) are then the ones
        the coordinator checked."""
        return self._timed(self._joint_move_to(target_base, q0, line, layer,
                                               seed=np.asarray(self.arm.profile.home, dtype=float)))

    def joints_at(self, target_base, q0, seed=None):
        """(joints, None) that put the nozzle at ``target_base`` (3,) base-frame
        m pointing down, by IK from ``seed`` then ``q0`` (no seed: from ``q0``
        then the home pose), or (None, why) when neither reaches it."""
        q0 = np.asarray(q0, dtype=float)
        seeds = [q0, np.asarray(self.arm.profile.home, dtype=float)] if seed is None else [seed, q0]
        why = None
        for s in seeds:
            try:
                return self.kin.ik(target_base, s, self.down), None
            except UnreachableError as exc:
                why = why or exc
        return None, why

    def _joint_move_to(self, target_base, q0, line=0, layer=0, seed=None):
        q0 = np.asarray(q0, dtype=float)
        q1, why = self.joints_at(target_base, q0, seed)
        if q1 is None:
            return self._still(q0, line, layer, MotionError(line, "unreachable: %s" % why))
        return self._joint_path(q0, q1, line, layer)

    def _joint_path(self, q0, q1, line=0, layer=0):
        """Joint-space path q0 -> q1 (straight if clear, else OMPL), timed
        from the joint limits (the caller applies the planner's ``timing``)."""
        from ambots.planning import JointPlanner, PlanningError, interpolate, time_parametrize
        path, how = np.array([q0, q1]), "joint"
        if self.is_valid is not None:
            planner = JointPlanner(self.kin.lower, self.kin.upper, self.is_valid, resolution=0.02)
            try:
                path = planner.plan(q0, q1, timeout=self.plan_timeout)
            except PlanningError as exc:
                why = self._why(exc)
                if self._clear_without_others(q0, q1):
                    # only other arms, where they are now, are in the way: they move on
                    block = self.dwell(q0, self.blocked_wait_s, line, layer)
                    block.blocked = why
                    return block
                return self._still(q0, line, layer, MotionError(line, "no collision-free path: %s" % why))
            how = "joint" if len(path) == 2 else "ompl"
        path = interpolate(path, 0.05)
        t = np.asarray(time_parametrize(path, self.vmax, self.amax), dtype=float)
        K = len(path)
        tip = self.tip_world(path)
        L = float(np.linalg.norm(np.diff(tip, axis=0), axis=1).sum())
        return Block(np.asarray(t, dtype=float), path, tip, np.full(K, line), np.full(K, layer),
                     np.zeros(K, dtype=bool), np.zeros(K), travel_m=L, planned=how)

    def _why(self, exc):
        """The planner's message, and for a start or goal in collision what it
        is too close to (``is_valid.explain``, when it has one: obstacles,
        clearances in mm, links)."""
        explain = getattr(self.is_valid, "explain", None)
        q = {"start_invalid": exc.q_start, "goal_invalid": exc.q_goal}.get(exc.reason)
        if explain is None or q is None:
            return str(exc)
        return "%s: %s" % (exc, explain(q))

    def _clear_without_others(self, q0, q1):
        """Whether q0 -> q1 could be planned if the other arms were not
        where they are now (``is_valid.static``: the same check without
        moving obstacles; False when ``is_valid`` has none)."""
        from ambots.planning import JointPlanner, PlanningError
        static = getattr(self.is_valid, "static", None)
        if static is None:
            return False
        try:
            JointPlanner(self.kin.lower, self.kin.upper, static, resolution=0.02).plan(
                q0, q1, timeout=self.plan_timeout)
        except PlanningError:
            return False
        return True

    def _still(self, q, line, layer, error=None):
        return Block(np.zeros(1), np.asarray(q, dtype=float)[None], self.tip_world(np.asarray(q)[None]),
                     np.array([line]), np.array([layer]), np.zeros(1, dtype=bool), np.zeros(1), error=error)

    def dwell(self, q, seconds, line=0, layer=0):
        """Stand still for ``seconds``."""
        q = np.asarray(q, dtype=float)
        return self._timed(Block(np.array([0.0, float(seconds)]), np.stack([q, q]), self.tip_world(np.stack([q, q])),
                     np.array([line, line]), np.array([layer, layer]), np.zeros(2, dtype=bool), np.zeros(2)),
                           scaled=False)
