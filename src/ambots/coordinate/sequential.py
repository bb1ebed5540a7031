"""Sequential mode: the original project's hand-over, in rounds.

The original: the UR10 moved out of the way first; the Kinova printed,
parked and started the UR10; the UR10 printed, parked, resumed the Kinova
and paused itself.  Here, for the arms of the parts in order (any number)
and ``k`` rounds:

* the first arm's program opens with an A7 to every other arm (and to every
  idle arm of the cell): out of the way, to its park position;
* a *turn* is one arm printing its layers of one round, then parking
  (retract once, lift straight up clear of everything printed so far, A7 to
  its park position), then handing over: ``;@A1`` to the next turn's arm the
  first time it prints, ``;@A6`` (resume) after that, and ``;@A2`` to itself
  (pause) when it has a later turn, until an ``;@A6`` resumes it;
* turns go round the arms in order, round after round (an arm without
  layers in a round has no turn in it); the last turn ends its program
  (DONE: no arm would resume it), and so does every arm's last turn.

With two arms and one round that is the original's order without its last
two commands; with k rounds the last arm ends rounds 1 .. k-1 as the
original's UR10 does: park, A6 the first arm, A2 itself.

**Why rounds** (:func:`slab_rounds`).  The parts meet at vertical seams, so
an arm never prints above another's region; but an arm printing a layer at
height z next to another arm's slab has its print head over that slab near
the seam.  The head's lowest body is ``gap`` behind the tip (5 mm in the
profiles' ``tool.head``: :func:`head_gap_mm`), so the other slab may stand
at most ``gap - SLAB_MARGIN_MM`` over the layer being printed.  One round
(the first arm's whole half, then the second's) has the second head inside
the first half as soon as that is taller: the demo block's 10 mm half
4.8 mm inside it.  So the layers are cut into rounds whose slab rises at
most ``gap - SLAB_MARGIN_MM`` over its first layer (4 mm: the demo's 50
layers in 3 rounds of 17, 17 and 16): the fewest such rounds, with equal
numbers of layers where that holds.  Each arm starts a round on top of its
own previous slab, level with or above every other arm's.

**First moves** (:func:`~ambots.coordinate.parking.safe_height`).  A turn's first move goes from
wherever the arm stands (its home pose, its park position) to
``APPROACH_MM`` over the top of everything printed so far, above its first
point: a joint move of the firmware's planner, since the nozzle is not
where the G-code was.  That move is sampled here
(:meth:`~ambots.coordinate.parking.JointMoves.clearance_mm`) with the
arm's bodies against the bed and the box of the parts printed so far (the
footprint of the whole model, up to the top so far) and raised until it
keeps ``CLEAR_MM``; then the nozzle goes straight down.  The lift before
the A7 that parks it is chosen the same way
(:func:`~ambots.coordinate.parking.lift_height`: the park height for an
arm with joints to spare).  Also a one-arm job with idle
arms (one turn, the idle arms parked first).

Units: mm in the bed frame (G-code)."""
from ambots.config import HEAD_TIP_GAP
from ambots.protocol import MoveTo, Pause, Resume, Start

from ambots.coordinate.emit import ArmProgram, Emitter
from ambots.coordinate.parking import APPROACH_MM, CLEAR_MM, lift_height, safe_height
from ambots.coordinate.steps import Step

__all__ = ["sequential_programs", "slab_rounds", "head_gap_mm", "SLAB_MARGIN_MM", "APPROACH_MM", "CLEAR_MM"]

#: clearance (mm) the print head keeps over the other arms' slabs
SLAB_MARGIN_MM = 1.0


def head_gap_mm(arm):
    """How far (mm) the print head's bodies stay behind the nozzle tip (the
    nearest of the profile's ``tool.head`` bodies; :data:`ambots.config.
    HEAD_TIP_GAP` without any)."""
    head = arm.profile.head
    if not head:
        return HEAD_TIP_GAP * 1000.0
    return -max(max(c.a[2], c.b[2]) + c.radius for c in head) * 1000.0


def slab_rounds(tops, slab_mm):
    """Sorted distinct layer tops (mm) -> the rounds' upper bounds (mm): a
    round holds the layers with tops in (previous bound, its bound].  The
    fewest rounds whose layers rise at most ``slab_mm`` over the round's
    first layer; as many layers in each as can be (equal counts) while
    that holds, else greedily from the bottom."""
    tops = sorted(set(float(z) for z in tops))
    if not tops:
        return []
    groups, i = [], 0
    while i < len(tops):
        j = i
        while j + 1 < len(tops) and tops[j + 1] - tops[i] <= slab_mm + 1e-9:
            j += 1
        groups.append((i, j))
        i = j + 1
    k, n = len(groups), len(tops)
    ends = [round(n * (r + 1) / k) - 1 for r in range(k)]
    equal = list(zip([0] + [e + 1 for e in ends[:-1]], ends))
    if all(tops[b] - tops[a] <= slab_mm + 1e-9 for a, b in equal):
        groups = equal
    return [tops[b] for _, b in groups]


def _layer_pieces(layers):
    """{layer: [Segment]} -> [(top z mm, extruding segments)] in layer order:
    the slicer's travels and retractions are dropped (the writer makes its
    own, and retracts once before a park)."""
    out = []
    for k in sorted(layers):
        pieces = [s for s in layers[k] if s.extrude and s.start != s.end]
        if pieces:
            out.append((max(s.end[2] for s in pieces), pieces))
    return out


def turns_of(arms, pieces, bounds):
    """The turns in order: (round, arm index, [(top, pieces)]) for every arm
    with layers in the round (an arm's turns in a row, when the others have
    nothing left, are one)."""
    turns = []
    lo = -float("inf")
    for r, hi in enumerate(bounds):
        for i, arm in enumerate(arms):
            mine = [(z, p) for z, p in pieces[arm.name] if lo + 1e-9 < z <= hi + 1e-9]
            if mine and turns and turns[-1][1] == i:     # the only arm left: it goes on
                turns[-1] = (turns[-1][0], i, turns[-1][2] + mine)
            elif mine:
                turns.append((r, i, mine))
        lo = hi
    return turns


def sequential_programs(arms, read, park, idle=(), mode="sequential", moves=None, slab_mm=None, written=None):
    """{arm name: ArmProgram}, ``read``: {arm name: Sliced}; ``moves``: a
    :class:`~ambots.coordinate.parking.JointMoves` of the arms to check
    the first moves with (None: the lowest approach height, unchecked);
    ``slab_mm``: the most a round's slab may rise over its first layer
    (default: the heads' gap less :data:`SLAB_MARGIN_MM`); ``written``: one
    arm's program only: a list shared with the other arms' programs of the
    same G-code, each alone (:class:`~ambots.coordinate.emit.Emitter`)."""
    arms = list(arms)
    pieces = {a.name: _layer_pieces(read[a.name].layers) for a in arms}
    tops = [z for a in arms for z, _ in pieces[a.name]]
    if slab_mm is None:
        slab_mm = min(head_gap_mm(a) for a in arms) - SLAB_MARGIN_MM
    bounds = slab_rounds(tops, slab_mm) if len(arms) > 1 else ([max(tops)] if tops else [])
    turns = turns_of(arms, pieces, bounds)
    # the footprint of the whole model (every arm's extrusions): the printed box's x, y
    xy = [(s.start[0], s.start[1]) for a in arms for _, p in pieces[a.name] for s in p] + \
         [(s.end[0], s.end[1]) for a in arms for _, p in pieces[a.name] for s in p]
    lo_xy = (min(x for x, _ in xy), min(y for _, y in xy)) if xy else (0.0, 0.0)
    hi_xy = (max(x for x, _ in xy), max(y for _, y in xy)) if xy else (0.0, 0.0)

    def box(top):
        return (lo_xy[0], lo_xy[1], 0.0), (hi_xy[0], hi_xy[1], max(top, 0.0))

    steps = {a.name: [] for a in arms}
    where = {a.name: None for a in arms}               # None: home; else the park position (mm)
    started = set()
    if arms:
        others = [o for o in arms[1:] + list(idle)]
        steps[arms[0].name].append(Step(directives=[MoveTo(o.id, *(round(float(v), 3) for v in park[o.name]))
                                                    for o in others]))
        for o in arms[1:]:
            where[o.name] = tuple(park[o.name])
        started.add(arms[0].name)
    top = 0.0                                           # of everything printed so far (mm)
    for t, (r, i, layers) in enumerate(turns):
        arm = arms[i]
        name = arm.name
        first = layers[0][1][0].start
        z_in = safe_height(moves, name, where[name], first, max(top, first[2]) + APPROACH_MM,
                            float(park[name][2]), box(top))
        for n, (z, segs) in enumerate(layers):
            steps[name].append(Step(layers=[z], pieces=segs, approach=z_in if n == 0 else None))
        top = max(top, max(z for z, _ in layers))
        last = layers[-1][1][-1].end
        z_out = lift_height(moves, name, last, park[name], max(top, last[2]) + APPROACH_MM, box(top))
        steps[name].append(Step(park=park[name], lift_to=z_out))
        where[name] = tuple(park[name])
        hand = []
        if t + 1 < len(turns):
            nxt = arms[turns[t + 1][1]]
            hand.append(Start(nxt.id) if nxt.name not in started else Resume(nxt.id))
            started.add(nxt.name)
        if any(j == i for _, j, _ in turns[t + 1:]):
            hand.append(Pause(arm.id))                  # until the arm before its next turn resumes it
        if hand:
            steps[name].append(Step(directives=hand))
    programs = {}
    for i, arm in enumerate(arms):
        em = Emitter(arm, mode, written=written if len(arms) == 1 else None).steps(steps[arm.name])
        n_turns = sum(1 for _, j, _ in turns if j == i)
        programs[arm.name] = ArmProgram(arm, mode, em.lines, read[arm.name].removed, len(read[arm.name].layers),
                                        max(1, n_turns), start_first=(i == 0), events=em.events())
    return programs
