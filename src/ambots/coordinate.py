"""Coordination: each arm's sliced G-code -> one program per arm (G-code plus
A-series commands), in one of two modes.

``sequential`` (the original project's behaviour): the first arm sends every
other arm to its park position (A7), prints its whole part, parks itself and
starts the next arm (A1); and so on down the cell's list of arms.

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
  colours sweep the bands in opposite directions (:func:`_banded`).
* Otherwise (three arms around a point, four in the corners of a bed) the
  layer is cut into chunks by band with respect to every adjacent pair's
  plane, and a greedy schedule on estimated durations decides which chunk
  each arm prints when, so that no two chunks that come within the zone run
  at the same time; an arm whose waiting position is in another's way
  retreats to its park position (:func:`_timeline`).

Both wait (``;@A9 R<self> W<other> N<line>``) only for adjacent arms, and
only at lines the other arm reports at once (the end of a step followed by
its own barrier, or a ``;@A3`` report), so no wait can outlast the work it
waits for; and every wait names work that ends earlier in the schedule, so
no set of arms can wait for each other.  Barriers name exact lines of the
other arm's program, which the builder knows because it writes every
program.

Park positions (:func:`park_positions_mm`) are clear of the bed: an arm
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
"""
import bisect
import math
from dataclasses import dataclass, field
from typing import Dict, List

import numpy as np

from ambots.gcode import Segment, parse_gcode_text
from ambots.program import directive, sanitize_gcode
from ambots.protocol import MoveTo, SendPosition, Start, WaitFor

__all__ = ["ArmProgram", "build_programs", "park_positions_mm", "home_positions_mm", "seam_zone_for",
           "seam_zones_for", "seam_planes", "adjacent_arms"]


@dataclass
class ArmProgram:
    """One arm's program.  ``lines`` are G-code and directive lines without
    line breaks; line numbers are 1-based positions in ``lines``."""
    arm: object
    mode: str
    lines: List[str] = field(default_factory=list)
    removed: list = field(default_factory=list)      #: (line, text) stripped from the slicer output
    layers: int = 0
    phases: int = 1
    start_first: bool = True                         #: the front end starts this arm with A1

    @property
    def text(self):
        return "\n".join(self.lines) + "\n"


def home_positions_mm(cell, arms):
    """Each arm's nozzle at its home pose, in bed-frame mm."""
    from ambots.model import arm_kinematics
    inv = np.linalg.inv(cell.bed.pose)
    out = {}
    for arm in arms:
        T = arm.base_pose @ arm_kinematics(arm).fk(np.asarray(arm.profile.home))
        out[arm.name] = (inv[:3, :3] @ T[:3, 3] + inv[:3, 3]) * 1000.0
    return out


_PARKS = {}


def park_positions_mm(cell, arms, margin_mm=60.0):
    """Where each arm parks its nozzle (bed-frame mm): clear of the bed, on
    the arm's own side.

    From the arm's base (projected on the bed) towards the nearest point of
    the bed, the nozzle stops ``margin_mm`` short of the bed's edge, 50 mm
    over the printable height, so that the arm (base, links and nozzle)
    stays outside the bed and out of every other arm's way.  If the arm
    cannot reach that point with the nozzle down, points nearer to its base
    (or up to 30 mm nearer the bed) and higher are tried; an arm whose base
    stands over the bed, or that reaches none of them, parks at home."""
    from ambots.model import arm_kinematics
    from ambots.partition import arm_sites_mm
    from ambots.workspace import down_in_base, world_to_base
    arms = list(arms)
    key = (getattr(cell, "path", cell.name), tuple(a.name for a in arms), float(margin_mm))
    if key in _PARKS:
        return {k: v.copy() for k, v in _PARKS[key].items()}
    home = home_positions_mm(cell, arms)
    bx, by = cell.bed.size[0] * 500.0, cell.bed.size[1] * 500.0
    sites = dict(zip([a.name for a in arms], arm_sites_mm(cell, arms)))
    out = {}
    for arm in arms:
        h = np.asarray(home[arm.name], dtype=float)
        out[arm.name] = h
        site = np.asarray(sites[arm.name], dtype=float)
        nearest = np.clip(site, [-bx, -by], [bx, by])
        gap = float(np.linalg.norm(nearest - site))
        if gap < 1e-6:
            continue                                  # the base stands over the bed
        u = (nearest - site) / gap
        # where the ray from the base enters the bed grown by the margin
        lo, hi = np.array([-bx - margin_mm, -by - margin_mm]), np.array([bx + margin_mm, by + margin_mm])
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (lo - site) / u, (hi - site) / u
        t_in = float(np.nanmax(np.where(np.abs(u) > 1e-12, np.minimum(t1, t2), -np.inf)))
        z0 = cell.bed.max_height * 1000.0 + 50.0
        cands = [np.array([*(site + u * r), z]) for r in (t_in, t_in - 40.0, t_in + 30.0, t_in - 80.0, t_in - 120.0)
                 if r >= 100.0 for z in (z0, z0 + 50.0, z0 + 100.0)]
        if not cands:
            continue
        P = np.array(cands)
        world = (P / 1000.0) @ cell.bed.pose[:3, :3].T + cell.bed.pose[:3, 3]
        _, ok, _ = arm_kinematics(arm).ik_batch(world_to_base(arm, world), np.asarray(arm.profile.home),
                                                down_in_base(arm))
        if ok.any():
            out[arm.name] = P[int(np.argmax(ok))]
    _PARKS[key] = out
    return {k: v.copy() for k, v in out.items()}


class _Writer:
    """Emits canonical G-code for runs of segments, inserting a retracted
    travel wherever a run does not start where the nozzle is."""

    def __init__(self, retract_mm=0.8, retract_feed=2100.0, travel_feed=9000.0, short_travel_mm=2.0, hop_mm=0.0):
        self.lines = []
        self.pos = None
        #: the nozzle was sent elsewhere by a directive (A7 to a park position)
        #: after a retraction: the next travel starts with a move straight over
        #: its target and ends with the unretraction
        self.parked = False
        self.retract_mm, self.retract_feed, self.travel_feed = retract_mm, retract_feed, travel_feed
        #: travels shorter than this within a layer are not retracted or lifted
        #: (the slicers' ``retract_before_travel``)
        self.short_travel_mm = short_travel_mm
        #: lift during a retracted travel (the slicers' ``z_hop``; 0 as the
        #: built-in slicer's default: two more moves from rest to rest per travel
        #: under the one timing law, about 0.1 s each)
        self.hop_mm = hop_mm

    def emit(self, line):
        self.lines.append(line)

    def travel_to(self, p, feed=None):
        if self.parked:
            self.emit("G0 X%.3f Y%.3f Z%.3f F%.0f" % (p[0], p[1], p[2] + 10.0, feed or self.travel_feed))
            self.emit("G0 Z%.3f" % p[2])
            self.emit("G1 E%.5f F%.0f" % (self.retract_mm, self.retract_feed))
            self.parked = False
            self.pos = tuple(p)
            return
        if self.pos is not None and np.allclose(self.pos, p, atol=1e-6):
            return
        if (self.pos is not None and abs(self.pos[2] - p[2]) < 1e-6
                and np.hypot(self.pos[0] - p[0], self.pos[1] - p[1]) < self.short_travel_mm):
            self.emit("G0 X%.3f Y%.3f F%.0f" % (p[0], p[1], feed or self.travel_feed))
        elif self.pos is not None:
            self.emit("G1 E-%.5f F%.0f" % (self.retract_mm, self.retract_feed))
            if self.hop_mm > 0 or abs(self.pos[2] - p[2]) > 1e-6:
                lift = max(self.pos[2], p[2]) + self.hop_mm        # clear what was printed
                self.emit("G0 Z%.3f F%.0f" % (lift, feed or self.travel_feed))
                self.emit("G0 X%.3f Y%.3f F%.0f" % (p[0], p[1], feed or self.travel_feed))
                if lift != p[2]:
                    self.emit("G0 Z%.3f" % p[2])
            else:
                self.emit("G0 X%.3f Y%.3f F%.0f" % (p[0], p[1], feed or self.travel_feed))
            self.emit("G1 E%.5f F%.0f" % (self.retract_mm, self.retract_feed))
        else:
            self.emit("G0 X%.3f Y%.3f Z%.3f F%.0f" % (p[0], p[1], p[2], feed or self.travel_feed))
        self.pos = tuple(p)

    def park(self, arm, xyz, lift_mm=10.0):
        """Retract, lift clear of the part and go to ``xyz`` (mm; an A7
        directive: a joint move of the firmware's planner)."""
        if self.pos is not None and not self.parked:
            self.emit("G1 E-%.5f F%.0f" % (self.retract_mm, self.retract_feed))
            self.emit("G0 Z%.3f F%.0f" % (self.pos[2] + lift_mm, self.travel_feed))
        x, y, z = xyz
        self.emit(directive(MoveTo(arm.id, round(float(x), 3), round(float(y), 3), round(float(z), 3))))
        self.parked = self.pos is not None

    def segments(self, segs):
        for s in segs:
            moved = s.start != s.end
            if not moved:
                if s.e:
                    self.emit("G1 E%.5f F%.0f" % (s.e, s.feedrate or self.retract_feed))
                continue
            if self.pos is None or not np.allclose(self.pos, s.start, atol=1e-6):
                self.travel_to(s.start)
            x, y, z = s.end
            if s.extrude:
                self.emit("G1 X%.3f Y%.3f Z%.3f E%.5f F%.0f" % (x, y, z, s.e, s.feedrate))
            else:
                self.emit("G0 X%.3f Y%.3f Z%.3f F%.0f" % (x, y, z, s.feedrate or self.travel_feed))
            self.pos = s.end


def _read_layers(text, path):
    """Sanitised slicer G-code -> (removed lines, {layer: [Segment]})."""
    clean, removed = sanitize_gcode(text, path, trusted=False, mode="strip")
    layers: Dict[int, List[Segment]] = {}
    for ev in parse_gcode_text(clean, path):
        if type(ev) is Segment:
            layers.setdefault(max(ev.layer, 0), []).append(ev)
    return removed, layers


def _header(arm, mode, extra=()):
    return ["; ambots program for arm %s (R%d), mode %s" % (arm.name, arm.id, mode),
            "; frame: print bed, mm; absolute XYZ, relative E", *extra, "G21", "G90", "M83"]


def _distance_to_planes(points, planes):
    """(N, 3) points, [(n, off)] -> (N, P) signed distances (inside >= 0)."""
    if not planes:
        return np.zeros((len(points), 0))
    normals = np.array([n for n, _ in planes])
    offs = np.array([o for _, o in planes])
    return points @ normals.T - offs


def build_programs(sliced, parts, cell, mode="concurrent", zone_mm=None, park=None, idle=()):
    """Build every arm's program.

    Parameters
    ----------
    sliced : {arm name: G-code text} of each part, bed frame, mm
    parts : the :class:`~ambots.partition.Part` list (gives arm order and seam
        planes, each with the arm on its other side)
    cell : the cell (home and park positions come from the arms' geometry)
    mode : ``"concurrent"`` or ``"sequential"``
    zone_mm : how far apart (mm) two nozzles across a seam must stay
        (concurrent mode), one figure for every pair; default: pair by pair
        from the arms' real geometry in the poses they print these parts
        in, :func:`seam_zones_for`
    park : optional {arm name: (x, y, z) mm} overriding the park positions
    idle : arms of the cell without work in this job: a one-arm job (or a
        sequential one) sends them to their park positions first (A7), as
        sequential mode does with the arms that wait for their turn

    Returns {arm name: :class:`ArmProgram`}, in the parts' order.
    """
    if mode not in ("concurrent", "sequential"):
        raise ValueError("mode must be 'concurrent' or 'sequential', got %r" % mode)
    arms = [p.arm for p in parts]
    idle = [a for a in idle if a.name not in {b.name for b in arms}]
    park = park or park_positions_mm(cell, arms + idle)
    read = {a.name: _read_layers(sliced[a.name], "%s.gcode" % a.name) for a in arms}
    n_layers = max([max(layers) + 1 for _, layers in read.values() if layers] or [0])
    if mode == "sequential" or (len(arms) == 1 and idle):
        return _sequential(arms, read, park, n_layers, idle, mode)
    planes = seam_planes(parts)
    if zone_mm is None:
        zones = seam_zones_for(cell, arms, parts)
    else:
        zones = {pair: float(zone_mm) for pair in planes}
    home = home_positions_mm(cell, arms)
    return _concurrent(arms, read, park, home, n_layers, planes, zones, _JointMoves(cell, arms))


def seam_planes(parts):
    """The plane between every two parts, from each side: {(a, b): (n, o)}
    with a's signed distance ``n . p - o`` (mm, >= 0 on a's side), for arm
    names a != b.  ``parts[i].planes[j]`` bounds part i against the arm
    ``parts[i].neighbours[j]``; with an overlap seam the two parts' planes
    are half a bead apart and the plane returned is the one midway, the
    true seam.  Planes against arms without a part here are left out."""
    own = {}
    names = [p.arm.name for p in parts]
    for p in parts:
        others = list(getattr(p, "neighbours", None) or [])
        if len(others) != len(p.planes):      # a Part made without neighbours: the other arms in order
            others = [n for n in names if n != p.arm.name]
        for other, (n, off) in zip(others, p.planes):
            own[p.arm.name, other] = (np.asarray(n, dtype=float), float(off))
    out = {}
    for (a, b), (n, off) in own.items():
        if b not in names or a == b:
            continue
        o = (off - own[b, a][1]) / 2.0 if (b, a) in own else off
        out[a, b] = (n, o)
    return out


def adjacent_arms(arms, read, planes, zones):
    """{arm: set of arms} whose extrusions come within the pair's zone of each
    other across the plane between them (sum of the two distances), in any layer."""
    names = [a.name for a in arms]
    pts = {}
    for n in names:
        segs = [s for layer in read[n][1].values() for s in layer if s.extrude and s.start != s.end]
        pts[n] = np.array([s.start for s in segs] + [s.end for s in segs], dtype=float).reshape(-1, 3)
    adjacent = {n: set() for n in names}
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            if (a, b) not in planes or (b, a) not in planes or not len(pts[a]) or not len(pts[b]):
                continue
            nrm, o = planes[a, b]
            da = float(np.min(pts[a] @ nrm - o))
            db = float(np.min(o - pts[b] @ nrm))
            if da + db < zones[a, b]:
                adjacent[a].add(b)
                adjacent[b].add(a)
    return adjacent


_ZONES = {}


def seam_zone_for(cell, arms):
    """Seam zone (mm) of these arms of the cell: the largest of
    :func:`seam_zones_for` (cached)."""
    if len(arms) < 2:
        return 0.0
    return max(seam_zones_for(cell, arms).values())


def seam_zones_for(cell, arms, parts=None):
    """Seam zone (mm) of every pair of these arms, from their geometry
    (:func:`ambots.collision.seam_zones_mm`): {(a, b): mm}, both orders.
    From the poses on the arms' shares of the whole bed (cached); with
    ``parts`` (a job's), the larger of that and the zone from the poses on
    those parts (the parts' planes can differ from the shares', and two arms
    whose shares are far apart can get parts that meet), except for pairs of
    arms beside each other along their seam (a beam's), whose zone is the
    one the sampled poses on the parts keep clear
    (``seam_zones_mm(..., clearance=)``)."""
    from ambots.collision import seam_zones_mm
    if len(arms) < 2:
        return {}
    key = (cell.path if hasattr(cell, "path") else cell.name, tuple(a.name for a in arms))
    if key not in _ZONES:
        _ZONES[key] = {k: float(v) for k, v in seam_zones_mm(cell, arms).items()}
    zones = dict(_ZONES[key])
    if parts is not None:
        tight = {}
        for k, v in seam_zones_mm(cell, arms, parts=parts, clearance=tight).items():
            zones[k] = max(zones.get(k, 0.0), float(v))
        for k, v in tight.items():          # arms beside each other: the poses' own clearance
            zones[k] = min(zones[k], float(v))
    # rounded up to 0.01 mm: the last bits of the sums vary with how BLAS
    # threads split them, and band edges cut segments: the same job must get
    # the very same programs every time
    return {k: math.ceil(v * 100.0 - 1e-6) / 100.0 for k, v in zones.items()}


def _finish(w, arm, park):
    """Lift clear of the part, then go to the park position."""
    w.park(arm, park[arm.name])


def _sequential(arms, read, park, n_layers, idle=(), mode="sequential"):
    programs = {}
    for i, arm in enumerate(arms):
        removed, layers = read[arm.name]
        w = _Writer()
        for line in _header(arm, mode):
            w.emit(line)
        if i == 0:     # the first arm moves every other arm out of the way
            for other in list(arms[1:]) + list(idle):
                x, y, z = park[other.name]
                w.emit(directive(MoveTo(other.id, round(float(x), 3), round(float(y), 3), round(float(z), 3))))
        for k in sorted(layers):
            w.emit(";LAYER_CHANGE")
            w.emit(";Z:%.3f" % layers[k][-1].end[2])
            w.segments(layers[k])
        _finish(w, arm, park)
        if i + 1 < len(arms):
            w.emit(directive(Start(arms[i + 1].id)))
        programs[arm.name] = ArmProgram(arm, mode, w.lines, removed, len(layers), 1, start_first=(i == 0))
    return programs


def _two_colours(names, adjacent):
    """{arm: 0 or 1} with adjacent arms of different colours, or None if
    the adjacency graph has an odd cycle (three arms around a point)."""
    colour = {}
    for root in names:
        if root in colour:
            continue
        colour[root] = 0
        todo = [root]
        while todo:
            a = todo.pop()
            for b in sorted(adjacent[a], key=names.index):
                if b not in colour:
                    colour[b] = 1 - colour[a]
                    todo.append(b)
                elif colour[b] == colour[a]:
                    return None
    return colour


def _concurrent(arms, read, park, home, n_layers, planes, zones, moves=None):
    names = [a.name for a in arms]
    adjacent = adjacent_arms(arms, read, planes, zones)
    colour = _two_colours(names, adjacent)
    if colour is not None:
        near = {a: [planes[a, b] for b in names if b in adjacent[a]] for a in names}
        zone = max([zones[a, b] for a in names for b in adjacent[a]] or [0.0])
        programs = _banded(arms, read, park, n_layers, zone, near, colour, adjacent, home, zones)
        if programs is not None:
            return programs
    # no two colours, or an arm between two seams cannot stand clear of both
    # (their zones about as wide as its part): the scheduled timeline
    return _timeline(arms, read, park, home, n_layers, planes, zones, adjacent, moves=moves)


def _report_line(lines, is_wait, target):
    """The line at which an arm reports having done ``target`` (1-based): an
    arm reports its last completed line when it reaches the first barrier
    line of a run of them, never while it waits there, so a target inside a
    run of barrier lines is moved back to the line before the run (the same
    motion done)."""
    while target > 0 and is_wait[target - 1]:
        target -= 1
    return target


# ----------------------------------------------------------- banded sweep
def _split_at_bands(seg, planes, t):
    """Cut a segment where its distance to any seam plane crosses a band
    boundary ``t[1:]`` (mm, increasing; band i is [t[i], t[i+1]), the last
    band the rest); E is shared in proportion to length."""
    a, b = np.array(seg.start, dtype=float), np.array(seg.end, dtype=float)
    if not planes or np.allclose(a, b):
        return [seg]
    cuts = []
    for n, off in planes:
        fa, fb = float(n @ a - off), float(n @ b - off)
        if abs(fb - fa) < 1e-12:
            continue
        lo, hi = sorted((fa, fb))
        for edge in t[1:]:
            if lo < edge < hi:
                u = (edge - fa) / (fb - fa)
                if 1e-9 < u < 1 - 1e-9:
                    cuts.append(u)
    if not cuts:
        return [seg]
    ts = [0.0] + sorted(set(cuts)) + [1.0]
    out = []
    for t0, t1 in zip(ts[:-1], ts[1:]):
        p0, p1 = a + (b - a) * t0, a + (b - a) * t1
        out.append(seg._replace(start=tuple(p0), end=tuple(p1), e=seg.e * (t1 - t0)))
    return out


def _order_runs(segs, pos):
    """Extrusion pieces of one step -> the same pieces in a short-travel order.

    Travels and pure retractions are dropped (the writer makes its own);
    extruding segments are grouped into runs (maximal chains that the
    slicer printed end to start), and the runs are visited greedily, nearest
    end first, a run reversed when its far end is nearer.  Deposit geometry
    and E are unchanged; only the order and direction of runs differ.
    ``pos``: the nozzle's position (mm) before the step, or None."""
    runs = []
    for s in segs:
        if not s.extrude or s.start == s.end:
            continue
        if runs and runs[-1][-1].end == s.start:
            runs[-1].append(s)
        else:
            runs.append([s])
    if len(runs) < 2:
        return [s for r in runs for s in r]
    heads = np.array([r[0].start for r in runs], dtype=float)
    tails = np.array([r[-1].end for r in runs], dtype=float)
    left = np.ones(len(runs), dtype=bool)
    here = np.asarray(pos if pos is not None else runs[0][0].start, dtype=float)
    out = []
    for _ in range(len(runs)):
        dh = np.where(left, np.linalg.norm(heads - here, axis=1), np.inf)
        dt = np.where(left, np.linalg.norm(tails - here, axis=1), np.inf)
        i, j = int(np.argmin(dh)), int(np.argmin(dt))
        if dt[j] < dh[i] - 1e-9:
            left[j] = False
            out.extend(s._replace(start=s.end, end=s.start) for s in reversed(runs[j]))
            here = heads[j]
        else:
            left[i] = False
            out.extend(runs[i])
            here = tails[i]
    return out


def _band_of(segs, planes, t):
    """Band index (S,) of each segment from its midpoint's distance to the
    nearest seam; band i is [t[i], t[i+1]) (mm), the last band the rest."""
    k = len(t)
    if not planes:
        return np.full(len(segs), k - 1)
    mid = np.array([(np.add(s.start, s.end)) / 2.0 for s in segs], dtype=float)
    d = _distance_to_planes(mid, planes).min(axis=1)
    return np.clip(np.searchsorted(np.asarray(t), d, side="right") - 1, 0, k - 1).astype(int)


def _seg_time(segs):
    t = 0.0
    for s in segs:
        L = float(np.linalg.norm(np.subtract(s.end, s.start)))
        f = s.feedrate if s.feedrate > 0 else 1800.0
        t += (L if L > 0 else abs(s.e)) / f * 60.0
    return t


#: what a piece of path costs besides its time at the feedrate when the bands
#: cut it out of its neighbours (s): a retracted travel to it, and the ramps
#: from rest and to rest at its ends under the one timing law (about 0.3 s on
#: the demo's layers: :mod:`ambots.estimate`'s per-move model for the UR10
#: and the Kinova, 3 mm travels and 7-14 mm pieces)
PIECE_S = 0.3
#: the estimated makespans (s) and k of the last banded programs, by kind of band edges, for inspection
_last_bands = None
#: balanced band edges are used when their estimate is below this share of the equal widths' estimate
_BALANCED_GAIN = 0.95


def _banded(arms, read, park, n_layers, zone_mm, planes, colour, adjacent, home=None, zones=None):
    """Two colours (every seam between adjacent arms separates a colour-0
    from a colour-1 arm).  ``planes[arm]``: the planes (n, o) between the
    arm and its adjacent arms; ``zone_mm``: the largest zone of an adjacent
    pair; ``zones``: {(a, b): mm} each adjacent pair's own (default: all
    ``zone_mm``).  Only adjacent arms wait for each other.

    Each arm's work is cut into k bands by distance from its nearest seam:
    band i is [t[i], t[i+1]) (t[0] = 0), band k-1 the rest; each arm has its
    own boundaries t.  In phase i of a layer one colour prints band i while
    the other prints band k-1-i, so two adjacent arms a, b are always at
    least t_a[i] + t_b[k-1-i] apart across their seam, which the boundaries
    keep >= the pair's zone for every i.  Boundaries: either equal widths w
    >= zone / (k-1) (w = the arm's reach from its nearest seam / k when that
    is wider), or each arm's own work split into k equal shares, raised
    where a pair needs it (:func:`_balanced_bounds`; in a row of arms along
    a beam the parts between two seams reach half as far from their nearest
    seam as the ones at the ends); ``k`` (2..12) and the kind are chosen to
    minimise the estimated makespan.  Directions alternate with the layer
    (even layers: colour 0 moves away from the seam, colour 1 towards it;
    odd layers the reverse), so no arm ever crosses another's path at a
    layer change.  Between phases the arm moving away first travels to its
    next band (its *approach*, reported with an A3), and the arm moving
    towards the seam waits for that (an A9 on the approach line) before it
    approaches; an arm with no work in its next band still moves there (a
    retreat), so the spacing holds whatever the timing.  That is the only
    wait: an arm moving away only widens the gap, so it goes on at once (it
    can get at most one phase ahead: at the next layer it moves towards the
    seam and waits).  At the end, the arms that finish away from their
    seams park only when their neighbours (which finish at the seams) are
    done.  Returns the programs, or None when an arm with no work in a band
    cannot retreat into it without coming nearer than the band to another
    of its seams (:func:`_retreat`)."""
    names = [a.name for a in arms]
    if zones is None:
        zones = {}
    pair_zone = {(a, b): float(zones.get((a, b), zone_mm)) for a in names for b in adjacent[a]}
    segs_by = {(a.name, k): segs for a in arms for k, segs in read[a.name][1].items()}
    # choose k and the band edges on the segments cut into pieces of at most
    # 5 mm (midpoint distance, duration), vectorised: a long line along the
    # seam's normal (a perimeter along a beam) spreads over many bands
    stats = {}
    for a in arms:
        for layer in range(n_layers):
            segs = segs_by.get((a.name, layer), [])
            if not segs:
                continue
            P0 = np.array([s.start for s in segs], dtype=float)
            P1 = np.array([s.end for s in segs], dtype=float)
            dur = np.array([_seg_time([s]) for s in segs])
            pieces = np.maximum(1, np.ceil(np.linalg.norm(P1 - P0, axis=1) / 5.0)).astype(int)
            seg = np.repeat(np.arange(len(segs)), pieces)
            frac = (np.arange(len(seg)) - np.repeat(np.cumsum(pieces) - pieces, pieces) + 0.5) / pieces[seg]
            mid = P0[seg] + frac[:, None] * (P1 - P0)[seg]
            d = (_distance_to_planes(mid, planes[a.name]).min(axis=1) if planes[a.name]
                 else np.full(len(seg), np.inf))
            # a piece follows on from the one before (no travel between them): same
            # segment, or the segment before ends where it starts
            joined = np.zeros(len(segs), bool)
            joined[1:] = np.all(P1[:-1] == P0[1:], axis=1)
            follows = np.ones(len(seg), bool)
            follows[0] = False
            first_piece = np.cumsum(pieces) - pieces
            follows[first_piece] = joined
            stats[a.name, layer] = (d, dur[seg] / pieces[seg], follows)
    # each arm's reach from its nearest seam
    far = {}
    for a in arms:
        ds = [float(np.max(d[np.isfinite(d)])) for (n, _), (d, _, _) in stats.items()
              if n == a.name and np.isfinite(d).any()]
        far[a.name] = max(ds or [0.0])
    work = {}
    for a in arms:
        ds = [stats[a.name, layer] for layer in range(n_layers) if (a.name, layer) in stats]
        d = np.concatenate([x for x, _, _ in ds]) if ds else np.zeros(0)
        dur = np.concatenate([y for _, y, _ in ds]) if ds else np.zeros(0)
        work[a.name] = (d[np.isfinite(d)], dur[np.isfinite(d)])

    def uniform(k):
        out = {}
        for a in arms:
            w = max(max(zone_mm, 1e-3) / (k - 1), far[a.name] / k)
            out[a.name] = np.arange(k) * w
        return out

    def estimate(k, t):
        est = 0.0
        for layer in range(n_layers):
            phase_t = np.zeros(k)
            for a in arms:
                if (a.name, layer) not in stats:
                    continue
                d, dur, follows = stats[a.name, layer]
                band = np.clip(np.searchsorted(t[a.name], d, side="right") - 1, 0, k - 1)
                # every piece of path a band cuts out starts and ends at rest, with a travel
                fresh = ~follows
                fresh[1:] |= band[1:] != band[:-1]
                per_band = (np.bincount(band, weights=dur, minlength=k)
                            + PIECE_S * np.bincount(band, weights=fresh, minlength=k))
                phases = np.array([_phase_of(b, colour[a.name], layer, k) for b in range(k)])
                np.maximum.at(phase_t, phases, per_band)
            est += phase_t.sum() + k * 0.5          # a barrier costs about half a second
        return est

    best = {}
    for k in range(2, 13):
        for kind, t in (("uniform", uniform(k)), ("balanced", _balanced_bounds(names, work, adjacent, pair_zone, k))):
            if t is None:
                continue
            est = estimate(k, t)
            if kind not in best or est < best[kind][0] - 1e-9:
                best[kind] = (est, k, t)
    global _last_bands
    _last_bands = {kind: (est, k) for kind, (est, k, _) in best.items()}
    # balanced bands only when clearly better: at a band edge of its own work
    # an arm waits more often than the estimate counts
    kind = "balanced" if "balanced" in best and best["balanced"][0] < _BALANCED_GAIN * best["uniform"][0] else "uniform"
    k, bounds = best[kind][1], best[kind][2]
    steps = {}
    for a in arms:
        for layer in range(n_layers):
            segs = [p for s in segs_by.get((a.name, layer), [])
                    for p in _split_at_bands(s, planes[a.name], bounds[a.name])]
            band = _band_of(segs, planes[a.name], bounds[a.name]) if segs else np.zeros(0, dtype=int)
            for b in range(k):
                steps[a.name, layer, _phase_of(b, colour[a.name], layer, k)] = (
                    b, [s for s, bb in zip(segs, band) if bb == b])
    parks_first, park_waits = _banded_start(arms, names, steps, planes, adjacent, home, n_layers, k, bounds,
                                            pair_zone)
    writers, approach_end, slots, park_report, park_slots = {}, {}, {}, {}, {}
    end_slots = []
    for a in arms:
        w_ = _Writer()
        for line in _header(a, "concurrent", ["; seam zone %.1f mm, %d band(s) per layer from %s mm, colour %d"
                                              % (zone_mm, k, " ".join("%.3f" % v for v in bounds[a.name]),
                                                 colour[a.name])]):
            w_.emit(line)
        slots[a.name] = []
        if parks_first[a.name]:
            w_.park(a, park[a.name])
            w_.emit(directive(SendPosition(_arm_id(arms, sorted(adjacent[a.name], key=names.index)[0]))))
            park_report[a.name] = len(w_.lines)
        park_slots[a.name] = []
        for other in park_waits[a.name]:
            park_slots[a.name].append((other, len(w_.lines)))
            w_.lines.append(None)
        for layer in range(n_layers):
            for p in range(k):
                band, segs = steps[a.name, layer, p]
                if planes[a.name] or len(arms) > 1:   # drop slicer travels, shortest-travel order
                    segs = _order_runs(segs, w_.pos)
                if p == 0:
                    w_.emit(";LAYER_CHANGE")
                    zs = [s.end[2] for q in range(k) for s in steps[a.name, layer, q][1]]
                    w_.emit(";Z:%.3f" % (zs[-1] if zs else 0.0))
                towards = p > 0 and band < steps[a.name, layer, p - 1][0]
                if towards:       # wait until the neighbours moving away have approached their band
                    for other in arms:
                        if other.name in adjacent[a.name]:
                            slots[a.name].append((other.name, layer, p, len(w_.lines)))
                            w_.lines.append(None)
                first = next((s for s in segs if s.start != s.end), None)
                if first is not None:
                    w_.travel_to(first.start)
                elif p > 0 and not towards and w_.pos is not None:
                    target = _retreat(w_.pos, planes[a.name], band, bounds[a.name])
                    if target is None:    # no point of this band clear of all its seams: not banded
                        return None
                    w_.travel_to(target)
                if p > 0 and not towards and any(n in adjacent[a.name] for n in names):
                    # tell the neighbours (A10 with position, via the hub) that the approach is done
                    other = next(o for o in arms if o.name in adjacent[a.name])
                    w_.emit(directive(SendPosition(other.id)))
                approach_end[a.name, layer, p] = len(w_.lines)
                w_.segments(segs)
        if n_layers and (colour[a.name] + n_layers - 1) % 2 == 0:
            # this arm ends the last layer away from its seams and its neighbours at
            # them: it parks only when they are done (a joint move to the park
            # position is not a straight line, and it would pass them at work)
            for other in arms:
                if other.name in adjacent[a.name]:
                    end_slots.append((a.name, other.name, len(w_.lines)))
                    w_.lines.append(None)
        _finish(w_, a, park)
        writers[a.name] = w_
    for name, other, index in end_slots:       # the other arm's last line: it reports it when done
        writers[name].lines[index] = directive(WaitFor(_arm_id(arms, name), _arm_id(arms, other),
                                                       line=len(writers[other].lines)))
    programs = {}
    is_wait = {n: [line is None for line in writers[n].lines] for n in names}
    for a in arms:
        w_ = writers[a.name]
        for other, layer, p, index in slots[a.name]:
            target = _report_line(writers[other].lines, is_wait[other], approach_end[other, layer, p])
            w_.lines[index] = directive(WaitFor(a.id, _arm_id(arms, other), line=target))
        for other, index in park_slots[a.name]:
            w_.lines[index] = directive(WaitFor(a.id, _arm_id(arms, other), line=park_report[other]))
        removed, _ = read[a.name]
        programs[a.name] = ArmProgram(a, "concurrent", w_.lines, removed, n_layers, k, start_first=True)
    return programs


def _banded_start(arms, names, steps, planes, adjacent, home, n_layers, k, bounds, zones):
    """How the banded programs start.  An arm leaves home at once for its
    first band, unless it has no work in the first phase (it would wait at
    home) or its home is in the way of an adjacent arm's first step (home
    and first band nearer than the zone across their plane): then it first
    goes to its park position and reports (A3), and the adjacent arms whose
    first step it was in the way of wait for that report before they move.
    Returns ({arm: parks first}, {arm: [arms to wait for]})."""
    nb = {a.name: [b for b in names if b in adjacent[a.name]] for a in arms}
    first = {}
    for a in arms:
        first[a.name] = next(((layer, p, steps[a.name, layer, p][0]) for layer in range(n_layers) for p in range(k)
                              if any(s.extrude and s.start != s.end for s in steps[a.name, layer, p][1])), None)
    parks_first = {a.name: first[a.name] is not None and first[a.name][:2] != (0, 0) for a in arms}
    waits = {a.name: [] for a in arms}
    if home is None:
        return parks_first, waits
    home_d = {a.name: _distance_to_planes(np.asarray(home[a.name], dtype=float)[None], planes[a.name])[0]
              for a in arms}
    for a in arms:
        for i, b in enumerate(nb[a.name]):
            j = nb[b].index(a.name)
            lo = bounds[b][first[b][2]] if first[b] is not None else np.inf
            if home_d[a.name][i] + min(lo, home_d[b][j]) < zones[a.name, b] - 1e-9:
                parks_first[a.name] = True
                waits[b].append(a.name)
    for a in arms:
        if parks_first[a.name] and not nb[a.name]:
            parks_first[a.name] = False
    return parks_first, {n: sorted(set(v), key=names.index) for n, v in waits.items()}


def _phase_of(band, colour, layer, k):
    """Phase in which an arm of ``colour`` prints ``band`` on ``layer``."""
    away = (colour + layer) % 2 == 0          # this arm sweeps away from the seam on this layer
    return band if away else k - 1 - band


def _arm_id(arms, name):
    return next(a.id for a in arms if a.name == name)


def _retreat(pos, planes, band, t):
    """A point on the same side as ``pos`` just inside ``band`` (mm; band i
    is [t[i], t[i+1])), moving away from the nearest seam; None if that
    brings it nearer than the band to another of its seams (an arm between
    two seams whose zones together are about as wide as its part)."""
    p = np.array(pos, dtype=float)
    if not planes:
        return tuple(p)
    d = _distance_to_planes(p[None], planes)[0]
    j = int(np.argmin(d))
    n = np.asarray(planes[j][0], dtype=float)
    width = t[band + 1] - t[band] if band + 1 < len(t) else 8.0
    want = t[band] + min(2.0, width / 4)
    if d[j] >= want:
        return tuple(p)
    q = p + n * (want - d[j])
    q = np.array([q[0], q[1], p[2]])
    if _distance_to_planes(q[None], planes)[0].min() < t[band] - 1e-6:
        return None
    return (float(q[0]), float(q[1]), float(p[2]))


def _balanced_bounds(names, work, adjacent, zones, k):
    """Band boundaries {arm: (k,) mm} that split each arm's work (``work``:
    {arm: (distance to the nearest seam (S,), duration (S,))}) into k equal
    shares, then raised until every adjacent pair a, b keeps
    t_a[i] + t_b[k-1-i] >= its zone for every i (t[0] = 0 stays; raising a
    boundary only moves work to lower bands, and only widens the gaps)."""
    t = {}
    for n in names:
        d, dur = work[n]
        if not len(d) or dur.sum() <= 0:
            t[n] = np.zeros(k)
            continue
        order = np.argsort(d)
        cum = np.cumsum(dur[order]) / dur.sum()
        q = [0.0] + [float(d[order][min(int(np.searchsorted(cum, i / k)), len(d) - 1)]) for i in range(1, k)]
        t[n] = np.maximum.accumulate(np.maximum(np.array(q), 0.0))
    for _ in range(10 * k * len(names) + 10):
        changed = False
        for a in names:
            for b in adjacent[a]:
                z = zones[a, b]
                for i in range(k):
                    j = k - 1 - i
                    short = z - (t[a][i] + t[b][j])
                    if short <= 1e-9:
                        continue
                    changed = True
                    if i == 0:
                        t[b][j] += short
                    elif j == 0:
                        t[a][i] += short
                    else:
                        t[a][i] += short / 2
                        t[b][j] += short / 2
                t[a] = np.maximum.accumulate(t[a])
                t[b] = np.maximum.accumulate(t[b])
        if not changed:
            break
    ok = all(t[a][i] + t[b][k - 1 - i] >= zones[a, b] - 1e-6 for a in names for b in adjacent[a] for i in range(k))
    return t if ok else None


# ----------------------------------------------------------- timeline
#: the last schedule :func:`_timeline` made ({arm: [_Act]}), for inspection
_last_schedule = None
#: estimated nozzle speed of travels (mm/s) and fixed cost (s) of a
#: retracted travel, and of a joint move (to or from a park position)
_TRAVEL_MM_S, _TRAVEL_S, _JOINT_MM_S, _JOINT_S = 150.0, 0.1, 100.0, 2.0


def _split_at(seg, N, O, W, bands):
    """Cut a segment where its distance to plane p (normals ``N`` (P, 3),
    offsets ``O`` (P,)) crosses m ``W[p]``, 1 <= m <= ``bands``; E is shared
    in proportion to length."""
    a, b = np.array(seg.start, dtype=float), np.array(seg.end, dtype=float)
    if not len(N) or np.allclose(a, b):
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
    if not cuts:
        return [seg]
    ts = [0.0] + sorted(set(cuts)) + [1.0]
    return [seg._replace(start=tuple(a + (b - a) * t0), end=tuple(a + (b - a) * t1), e=seg.e * (t1 - t0))
            for t0, t1 in zip(ts[:-1], ts[1:])]


class _JointMoves:
    """Where the nozzle goes (bed frame, mm) on the joint moves the firmware
    makes between the park position (or home) and the part: a move to an
    A7 target, and a travel whose start is not where the nozzle is, are
    straight lines in joint space (:meth:`ambots.motion.MotionPlanner.
    joint_move_to`, nozzle-down IK seeded with the joints it starts from),
    which bulge off the straight line between their ends: a Panda coming
    down from its park position passed 21 mm nearer the seam than both
    ends.  :meth:`path` samples such a move; the timeline counts its points
    below the printable height in the step's footprint."""

    def __init__(self, cell, arms, samples=32):
        from ambots.model import arm_kinematics
        self.arm = {a.name: a for a in arms}
        self.kin = {a.name: arm_kinematics(a) for a in arms}
        self.bed = np.asarray(cell.bed.pose, dtype=float)
        self.top = cell.bed.max_height * 1000.0
        self.samples = int(samples)
        self._cache = {}

    def _ik(self, name, p_mm, seed):
        from ambots.workspace import down_in_base, world_to_base
        arm = self.arm[name]
        world = (np.asarray(p_mm, dtype=float) / 1000.0) @ self.bed[:3, :3].T + self.bed[:3, 3]
        Q, ok, _ = self.kin[name].ik_batch(world_to_base(arm, world[None]), np.asarray(seed, dtype=float),
                                           down_in_base(arm))
        return Q[0] if ok[0] else None

    def path(self, name, a_mm, b_mm):
        """Nozzle positions (K, 3), bed mm, on the joint move from nozzle-down
        at ``a_mm`` (None: the arm's home pose) to nozzle-down at ``b_mm``,
        only those at most at the printable height; empty if either end is
        out of reach (the firmware reports that itself)."""
        key = (name, None if a_mm is None else tuple(np.round(a_mm, 6)), tuple(np.round(b_mm, 6)))
        if key in self._cache:
            return self._cache[key]
        home = np.asarray(self.arm[name].profile.home, dtype=float)
        qa = home if a_mm is None else self._ik(name, a_mm, home)
        qb = None if qa is None else self._ik(name, b_mm, qa)
        out = np.zeros((0, 3))
        if qb is not None:
            u = np.linspace(0.0, 1.0, self.samples)[:, None]
            T = self.arm[name].base_pose @ self.kin[name].fk_batch((1.0 - u) * qa + u * qb)
            inv = np.linalg.inv(self.bed)
            P = (T[:, :3, 3] @ inv[:3, :3].T + inv[:3, 3]) * 1000.0
            out = P[P[:, 2] <= self.top]
        self._cache[key] = out
        return out


@dataclass
class _Act:
    """One step of an arm's schedule: ``kind`` "chunk" (print ``segs``),
    "retreat" (to the park position and back later) or "park" (the end)."""
    kind: str
    layer: int
    S: float                     #: scheduled start (s)
    C: float                     #: scheduled end (s)
    fp: np.ndarray               #: distance (mm) to each adjacent arm's plane: closest over the step
    segs: list = field(default_factory=list)
    waits: dict = field(default_factory=dict)    #: {other arm: index of its step to wait for}
    report: int = 0              #: the arm that first waits for this step's end (robot id), 0: none


def _path_time(pos, segs):
    """Estimated seconds to print ``segs`` (in order) from ``pos`` (None: a
    joint move from somewhere else)."""
    t = _seg_time(segs)
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


def _timeline(arms, read, park, home, n_layers, planes, zones, adjacent, bands=4, priority_only=False,
              moves=None):
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
    :class:`_JointMoves`: their points below the printable height).  A
    layer starts when the adjacent arms have finished the previous one.  An
    arm with nothing to do that stands in another's way (or when nobody can
    go on) retreats to its park position.  The schedule is made
    twice, once with the arms' priorities (an arm leaves alone what an
    adjacent arm earlier in the cell's list, later on odd layers, still has
    to print within the zone, so that arm sweeps away from their seam and
    this one follows), once without, and the shorter is kept.

    The order becomes barriers: before each step an arm waits for every
    adjacent arm to have completed the steps that, in the schedule, ended by
    the time this step starts (each such step ends with an ``;@A3`` report).
    Whatever the real durations, an arm is then never behind its place in
    the schedule relative to another, and every pair of steps running at
    the same time was checked in the schedule; waits only name steps that
    end earlier in the schedule, so they cannot form a cycle."""
    names = [a.name for a in arms]
    arm_of = {a.name: a for a in arms}
    nbrs = {n: [b for b in names if b in adjacent[n]] for n in names}
    where = {n: {b: nbrs[b].index(n) for b in nbrs[n]} for n in names}       # my index in b's list
    N = {n: np.array([planes[n, b][0] for b in nbrs[n]], dtype=float).reshape(-1, 3) for n in names}
    O = {n: np.array([planes[n, b][1] for b in nbrs[n]], dtype=float) for n in names}
    Z = {n: np.array([zones[n, b] for b in nbrs[n]], dtype=float) for n in names}

    def dist(n, pts):
        return np.asarray(pts, dtype=float).reshape(-1, 3) @ N[n].T - O[n]

    def path_d(n, a, b):
        """Closest distance to each adjacent arm's plane on arm n's joint move
        from ``a`` (None: home) to ``b`` below the printable height (inf: none)."""
        P = moves.path(n, a, b) if moves is not None and len(N[n]) else np.zeros((0, 3))
        return dist(n, P).min(axis=0) if len(P) else np.full(len(N[n]), np.inf)

    # a pair whose parts never get a zone apart anywhere (a strip along a
    # seam) can never print at once: where an arm is across that plane makes
    # no difference, so those planes neither cut chunks nor order them
    reach = {}
    for n in names:
        pts = np.array([s.start for layer in read[n][1].values() for s in layer if s.extrude]
                       + [s.end for layer in read[n][1].values() for s in layer if s.extrude], dtype=float)
        reach[n] = dist(n, pts).max(axis=0) if len(pts) and len(N[n]) else np.zeros(len(N[n]))
    useful = {n: np.array([reach[n][i] + reach[b][where[n][b]] >= Z[n][i] for i, b in enumerate(nbrs[n])],
                          dtype=bool) for n in names}

    # ---- chunks of every (arm, layer)
    chunks = {}
    for n in names:
        W = np.where(useful[n], Z[n] / bands, np.inf)
        for layer in range(n_layers):
            segs = [s for s in read[n][1].get(layer, []) if s.extrude and s.start != s.end]
            pieces = [p for s in segs for p in _split_at(s, N[n], O[n], W, bands)]
            groups = {}
            if pieces:
                mid = np.array([np.add(p.start, p.end) / 2.0 for p in pieces])
                keys = np.minimum(np.floor(dist(n, mid) / np.maximum(W, 1e-9)), bands).astype(int)
                keys[:, ~useful[n]] = 0
                for p, key in zip(pieces, map(tuple, keys)):
                    groups.setdefault(key, []).append(p)
            out = []
            for key in sorted(groups):
                ps = groups[key]
                pts = np.array([p.start for p in ps] + [p.end for p in ps], dtype=float)
                dmin = dist(n, pts).min(axis=0) if len(N[n]) else np.zeros(0)
                level = min([k for k, u in zip(key, useful[n]) if u] or [bands])
                out.append((ps, dmin, level))
            chunks[n, layer] = out

    # ---- the schedule
    def schedule(priority):
        INF = np.inf
        acts = {n: [] for n in names}
        pos = {n: np.asarray(home[n], dtype=float) for n in names}           # where the nozzle waits
        pos_d = {n: dist(n, pos[n])[0] if len(N[n]) else np.zeros(0) for n in names}
        first = {n: True for n in names}                                      # still at home
        parked = {n: False for n in names}                                    # at the park position
        layer_of = {n: 0 for n in names}
        left = {n: list(range(len(chunks[n, 0]))) if n_layers else [] for n in names}
        layer_end = {}                                                        # (arm, layer) -> time printed
        done = {n: False for n in names}
        t_free = {n: 0.0 for n in names}

        def state_d(b, t):
            if acts[b] and acts[b][-1].C > t:
                return acts[b][-1].fp
            return pos_d[b]

        def clash(n, fp, t):
            """Arms whose current state is too near a step of arm n with footprint fp at time t."""
            out = []
            for i, b in enumerate(nbrs[n]):
                if fp[i] + state_d(b, t)[where[n][b]] < Z[n][i] - 1e-9:
                    out.append(b)
            return out

        def start(n, act, end_pos, at_park):
            acts[n].append(act)
            t_free[n] = act.C
            pos[n] = np.asarray(end_pos, dtype=float)
            pos_d[n] = np.full(len(N[n]), INF) if at_park else dist(n, pos[n])[0]
            parked[n] = at_park
            first[n] = False

        def to_park(n, t, kind):
            p = np.asarray(park[n], dtype=float)
            dur = float(np.linalg.norm(p - pos[n])) / _JOINT_MM_S + _JOINT_S
            fp = pos_d[n].copy()
            if not parked[n]:                     # the joint move up there (lifted 10 mm from the part)
                fp = np.minimum(fp, path_d(n, None, p) if first[n] else
                                path_d(n, pos[n] + (0.0, 0.0, 10.0), p))
            start(n, _Act(kind, layer_of[n], t, t + dur, fp), p, True)

        def layer_ready(n, layer, t):
            """Every adjacent arm has printed ``layer``, by time t."""
            return all(done[b] or layer_of[b] > layer or
                       (layer_of[b] == layer and not left[b] and layer_end.get((b, layer), 0.0) <= t)
                       for b in nbrs[n])

        def candidates(n, t):
            """(chunk index, footprint, clashing arms, score) of arm n's chunks left in its layer."""
            out = []
            for ci in left[n]:
                ps, dmin, level = chunks[n, layer_of[n]][ci]
                fp = np.minimum(dmin, pos_d[n])
                if first[n] or parked[n]:         # the joint move there, from home or the park position
                    p = np.asarray(_order_runs(ps, None)[0].start, dtype=float)
                    fp = np.minimum(fp, path_d(n, None, p) if first[n] else
                                    path_d(n, park[n], p + (0.0, 0.0, 10.0)))
                near = min(float(np.linalg.norm(np.subtract(ps[0].start, pos[n]))),
                           float(np.linalg.norm(np.subtract(ps[-1].end, pos[n]))))
                out.append((ci, fp, clash(n, fp, t), (level, near)))
            return out

        def rank(n):
            """Priority in the current layer: the cell's order on even layers,
            reversed on odd ones (the last arm of a layer goes on first)."""
            i = names.index(n)
            return i if layer_of[n] % 2 == 0 else len(names) - 1 - i

        def before(n, fp):
            """True if a step with footprint fp would come within the zone of work
            still left in this layer to an adjacent arm of higher priority: that
            work goes first, so an arm sweeps towards a seam behind its
            neighbour instead of both racing to it."""
            for i, b in enumerate(nbrs[n]):
                if done[b] or layer_of[b] != layer_of[n] or rank(b) > rank(n) or not left[b]:
                    continue
                j = where[n][b]
                rest = min(chunks[b, layer_of[b]][ci][1][j] for ci in left[b])
                if fp[i] + rest < Z[n][i] - 1e-9:
                    return True
            return False

        def try_step(n, t):
            if done[n]:
                return False
            if layer_of[n] >= n_layers:
                to_park(n, t, "park")
                done[n] = True
                return True
            if not left[n]:
                if layer_ready(n, layer_of[n], t):
                    layer_of[n] += 1
                    left[n] = list(range(len(chunks[n, layer_of[n]]))) if layer_of[n] < n_layers else []
                    return True
                return False
            ok = [c for c in candidates(n, t) if not c[2] and not (priority and before(n, c[1]))]
            if not ok:
                return False
            ci, fp, _, _ = min(ok, key=lambda c: c[3])
            ps, _, _ = chunks[n, layer_of[n]][ci]
            here = None if first[n] or parked[n] else pos[n]
            segs = _order_runs(ps, None if here is None else tuple(here))
            dur = _path_time(here, segs)
            left[n].remove(ci)
            start(n, _Act("chunk", layer_of[n], t, t + dur, fp, segs), segs[-1].end, False)
            if not left[n]:
                layer_end[n, layer_of[n]] = t + dur
            return True

        def in_the_way(n, t, waiting):
            """Arms standing still (waiting too) in the way of one of arm n's chunks."""
            best = None
            for ci, fp, who, score in candidates(n, t):
                if who and all(b in waiting and not (acts[b] and acts[b][-1].C > t) for b in who):
                    if best is None or (len(who), score) < best[0]:
                        best = ((len(who), score), who)
            return [] if best is None else best[1]

        guard = 0
        while not all(done.values()):
            guard += 1
            if guard > 10_000_000:
                raise RuntimeError("coordinate: the schedule does not progress")
            t = min(t_free[n] for n in names if not done[n])
            moved = True
            while moved:
                moved = False
                for n in names:
                    if not done[n] and t_free[n] <= t and try_step(n, t):
                        moved = True
            waiting = [n for n in names if not done[n] and t_free[n] <= t]
            if not waiting:
                continue
            running = [acts[n][-1].C for n in names if acts[n] and acts[n][-1].C > t]
            # arms that have finished their layer and stand in someone's way go
            # to their park position; so do arms in the way when nobody can go on
            retreat = set()
            for n in waiting:
                for b in in_the_way(n, t, waiting):
                    if (not left[b] or not running) and not parked[b]:
                        retreat.add(b)
            if not retreat and not running:
                for n in waiting:                     # nobody can go on: clear the way of the first waiting arm
                    who = [b for c in candidates(n, t) for b in c[2] if not parked[b]]
                    if left[n] and who:
                        retreat.add(who[0])
                        break
                if not retreat:
                    raise RuntimeError("coordinate: the schedule is stuck at %.1f s: %s" % (
                        t, {n: (layer_of[n], len(left[n])) for n in waiting}))
            if retreat:
                for b in sorted(retreat, key=names.index):
                    to_park(b, t, "retreat")
                continue
            for n in waiting:
                t_free[n] = min(running)
        return acts

    # the cell's order as priorities or none: keep the shorter schedule
    acts = min((schedule(p) for p in (True, False) if p or not priority_only),
               key=lambda acts: max((a[-1].C for a in acts.values() if a), default=0.0))

    global _last_schedule
    _last_schedule = acts
    # ---- barriers: wait for what the other arm completed by the time a step starts
    ends = {n: [act.C for act in acts[n]] for n in names}
    for n in names:
        last = {b: -1 for b in nbrs[n]}
        for act in acts[n]:
            for b in nbrs[n]:
                m = bisect.bisect_right(ends[b], act.S) - 1
                if m > last[b]:
                    act.waits[b] = m
                    last[b] = m
                    if not acts[b][m].report:
                        acts[b][m].report = arm_of[n].id

    # ---- the programs
    writers, report_at, slots = {}, {}, {}
    for n in names:
        a = arm_of[n]
        w = _Writer()
        for line in _header(a, "concurrent", ["; seam zones %s mm, %d chunk band(s) per seam, scheduled"
                                              % (", ".join("%s %.1f" % (b, zones[n, b]) for b in nbrs[n]) or "-",
                                                 bands)]):
            w.emit(line)
        slots[n] = []
        marked = -1
        for i, act in enumerate(acts[n]):
            upto = act.layer if act.kind == "chunk" else (n_layers - 1 if act.kind == "park" else -1)
            while marked < upto:
                marked += 1
                w.emit(";LAYER_CHANGE")
                w.emit(";Z:%.3f" % (act.segs[-1].end[2] if marked == act.layer and act.segs else 0.0))
            for b, m in sorted(act.waits.items(), key=lambda kv: names.index(kv[0])):
                slots[n].append((len(w.lines), b, m))
                w.lines.append(None)
            if act.kind == "chunk":
                w.travel_to(act.segs[0].start)
                w.segments(act.segs)
            else:
                w.park(a, park[n])
            if act.report:
                w.emit(directive(SendPosition(act.report)))
                report_at[n, i] = len(w.lines)
        writers[n] = w
    programs = {}
    for n in names:
        a = arm_of[n]
        w = writers[n]
        for index, b, m in slots[n]:
            w.lines[index] = directive(WaitFor(a.id, arm_of[b].id, line=report_at[b, m]))
        removed, _ = read[n]
        programs[n] = ArmProgram(a, "concurrent", w.lines, removed, n_layers, bands + 1, start_first=True)
    return programs
