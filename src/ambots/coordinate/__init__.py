"""Coordination: each arm's sliced G-code -> one program per arm (G-code plus
A-series commands), in one of two modes.

``sequential`` (the original project's hand-over, in rounds): the first arm
sends every other arm to its park position (A7); the arms print in turn, each
its layers of a round (a slab low enough for the next arm's print head to
pass over it), then park and hand over: A1 starts the next arm, A6 resumes
it later, A2 pauses the arm until its next turn
(:mod:`~ambots.coordinate.sequential`).

``concurrent`` (default): all arms print the same layer at the same time,
for any number of arms.  The spacing rule: two arms whose work comes within
``zone`` of each other across the plane between them (their seam, or for
two parts that meet only at a corner, the power-diagram plane between them)
never have nozzles closer than ``zone`` to each other *measured across that
plane* (the sum of the two nozzles' distances to it).  ``zone`` comes from
the arms' real geometry (:func:`ambots.collision.seam_zones_mm`, pair by
pair).  Such arms are *adjacent*.

* When the adjacent arms can be given two colours so that every adjacent
  pair has different colours (two arms; a row of arms along a beam), each
  layer is cut into bands by distance from the nearest seam, and the two
  colours sweep the bands in opposite directions (:mod:`ambots.coordinate.banded`).
* Otherwise (three arms around a point, four in the corners of a bed) the
  layer is cut into chunks by band with respect to every adjacent pair's
  plane, and a schedule on estimated durations decides which chunk each
  arm prints when, so that no two chunks that come within the zone run at
  the same time; an arm whose waiting position is in another's way
  retreats to its park position (:mod:`ambots.coordinate.timeline`; the
  order of each layer's chunks looked ahead: :mod:`~ambots.coordinate.lookahead`).

Both wait (``;@A9 R<self> W<other> N<line>``) only for adjacent arms, and
only at lines the other arm reports at once (the end of a step followed by
its own barrier, or a ``;@A3`` report), so no wait can outlast the work it
waits for; and every wait names work that ends earlier in the schedule, so
no set of arms can wait for each other.  Barriers name exact lines of the
other arm's program, which the builder knows because it writes every
program.

Park positions (:func:`~ambots.coordinate.parking.park_positions_mm`) are clear of the bed: an arm
whose home pose hangs over the bed parks raised and retracted towards its
own base.

Coordination commands are directive lines (``;@A9 R1 W2 N120``, see
:mod:`ambots.program`): comments to any other reader, executed by the
firmware at that point of the program.

Programs are canonical G-code re-emitted from the reader's segments
(absolute XYZ, relative E, mm and mm/min in the bed frame), with PrusaSlicer
style ``;LAYER_CHANGE`` comments, so any firmware or ``python -m ambots
info`` reads them.  Slicer output is sanitised first: A-series lines in it
are stripped and reported.

The package: :mod:`~ambots.coordinate.steps` (the one intermediate form:
the sliced G-code read once, pieces, steps with their waits and reports),
:mod:`~ambots.coordinate.zones` (seam planes, zones, adjacency),
:mod:`~ambots.coordinate.parking` (home and park positions, joint moves to
and from them), one module per strategy (:mod:`~ambots.coordinate.
sequential`, :mod:`~ambots.coordinate.banded` with the band choice in
:mod:`~ambots.coordinate.bands`, :mod:`~ambots.coordinate.timeline` with
its schedule in :mod:`~ambots.coordinate.schedule` and the look-ahead
order in :mod:`~ambots.coordinate.lookahead`) and
:mod:`~ambots.coordinate.emit` (steps -> G-code and directives).
"""

from ambots.coordinate.banded import banded_programs
from ambots.coordinate.emit import ArmProgram, _Writer
from ambots.coordinate.parking import JointMoves, home_positions_mm, park_positions_mm
from ambots.coordinate.sequential import sequential_programs
from ambots.coordinate.steps import Sliced, _order_runs, read_sliced
from ambots.coordinate.timeline import timeline_programs
from ambots.coordinate.zones import (LayerPlanes, adjacent_arms, seam_planes, seam_zone_for, seam_zones_for,
                                     two_colours)
from ambots.errors import AmbotsError
from ambots.protocol import MoveTo

__all__ = ["ArmProgram", "build_programs", "CHUNK_BANDS", "CHUNK_BAND_CHOICES", "park_positions_mm",
           "home_positions_mm", "seam_zone_for",
           "seam_zones_for", "seam_planes", "adjacent_arms", "read_sliced", "Sliced"]


def build_programs(sliced, parts, cell, mode="concurrent", zone_mm=None, park=None, idle=(), slab_mm=None,
                   chunk_bands=None, written=None):
    """Build every arm's program.

    Parameters
    ----------
    sliced : {arm name: G-code text, or that text read (:class:`Sliced`,
        :func:`read_sliced`: a job that uses the same G-code in several
        plans reads it once)} of each part, bed frame, mm
    parts : the :class:`~ambots.partition.Part` list (gives arm order and seam
        planes, each with the arm on its other side)
    cell : the cell (home and park positions come from the arms' geometry)
    mode : ``"concurrent"`` or ``"sequential"``
    zone_mm : how far apart (mm) two nozzles across a seam must stay
        (concurrent mode), one figure for every pair; default: pair by pair
        from the arms' real geometry in the poses they print these parts
        in, :func:`seam_zones_for`
    park : optional {arm name: (x, y, z) mm} overriding the park positions
    idle : arms of the cell without work in this job: the first arm's
        program sends them to their park positions first (A7), as
        sequential mode does with the arms that wait for their turn (a
        job of one arm, or of a group of the cell's arms)
    slab_mm : sequential mode: the most a round's slab may rise over its
        first layer (default: from the print heads,
        :func:`~ambots.coordinate.sequential.slab_rounds`)
    chunk_bands : a scheduled timeline's chunk bands per seam (default
        :data:`CHUNK_BANDS`; :attr:`ArmProgram.phases` is that + 1); the
        job tries :data:`CHUNK_BAND_CHOICES` and keeps the fastest plan
    written : a one-arm program: a list shared by the programs of the same
        G-code for other arms alone, which the first fills and the others
        copy their moves from where they are the same
        (:class:`~ambots.coordinate.emit.Emitter`)

    Returns {arm name: :class:`ArmProgram`}, in the parts' order.
    """
    if mode not in ("concurrent", "sequential"):
        raise ValueError("mode must be 'concurrent' or 'sequential', got %r" % mode)
    arms = [p.arm for p in parts]
    idle = [a for a in idle if a.name not in {b.name for b in arms}]
    park = park or park_positions_mm(cell, arms + idle)
    read = {a.name: _read(sliced[a.name], "%s.gcode" % a.name) for a in arms}
    n_layers = max([max(layers) + 1 for layers in (r.layers for r in read.values()) if layers] or [0])
    if mode == "sequential" or (len(arms) == 1 and idle):
        return sequential_programs(arms, read, park, idle, mode, moves=JointMoves(cell, arms), slab_mm=slab_mm,
                                   written=written)
    planes = seam_planes(parts)
    if zone_mm is None:
        zones = seam_zones_for(cell, arms, parts)
    else:
        zones = {pair: float(zone_mm) for pair in planes}
    shifts = {p.arm.name: p.layer_offsets for p in parts if getattr(p, "layer_offsets", None) is not None}
    if shifts:
        # a stepped seam (:mod:`ambots.seam_steps`): two arms only, banded; an arm can be a
        # layer ahead of its neighbour, so the zone grows by the seam's largest step
        from ambots.seam_steps import largest_step
        if len(arms) != 2:
            raise ValueError("a stepped seam is for two arms, got %d" % len(arms))
        step = max(largest_step(s) for s in shifts.values())
        zones = {pair: z + step for pair, z in zones.items()}
    home = home_positions_mm(cell, arms)
    # the cell's arms without work (a group of its arms prints): parked first, as for an arm alone
    opening = {arms[0].name: [MoveTo(o.id, *(round(float(v), 3) for v in park[o.name])) for o in idle]
               } if idle else {}
    return _concurrent(arms, read, park, home, n_layers, planes, zones, JointMoves(cell, arms),
                       CHUNK_BANDS if chunk_bands is None else chunk_bands, shifts, opening)


def _read(gcode, path):
    """A part's G-code as :class:`Sliced` (read here if it is text)."""
    return gcode if isinstance(gcode, Sliced) else read_sliced(gcode, path)


#: chunk bands per seam of a scheduled timeline (:func:`~ambots.coordinate.timeline.timeline_programs`)
CHUNK_BANDS = 4
#: the chunk bands a job tries for a scheduled timeline, keeping the fastest
#: plan by the one timing law (:func:`ambots.job.run_job`): fewer bands cut
#: the layers into fewer, longer pieces (each starts and stops at rest),
#: more let the schedule pack the arms closer in time; which wins depends
#: on the part (session 14: the 300 mm plate with four arms 0.439 with 4,
#: 0.421 with 3; a 140 mm ring 0.869 with 4, 0.698 with 2).  One band (the
#: pieces cut only at the zones' edges) pays with the look-ahead order
#: (:mod:`~ambots.coordinate.lookahead`; session 24, the plate: 12 % less
#: work than with 3 bands, 16,121 s against 17,966 s)
CHUNK_BAND_CHOICES = (1, 2, 3, 4)


def _concurrent(arms, read, park, home, n_layers, planes, zones, moves=None, chunk_bands=CHUNK_BANDS, shifts=None,
                opening=None):
    """Banded sweeps when the adjacent arms have two colours and every arm
    can keep clear of its seams; otherwise the scheduled timeline.
    ``shifts``: a stepped seam's {arm: (L,) mm per layer} (banded only);
    ``opening``: {arm: [messages]} its program sends first (A7 to the idle arms)."""
    names = [a.name for a in arms]
    adjacent = adjacent_arms(arms, read, planes, zones)
    colour = two_colours(names, adjacent)
    if colour is not None:
        near = {a: [planes[a, b] for b in names if b in adjacent[a]] for a in names}
        if shifts:
            near = LayerPlanes(near, shifts)
        zone = max([zones[a, b] for a in names for b in adjacent[a]] or [0.0])
        programs = banded_programs(arms, read, park, n_layers, zone, near, colour, adjacent, home, zones, moves,
                                   opening)
        if programs is not None:
            return programs
    if shifts:
        raise AmbotsError("a stepped seam needs the banded sweeps, and these arms cannot keep clear of it "
                          "in bands")
    # no two colours, or an arm between two seams cannot stand clear of both
    # (their zones about as wide as its part): the scheduled timeline
    return timeline_programs(arms, read, park, home, n_layers, planes, zones, adjacent, bands=chunk_bands,
                             moves=moves, opening=opening)
