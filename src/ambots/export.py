"""Offline export of a planned job for real controllers (no ROS):
``python -m ambots export DIR --format trajectory|urscript``.

``DIR`` is an output folder of ``python -m ambots plan``: the per-arm
programs ``<arm>.gcode``, ``job.json`` (names the cell, the mode and the
arms) and ``report.json`` (the collision check).  The programs are executed
again exactly as ``plan`` executed them -- every arm's firmware
(:class:`~ambots.runner.ArmRunner` with its
:class:`~ambots.motion.MotionPlanner`) on one simulated clock
(:func:`ambots.sim.simulate`), barriers included -- while every executed
block is recorded together with what produced it (a run of G-code moves, a
``G4``, an ``A7`` park move) and when it started (after a barrier wait, a
block starts later than the previous one ended).  Then, per arm:

``trajectory``
    ``<arm>.trajectory.csv``: one row per executed waypoint: ``time_s``, the
    joints under the driver's names (rad), ``extruding`` (0/1) and ``e_mm``
    (filament pushed); a row's ``extruding``/``e_mm`` describe the motion
    from the previous row to it.  Times are the job's simulated clock (0 =
    start), strictly increasing; a wait is two rows with the same joints.
    ``<arm>.trajectory.yaml``: the header (arm, joint names, limits from the
    arm profile, samples, duration) and the checks: the largest joint speed
    (never above ``velocity`` x ``velocity_scaling``: the planner guarantees
    it, the export checks it and refuses otherwise) and the largest joint
    acceleration the waypoints imply (finite differences, see
    :func:`check_limits`), against the profile's ``acceleration``.
``urscript`` (arms whose profile's brand is ``Universal Robots`` only)
    ``<arm>.script``: ``def ambots_<arm>(): ... end``.  ``set_tcp`` to the
    profile's tool offset; ``movej`` to the profile's home (where the plan
    starts); one ``movel(p[x, y, z, rx, ry, rz], a, v)`` per G-code move of
    non-zero length (the nozzle's pose in the robot's base frame: position
    = the G-code target, orientation = forward kinematics of the planned
    joints at the move's end; ``v`` = the planned tool speed, i.e. the
    feedrate, or less where the planner slowed down for a joint's speed
    limit); ``movej`` for the planner's joint-space moves (the first travel
    of a run of moves that does not start at the nozzle, park moves);
    ``set_tool_digital_out(0, True/False)`` switches the extruder around
    extruding moves; ``sleep`` for the plan's ``G4`` dwells and idle time.
    Only a job of one arm is exported this way: a URScript program runs open
    loop on its controller and cannot wait at a barrier for another arm, so
    a job of several arms is refused (drive those through ROS: the
    trajectory format, or the firmware's ``driver:=trajectory``).

Frames: the UR profile's ``base_link`` is the manufacturer's base frame (DH
frame 0) and its ``flange`` the tool flange (DH frame 6), so the poses are
those the controller uses and ``set_tcp`` is the profile's ``tool`` offset.

Units: metres, radians, seconds; mm only for G-code lines and filament.
"""
import json
import math
import os
from dataclasses import dataclass, field
from typing import Dict, List, Optional

import numpy as np

from ambots.errors import ConfigError, ExportError
from ambots.motion import Directive, MotionPlanner, Moves, Pause as Dwell, read_program
from ambots.runner import ArmRunner
from ambots.trajectory import finite_differences, joint_limits

__all__ = ["FORMATS", "TIMINGS", "UR_BRAND", "PlanFolder", "ExecutedBlock", "ArmRecord", "Trajectory",
           "load_plan", "record_plan", "trajectory", "check_limits", "urscript", "export_plan",
           "rotation_vector"]

#: what ``--format`` accepts
FORMATS = ("trajectory", "urscript")
#: the ``brand`` of an arm profile that URScript export accepts
UR_BRAND = "Universal Robots"
#: rows of a trajectory closer in time than this (s) are merged into one
TIME_EPS = 1e-9
#: a simulated wait shorter than this (s) gets no ``sleep``
MIN_SLEEP_S = 1e-3
#: a planned waypoint and a G-code target closer than this (m) are the same point
POINT_EPS = 1e-5


# ------------------------------------------------------------- the plan folder
@dataclass
class PlanFolder:
    """What an output folder of ``plan`` holds."""
    path: str
    cell: object
    job: dict                          #: job.json
    programs: Dict[str, object]        #: arm name -> :class:`~ambots.coordinate.ArmProgram`
    report: Optional[dict] = None      #: report.json, if there is one


def load_plan(path, cell=None):
    """Read a ``plan`` output folder.  ``cell``: a :class:`~ambots.config.Cell`,
    a cell file, or None for the package's cell that job.json names."""
    from ambots import data_path
    from ambots.config import load_cell
    from ambots.coordinate import ArmProgram
    from ambots.program import is_directive, parse_directive
    from ambots.protocol import Start

    if not os.path.isdir(path):
        raise ExportError("%s: plan folder not found (write one with `python -m ambots plan MODEL --out %s`)"
                          % (path, path))
    job_path = os.path.join(path, "job.json")
    if not os.path.isfile(job_path):
        raise ExportError("%s: not found, so %s is not an output folder of `python -m ambots plan`"
                          % (job_path, path))
    job = _read_json(job_path)
    if not isinstance(job, dict) or not isinstance(job.get("cell"), str) or not isinstance(job.get("arms"), dict) \
            or not job["arms"]:
        raise ExportError("%s: expected a JSON object with 'cell' (a name) and 'arms' (one entry per arm)"
                          % os.path.join(path, "job.json"))
    if cell is None:
        candidate = data_path("config", "cells", job["cell"] + ".yaml")
        if not os.path.isfile(candidate):
            raise ExportError("%s: the job was planned for cell %r, which is not one of the package's cells "
                              "(config/cells/); pass --cell with that cell's file" % (path, job["cell"]))
        cell = load_cell(candidate)
    elif isinstance(cell, str):
        cell = load_cell(cell)
    if cell.name != job["cell"]:
        raise ExportError("%s: the job was planned for cell %r, not for cell %r (%s)"
                          % (path, job["cell"], cell.name, cell.path))
    programs = {}
    for name, info in job["arms"].items():
        try:
            arm = cell.arm(name)
        except ConfigError:
            raise ExportError("%s: arm %r of job.json is not in cell %r (%s)" % (path, name, cell.name, cell.path)) \
                from None
        if isinstance(info, dict) and info.get("id") not in (None, arm.id):
            raise ExportError("%s: arm %r is R%s in job.json but R%d in cell %s"
                              % (path, name, info.get("id"), arm.id, cell.path))
        gpath = os.path.join(path, name + ".gcode")
        if not os.path.isfile(gpath):
            raise ExportError("%s: not found (job.json lists arm %r)" % (gpath, name))
        with open(gpath) as f:
            lines = f.read().split("\n")
        if lines and lines[-1] == "":
            lines.pop()
        programs[name] = ArmProgram(arm, job.get("mode", "concurrent"), lines)
    # an arm that another arm starts (;@A1 R<id>, sequential mode) is not started by the front end
    started_by_others = set()
    for name, prog in programs.items():
        for number, line in enumerate(prog.lines, 1):
            if is_directive(line):
                msg = parse_directive(line, os.path.join(path, name + ".gcode"), number)
                if isinstance(msg, Start) and msg.robot != prog.arm.id:
                    started_by_others.add(msg.robot)
    for prog in programs.values():
        prog.start_first = prog.arm.id not in started_by_others
    report = None
    if os.path.isfile(os.path.join(path, "report.json")):
        report = _read_json(os.path.join(path, "report.json"))
    return PlanFolder(path, cell, job, programs, report if isinstance(report, dict) else None)


def _read_json(path):
    try:
        with open(path) as f:
            return json.load(f)
    except ValueError as exc:
        raise ExportError("%s: not valid JSON: %s" % (path, exc)) from None


# ------------------------------------------------------------- recording
class _Planner(MotionPlanner):
    """The firmware's planner; tags every block of :meth:`plan_moves` with
    ``lead``: how many of its first waypoints are a joint-space move (0: the
    block is all Cartesian; ``len(block.t)``: all joint-space).  Blocks are
    timed by the planner's one timing law, as in ``plan`` and the firmware."""

    _lead = None

    def _joint_move_to(self, *args, **kw):
        block = super()._joint_move_to(*args, **kw)
        self._lead = block
        return block

    def plan_moves(self, segments, q0):
        self._lead = None
        block = super().plan_moves(segments, q0)
        lead = self._lead
        block.lead = 0 if lead is None else (len(block.t) if lead is block else len(lead.t))
        return block


@dataclass
class ExecutedBlock:
    """One block an arm executed: ``origin`` the program item that produced
    it (:class:`~ambots.motion.Moves`, :class:`~ambots.motion.Pause` for a
    ``G4``, a :class:`~ambots.motion.Directive` for a ``;@A7`` of the arm's
    own program) or the :class:`~ambots.protocol.MoveTo` received from
    another arm; ``item`` its index in the program (-1 for a received A7);
    ``lead`` see :class:`_Planner`; ``slices`` (block start time, k0, k1):
    waypoints k0 -> k1 reached, as executed."""
    block: object
    origin: object
    item: int
    lead: int = 0
    slices: list = field(default_factory=list)

    @property
    def start_s(self):
        t0, k0, _ = self.slices[0]
        return t0 + float(self.block.t[k0])

    @property
    def end_s(self):
        t0, _, k1 = self.slices[-1]
        return t0 + float(self.block.t[k1])


class _Recorder(ArmRunner):
    """The firmware, keeping every executed block with its origin."""

    def __init__(self, *args, **kw):
        super().__init__(*args, **kw)
        self.executed: List[ExecutedBlock] = []
        self.q_start = self.q.copy()

    def _started(self, origin, item):
        self.executed.append(ExecutedBlock(self.block, origin, item, getattr(self.block, "lead", 0)))

    def _next_block(self):
        idx, before = self.idx, self.block
        ready = super()._next_block()
        if self.block is not None and self.block is not before:
            self._started(self.items[idx], idx)
        return ready

    def _manual_move(self, msg, now):
        before = self.block
        super()._manual_move(msg, now)
        if self.block is not None and self.block is not before:
            self._started(msg, -1)

    def _execute(self, b, k0, k1):
        super()._execute(b, k0, k1)
        if not self.executed or self.executed[-1].block is not b:     # cannot happen; be safe
            self._started(None, -1)
        self.executed[-1].slices.append((self.block_t0, k0, k1))


@dataclass
class ArmRecord:
    """What one arm did in the re-run of the plan."""
    name: str
    arm: object
    planner: object
    program: object                 #: its :class:`~ambots.coordinate.ArmProgram`
    items: list                     #: the program's items (:func:`ambots.motion.read_program`)
    q_start: np.ndarray             #: joints at time 0 (the profile's home)
    blocks: List[ExecutedBlock]     #: executed blocks in order (only those with motion)
    moves: int = 0
    done_s: Optional[float] = None


def record_plan(plan, dt=2.0):
    """Execute the plan's programs again, recording.  Returns ``(SimResult,
    {arm name: ArmRecord})``; a run that does not finish raises
    :class:`~ambots.errors.ExportError`."""
    from ambots.sim import simulate
    result = simulate(plan.programs, plan.cell, dt=dt, planner_cls=_Planner, runner_cls=_Recorder)
    if not result.finished:
        errors = "; ".join("R%d line %d: %s" % (e.robot, e.line, e.message) for e in result.errors[:3])
        raise ExportError("%s: the plan does not run to the end (%s%s); nothing exported"
                          % (plan.path, result.reason, ": " + errors if errors else ""))
    records = {}
    for name, r in result.runners.items():
        records[name] = ArmRecord(name, r.arm, r.planner, plan.programs[name], r.items, r.q_start,
                                  [b for b in r.executed if b.slices], r.stats.moves, r.stats.done_s)
    return result, records


# ------------------------------------------------------------- trajectory
@dataclass
class Trajectory:
    """Timed joint waypoints of one arm.  Row k: ``t`` (s), ``Q`` (n,) rad in
    the profile's joint order (= the driver's ``joint_names``); ``extrude``,
    ``e_mm``, ``line``: the motion from row k-1 to row k (row 0: none);
    ``V`` (n,) rad/s the joint speeds at row k: between rows the motion is
    the cubic Hermite through the rows' positions and speeds (the one
    timing law's commanded motion; a controller interpolating positions and
    velocities with cubic splines, as ros_control's joint trajectory
    controller does, follows it exactly)."""
    arm: object
    joint_names: tuple
    t: np.ndarray
    Q: np.ndarray
    extrude: np.ndarray
    e_mm: np.ndarray
    line: np.ndarray
    V: np.ndarray = None

    @property
    def duration(self):
        return float(self.t[-1] - self.t[0])


def trajectory(record):
    """An :class:`ArmRecord` -> its :class:`Trajectory`: every executed
    waypoint at its simulated time, a hold row where the arm waited, rows
    closer than :data:`TIME_EPS` merged (the later one's joints, filament
    summed), so that times are strictly increasing."""
    t, Q, ex, e, line = [np.zeros(1)], [np.asarray(record.q_start, float)[None]], [np.zeros(1, bool)], \
        [np.zeros(1)], [np.zeros(1, int)]
    V = [np.zeros((1, len(record.q_start)))]
    last_t, last_q = 0.0, np.asarray(record.q_start, float)
    for eb in record.blocks:
        b = eb.block
        for t0, k0, k1 in eb.slices:
            ts = t0 + b.t[k0:k1 + 1]
            if ts[0] > last_t + TIME_EPS:                 # waited: hold where it was
                t.append(ts[:1])
                Q.append(last_q[None])
                ex.append(np.zeros(1, bool))
                e.append(np.zeros(1))
                line.append(np.array([int(b.line[k0])]))
                V.append(np.zeros((1, len(last_q))))
            sl = slice(k0 + 1, k1 + 1)
            t.append(ts[1:])
            Q.append(b.Q[sl])
            V.append(b.motion.eval(b.t[sl])[1] if b.motion is not None else np.zeros_like(b.Q[sl]))
            ex.append(np.asarray(b.extrude[sl], bool))
            e.append(np.asarray(b.e_mm[sl], float))
            line.append(np.asarray(b.line[sl], int))
            last_t, last_q = float(ts[-1]), b.Q[k1]
    t, Q, ex, e, line, V = (np.concatenate(x) for x in (t, Q, ex, e, line, V))
    # merge rows that are (nearly) at the same time into the last one of each group
    new = np.concatenate([[True], np.diff(t) > TIME_EPS])
    starts = np.nonzero(new)[0]
    ends = np.concatenate([starts[1:], [len(t)]]) - 1
    arm = record.arm
    return Trajectory(arm, tuple(arm.profile.driver_joint_names), t[ends], Q[ends],
                      np.maximum.reduceat(ex.astype(int), starts).astype(bool), np.add.reduceat(e, starts),
                      line[ends], V[ends])


def check_limits(traj, profile=None):
    """Joint speeds and accelerations of a trajectory against the profile's
    limits times its ``velocity_scaling`` (the fraction of the limits used
    when printing, as the planner uses them; speeds capped by the driver's
    ``max_joint_speed``: :func:`ambots.trajectory.joint_limits`), measured by
    :func:`ambots.trajectory.finite_differences`.

    Speed: per interval, the joint change over the interval's duration
    (what a controller interpolating linearly between the rows commands).
    Acceleration: at each row, the change of that speed from the interval
    before to the interval after it, over the mean of their durations; an
    interval in which the arm stands still (a wait, a retraction) counts as
    rest of zero duration, so stopping and starting are charged to the
    moving interval next to them.  The one timing law keeps the commanded
    motion within both limits everywhere, so samples of it (these rows
    among them) pass this measure (:mod:`ambots.trajectory`).

    Returns a dict (the ``checks`` of the trajectory's YAML header)."""
    profile = profile or traj.arm.profile
    names = list(traj.joint_names)
    vlim, alim = joint_limits(profile)
    n = len(names)
    V, A = finite_differences(traj.t, traj.Q)
    speed = np.abs(V).max(axis=0) if len(V) else np.zeros(n)
    accel = np.abs(A).max(axis=0)
    ratio = np.abs(A) / alim
    rows_over = np.nonzero((ratio > 1 + 1e-6).any(axis=1))[0]
    k, j = np.unravel_index(int(np.argmax(ratio)), ratio.shape)
    worst = {"time_s": round(float(traj.t[k]), 6), "joint": names[j], "acceleration": round(float(A[k, j]), 4),
             "line": int(traj.line[min(k + 1, len(traj.line) - 1)])}
    vbad = speed > vlim * (1 + 1e-6) + 1e-12
    return {
        "velocity_limit": {n: round(float(v), 6) for n, v in zip(names, vlim)},
        "max_velocity": {n: round(float(v), 6) for n, v in zip(names, speed)},
        "velocity_ok": bool(not vbad.any()),
        "acceleration_limit": {n: round(float(a), 6) for n, a in zip(names, alim)},
        "max_acceleration": {n: round(float(a), 4) for n, a in zip(names, accel)},
        "acceleration_ok": bool(not len(rows_over)),
        "acceleration_rows_over_limit": int(len(rows_over)),
        "acceleration_worst": worst,
    }


#: how exported motion is timed (the summary's and the YAML header's ``timing``)
TIMING = "one law"


def _write_trajectory(record, traj, checks, plan, out_dir):
    name = record.name
    prof = record.arm.profile
    csv_path = os.path.join(out_dir, name + ".trajectory.csv")
    cols = ["time_s"] + list(traj.joint_names) + ["extruding", "e_mm"] + \
        ["%s_velocity" % j for j in traj.joint_names]
    with open(csv_path, "w") as f:
        f.write(",".join(cols) + "\n")
        for k in range(len(traj.t)):
            f.write("%.9f,%s,%d,%.6f,%s\n" % (traj.t[k], ",".join("%.9f" % q for q in traj.Q[k]),
                                              int(traj.extrude[k]), traj.e_mm[k] + 0.0,
                                              ",".join("%.9f" % v for v in traj.V[k])))
    header = {
        "arm": name, "robot_id": record.arm.id, "profile": prof.name, "brand": prof.brand,
        "cell": plan.cell.name, "plan": os.path.abspath(plan.path), "program": name + ".gcode",
        "csv": os.path.basename(csv_path), "columns": cols,
        "joint_names": list(traj.joint_names),
        "rows": "extruding/e_mm of a row: the motion from the previous row to it; times: the job's simulated "
                "clock (s, 0 = job start), strictly increasing; joints rad",
        "samples": int(len(traj.t)),
        "start_s": round(float(traj.t[0]), 9), "end_s": round(float(traj.t[-1]), 9),
        "duration_s": round(traj.duration, 6),
        "extruded_filament_mm": round(float(traj.e_mm[traj.extrude].sum()), 4),
        "limits": {d: {"lower": _finite(j.lower), "upper": _finite(j.upper), "velocity": j.velocity,
                       "acceleration": j.acceleration} for j, d in zip(prof.joints, traj.joint_names)},
        "velocity_scaling": prof.velocity_scaling,
        "timing": TIMING,
        "timing_meaning": ("the firmware's one timing law (ambots.trajectory), as report.json checked it: "
                           "between rows the cubic Hermite through the rows' positions and *_velocity columns "
                           "(rad/s), within every joint's speed limit and 80 % of its acceleration limit "
                           "(x velocity_scaling); the nozzle at most at the programmed feedrate"),
        "checks": checks,
    }
    import yaml
    yaml_path = os.path.join(out_dir, name + ".trajectory.yaml")
    with open(yaml_path, "w") as f:
        f.write("# ambots joint trajectory of arm %s (python -m ambots export --format trajectory)\n" % name)
        yaml.safe_dump(header, f, sort_keys=False, default_flow_style=None, width=120)
    return [csv_path, yaml_path]


def _finite(x):
    return float(x) if math.isfinite(x) else None


# ------------------------------------------------------------- URScript
def rotation_vector(R, near=None):
    """Rotation matrix (3, 3) -> rotation vector (3,) (axis x angle, rad),
    angle in [0, pi]; at an angle near pi, of the two equivalent vectors the
    one closer to ``near`` (keeps a sequence of poses continuous)."""
    R = np.asarray(R, float)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    s = 0.5 * np.linalg.norm(w)
    c = 0.5 * (np.trace(R) - 1.0)
    angle = math.atan2(s, c)
    if angle < 1e-12:
        return np.zeros(3)
    if c > -0.5:
        axis = w / (2.0 * s)
    else:                  # near pi: the axis from the symmetric part, (R + R^T) / 2 = c I + (1 - c) a a^T
        B = (0.5 * (R + R.T) - c * np.eye(3)) / (1.0 - c)
        i = int(np.argmax(np.diag(B)))
        axis = B[:, i] / math.sqrt(max(B[i, i], 1e-300))
        axis /= np.linalg.norm(axis)
        if w @ axis < 0:
            axis = -axis
    v = axis * angle
    if near is not None and angle > math.pi - 0.5:
        alt = axis * (angle - 2.0 * math.pi)          # the same rotation, the other way round
        if np.linalg.norm(alt - near) < np.linalg.norm(v - near):
            v = alt
    return v


def _rpy_matrix(rpy):
    from ambots.config import pose_matrix
    return pose_matrix((0.0, 0.0, 0.0), rpy)[:3, :3]


def _num(x, digits=6):
    text = "%.*f" % (digits, x)
    if float(text) == 0.0:
        text = "%.*f" % (digits, 0.0)
    if not math.isfinite(float(text)):
        raise ExportError("URScript: a non-finite number (%r)" % x)
    return text


def _vec(v, digits=6):
    return ", ".join(_num(float(x), digits) for x in v)


class _Script:
    """Builds the lines of a URScript program."""

    def __init__(self, digital_out, tool_acceleration, joint_speed, joint_acceleration):
        self.lines = []
        self.kind, self.port = digital_out
        self.tool_a = tool_acceleration
        self.joint_v, self.joint_a = joint_speed, joint_acceleration
        self.extruding = None
        self.rotvec = None
        self.movel = self.movej = self.sleeps = 0
        self.sleep_s = 0.0

    def add(self, text):
        self.lines.append("  " + text)

    def comment(self, text):
        self.add("# " + text)

    def extruder(self, on):
        if on != self.extruding:
            fn = "set_tool_digital_out" if self.kind == "tool" else "set_standard_digital_out"
            self.add("%s(%d, %s)" % (fn, self.port, "True" if on else "False"))
            self.extruding = on

    def move_l(self, position, R, v, note):
        self.rotvec = rotation_vector(R, self.rotvec)
        self.add("movel(p[%s, %s], a=%s, v=%s)  # %s" % (_vec(position), _vec(self.rotvec), _num(self.tool_a, 3),
                                                        _num(v, 5), note))
        self.movel += 1

    def move_j(self, q, note=None):
        self.add("movej([%s], a=%s, v=%s)%s" % (_vec(q), _num(self.joint_a, 4), _num(self.joint_v, 4),
                                                "  # " + note if note else ""))
        self.movej += 1

    def sleep(self, seconds, why):
        self.extruder(False)
        self.add("sleep(%s)  # %s" % (_num(seconds, 3), why))
        self.sleeps += 1
        self.sleep_s += seconds


def _corners(P):
    """Indices of the waypoints of a joint path (M, n) where it changes
    direction, and its last one (M-1): the targets of its ``movej``s."""
    d = np.diff(P, axis=0)
    L = np.linalg.norm(d, axis=1)
    idx = np.nonzero(L > 1e-12)[0]
    out = []
    for a, b in zip(idx[:-1], idx[1:]):
        if float(d[a] @ d[b]) < (1 - 1e-9) * L[a] * L[b]:
            out.append(int(a) + 1)
    return out + [len(P) - 1]


def _directive_text(msg):
    from ambots.program import directive
    return directive(msg)


def urscript(record, digital_out=("tool", 0), tool_acceleration=1.2, plan_path=None, cell=None):
    """The URScript program of one UR arm's :class:`ArmRecord`.  Returns
    ``(text, stats)``.  ``digital_out``: the extruder's output,
    ``("tool", n)`` or ``("standard", n)``; ``tool_acceleration`` (m/s^2)
    of the ``movel``s."""
    from ambots.protocol import MoveTo, WaitFor
    arm, prof, planner = record.arm, record.arm.profile, record.planner
    if prof.brand != UR_BRAND:
        raise ExportError(_not_ur(arm))
    if not record.program.start_first or any(isinstance(it, Directive) and isinstance(it.message, WaitFor)
                                             for it in record.items):
        raise ExportError("arm %s: its program waits for other arms; a URScript program cannot (export "
                          "--format trajectory)" % record.name)
    kind, port = digital_out
    if kind not in ("tool", "standard") or not isinstance(port, int) or not 0 <= port <= 7:
        raise ExportError("extruder output %r: expected ('tool' or 'standard', 0..7)" % (digital_out,))
    vmax = np.array([j.velocity for j in prof.joints]) * prof.velocity_scaling
    amax = np.array([j.acceleration for j in prof.joints]) * prof.velocity_scaling
    s = _Script(digital_out, tool_acceleration, float(vmax.min()), float(amax.min()))
    fn = "ambots_" + record.name
    tcp = np.concatenate([prof.tool_xyz, rotation_vector(_rpy_matrix(prof.tool_rpy))])
    s.lines.append("def %s():" % fn)
    s.comment("generated by `python -m ambots export --format urscript`%s"
              % (" from " + plan_path if plan_path else ""))
    s.comment("arm %s (R%d, %s), cell %s, base at (%s) m, yaw %.1f deg in the cell's world frame"
              % (record.name, arm.id, prof.name, cell.name if cell is not None else "?", _vec(arm.base_xyz, 3),
                 math.degrees(arm.base_rpy[2])))
    s.comment("poses: the nozzle (TCP) in the robot's base frame, m, rotation vector rad; joints rad")
    s.comment("extruder: %s digital output %d (True = extrude); retractions are not emitted"
              % (kind, port))
    s.comment("timing: the plan's, for this arm printing alone (URScript cannot wait for another arm)")
    s.add('textmsg("ambots: %s starts")' % record.name)
    s.add("set_tcp(p[%s])" % _vec(tcp))
    s.extruder(False)
    s.move_j(record.q_start, "the plan's start: the profile's home")
    items = record.items
    next_item = 0
    prev_end = 0.0

    def directives_until(stop):
        """Comment the directives of items [next_item, stop)."""
        nonlocal next_item
        for i in range(next_item, stop):
            if isinstance(items[i], Directive):
                s.comment("line %d: %s" % (items[i].line, _directive_text(items[i].message)))
        next_item = max(next_item, stop)

    for eb in record.blocks:
        if eb.item >= 0:
            directives_until(eb.item)
        gap = eb.start_s - prev_end
        if gap > MIN_SLEEP_S:
            s.sleep(gap, "idle in the plan")
        if eb.item >= 0:
            next_item = max(next_item, eb.item + 1)
        origin = eb.origin
        b = eb.block
        if isinstance(origin, Moves):
            _moves(s, eb, planner)
        elif isinstance(origin, Dwell):
            s.sleep(b.duration, "line %d: G4 dwell" % origin.line)
        else:
            if isinstance(origin, Directive):
                note = "line %d: %s (joint move)" % (origin.line, _directive_text(origin.message))
            elif isinstance(origin, MoveTo):
                note = "A7 received%s: move to X%g Y%g Z%g mm (joint move)" % (
                    "" if origin.sender is None else " from R%d" % origin.sender, origin.x, origin.y, origin.z)
            else:
                note = "joint move"
            s.extruder(False)
            s.comment(note)
            for k in _corners(b.Q):
                s.move_j(b.Q[k])
        prev_end = eb.end_s
    directives_until(len(items))
    s.extruder(False)
    s.add('textmsg("ambots: %s done")' % record.name)
    s.lines.append("end")
    stats = {"movel": s.movel, "movej": s.movej, "sleeps": s.sleeps, "sleep_s": round(s.sleep_s, 3),
             "lines": len(s.lines), "function": fn}
    return "\n".join(s.lines) + "\n", stats


def _moves(s, eb, planner):
    """The ``movej``/``movel``s of a run of G-code moves."""
    b = eb.block
    segs = list(eb.origin.segments)
    K = len(b.t)
    T = planner.kin.fk_batch(b.Q)                    # nozzle poses, base frame
    tip = T[:, :3, 3]
    vmax = joint_limits(planner.arm.profile)[0]
    k = 0
    if eb.lead:
        s.extruder(False)
        s.comment("line %d: joint move to the start of the next moves" % segs[0].line)
        lead = b.Q[:eb.lead]
        for j in _corners(lead):
            s.move_j(lead[j])
        k = eb.lead - 1
        if not segs[0].extrude:                     # the planner's joint move went to this travel's end
            segs = segs[1:]
    for seg in segs:
        start, end = planner.bed_mm_to_base(np.array([seg.start, seg.end]))
        j = k + 1
        while j < K and not (b.line[j] == seg.line and np.linalg.norm(tip[j] - end) < POINT_EPS):
            j += 1
        if j >= K:
            raise ExportError("arm %s, line %d: the planned motion does not reach the G-code target "
                              "(%.3f, %.3f, %.3f) mm" % ((planner.arm.name, seg.line) + tuple(seg.end)))
        L = float(np.linalg.norm(end - start))
        if L > 1e-9:
            s.extruder(bool(np.any(b.extrude[k + 1:j + 1])))
            feed = (seg.feedrate if seg.feedrate > 0 else 1800.0) / 60000.0         # m/s
            # the cruise speed: the feedrate, capped where a joint would exceed its speed
            # limit (the one timing law's limits; UR's own ramps use ``a``)
            dq = np.abs(np.diff(b.Q[k:j + 1], axis=0))
            dl = np.linalg.norm(np.diff(tip[k:j + 1], axis=0), axis=1)
            t_min = (dq / vmax).max(axis=1)
            cap = dl[t_min > 0] / t_min[t_min > 0]
            v = max(min(feed, float(cap.min())) if len(cap) else feed, 1e-5)
            s.move_l(end, T[j, :3, :3], v, "line %d" % seg.line)
        k = j


def _not_ur(arm):
    return ("arm %s (R%d) is a %s %s, not a %s arm: URScript export is for UR arms only "
            "(use --format trajectory, or --arms to choose the UR arms)"
            % (arm.name, arm.id, arm.profile.brand or "(no brand)", arm.profile.name, UR_BRAND))


# ------------------------------------------------------------- the command
def _open_loop(path, plan):
    """Why a job of several arms is not exported as URScript."""
    from ambots.protocol import WaitFor
    waits = sum(1 for prog in plan.programs.values() for it in read_program(prog.text)[0]
                if isinstance(it, Directive) and isinstance(it.message, WaitFor))
    return ("%s: a job of %d arms (%s, %d barriers) is not exported as URScript: a URScript program runs open "
            "loop on its controller and cannot wait for another arm, so the arms would drift apart and could "
            "collide.  Drive the arms through ROS instead (export --format trajectory, or the firmware's "
            "driver:=trajectory, whose barriers go through the hub), or plan the job for one UR arm alone "
            "(python -m ambots plan MODEL --arms NAME) and export that"
            % (path, len(plan.programs), ", ".join(plan.programs), waits))


def _parse_output(text):
    kind, _, port = str(text).partition(":")
    try:
        port = int(port)
    except ValueError:
        port = None
    if kind not in ("tool", "standard") or port is None or not 0 <= port <= 7:
        raise ExportError("extruder output %r: expected tool:N or standard:N with N in 0..7" % (text,))
    return kind, port


def export_plan(path, fmt, arms=None, cell=None, out=None, force=False, extruder_output="tool:0",
                tool_acceleration=1.2):
    """Export the plan in folder ``path`` as ``fmt`` (one of :data:`FORMATS`)
    for ``arms`` (names; default every arm of the job) into ``out``
    (default ``path``).

    The motion is the plan's, timed by the one timing law
    (:mod:`ambots.trajectory`) as ``plan`` checked it and the firmware runs
    it.  Refuses a plan whose report.json says it collided or did not finish, or
    that has no report.json, unless ``force``.  Returns a summary dict
    (files written, per-arm figures, warnings)."""
    if fmt not in FORMATS:
        raise ExportError("unknown export format %r: expected one of %s" % (fmt, ", ".join(FORMATS)))
    digital_out = _parse_output(extruder_output) if isinstance(extruder_output, str) else tuple(extruder_output)
    if not (isinstance(tool_acceleration, (int, float)) and 0 < tool_acceleration < 100):
        raise ExportError("tool acceleration must be in (0, 100) m/s^2, got %r" % (tool_acceleration,))
    plan = load_plan(path, cell)
    if arms is None:
        names = list(plan.programs)
    else:
        names = [n.strip() for n in (arms.split(",") if isinstance(arms, str) else arms) if n.strip()]
        unknown = [n for n in names if n not in plan.programs]
        if unknown or not names:
            raise ExportError("%s: no arm %s in this plan (it has: %s)"
                              % (path, ", ".join(repr(n) for n in unknown) or "given", ", ".join(plan.programs)))
    if fmt == "urscript":
        for n in names:
            if plan.programs[n].arm.profile.brand != UR_BRAND:
                raise ExportError(_not_ur(plan.programs[n].arm))
        if len(plan.programs) > 1:
            raise ExportError(_open_loop(path, plan))
    warnings = _check_report(plan, force)
    result, records = record_plan(plan)
    warnings += _compare_report(plan, records)
    out = out or path
    os.makedirs(out, exist_ok=True)
    summary = {"format": fmt, "plan": path, "out": out, "cell": plan.cell.name, "timing": TIMING,
               "makespan_s": round(result.makespan_s, 3), "arms": {}, "warnings": warnings}
    for n in names:
        rec = records[n]
        if fmt == "trajectory":
            traj = trajectory(rec)
            checks = check_limits(traj)
            if not (checks["velocity_ok"] and checks["acceleration_ok"]):   # a bug of the timing law
                raise ExportError("arm %s: the planned motion exceeds a joint limit (speeds %s, limits %s; worst "
                                  "acceleration %s); nothing written" % (n, checks["max_velocity"],
                                                                        checks["velocity_limit"],
                                                                        checks["acceleration_worst"]))
            files = _write_trajectory(rec, traj, checks, plan, out)
            summary["arms"][n] = {"files": files, "samples": int(len(traj.t)), "duration_s": traj.duration,
                                  "checks": checks}
        else:
            text, stats = urscript(rec, digital_out, tool_acceleration, os.path.abspath(path), plan.cell)
            fpath = os.path.join(out, n + ".script")
            with open(fpath, "w") as f:
                f.write(text)
            summary["arms"][n] = dict(stats, files=[fpath])
    return summary


def _check_report(plan, force):
    rep = plan.report
    problems = []
    if rep is None:
        problems.append("no report.json: the motion was never checked for collisions "
                        "(run `python -m ambots plan`, which writes it)")
    else:
        if rep.get("finished") is False:
            problems.append("report.json: the run did not finish (%s)" % rep.get("reason"))
        coll = rep.get("collisions") or {}
        if isinstance(coll, dict) and sum(v for v in coll.values() if isinstance(v, (int, float))):
            problems.append("report.json: collisions %s" % coll)
    if problems and not force:
        raise ExportError("%s: %s; not exported (--force exports anyway)" % (plan.path, "; ".join(problems)))
    return problems


def _compare_report(plan, records):
    """Warnings where the re-run differs from report.json (another cell file,
    edited programs, a ``--slow`` plan)."""
    rep = plan.report or {}
    out = []
    for name, rec in records.items():
        a = (rep.get("arms") or {}).get(name) or {}
        if a.get("moves") is not None and a["moves"] != rec.moves:
            out.append("arm %s: %d moves executed, report.json says %d" % (name, rec.moves, a["moves"]))
        if a.get("done_at_s") is not None and rec.done_s is not None \
                and abs(a["done_at_s"] - rec.done_s) > 2e-3:
            out.append("arm %s: done at %.3f s, report.json says %.3f s (planned with --slow, or another cell?)"
                       % (name, rec.done_s, a["done_at_s"]))
    return out
