"""The timeline's greedy schedule (:class:`Schedule`): every arm at once on
estimated durations, each starting a chunk of its layer when no adjacent
arm's current step is within the pair's zone of it across their plane; an
arm in another's way retreats to its park position.  See
:func:`ambots.coordinate.timeline.timeline_programs`.

Units: mm, s."""
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from ambots.coordinate.parking import APPROACH_MM, lift_height, safe_height
from ambots.coordinate.steps import _order_runs, first_start, reversed_segments, seg_time

__all__ = ["Schedule", "Act"]

#: estimated nozzle speed of travels (mm/s) and fixed cost (s) of a
#: retracted travel, and of a joint move (to or from a park position)
_TRAVEL_MM_S, _TRAVEL_S, _JOINT_MM_S, _JOINT_S = 150.0, 0.1, 100.0, 2.0


@dataclass
class Act:
    """One step of an arm's schedule: ``kind`` "chunk" (print ``segs``),
    "retreat" (to the park position and back later) or "park" (the end)."""
    kind: str
    layer: int
    S: float                     #: scheduled start (s)
    C: float                     #: scheduled end (s)
    fp: np.ndarray               #: distance (mm) to each adjacent arm's plane: closest over the step
    segs: list = field(default_factory=list)
    waits: dict = field(default_factory=dict)    #: {other arm: index of its step to wait for}
    report: Optional[int] = None  #: the arm that first waits for this step's end (robot id; 0 is one), or None
    #: a chunk started from home or the park position: the height (mm) its joint move
    #: arrives at over the chunk's start; a retreat or park from the part: the height
    #: the nozzle lifts to before the joint move (:func:`~ambots.coordinate.parking.safe_height`,
    #: :func:`~ambots.coordinate.parking.lift_height`)
    z: Optional[float] = None


def _path_time(pos, segs):
    """Estimated seconds to print ``segs`` (in order) from ``pos`` (None: a
    joint move from somewhere else)."""
    t = seg_time(segs)
    here = None if pos is None else np.asarray(pos, dtype=float)
    for s in segs:
        start = np.asarray(s.start, dtype=float)
        if here is None:
            t += _JOINT_S
        else:
            gap = float(np.linalg.norm(start - here))
            if gap > 1e-6:
                t += gap / _TRAVEL_MM_S + (_TRAVEL_S if gap >= 2.0 else 0.0)
        here = np.asarray(s.end, dtype=float)
    return t


class Schedule:
    """One greedy schedule of the chunks (:meth:`run` -> {arm: [Act]}).
    ``seams``: the arms' planes and zones (:class:`~ambots.coordinate.
    timeline.Seams`); ``chunks``: {(arm, layer): [(pieces, closest distance
    to each plane, level)]}; ``priority``: an arm leaves alone what an
    adjacent arm of higher rank still has to print within the zone;
    ``order``: {(arm, layer): {chunk index: rank}} (:func:`~ambots.
    coordinate.lookahead.layer_orders`): a free arm starts the chunk of
    least rank that nobody is in the way of, and a chunk started from the
    part ends at its point clearest of the seams (:meth:`_runs`)."""

    def __init__(self, seams, chunks, home, park, n_layers, priority, order=None):
        self.seams, self.chunks, self.park, self.n_layers, self.priority = seams, chunks, park, n_layers, priority
        self.order = order
        names = self.names = seams.names
        self.acts = {n: [] for n in names}
        self.pos = {n: np.asarray(home[n], dtype=float) for n in names}           # where the nozzle waits
        self.pos_d = {n: seams.dist(n, self.pos[n])[0] if len(seams.N[n]) else np.zeros(0) for n in names}
        self.first = {n: True for n in names}                                      # still at home
        self.parked = {n: False for n in names}                                    # at the park position
        self.layer_of = {n: 0 for n in names}
        self.left = {n: list(range(len(chunks[n, 0]))) if n_layers else [] for n in names}
        self.layer_end = {}                                                        # (arm, layer) -> time printed
        self.done = {n: False for n in names}
        self.t_free = {n: 0.0 for n in names}
        self._arrays = {}                                                          # (arm, layer) -> arrays
        # the part printed so far, for the joint moves' clearance: the whole
        # model's footprint up to the top of a layer
        ends = [s.end for (_, layer), cs in chunks.items() for c in cs for s in c[0]]
        xy = np.array([e[:2] for e in ends], dtype=float).reshape(-1, 2)
        self.lo_xy = xy.min(axis=0) if len(xy) else np.zeros(2)
        self.hi_xy = xy.max(axis=0) if len(xy) else np.zeros(2)
        self.tops = np.zeros(max(n_layers, 1))
        for (_, layer), cs in chunks.items():
            for c in cs:
                self.tops[layer] = max(self.tops[layer], max(s.end[2] for s in c[0]))
        self.tops = np.maximum.accumulate(self.tops)

    # ---- the state
    def state_d(self, b, t):
        if self.acts[b] and self.acts[b][-1].C > t:
            return self.acts[b][-1].fp
        return self.pos_d[b]

    def start(self, n, act, end_pos, at_park):
        self.acts[n].append(act)
        self.t_free[n] = act.C
        self.pos[n] = np.asarray(end_pos, dtype=float)
        self.pos_d[n] = np.full(len(self.seams.N[n]), np.inf) if at_park else self.seams.dist(n, self.pos[n])[0]
        self.parked[n] = at_park
        self.first[n] = False

    def box(self, layer):
        """The part printed by the time an arm prints ``layer`` ((lo, hi) bed
        mm): the model's footprint up to the top of the layer as many layers
        on as the arms can be apart (a layer starts when the adjacent arms
        have printed the one before)."""
        top = float(self.tops[min(layer + len(self.names) - 1, len(self.tops) - 1)])
        return (self.lo_xy[0], self.lo_xy[1], 0.0), (self.hi_xy[0], self.hi_xy[1], top)

    def to_park(self, n, t, kind):
        p = np.asarray(self.park[n], dtype=float)
        dur = float(np.linalg.norm(p - self.pos[n])) / _JOINT_MM_S + _JOINT_S
        fp = self.pos_d[n].copy()
        z = None
        if self.first[n]:                          # the joint move there from home
            fp = np.minimum(fp, self.seams.path_d(n, None, p))
        elif not self.parked[n]:                   # straight up, then the A7's joint move
            box = self.box(self.layer_of[n])
            z = lift_height(self.seams.moves, n, self.pos[n], p, float(self.pos[n][2]) + APPROACH_MM, box)
            fp = np.minimum(fp, self.seams.path_d(n, (self.pos[n][0], self.pos[n][1], z), p, park=True))
        self.start(n, Act(kind, self.layer_of[n], t, t + dur, fp, z=z), p, True)

    def layer_ready(self, n, layer, t):
        """Every adjacent arm has printed ``layer``, by time t."""
        return all(self.done[b] or self.layer_of[b] > layer or
                   (self.layer_of[b] == layer and not self.left[b] and self.layer_end.get((b, layer), 0.0) <= t)
                   for b in self.seams.nbrs[n])

    def _layer_arrays(self, n, layer):
        """Arm n's chunks of ``layer`` as arrays (kept): closest distances to
        each plane (C, P), levels (C,), first pieces' starts and last pieces'
        ends (2C, 3), and a dict for :meth:`_joint_d`."""
        key = (n, layer)
        out = self._arrays.get(key)
        if out is None:
            chunks = self.chunks[key]
            P = len(self.seams.N[n])
            D = np.array([c[1] for c in chunks], dtype=float).reshape(len(chunks), P)
            ends = np.array([c[0][0].start for c in chunks] + [c[0][-1].end for c in chunks],
                            dtype=float).reshape(-1, 3)
            out = self._arrays[key] = (D, [c[2] for c in chunks], ends, {})
        return out

    def _joint_d(self, n, layer, ci, first):
        """(closest distances to the planes (P,), height (mm)) of the joint
        move to over chunk ci's start from home (``first``) or from the park
        position: it arrives :data:`APPROACH_MM` over the start (under it
        only the arm's own part, a layer lower) or higher, until the arm's
        bodies keep clear of the bed and the part printed (:meth:`box`;
        :func:`~ambots.coordinate.parking.safe_height`); the nozzle then goes
        straight down, no nearer any plane than the start; kept."""
        cache = self._layer_arrays(n, layer)[3]
        key = (ci, first)
        out = cache.get(key)
        if out is None:
            p = np.asarray(first_start(self.chunks[n, layer][ci][0]), dtype=float)
            a = None if first else self.park[n]
            box = self.box(layer)
            z = safe_height(self.seams.moves, n, a, p, float(p[2]) + APPROACH_MM, float(self.park[n][2]), box)
            out = cache[key] = (self.seams.path_d(n, a, (p[0], p[1], z)), z)
        return out

    def candidates(self, n, t):
        """(chunk index, footprint, clashing arms, score) of arm n's chunks left
        in its layer, all chunks at once."""
        if not self.left[n]:
            return []
        layer = self.layer_of[n]
        D, levels, ends, _ = self._layer_arrays(n, layer)
        left = self.left[n]
        C = len(D)
        # how near the arm is to each chunk's ends, all at once
        d = ends[left + [C + ci for ci in left]] - self.pos[n]
        d = np.sqrt(np.add.reduce(d * d, axis=1)).reshape(2, -1)      # np.linalg.norm(axis=1)'s arithmetic
        nearest = np.minimum(d[0], d[1]).tolist()
        FP = np.minimum(D[left], self.pos_d[n])
        if self.first[n] or self.parked[n]:         # the joint move there, from home or the park position
            first = self.first[n]
            FP = np.minimum(FP, np.array([self._joint_d(n, layer, ci, first)[0] for ci in left]).reshape(FP.shape))
        sm = self.seams
        nbrs = sm.nbrs[n]
        if nbrs:
            S = np.array([self.state_d(b, t)[sm.where[n][b]] for b in nbrs], dtype=float)
            hit = (FP + S < sm.Z[n] - 1e-9).tolist()
        else:
            hit = [[]] * len(left)
        return [(ci, fp, [b for b, h in zip(nbrs, row) if h], (levels[ci], near))
                for ci, fp, row, near in zip(left, FP, hit, nearest)]

    def rank(self, n):
        """Priority in the current layer: the cell's order on even layers,
        reversed on odd ones (the last arm of a layer goes on first)."""
        i = self.names.index(n)
        return i if self.layer_of[n] % 2 == 0 else len(self.names) - 1 - i

    def before(self, n, fp):
        """True if a step with footprint fp would come within the zone of work
        still left in this layer to an adjacent arm of higher priority: that
        work goes first, so an arm sweeps towards a seam behind its
        neighbour instead of both racing to it."""
        sm = self.seams
        for i, b in enumerate(sm.nbrs[n]):
            if (self.done[b] or self.layer_of[b] != self.layer_of[n] or self.rank(b) > self.rank(n)
                    or not self.left[b]):
                continue
            j = sm.where[n][b]
            rest = self._layer_arrays(b, self.layer_of[b])[0][self.left[b], j].min()
            if fp[i] + rest < sm.Z[n][i] - 1e-9:
                return True
        return False

    # ---- the moves
    def try_step(self, n, t):
        if self.done[n]:
            return False
        if self.layer_of[n] >= self.n_layers:
            self.to_park(n, t, "park")
            self.done[n] = True
            return True
        if not self.left[n]:
            if self.layer_ready(n, self.layer_of[n], t):
                self.layer_of[n] += 1
                self.left[n] = (list(range(len(self.chunks[n, self.layer_of[n]])))
                                if self.layer_of[n] < self.n_layers else [])
                return True
            return False
        ok = [c for c in self.candidates(n, t) if not c[2] and not (self.priority and self.before(n, c[1]))]
        if not ok:
            return False
        rank = {} if self.order is None else self.order.get((n, self.layer_of[n]), {})
        ci, fp, _, _ = min(ok, key=lambda c: (rank.get(c[0], 0), c[3]))
        ps, _, _ = self.chunks[n, self.layer_of[n]][ci]
        here = None if self.first[n] or self.parked[n] else self.pos[n]
        z = None if here is not None else self._joint_d(n, self.layer_of[n], ci, self.first[n])[1]
        segs = self._runs(n, ps, here)
        dur = _path_time(here, segs)
        self.left[n].remove(ci)
        self.start(n, Act("chunk", self.layer_of[n], t, t + dur, fp, segs, z=z), segs[-1].end, False)
        if not self.left[n]:
            self.layer_end[n, self.layer_of[n]] = t + dur
        return True

    def _runs(self, n, ps, here):
        """A chunk's pieces in the order printed from ``here`` (None: from
        home or the park position; :func:`~ambots.coordinate.steps._order_runs`).
        With an ``order``, a chunk started from the part ends where it is
        clearest of the seams (:meth:`~ambots.coordinate.timeline.Seams.
        clearance`) when the order from ``here`` does not: the runs are
        ordered from that point and printed backwards, so that the arm then
        waits, and travels to its next chunk, away from its neighbours'
        work.  (Session 24, the four-arm plate with one chunk band per
        seam and the look-ahead order: 19,285 s without, 17,070 s with.)"""
        segs = _order_runs(ps, None if here is None else tuple(here))
        if self.order is None or here is None or len(segs) < 2:
            return segs
        pts = np.array([p.start for p in segs] + [p.end for p in segs], dtype=float)
        clear = self.seams.clearance(n, pts)
        back = _order_runs(ps, tuple(pts[int(np.argmax(clear))]))
        back = reversed_segments(back)
        ends = self.seams.clearance(n, np.array([segs[-1].end, back[-1].end], dtype=float))
        return back if ends[1] > ends[0] + 1e-6 else segs

    def in_the_way(self, n, t, waiting):
        """Arms standing still (waiting too) in the way of one of arm n's chunks."""
        best = None
        for ci, fp, who, score in self.candidates(n, t):
            if who and all(b in waiting and not (self.acts[b] and self.acts[b][-1].C > t) for b in who):
                if best is None or (len(who), score) < best[0]:
                    best = ((len(who), score), who)
        return [] if best is None else best[1]

    def retreats(self, t, waiting, running):
        """The arms to send to their park positions at time t: those that have
        finished their layer and stand in someone's way; those in the way
        when nobody can go on."""
        retreat = set()
        for n in waiting:
            for b in self.in_the_way(n, t, waiting):
                if (not self.left[b] or not running) and not self.parked[b]:
                    retreat.add(b)
        if not retreat and not running:
            for n in waiting:                     # nobody can go on: clear the way of the first waiting arm
                who = [b for c in self.candidates(n, t) for b in c[2] if not self.parked[b]]
                if self.left[n] and who:
                    retreat.add(who[0])
                    break
            if not retreat:
                raise RuntimeError("coordinate: the schedule is stuck at %.1f s: %s" % (
                    t, {n: (self.layer_of[n], len(self.left[n])) for n in waiting}))
        return retreat

    def run(self):
        names = self.names
        guard = 0
        while not all(self.done.values()):
            guard += 1
            if guard > 10_000_000:
                raise RuntimeError("coordinate: the schedule does not progress")
            t = min(self.t_free[n] for n in names if not self.done[n])
            moved = True
            while moved:
                moved = False
                for n in names:
                    if not self.done[n] and self.t_free[n] <= t and self.try_step(n, t):
                        moved = True
            waiting = [n for n in names if not self.done[n] and self.t_free[n] <= t]
            if not waiting:
                continue
            running = [self.acts[n][-1].C for n in names if self.acts[n] and self.acts[n][-1].C > t]
            retreat = self.retreats(t, waiting, running)
            if retreat:
                for b in sorted(retreat, key=names.index):
                    self.to_park(b, t, "retreat")
                continue
            for n in waiting:
                self.t_free[n] = min(running)
        return self.acts
