"""Offline run of a whole cell: every arm's firmware (:class:`~ambots.runner.ArmRunner`)
on one simulated clock, messages passed directly instead of through ROS,
then the executed motion checked for collisions and summarised in the
report (``report.json``) that the live system writes too.

Steps (``python -m ambots plan`` runs them in this order):

1. :func:`simulate` -- load each arm's program (A5), start the arms the
   job says (A1) and advance all runners until every arm is done or one
   fails; A10/A11 of each arm reach the others, A1/A7 reach their target;
2. :func:`check_motion` -- arm-arm, arm-bed and arm-part clearance of every
   arm's executed joint trajectory, checked continuously
   (:mod:`ambots.contact`) with the capsule model (:mod:`ambots.collision`);
3. :func:`report` -- the report dictionary (see the README for its keys).
"""
import time
from dataclasses import dataclass, field
from typing import Dict, List

import numpy as np

from ambots.protocol import ArmState, ErrorReport, LoadChunk, Start, Status
from ambots.runner import ArmRunner
from ambots.units import MM

__all__ = ["SimResult", "simulate", "check_motion", "report", "CONTACT_MM"]

#: surfaces closer than this (mm) count as a contact (collision)
CONTACT_MM = 0.0


@dataclass
class SimResult:
    runners: Dict[str, ArmRunner]
    errors: List[ErrorReport] = field(default_factory=list)
    messages: int = 0
    wall_time_s: float = 0.0
    finished: bool = False
    reason: str = ""
    #: the runners' names of the cell's arms without a program (parked by an A7)
    idle: tuple = ()

    @property
    def makespan_s(self):
        """Simulated time from the first motion of any arm to the last arm
        with a program done."""
        starts = [r.stats.first_motion_s for r in self.runners.values() if r.stats.first_motion_s is not None]
        ends = [r.stats.done_s if r.stats.done_s is not None else r.clock for n, r in self.runners.items()
                if r.stats.first_motion_s is not None and n not in self.idle]
        return (max(ends) - min(starts)) if starts else 0.0


def simulate(programs, cell, dt=2.0, max_time=10 * 24 * 3600.0, planner_kw=None, slow=None,
             planner_cls=None, runner_cls=None, seed=0, idle=()):
    """Run the programs of a job to completion.

    ``programs``: {arm name: :class:`~ambots.coordinate.ArmProgram`};
    ``dt``: the simulated step (s) between message exchanges (the runners
    keep exact time inside a step and wake exactly when a report arrives);
    ``slow``: optional {arm name: factor} stretching an arm's motion (a
    firmware that runs slower than planned), or {arm name: (lo, hi)}: each
    block of the arm's motion (a run of G-code moves between two
    directives, a park move) stretched by its own factor drawn uniformly
    from [lo, hi] (an arm whose speed varies from move to move; ``seed``
    seeds the draws, one generator per arm); the joint moves are planned
    as the firmware node plans them, against the bed
    (:class:`~ambots.collision.CollisionCheck`; the other arms are left to
    the barriers and the contact check after the run), unless
    ``planner_kw`` gives an ``is_valid``; ``planner_cls``/``runner_cls``:
    subclasses of :class:`~ambots.motion.MotionPlanner` /
    :class:`~ambots.runner.ArmRunner` to use instead (e.g. ones that record
    more, see :mod:`ambots.export`); ``idle``: arms of the cell without a
    program, which stand at home until a program's A7 parks them (a job of
    one arm, or of a group of the cell's arms): they move and are checked
    for contacts like the others, and are done when they stand still.
    Returns :class:`SimResult`."""
    from ambots.collision import CollisionCheck
    from ambots.motion import MotionPlanner
    t_wall = time.perf_counter()
    idle = [a for a in idle if a.name not in programs]
    runners = {}
    for i, arm in enumerate([p.arm for p in programs.values()] + idle):
        kw = dict(planner_kw or {})
        kw.setdefault("is_valid", CollisionCheck(arm, cell))     # the firmware node's check, the bed only
        planner = (planner_cls or MotionPlanner)(arm, cell, **kw)
        if slow and arm.name in slow:
            factor = slow[arm.name]
            if np.ndim(factor):
                lo, hi = (float(v) for v in factor)
                planner.time_jitter = (np.random.default_rng([int(seed), i]), lo, hi)
            else:
                planner.time_scale = float(factor)
        runners[arm.name] = (runner_cls or ArmRunner)(arm, cell, planner=planner, record=True)
    by_id = {r.id: r for r in runners.values()}
    result = SimResult(runners, idle=tuple(a.name for a in idle))

    def deliver(t_sent, msg, src):
        result.messages += 1
        if isinstance(msg, (Status, ErrorReport)):
            if isinstance(msg, ErrorReport):
                result.errors.append(msg)
            for r in runners.values():
                if r is not src:
                    r.handle(msg, now=t_sent)
        elif msg.robot in by_id:
            target = by_id[msg.robot]
            target.handle(msg, now=max(t_sent, target.clock))

    for name, prog in programs.items():
        runners[name].handle(LoadChunk(prog.arm.id, prog.text, chunk_id=1))
    for name, prog in programs.items():
        if prog.start_first:
            runners[name].handle(Start(prog.arm.id))
    t = 0.0
    active = (ArmState.PRINTING, ArmState.WAITING, ArmState.PAUSED)
    while t < max_time:
        t += dt
        for _ in range(1000):                  # exchange until nothing new at this time
            moved = False
            for r in runners.values():
                r.advance(t)
                while r.outbox:
                    moved = True
                    deliver(*r.outbox.pop(0), r)
            if not moved:
                break
        states = [r.state for r in runners.values()]
        if any(s is ArmState.ERROR for s in states):
            result.reason = "arm error"
            break
        if not any(s in active for s in states):
            # done: every arm with a program; an idle arm, standing still where it was sent
            result.finished = all(r.state is (ArmState.IDLE if n in result.idle else ArmState.DONE)
                                  and (n not in result.idle or r.block is None) for n, r in runners.items())
            if not result.finished:
                result.reason = "arms idle but not done: %s" % {n: r.state.name for n, r in runners.items()}
            break
        if all(s is ArmState.WAITING for s in states if s in active) and \
                all(r.clock < t for r in runners.values() if r.state is ArmState.WAITING) and \
                not any(s is ArmState.PRINTING for s in states):
            result.reason = "deadlock: every active arm waits"
            break
    result.wall_time_s = time.perf_counter() - t_wall
    return result


def _trace(runner):
    """A runner's executed motion as Hermite knots ``(t, Q, V)``."""
    if not runner.trace_t:
        q = runner.q[None]
        return np.array([0.0]), q, np.zeros_like(q)
    return np.concatenate(runner.trace_t), np.concatenate(runner.trace_q), np.concatenate(runner.trace_v)


def check_motion(result, cell):
    """Clearances of the executed motion, checked continuously
    (:mod:`ambots.contact`).  The printed part is the box around every bead
    deposited so far (its top grows with time); an arm's nozzle body stops
    short of the tip, so printing is not contact.

    Returns a dict: ``collisions`` {arm_arm, arm_bed, arm_part: samples in
    contact}, ``min_clearance_mm`` (closest approach of two arms),
    ``min_bed_clearance_mm``, ``min_part_clearance_mm`` (smallest sampled
    clearances), ``bound_mm`` {arm_arm, arm_bed, arm_part: provable lower
    bounds over the whole time line}, ``samples``, ``resolution_mm``."""
    runners = result.runners
    return check_traces({n: _trace(r) for n, r in runners.items()}, {n: r.arm for n, r in runners.items()},
                        cell, beads=[b for r in runners.values() for b in r.beads])


def _part_growth(beads, bed_z):
    """The part printed so far as a box: its xy extent (2, 2) (every bead's,
    conservatively), its top z at times t (the bed's top before the first
    bead), and how much the top grows in intervals (t0, t1)."""
    P = np.concatenate([np.concatenate([b.p0, b.p1]) for b in beads])
    T = np.concatenate([np.concatenate([b.t, b.t]) for b in beads])
    order = np.argsort(T, kind="stable")
    Ts, ztop = T[order], np.maximum.accumulate(np.maximum(P[order, 2], bed_z))

    def top(t):
        i = np.searchsorted(Ts, t, side="right") - 1
        return np.where(i >= 0, ztop[np.maximum(i, 0)], bed_z)

    return np.array([P[:, :2].min(axis=0), P[:, :2].max(axis=0)]), top, lambda t0, t1: top(t1) - top(t0)


def check_traces(traces, arms, cell, beads=None):
    """:func:`check_motion` for recorded traces: ``traces`` {name: (t (K,)
    s, Q (K, n) rad[, V (K, n) rad/s])} (with V: the cubic Hermite motion
    through the knots, as the one timing law commands it; without: linear
    between knots), ``arms`` {name: arm}, ``beads`` (with times) for the
    arm-part check (None: not checked)."""
    from ambots.collision import ArmBody, bed_clearance, clearance_between, part_clearance
    from ambots.contact import RESOLUTION_M, Sweep, scan, sweep_radii
    names = list(traces)
    t_start = min(float(tr[0][0]) for tr in traces.values())     # a wall clock starts far from 0
    t_end = max(float(tr[0][-1]) for tr in traces.values())
    bodies = {n: ArmBody.from_arm(arms[n]) for n in names}
    sweeps = {n: Sweep(traces[n][0], traces[n][1], sweep_radii(bodies[n]),
                       traces[n][2] if len(traces[n]) > 2 else None) for n in names}
    contact = CONTACT_MM * MM
    out = {"collisions": {"arm_arm": 0, "arm_bed": 0, "arm_part": 0}, "samples": 0,
           "min_clearance_mm": None, "min_bed_clearance_mm": None, "min_part_clearance_mm": None,
           "bound_mm": {"arm_arm": None, "arm_bed": None, "arm_part": None},
           "closest_pair": None, "closest_time_s": None, "resolution_mm": RESOLUTION_M / MM}

    def record(kind, s):
        out["collisions"][kind] += s.contacts
        out["samples"] += s.samples
        old = out["bound_mm"][kind]
        out["bound_mm"][kind] = s.bound / MM if old is None else min(old, s.bound / MM)

    best = np.inf
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            s = scan(lambda t: clearance_between(bodies[a], sweeps[a].at(t), bodies[b], sweeps[b].at(t)),
                     lambda t0, t1: sweeps[a].swept(t0, t1) + sweeps[b].swept(t0, t1), t_end, contact,
                     t_start=t_start)
            record("arm_arm", s)
            if s.min < best:
                best = s.min
                out["closest_pair"], out["closest_time_s"] = [a, b], s.t_min
    if len(names) > 1:
        out["min_clearance_mm"] = best / MM
    bed_min = np.inf
    for n in names:
        s = scan(lambda t: bed_clearance(bodies[n], sweeps[n].at(t), cell), sweeps[n].swept, t_end, contact,
                 track_min=False, t_start=t_start)
        record("arm_bed", s)
        bed_min = min(bed_min, s.min)
    out["min_bed_clearance_mm"] = bed_min / MM
    if beads:
        bed_z = cell.bed.pose[2, 3]
        xy, top, growth = _part_growth(beads, bed_z)
        part_min = np.inf

        def part(n, t):
            lo = np.tile([xy[0, 0], xy[0, 1], bed_z], (len(t), 1))
            hi = np.column_stack([np.full(len(t), xy[1, 0]), np.full(len(t), xy[1, 1]), top(t)])
            return part_clearance(bodies[n], sweeps[n].at(t), lo, hi)

        for n in names:
            s = scan(lambda t: part(n, t), sweeps[n].swept, t_end, contact, track_min=False, growth=growth,
                     t_start=t_start)
            record("arm_part", s)
            part_min = min(part_min, s.min)
        out["min_part_clearance_mm"] = part_min / MM
    return out


def report(result, motion, job=None, model=None, cell=None, mode=None, slicer=None, wall_time_s=None):
    """The ``report.json`` dictionary of a finished (or failed) run
    (:func:`ambots.report.build`, the builder the live capture uses too)."""
    from dataclasses import asdict

    from ambots.deposit import FILAMENT_AREA_MM2
    from ambots.report import arm_entry, build
    arms = {}
    deposit_mm3 = 0.0
    for name, r in result.runners.items():
        e = float(sum(b.e_mm.sum() for b in r.beads))
        deposit_mm3 += e * FILAMENT_AREA_MM2
        arms[name] = arm_entry(r.id, r.state.name, asdict(r.stats), sum(len(b.e_mm) for b in r.beads), e)
        del arms[name]["error"]
    meta = {"model": model if model is not None else (job.model_path if job else None),
            "cell": cell.name if cell is not None else (job.cell.name if job else None),
            "mode": mode if mode is not None else (job.mode if job else None),
            "slicer": slicer if slicer is not None else (job.slicer if job else None)}
    from ambots.mesh import signed_volume
    model_mm3 = signed_volume(job.mesh) if job is not None and job.mesh is not None else None
    extra = {"plan": job.plan_summary()} if job is not None and getattr(job, "candidates", None) else {}
    if job is not None and getattr(job, "programs", None):
        extra["overhang"] = job.overhang()
    if job is not None and getattr(job, "mesh", None) is not None and hasattr(job, "repair"):
        extra["repair"] = job.repair()
    return build(meta, result.finished, arms, round(result.makespan_s, 3), motion, deposit_mm3, model_mm3,
                 result.wall_time_s if wall_time_s is None else wall_time_s, reason=result.reason,
                 errors=[{"arm": e.robot, "line": e.line, "message": e.message} for e in result.errors],
                 messages=result.messages, **extra)
