"""The scheduled timeline: concurrent programs for any adjacency (an odd
cycle of adjacent arms: three or more around a point, four in the corners
of a bed), and for rows the banded sweeps cannot serve.  Each arm's layer
is cut into chunks (:func:`_chunks`), a greedy schedule on estimated
durations orders them (:class:`~ambots.coordinate.schedule.Schedule`), and
the order becomes barriers (:func:`_barriers`) in the programs
(:func:`timeline_programs`)."""
import bisect

import numpy as np

from ambots.coordinate.emit import ArmProgram, Emitter, resolve_waits
from ambots.coordinate.links import LayerWalls, edge_links
from ambots.coordinate.lookahead import layer_orders
from ambots.coordinate.schedule import Schedule
from ambots.coordinate.steps import Step, Wait, close, cut_segment

__all__ = ["timeline_programs", "Seams", "SCHEDULES"]

#: the last schedule :func:`timeline_programs` made ({arm: [Act]}), for inspection
_last_schedule = None


#: the most a point of a program lies across its part's plane by the G-code's
#: rounding to 0.001 mm (0.0005 mm per coordinate, both coordinates; the
#: schedule was measured 25 % longer on the four-arm 300 mm plate when
#: such points counted as across)
ROUNDING_MM = 0.001


#: the schedules :func:`timeline_programs` makes, the shortest kept: the
#: greedy one with the cell's order as priorities, without, and with the
#: look-ahead order (:func:`~ambots.coordinate.lookahead.layer_orders`)
SCHEDULES = ("priority", "greedy", "lookahead")

#: the chunks' infill linked along their edges (:func:`~ambots.coordinate.links.edge_links`)
#: and not: :func:`timeline_programs` schedules both and keeps the shorter.  A link
#: saves a start from rest, but a linked run is printed whole, in one direction:
#: the schedule can no longer take its lines in another order (session 36, the
#: four-arm 300 mm plate, one chunk band, the look-ahead order: its schedule
#: 15,895 s linked against 14,178 s not, 18,021 s against 16,119 s by the one
#: timing law; the 276 mm hex plate gained by the links, 12,495 -> 12,211 s,
#: session 33)
LINKS = (True, False)

#: the schedules made of the chunks as cut: the look-ahead order, whose chunks
#: end at their point clearest of the seams, any line's end.  The greedy and
#: priority schedules were never shorter with them on the four-arm 300 mm plate
#: (1-4 chunk bands, session 36), and made of them too they cost 18 % more of
#: the timeline's time for one plan they won: the 140 mm ring's four arms
#: together, 4,717 s against 4,745 s, a plan two of its arms beat (4,472 s)
CUT_SCHEDULES = ("lookahead",)


def timeline_programs(arms, read, park, home, n_layers, planes, zones, adjacent, bands=4, kinds=SCHEDULES,
                      moves=None, opening=None, links=None):
    """Any adjacency (an odd cycle of adjacent arms: three or more around a point).

    Each arm's layer is cut into *chunks*: pieces of its extrusions grouped
    by band (width zone / ``bands``) of distance to each adjacent arm's plane,
    all pieces beyond the zone in one band; planes of pairs that are within
    the zone of each other everywhere (a strip along a seam) cut nothing,
    since those two arms never print at once.  A greedy schedule on
    estimated durations then runs every arm at once: an arm starts a chunk
    (the travel to it included) when, for every adjacent arm, the sum of the
    two distances to their plane over the chunk and over what the other arm
    is doing (printing a chunk, or waiting at the end of one) is at least the
    pair's zone; chunks nearest a seam first, the nearest to the nozzle among
    equals.  A step's footprint covers the joint moves to and from the park
    position (or from home) too, as the firmware makes them (``moves``,
    :class:`~ambots.coordinate.parking.JointMoves`: their points below the
    printable height).  A layer starts when the adjacent arms have finished the previous one.  An
    arm with nothing to do that stands in another's way (or when nobody can
    go on) retreats to its park position.  The schedule is made
    three times (``kinds``, :data:`SCHEDULES`): with the arms' priorities
    (an arm leaves alone what an adjacent arm earlier in the cell's list,
    later on odd layers, still has to print within the zone, so that arm
    sweeps away from their seam and this one follows), without, and in the
    look-ahead order (each layer's chunks ordered by a search over the
    layer as a scheduling problem, :mod:`~ambots.coordinate.lookahead`;
    a chunk then ends at its point clearest of the seams), with the chunks'
    infill linked along their edges, and the look-ahead one also with the
    chunks as cut (``links``, default :data:`LINKS`;
    :data:`CUT_SCHEDULES`); the shortest (by its own estimated durations)
    is kept, the first on a tie.

    The order becomes barriers (:func:`_barriers`): before each step an
    arm waits, for every adjacent arm, for the last of that arm's steps
    which ended by this step's start in the schedule and whose footprint
    comes within the pair's zone of this step's (it ends with an ``;@A3``
    report); steps that keep the zone from it need no wait.  Whatever the
    real durations, two steps (or an arm standing between them) that overlap
    in reality were then checked against each other in the schedule or keep
    the zone; waits only name steps that end earlier in the schedule, so
    they cannot form a cycle.  ``opening``: {arm: [messages]} its program
    sends before anything else (A7 to the cell's idle arms)."""
    global _last_schedule
    links = LINKS if links is None else tuple(links)
    unknown = set(kinds) - set(SCHEDULES)
    if unknown or not kinds:
        raise ValueError("timeline_programs: kinds must be some of %s, got %r" % (", ".join(SCHEDULES), kinds))
    if not links or set(links) - set(LINKS):
        raise ValueError("timeline_programs: links must be some of %s, got %r" % (LINKS, links))
    seams = Seams(arms, read, planes, zones, adjacent, moves)
    variants = _chunk_variants(seams, read, n_layers, bands, links)

    def made(kind, chunks):
        order = layer_orders(seams, chunks, n_layers)[0] if kind == "lookahead" else None
        return Schedule(seams, chunks, home, park, n_layers, kind == "priority", order=order).run()

    tried = [(link, k) for link in links for k in SCHEDULES if k in kinds and (link or k in CUT_SCHEDULES)]
    if not tried:
        raise ValueError("timeline_programs: the chunks as cut are scheduled only in the orders %s, got %r"
                         % (", ".join(CUT_SCHEDULES), kinds))
    linked, acts = min(((link, made(k, variants[link])) for link, k in tried),
                       key=lambda r: max((a[-1].C for a in r[1].values() if a), default=0.0))
    _last_schedule = acts
    arm_of = {a.name: a for a in arms}
    _barriers(acts, seams, arm_of)
    emitters = {}
    for n in seams.names:
        extra = ["; seam zones %s mm, %d chunk band(s) per seam, scheduled, infill %s along chunk edges"
                 % (", ".join("%s %.1f" % (b, zones[n, b]) for b in seams.nbrs[n]) or "-", bands,
                    "linked" if linked else "not linked")]
        first = [Step(directives=list(opening[n]))] if (opening or {}).get(n) else []
        emitters[n] = Emitter(arm_of[n], "concurrent", extra).steps(first + _steps(acts[n], seams.names, park[n],
                                                                                   n_layers))
    resolve_waits(emitters)
    return {n: ArmProgram(arm_of[n], "concurrent", emitters[n].lines, read[n][0], n_layers, bands + 1,
                          start_first=True, events=emitters[n].events(), chunk_bands=bands) for n in seams.names}


class Seams:
    """Each arm's adjacent arms (``nbrs``, in the cell's order; ``where[n][b]``:
    n's index in b's list), the planes between them (normals ``N[n]`` (P, 3),
    offsets ``O[n]`` (P,)), their zones ``Z[n]`` (P,), and which planes are
    ``useful``: a pair whose parts never get a zone apart anywhere (a strip
    along a seam) can never print at once, so where an arm is across that
    plane makes no difference, and those planes neither cut chunks nor
    order them.  ``moves``: :class:`~ambots.coordinate.parking.JointMoves`
    (or None)."""

    def __init__(self, arms, read, planes, zones, adjacent, moves=None):
        names = self.names = [a.name for a in arms]
        self.moves = moves
        self._path_d = {}
        self.nbrs = {n: [b for b in names if b in adjacent[n]] for n in names}
        self.where = {n: {b: self.nbrs[b].index(n) for b in self.nbrs[n]} for n in names}
        self.N = {n: np.array([planes[n, b][0] for b in self.nbrs[n]], dtype=float).reshape(-1, 3) for n in names}
        self.O = {n: np.array([planes[n, b][1] for b in self.nbrs[n]], dtype=float) for n in names}
        self.Z = {n: np.array([zones[n, b] for b in self.nbrs[n]], dtype=float) for n in names}
        reach = {}
        for n in names:
            pts = np.array([s.start for layer in read[n][1].values() for s in layer if s.extrude]
                           + [s.end for layer in read[n][1].values() for s in layer if s.extrude], dtype=float)
            reach[n] = self.dist(n, pts).max(axis=0) if len(pts) and len(self.N[n]) else np.zeros(len(self.N[n]))
        self.useful = {n: np.array([reach[n][i] + reach[b][self.where[n][b]] >= self.Z[n][i]
                                    for i, b in enumerate(self.nbrs[n])], dtype=bool) for n in names}

    def dist(self, n, pts):
        """Signed distances (K, P) of points to arm n's planes; a point within
        the G-code's rounding across a plane (a part clipped from the whole
        model's toolpaths ends on it, :mod:`ambots.seam_clip`) is on it."""
        d = np.asarray(pts, dtype=float).reshape(-1, 3) @ self.N[n].T - self.O[n]
        d[(d < 0.0) & (d > -ROUNDING_MM)] = 0.0
        return d

    def clearance(self, n, pts):
        """How clear of arm n's seams each point is (K,): its smallest
        distance to a plane as a share of that pair's zone, at most 1 (1:
        clear of every zone; 1 for an arm without adjacent arms)."""
        d = self.dist(n, pts)
        if not d.shape[1]:
            return np.ones(len(d))
        return np.minimum(d / self.Z[n], 1.0).min(axis=1)

    def path_d(self, n, a, b, park=False):
        """Closest distance to each adjacent arm's plane on arm n's joint move
        from ``a`` (None: home) to ``b`` (``park``: an A7 to the park
        position) below the printable height (inf: none)."""
        key = (n, None if a is None else tuple(np.asarray(a, dtype=float).tolist()),
               tuple(np.asarray(b, dtype=float).tolist()), park)
        out = self._path_d.get(key)
        if out is None:              # the schedule asks again for every chunk it weighs: kept
            P = self.moves.path(n, a, b, park) if self.moves is not None and len(self.N[n]) else np.zeros((0, 3))
            out = self._path_d[key] = self.dist(n, P).min(axis=0) if len(P) else np.full(len(self.N[n]), np.inf)
        return out.copy()


def _split_at(seg, N, O, W, bands):
    """Cut a segment where its distance to plane p (normals ``N`` (P, 3),
    offsets ``O`` (P,)) crosses m ``W[p]``, 1 <= m <= ``bands``; E is shared
    in proportion to length."""
    a, b = np.array(seg.start, dtype=float), np.array(seg.end, dtype=float)
    if not len(N) or close(seg.start, seg.end):
        return [seg]
    fa, fb = N @ a - O, N @ b - O
    cuts = []
    for p in range(len(N)):
        if abs(fb[p] - fa[p]) < 1e-12:
            continue
        lo, hi = sorted((fa[p], fb[p]))
        for m in range(max(1, int(np.floor(lo / W[p])) + 1), min(bands, int(np.ceil(hi / W[p])) - 1) + 1):
            t = (m * W[p] - fa[p]) / (fb[p] - fa[p])
            if 1e-9 < t < 1 - 1e-9:
                cuts.append(t)
    return cut_segment(seg, cuts)


def _chunks(seams, read, n_layers, bands, links=True):
    """:func:`_chunk_variants` of one kind (``links``: the infill linked
    along the chunks' edges, or as cut)."""
    return _chunk_variants(seams, read, n_layers, bands, (links,))[links]


def _chunk_variants(seams, read, n_layers, bands, links=LINKS):
    """{link: {(arm, layer): [(pieces, closest distance to each plane (P,), level)]}}
    for each of ``links`` (True: linked along the chunks' edges; False: as cut):
    the arm's extrusions on the layer cut into pieces and grouped by band
    (width zone / ``bands``) of distance to each useful plane, all pieces
    beyond the zone in one band; ``level``: the nearest band to a seam.  A
    chunk's pieces keep the slicer's order, joined where its infill left
    the chunk across a band edge and came back across the same edge
    (:func:`~ambots.coordinate.links.edge_links`: without, each line of a
    zig-zag cut at an edge is a run of its own, with a retracted travel to
    the next).  A link lies on a chunk edge between two ends of its
    pieces: the closest distances are the pieces' either way."""
    out = {link: {} for link in links}
    for n in seams.names:
        useful = seams.useful[n]
        W = np.where(useful, seams.Z[n] / bands, np.inf)
        planes = list(zip(seams.N[n], seams.O[n]))
        edges = [w * np.arange(1, bands + 1) if u else np.zeros(0) for w, u in zip(W, useful)]
        features = getattr(read[n], "features", None)
        for layer in range(n_layers):
            layer_segs = read[n][1].get(layer, [])
            pieces, src = [], []
            for i, s in enumerate(layer_segs):
                if s.extrude and s.start != s.end:
                    cut = _split_at(s, seams.N[n], seams.O[n], W, bands)
                    pieces += cut
                    src += [i] * len(cut)
            groups = {}
            if pieces:
                mid = np.array([np.add(p.start, p.end) / 2.0 for p in pieces])
                keys = np.minimum(np.floor(seams.dist(n, mid) / np.maximum(W, 1e-9)), bands).astype(int)
                keys[:, ~useful] = 0
                for p, i, key in zip(pieces, src, map(tuple, keys)):
                    groups.setdefault(key, ([], []))
                    groups[key][0].append(p)
                    groups[key][1].append(i)
            walls = LayerWalls(layer_segs) if True in links else None
            for link in links:
                out[link][n, layer] = []
            for key in sorted(groups):
                cut = groups[key][0]
                pts = np.array([p.start for p in cut] + [p.end for p in cut], dtype=float)
                dmin = seams.dist(n, pts).min(axis=0) if len(seams.N[n]) else np.zeros(0)
                level = min([k for k, u in zip(key, useful) if u] or [bands])
                for link in links:
                    ps = edge_links(layer_segs, cut, groups[key][1], planes, edges, features, walls) if link else cut
                    out[link][n, layer].append((ps, dmin, level))
    return out


def _barriers(acts, seams, arm_of):
    """Each step's waits (``Act.waits``): for every adjacent arm b, the last
    of b's steps that ended by this step's start in the schedule and whose
    footprint comes within the pair's zone of this step's (across their
    plane), unless an earlier step of the arm already waited for it or a
    later one; each step waited for reports its end to the first arm that
    waits for it (``Act.report``).

    Why that is enough, whatever the real durations (a step's footprint
    covers where the arm stands before it, and the chunk's last point, where
    it stands after): while arm n runs step s (or stands before it), b has
    completed the step waited for, so b is in a later step or stands after
    one.  b's steps up to the last that ended by s's start in the schedule,
    after the one waited for, keep the zone from s by choice; the steps that
    overlapped s in the schedule were checked against it by the schedule;
    a step of b that comes after s in the schedule and comes within the zone
    of s waits for s (or a later step of n) by the same rule from b's side.
    The layers keep their order where it matters: the schedule starts a
    layer only when the neighbours have finished the one below, so a step
    of the next layer waits for every step of theirs below it that comes
    within the zone of it; elsewhere an arm may go on to its next layer
    while a neighbour, a zone away, still prints the one below.  Session 18, the four-arm 300 mm plate: 20,587 -> 19,896 s (3 chunk
    bands; every step waiting for every earlier step of its neighbours made
    the arms wait for work that was nowhere near them)."""
    ends = {n: [act.C for act in acts[n]] for n in acts}
    for n in acts:
        last = {b: -1 for b in seams.nbrs[n]}
        for act in acts[n]:
            for i, b in enumerate(seams.nbrs[n]):
                j, zone = seams.where[n][b], seams.Z[n][i]
                m = bisect.bisect_right(ends[b], act.S) - 1
                while m > last[b] and act.fp[i] + acts[b][m].fp[j] >= zone - 1e-9:
                    m -= 1                      # keeps the zone from this step: no need to wait for it
                if m > last[b]:
                    act.waits[b] = m
                    last[b] = m
                    if acts[b][m].report is None:
                        acts[b][m].report = arm_of[n].id


def _steps(acts, names, park, n_layers):
    """An arm's scheduled acts as steps: the layer changes up to the act's
    layer (a park: to the last), its waits (in the cell's order), the chunk
    printed (from home or the park position: over its start at the act's
    height, then down) or the park position (lifted to the act's height
    first), its report; the mark is the act's index."""
    steps, marked = [], -1
    for i, act in enumerate(acts):
        upto = act.layer if act.kind == "chunk" else (n_layers - 1 if act.kind == "park" else -1)
        st = Step(waits=[Wait(b, m) for b, m in sorted(act.waits.items(), key=lambda kv: names.index(kv[0]))])
        while marked < upto:
            marked += 1
            st.layers.append(act.segs[-1].end[2] if marked == act.layer and act.segs else 0.0)
        if act.kind == "chunk":
            st.travel, st.pieces, st.approach = act.segs[0].start, act.segs, act.z
        else:
            st.park, st.lift_to = park, act.z
        if act.report is not None:
            st.report, st.mark = act.report, i
        steps.append(st)
    return steps
