"""How long a plan takes, timed by the one timing law, fast enough to
compare plans before any arm moves (no ROS).

Two steps:

1. **One arm's program, line by line** (:func:`line_durations`).  The
   firmware's :class:`~ambots.motion.MotionPlanner` (IK, the one timing law)
   plans a sample of the program: its first run of moves, from the arm's
   home pose as the firmware starts it, then short windows of moves, one in
   each of equal strata of the rest (:func:`_plan_sample`).  Those lines
   take their planned time.  Every other move takes the
   time of a per-move model fitted on the sample, one per kind of move
   (extruding, travel in the layer, any other travel -- a lift, a lowering --
   and filament only): ``a * feed_time + b + c * sqrt(length)``, the time at
   the feedrate, a fixed cost, and the ramps of a move that starts and ends
   at rest (from rest over a distance L at a constant acceleration takes a
   time in sqrt(L)); coefficients >= 0.  Dwells take their time; a move to a
   park position (A7 to itself) is planned.
2. **The arms together on one clock** (:func:`makespan`).  Each arm runs its
   lines in order.  An arm that the front end does not start (sequential
   mode) begins at the A1 another arm's program sends it; an A9 holds its
   arm until the awaited arm has finished the line (or started the layer) it
   names -- what the firmware does with the hub's reports, without the
   messages' latency; an A2 to itself holds it until another arm's A6 (or
   A1) sent after it paused (sequential mode's rounds).  The makespan is
   when the last arm finishes.

The estimate is checked against the offline simulation on one clock
(:func:`ambots.sim.simulate`, every move planned, the hub and the runners'
messages) in ``tests/unit/test_estimate.py``.

Units: seconds; positions at the G-code boundary in mm (bed frame).
"""
import itertools
from dataclasses import dataclass, field
from typing import Dict, Optional

import numpy as np

from ambots.errors import AmbotsError
from ambots.protocol import MoveTo, Pause, Resume, Start, WaitFor

__all__ = ["ProgramTimes", "EstimateError", "line_durations", "program_time", "makespan", "estimate_programs",
           "MOVE_KINDS", "SAMPLE_MOVES"]

#: the kinds of move the per-move model tells apart
MOVE_KINDS = ("extrude", "travel", "lift", "filament")
#: about this many moves of a program are planned for the sample
SAMPLE_MOVES = 1500
#: moves in one window of the sample (:func:`_plan_sample`).  The estimate
#: against every move planned, over seven placements of the windows in their
#: strata: the hex plate 276 x 174 x 3 mm's four programs on four arms and
#: the demo's four (each arm alone, the pair's two), windows of 20 moves:
#: mean error -0.45 to +0.01 %, SD 0.15-0.44 % per program; of 50: SD up to
#: 1.2 %; of 10: no better (SD 0.34-0.46 %).  Before session 35 the sample
#: was whole runs of up to 400 moves: on one of the hex plate's programs mean
#: -1.4 %, SD 1.0 %; at the one placement used, -1.1 to -3.3 % on seven
#: of these programs (the Kinova's alone not measured).
WINDOW_MOVES = 20
#: moves of the run planned either side of a window, not counted: a window
#: of 50 moves in a run of 400 takes within 0.02 % of its time in the whole
#: run with none, exactly with 3 or more (six runs of the hex plate's program)
WINDOW_MARGIN = 3
#: where a window lies in its stratum (0.5: the middle)
_PHASE = 0.5


class EstimateError(AmbotsError):
    """A plan cannot be timed (an arm cannot reach a move, arms wait for each other)."""


@dataclass
class ProgramTimes:
    """One program's time per line: ``d`` (n_lines + 1,) s, index = line
    (0 unused); ``layer_of_line`` (n_lines + 1,); ``directives`` {line:
    protocol message}; ``planned_moves``/``moves`` how many moves were
    planned / in all; ``model`` {kind: (a, b, c)}."""
    d: np.ndarray
    layer_of_line: np.ndarray
    directives: Dict[int, object]
    moves: int = 0
    planned_moves: int = 0
    model: Dict[str, tuple] = field(default_factory=dict)
    error: Optional[str] = None

    @property
    def total_s(self):
        return float(self.d.sum())


#: a move whose direction turns by more than this from the one before (or
#: after) starts (ends) at a corner, where the arm slows down or rests
CORNER_DEG = 20.0


def _features(segments, first=None):
    """(kind index, feed time s, length mm, corners (0, 1 or 2: ends of the
    move at a corner or at rest)) per segment, vectorised; the feed time is
    :func:`ambots.gcode.summarize`'s (length / feedrate, a filament-only
    move at its E speed) per segment.  ``segments``: one run of moves, or
    several one after the other with ``first`` (bool per segment) marking
    where each run starts (a run starts and ends at rest)."""
    S = np.array([s.start for s in segments], float)
    E = np.array([s.end for s in segments], float)
    L = np.linalg.norm(E - S, axis=1)
    e = np.array([s.e for s in segments], float)
    feed = np.array([s.feedrate for s in segments], float)
    ext = np.array([s.extrude for s in segments], bool)
    with np.errstate(divide="ignore", invalid="ignore"):
        f = np.where(feed > 0, np.where(L > 0, L, np.abs(e)) * 60.0 / np.where(feed > 0, feed, 1.0), 0.0)
    flat = np.abs(E[:, 2] - S[:, 2]) < 1e-9
    kind = np.where(L == 0, 3, np.where(ext, 0, np.where(flat, 1, 2)))
    u = (E - S) / np.where(L > 0, L, 1.0)[:, None]
    smooth = np.zeros(len(L) + 1, bool)          # smooth[k]: no corner between move k-1 and move k
    if len(L) > 1:
        smooth[1:-1] = ((np.einsum("ij,ij->i", u[:-1], u[1:]) > np.cos(np.radians(CORNER_DEG)))
                        & (L[:-1] > 0) & (L[1:] > 0) & (kind[:-1] == kind[1:]))
    if first is not None:
        smooth[:-1] &= ~first
    corners = (~smooth[:-1]).astype(float) + (~smooth[1:]).astype(float)
    return kind, f, L, corners


#: a fit of more columns replaces one of fewer only if it lowers the squared
#: residual by more than this share of ``|y|^2`` (:func:`_nonneg_fit`)
FIT_TIE_SHARE = 1e-9


def _nonneg_fit(X, y, w=None):
    """Least squares with coefficients >= 0 (few columns: every subset
    tried, fewer columns first), rows weighted by ``w`` (default 1).

    Subsets that fit equally well (within :data:`FIT_TIE_SHARE`) keep the
    first one tried.  A sample whose moves of one kind all look alike (the
    12 lifts of a 40 mm cube's program: one row of features) fits every
    subset exactly as well, and the planned times differ in their last bits
    from one call to the next (numpy's vector loops depend on where the
    arrays lie in memory): with a strict ``<`` the model of those moves
    flipped between 26.9 x the feed time and 0.08 s x sqrt(length), and the
    UR10's program took 1,102.4 s or 1,100.9 s, one call or the next."""
    if w is not None:
        r = np.sqrt(np.asarray(w, float))
        X, y = X * r[:, None], y * r
    best, cost = np.zeros(X.shape[1]), float(np.sum(y * y))
    tie = FIT_TIE_SHARE * cost
    for r in range(1, X.shape[1] + 1):
        for cols in itertools.combinations(range(X.shape[1]), r):
            c, *_ = np.linalg.lstsq(X[:, cols], y, rcond=None)
            if (c < 0).any():
                continue
            full = np.zeros(X.shape[1])
            full[list(cols)] = c
            res = float(np.sum((X @ full - y) ** 2))
            if res < cost - tie:
                best, cost = full, res
    return best


def _design(f, L, corners):
    """Features of the per-move model: time at the feedrate, a fixed cost,
    and the ramps at the move's corners (sqrt(length) per corner)."""
    return np.stack([f, np.ones_like(f), 0.5 * corners * np.sqrt(L)], axis=1)


def line_durations(text, arm, cell, path="<program>", sample_moves=SAMPLE_MOVES, planner=None, events=None):
    """Per-line durations of ``arm`` executing program ``text`` alone (step 1
    of the module docstring).  An unreachable move in the sample sets
    ``error`` (the durations are then those of the model).  ``events``: the
    text's G-code events, if the caller has parsed it already."""
    from ambots.motion import Directive, MotionPlanner, Moves, Pause, read_program
    items, n_lines, layer_of_line = read_program(text, path, events=events)
    d = np.zeros(n_lines + 1)
    directives = {it.line: it.message for it in items if isinstance(it, Directive)}
    runs = [i for i, it in enumerate(items) if isinstance(it, Moves)]
    planner = planner or MotionPlanner(arm, cell)
    home = np.asarray(arm.profile.home, float)
    out = ProgramTimes(d, layer_of_line, directives)
    if not runs:
        for it in items:
            if isinstance(it, Pause):
                d[it.line] += it.seconds
        return out
    segs = [s for i in runs for s in items[i].segments]
    sizes = np.array([len(items[i].segments) for i in runs])
    first = np.zeros(len(segs), bool)
    first[np.cumsum(sizes) - sizes] = True
    kind, f, L, cor = _features(segs, first)
    lines = np.array([s.line for s in segs])
    out.moves = len(segs)
    planned = np.zeros(len(segs), bool)  # the moves that take their planned time
    rows = []            # (kind, feed time, length, corners, planned time, weight) of the sampled moves
    for a, b, weight, block in _plan_sample(planner, home, segs, sizes, lines, sample_moves):
        if block.error is not None:
            out.error = "%s: line %d: %s" % (path, block.error.line, block.error.message)
            break
        per_line = np.zeros(n_lines + 1)
        np.add.at(per_line, block.line[1:], np.diff(block.t))
        t = per_line[lines[a:b]]
        d[lines[a:b]] = t
        planned[a:b] = True
        k0 = 1 if (a == 0 and b - a > 1) else 0      # the program's first move holds the lead from home
        rows.append(np.column_stack([kind[a + k0:b], f[a + k0:b], L[a + k0:b], cor[a + k0:b], t[k0:],
                                     np.full(b - a - k0, weight)]))
        out.planned_moves += b - a
    out.model = _fit(rows)
    coef = np.array([out.model[name] for name in MOVE_KINDS])
    rest = ~planned
    if rest.any():                       # the other moves, all at once
        t = np.einsum("ij,ij->i", _design(f[rest], L[rest], cor[rest]), coef[kind[rest]])
        np.add.at(d, lines[rest], t)
    last_end = None                      # where the program's moves were before each item (bed mm)
    for it in items:
        if isinstance(it, Pause):
            d[it.line] += it.seconds
        elif isinstance(it, Moves):
            last_end = it.segments[-1].end
        elif isinstance(it.message, MoveTo) and it.message.robot == arm.id:
            d[it.line] += _park_time(planner, last_end, it.message, home)
    return out


def _plan_sample(planner, home, segs, sizes, lines, sample_moves):
    """The sample of step 1, planned: yields (a, b, weight, block) -- the
    moves ``segs[a:b]`` take their time in ``block`` and weigh ``weight``
    each in the fit -- and stops after a block with an error.

    A program of at most ``sample_moves`` moves is planned whole, run by run.
    Otherwise the first run is planned whole from ``home`` (as the firmware
    starts it), and the rest of the program is cut into equal strata of
    moves, one window of :data:`WINDOW_MOVES` moves in the middle of each
    (within the run there), planned with :data:`WINDOW_MARGIN` moves of the
    run either side so that its ends are timed as inside the run; each of
    its moves weighs the stratum's moves / the window's.  ``sizes``: the
    moves of each run, in order; ``lines``: each move's program line (a
    window never cuts a line's moves apart)."""
    ends = np.cumsum(sizes)
    starts = ends - sizes
    total = int(ends[-1])
    if total <= sample_moves:
        windows = [(int(a), int(b), int(a), int(b), 1.0) for a, b in zip(starts, ends)]
    else:
        windows = [(0, int(ends[0]), 0, int(ends[0]), 1.0)]
        n = total - int(ends[0])
        count = max(1, (sample_moves - int(ends[0])) // (WINDOW_MOVES + 2 * WINDOW_MARGIN))
        for k in range(count if n else 0):
            c = int(ends[0]) + (k + _PHASE) * n / count
            j = int(np.searchsorted(ends, c, side="right"))
            lo_run, hi_run = int(starts[j]), int(ends[j])
            b = min(hi_run, max(lo_run, int(c) - WINDOW_MOVES // 2) + WINDOW_MOVES)
            a = max(lo_run, b - WINDOW_MOVES, windows[-1][1])
            while a < b and a > lo_run and lines[a - 1] == lines[a]:
                a += 1
            while b < hi_run and lines[b] == lines[b - 1]:
                b += 1
            if a < b:
                windows.append((a, b, max(lo_run, a - WINDOW_MARGIN), min(hi_run, b + WINDOW_MARGIN),
                                n / count / (b - a)))
    q = home
    for a, b, lo, hi, weight in windows:
        if lo != 0:                     # the joints where the planned moves start (no move there: not counted)
            there = planner.joints_at(planner.bed_mm_to_base(np.array([segs[lo].start]))[0], q)[0]
            if there is not None:
                q = there
        block = planner.plan_moves(segs[lo:hi], q)
        yield a, b, weight, block
        if block.error is not None:
            return
        q = block.Q[-1]


def _fit(rows):
    """The per-move model {kind: (a, b, c)} fitted on the sample's rows
    (:func:`_plan_sample`); a kind with fewer than 8 moves in the sample
    takes the sample's overall ratio to the feed time."""
    R = np.concatenate(rows) if rows else np.zeros((0, 6))
    ratio = R[:, 4].sum() / max(R[:, 1].sum(), 1e-9) if len(R) else 1.0
    model = {}
    for k, name in enumerate(MOVE_KINDS):
        sel = R[:, 0] == k
        if sel.sum() >= 8:
            model[name] = tuple(_nonneg_fit(_design(R[sel, 1], R[sel, 2], R[sel, 3]), R[sel, 4], R[sel, 5]))
        else:
            model[name] = (ratio, 0.0, 0.0)
    return model


def program_time(text, arm, cell, path="<program>", sample_moves=SAMPLE_MOVES):
    """Seconds ``arm`` needs to execute ``text`` alone (the sum of
    :func:`line_durations`), or None if a sampled move is out of its reach."""
    pt = line_durations(text, arm, cell, path, sample_moves)
    return None if pt.error else pt.total_s


def _park_time(planner, prev, msg, home):
    """Duration of an A7 to itself: a joint move from ``prev`` (bed mm, the
    end of the moves before it; None: from home)."""
    q = home
    if prev is not None:
        lead = planner.joint_move_to(planner.bed_mm_to_base(np.array([prev]))[0], home)
        if lead.error is None:
            q = lead.Q[-1]
    block = planner.move_to(planner.bed_mm_to_base(np.array([[msg.x, msg.y, msg.z]]))[0], q)
    return block.duration if block.error is None else 0.0


class _OnTheClock:
    """One arm's program on the shared clock (:func:`makespan`): the
    directive it is at, the line it has reached, and when each stretch of
    its lines began (a stretch starts at a barrier it waited at, or where
    it was resumed)."""

    def __init__(self, pt, started):
        self.pt = pt
        self.marks = sorted(pt.directives)
        self.cs = np.concatenate([[0.0], np.cumsum(pt.d[1:])])    # cs[k]: lines 1..k
        self.i = 0                                  # the next directive, index into marks
        self.line = 0                               # the lines done so far
        self.clock = self.start = 0.0 if started else None
        self.stretches = [(0, 0.0)]                 # (first line, time it began)
        self.done = None

    def begin(self, t):
        """Started (A1 from another arm) at ``t``."""
        self.clock = self.start = t
        self.stretches = [(0, t)]

    def at(self, line):
        """When ``line`` ends in the stretch the arm is in now."""
        first, t0 = self.stretches[-1]
        return t0 + self.cs[line] - self.cs[first]

    def time_of_line(self, line):
        """When the arm finished ``line``, or None if not known yet."""
        if self.done is not None and line >= self.line:
            return self.done
        if self.clock is None or line > self.line:
            return None
        for first, t0 in reversed(self.stretches):
            if first <= line:
                return t0 + self.cs[line] - self.cs[first]
        return None

    def time_of_layer(self, layer):
        hit = np.nonzero(self.pt.layer_of_line[1:] >= layer)[0]
        if not len(hit):
            return self.done
        return self.time_of_line(int(hit[0]) + 1)


def makespan(times, arms, start_first=None):
    """The arms' programs together on one clock (step 2 of the module
    docstring).  ``times``: {arm name: :class:`ProgramTimes`}; ``arms``: the
    arm objects (name, id); ``start_first``: {name: bool}, arms the front end
    starts (default: all).  Returns {"makespan_s", "arms": {name: {"start_s",
    "finish_s", "busy_s", "idle_s", "layer_busy_s" (the s it moves on each
    layer of its program, (L,))}}}.  Raises :class:`EstimateError` if
    the arms would wait for each other for ever."""
    by_id = {a.id: a.name for a in arms}
    start_first = start_first or {}
    state = {a.name: _OnTheClock(times[a.name], start_first.get(a.name, True)) for a in arms if a.name in times}
    resumes = {n: [] for n in state}                 # when other arms sent an arm A6 (or A1 once started)
    progress = True
    while progress:
        progress = False
        for n, s in state.items():
            if s.clock is not None and s.done is None:
                progress |= _run_until_blocked(n, s, state, by_id, resumes)
    stuck = [n for n, s in state.items() if s.done is None]
    if stuck:
        raise EstimateError("the programs of %s wait for each other (or are never started)" % ", ".join(stuck))
    out = {"makespan_s": max((s.done for s in state.values()), default=0.0), "arms": {}}
    for n, s in state.items():
        busy = float(s.pt.d.sum())
        layer = np.maximum(np.asarray(s.pt.layer_of_line), 0)        # lines before the first layer: in it
        out["arms"][n] = {"start_s": float(s.start), "finish_s": float(s.done), "busy_s": busy,
                          "idle_s": float(s.done - s.start - busy),
                          "layer_busy_s": np.bincount(layer, weights=s.pt.d) if len(layer) else np.zeros(0)}
    return out


def _run_until_blocked(n, s, state, by_id, resumes):
    """Move arm ``n`` (``s``, :class:`_OnTheClock`) through its directives
    until it waits for what has not happened yet (another arm's line or
    layer, a resume) or ends; True if it got anywhere."""
    moved = False
    while s.i < len(s.marks):
        m = s.marks[s.i]
        at_m = s.at(m - 1)
        msg = s.pt.directives[m]
        if isinstance(msg, WaitFor) and by_id.get(msg.robot) == n and by_id.get(msg.other) in state:
            other = state[by_id[msg.other]]
            t = other.time_of_line(msg.line) if msg.line is not None else other.time_of_layer(msg.layer)
            if t is None:
                s.line = m - 1
                return moved                        # blocked: let the others run
            s.stretches.append((m, max(at_m, t)))   # line m (the barrier) ends then
        elif isinstance(msg, Pause) and by_id.get(msg.robot) == n:
            # paused until another arm's A6 (or A1) sent after it paused; earlier ones were ignored
            t = next((r for r in resumes[n] if r >= at_m), None)
            if t is None:
                s.line = m - 1
                return moved                        # paused: let the others run
            resumes[n] = [r for r in resumes[n] if r > t]
            s.stretches.append((m, t))
        elif isinstance(msg, (Start, Resume)) and by_id.get(msg.robot) in state and by_id[msg.robot] != n:
            o = state[by_id[msg.robot]]
            sent = at_m + s.cs[m] - s.cs[m - 1]
            if o.clock is None and isinstance(msg, Start):
                o.begin(sent)
            elif o.clock is not None:
                resumes[by_id[msg.robot]].append(sent)
        s.i += 1
        s.line = m
        moved = True
    s.line = len(s.pt.d) - 1
    s.done = s.at(s.line)
    return True


def estimate_programs(programs, cell, sample_moves=SAMPLE_MOVES, events=None):
    """Makespan of coordinated programs ({name: ArmProgram}, see
    :mod:`ambots.coordinate`), timed by the one timing law: :func:`makespan`
    of each program's :func:`line_durations`.  Adds ``errors`` {name: text}
    for programs with a move out of reach in the sample.  ``events``: {name:
    the program's G-code events} when the caller has parsed them already
    (:meth:`ambots.coordinate.ArmProgram.parse`)."""
    from ambots.parallel import fork_map
    events = events or {}
    # the arms' programs timed side by side (:mod:`ambots.parallel`), even beside the job's
    # background worker: the timing is a plan's last step, when the arms alone are about done
    # (the 60 mm sphere: 0.3 s sooner)
    names = list(programs)
    times = dict(zip(names, fork_map(lambda n: line_durations(programs[n].text, programs[n].arm, cell, n + ".gcode",
                                                              sample_moves, events=events.get(n)), names,
                                    share=False)))
    out = makespan(times, [p.arm for p in programs.values()],
                   {n: p.start_first for n, p in programs.items()})
    out["errors"] = {n: t.error for n, t in times.items() if t.error}
    out["planned_moves"] = {n: t.planned_moves for n, t in times.items()}
    return out
