"""Coordination: each arm's sliced G-code -> one program per arm (G-code plus
A-series commands), in one of two modes.

``sequential`` (the original project's behaviour): the first arm sends every
other arm to its park position (A7), prints its whole part, parks itself and
starts the next arm (A1); and so on down the cell's list of arms.

``concurrent`` (default): all arms print the same layer at the same time.
Moves closer than ``zone_mm`` to a seam with a neighbouring part belong to
the *seam zone*; arms that share a seam get different colours (greedy graph
colouring), and each layer is split into one phase per colour: in phase p
the arms of colour p print their seam-zone moves while the others print
their moves away from every seam.  At the end of every phase each arm waits
(``;@A9 ... N<line>``) until every other arm has completed the last line of its
own work for that phase, so nozzles never work on both sides of a seam at
once and a slow arm holds the others at the next barrier instead of being
run into.  Barriers name exact lines of the other arm's program, which the
builder knows because it writes every program.

Coordination commands are directive lines (``;@A9 R1 W2 N120``, see
:mod:`ambots.program`): comments to any other reader, executed by the
firmware at that point of the program.

Programs are canonical G-code re-emitted from the reader's segments
(absolute XYZ, relative E, mm and mm/min in the bed frame), with PrusaSlicer
style ``;LAYER_CHANGE`` comments, so any firmware or ``python -m ambots
info`` reads them.  Slicer output is sanitised first: A-series lines in it
are stripped and reported.
"""
from dataclasses import dataclass, field
from typing import Dict, List

import numpy as np

from ambots.gcode import Segment, parse_gcode_text
from ambots.program import directive, sanitize_gcode
from ambots.protocol import MoveTo, SendPosition, Start, WaitFor

__all__ = ["ArmProgram", "build_programs", "park_positions_mm", "seam_zone_for"]


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


def park_positions_mm(cell, arms):
    """Where each arm parks its nozzle: its home pose, in bed-frame mm."""
    from ambots.model import arm_kinematics
    inv = np.linalg.inv(cell.bed.pose)
    out = {}
    for arm in arms:
        T = arm.base_pose @ arm_kinematics(arm).fk(np.asarray(arm.profile.home))
        out[arm.name] = (inv[:3, :3] @ T[:3, 3] + inv[:3, 3]) * 1000.0
    return out


class _Writer:
    """Emits canonical G-code for runs of segments, inserting a retracted
    travel wherever a run does not start where the nozzle is."""

    def __init__(self, retract_mm=0.8, retract_feed=2100.0, travel_feed=9000.0, short_travel_mm=2.0):
        self.lines = []
        self.pos = None
        self.retract_mm, self.retract_feed, self.travel_feed = retract_mm, retract_feed, travel_feed
        #: travels shorter than this within a layer are not retracted or lifted
        #: (the slicers' ``retract_before_travel``)
        self.short_travel_mm = short_travel_mm

    def emit(self, line):
        self.lines.append(line)

    def travel_to(self, p, feed=None):
        if self.pos is not None and np.allclose(self.pos, p, atol=1e-6):
            return
        if (self.pos is not None and abs(self.pos[2] - p[2]) < 1e-6
                and np.hypot(self.pos[0] - p[0], self.pos[1] - p[1]) < self.short_travel_mm):
            self.emit("G0 X%.3f Y%.3f F%.0f" % (p[0], p[1], feed or self.travel_feed))
        elif self.pos is not None:
            self.emit("G1 E-%.5f F%.0f" % (self.retract_mm, self.retract_feed))
            lift = max(self.pos[2], p[2]) + 0.4        # clear what was just printed
            self.emit("G0 Z%.3f F%.0f" % (lift, feed or self.travel_feed))
            self.emit("G0 X%.3f Y%.3f F%.0f" % (p[0], p[1], feed or self.travel_feed))
            self.emit("G0 Z%.3f" % p[2])
            self.emit("G1 E%.5f F%.0f" % (self.retract_mm, self.retract_feed))
        else:
            self.emit("G0 X%.3f Y%.3f Z%.3f F%.0f" % (p[0], p[1], p[2], feed or self.travel_feed))
        self.pos = tuple(p)

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


def build_programs(sliced, parts, cell, mode="concurrent", zone_mm=None, park=None):
    """Build every arm's program.

    Parameters
    ----------
    sliced : {arm name: G-code text} of each part, bed frame, mm
    parts : the :class:`~ambots.partition.Part` list (gives arm order and seam planes)
    cell : the cell (park positions come from the arms' home poses)
    mode : ``"concurrent"`` or ``"sequential"``
    zone_mm : how far apart (mm) two nozzles across a seam must stay
        (concurrent mode); default: from the arms' real geometry,
        :func:`ambots.collision.seam_zone_mm`
    park : optional {arm name: (x, y, z) mm} overriding the park positions

    Returns {arm name: :class:`ArmProgram`}, in the parts' order.
    """
    if mode not in ("concurrent", "sequential"):
        raise ValueError("mode must be 'concurrent' or 'sequential', got %r" % mode)
    arms = [p.arm for p in parts]
    park = park or park_positions_mm(cell, arms)
    read = {a.name: _read_layers(sliced[a.name], "%s.gcode" % a.name) for a in arms}
    n_layers = max([max(layers) + 1 for _, layers in read.values() if layers] or [0])
    if mode == "sequential":
        return _sequential(arms, read, park, n_layers)
    if zone_mm is None:
        zone_mm = seam_zone_for(cell, arms)
    return _concurrent(arms, parts, read, park, n_layers, zone_mm)


_ZONES = {}


def seam_zone_for(cell, arms):
    """Seam zone (mm) of these arms of the cell, from their geometry (cached)."""
    from ambots.collision import seam_zone_mm
    if len(arms) < 2:
        return 0.0
    key = (cell.path if hasattr(cell, "path") else cell.name, tuple(a.name for a in arms))
    if key not in _ZONES:
        _ZONES[key] = float(seam_zone_mm(cell, arms))
    return _ZONES[key]


def _finish(w, arm, park):
    """Lift clear of the part, then go to the park position."""
    if w.pos is not None:
        w.emit("G1 E-%.5f F%.0f" % (w.retract_mm, w.retract_feed))
        w.emit("G0 Z%.3f F%.0f" % (w.pos[2] + 10.0, w.travel_feed))
    x, y, z = park[arm.name]
    w.emit(directive(MoveTo(arm.id, round(float(x), 3), round(float(y), 3), round(float(z), 3))))


def _sequential(arms, read, park, n_layers):
    programs = {}
    for i, arm in enumerate(arms):
        removed, layers = read[arm.name]
        w = _Writer()
        for line in _header(arm, "sequential"):
            w.emit(line)
        if i == 0:     # the first arm moves every other arm out of the way
            for other in arms[1:]:
                x, y, z = park[other.name]
                w.emit(directive(MoveTo(other.id, round(float(x), 3), round(float(y), 3), round(float(z), 3))))
        for k in sorted(layers):
            w.emit(";LAYER_CHANGE")
            w.emit(";Z:%.3f" % layers[k][-1].end[2])
            w.segments(layers[k])
        _finish(w, arm, park)
        if i + 1 < len(arms):
            w.emit(directive(Start(arms[i + 1].id)))
        programs[arm.name] = ArmProgram(arm, "sequential", w.lines, removed, len(layers), 1, start_first=(i == 0))
    return programs


def _colours(arms, adjacent):
    colour = {}
    for a in arms:
        used = {colour[b] for b in adjacent[a.name] if b in colour}
        colour[a.name] = next(c for c in range(len(arms)) if c not in used)
    return colour


def _concurrent(arms, parts, read, park, n_layers, zone_mm):
    names = [a.name for a in arms]
    planes = {p.arm.name: p.planes for p in parts}
    neighbour_of = {p.arm.name: [a.name for a in arms if a is not p.arm] for p in parts}
    # which arms share a seam with work near it
    adjacent = {n: set() for n in names}
    for part in parts:
        name = part.arm.name
        _, layers = read[name]
        for segs in layers.values():
            pts = np.array([s.start for s in segs] + [s.end for s in segs], dtype=float)
            d = _distance_to_planes(pts, part.planes)
            near = (np.abs(d) < zone_mm).reshape(2, len(segs), -1).any(axis=0)
            for j in np.where(near.any(axis=0))[0]:
                other = neighbour_of[name][j]
                adjacent[name].add(other)
                adjacent[other].add(name)
    colour = _colours(arms, adjacent)
    if max(colour.values()) <= 1:
        return _banded(arms, read, park, n_layers, zone_mm, planes, colour, adjacent)
    return _zone_phases(arms, parts, read, park, n_layers, zone_mm, colour)


# ----------------------------------------------------------- banded sweep
def _split_at_bands(seg, planes, w, k):
    """Cut a segment where its distance to any seam plane crosses a band
    boundary (multiples of ``w``); E is shared in proportion to length."""
    a, b = np.array(seg.start, dtype=float), np.array(seg.end, dtype=float)
    if not planes or np.allclose(a, b):
        return [seg]
    cuts = []
    for n, off in planes:
        fa, fb = float(n @ a - off), float(n @ b - off)
        if abs(fb - fa) < 1e-12:
            continue
        lo, hi = sorted((fa, fb))
        for m in range(int(np.floor(lo / w)) + 1, int(np.ceil(hi / w))):
            if 1 <= m <= k - 1:
                t = (m * w - fa) / (fb - fa)
                if 1e-9 < t < 1 - 1e-9:
                    cuts.append(t)
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


def _band_of(segs, planes, w, k):
    """Band index (S,) of each segment from its midpoint's distance to the nearest seam."""
    if not planes:
        return np.full(len(segs), k - 1)
    mid = np.array([(np.add(s.start, s.end)) / 2.0 for s in segs], dtype=float)
    d = _distance_to_planes(mid, planes).min(axis=1)
    return np.clip(np.floor(d / w), 0, k - 1).astype(int)


def _seg_time(segs):
    t = 0.0
    for s in segs:
        L = float(np.linalg.norm(np.subtract(s.end, s.start)))
        f = s.feedrate if s.feedrate > 0 else 1800.0
        t += (L if L > 0 else abs(s.e)) / f * 60.0
    return t


def _banded(arms, read, park, n_layers, zone_mm, planes, colour, adjacent):
    """Two colours (every seam separates a colour-0 from a colour-1 arm).

    Each arm's work is cut into bands by distance from its nearest seam:
    band i (0 <= i < k-1) is [i w, (i+1) w) with w >= zone / (k-1), band
    k-1 the rest (w = the part's reach from the seam / k when that is
    wider, so that the phases balance).  In phase i of a layer one colour prints band i while the
    other prints band k-1-i, so two nozzles across a seam are always at
    least (k-1) w = zone apart.  Directions alternate with the layer (even
    layers: colour 0 moves away from the seam, colour 1 towards it; odd
    layers the reverse), so no arm ever crosses another's path at a layer
    change.  Between phases the arm moving away first travels to its next
    band (its *approach*), and the arm moving towards the seam waits for
    that (an A9 on the approach line) before it approaches; an arm with no
    work in its next band still moves there (a retreat), so the spacing
    holds whatever the timing.  ``k`` (2..12) is chosen to minimise the
    estimated makespan."""
    names = [a.name for a in arms]
    segs_by = {(a.name, k): segs for a in arms for k, segs in read[a.name][1].items()}
    # choose k on the unsplit segments (midpoint distance, duration), vectorised
    stats = {}
    for a in arms:
        for layer in range(n_layers):
            segs = segs_by.get((a.name, layer), [])
            if not segs:
                continue
            mid = np.array([np.add(s.start, s.end) / 2.0 for s in segs], dtype=float)
            d = (_distance_to_planes(mid, planes[a.name]).min(axis=1) if planes[a.name]
                 else np.full(len(segs), np.inf))
            dur = np.array([_seg_time([s]) for s in segs])
            stats[a.name, layer] = (d, dur)
    # the widest reach from a seam: bands wider than zone / (k-1) (equal
    # widths H / k) keep the spacing and balance the phases
    far = max([float(np.max(d[np.isfinite(d)])) for d, *_ in stats.values() if np.isfinite(d).any()] or [0.0])
    best = None
    for k in range(2, 13):
        w = max(max(zone_mm, 1e-3) / (k - 1), far / k)
        est = 0.0
        for layer in range(n_layers):
            phase_t = np.zeros(k)
            for a in arms:
                if (a.name, layer) not in stats:
                    continue
                d, dur = stats[a.name, layer]
                band = np.clip(np.floor(d / w), 0, k - 1).astype(int)
                per_band = np.bincount(band, weights=dur, minlength=k)
                phases = np.array([_phase_of(b, colour[a.name], layer, k) for b in range(k)])
                np.maximum.at(phase_t, phases, per_band)
            est += phase_t.sum() + k * 0.5          # a barrier costs about half a second
        if best is None or est < best[0] - 1e-9:
            best = (est, k, w)
    k, w = best[1], best[2]
    steps = {}
    for a in arms:
        for layer in range(n_layers):
            segs = [p for s in segs_by.get((a.name, layer), []) for p in _split_at_bands(s, planes[a.name], w, k)]
            band = _band_of(segs, planes[a.name], w, k) if segs else np.zeros(0, dtype=int)
            for b in range(k):
                steps[a.name, layer, _phase_of(b, colour[a.name], layer, k)] = (
                    b, [s for s, bb in zip(segs, band) if bb == b])
    writers, step_end, approach_end, slots = {}, {}, {}, {}
    for a in arms:
        w_ = _Writer()
        for line in _header(a, "concurrent", ["; seam zone %.1f mm, %d band(s) of %.1f mm per layer, colour %d"
                                              % (zone_mm, k, w, colour[a.name])]):
            w_.emit(line)
        slots[a.name] = []
        for layer in range(n_layers):
            for p in range(k):
                band, segs = steps[a.name, layer, p]
                if planes[a.name]:      # cut pieces: drop slicer travels, shortest-travel order
                    segs = _order_runs(segs, w_.pos)
                if p == 0:
                    w_.emit(";LAYER_CHANGE")
                    zs = [s.end[2] for q in range(k) for s in steps[a.name, layer, q][1]]
                    w_.emit(";Z:%.3f" % (zs[-1] if zs else 0.0))
                towards = p > 0 and band < steps[a.name, layer, p - 1][0]
                if towards:       # wait until the neighbours moving away have approached their band
                    for other in arms:
                        if other.name in adjacent[a.name]:
                            slots[a.name].append(("approach", other.name, layer, p, len(w_.lines)))
                            w_.lines.append(None)
                first = next((s for s in segs if s.start != s.end), None)
                if first is not None:
                    w_.travel_to(first.start)
                elif p > 0 and not towards and w_.pos is not None:
                    w_.travel_to(_retreat(w_.pos, planes[a.name], band, w))
                if p > 0 and not towards and any(n in adjacent[a.name] for n in names):
                    # tell the neighbours (A10 with position, via the hub) that the approach is done
                    other = next(o for o in arms if o.name in adjacent[a.name])
                    w_.emit(directive(SendPosition(other.id)))
                approach_end[a.name, layer, p] = len(w_.lines)
                w_.segments(segs)
                step_end[a.name, layer, p] = len(w_.lines)
                for other in arms:
                    if other is not a:
                        slots[a.name].append(("step", other.name, layer, p, len(w_.lines)))
                        w_.lines.append(None)
        _finish(w_, a, park)
        writers[a.name] = w_
    programs = {}
    for a in arms:
        w_ = writers[a.name]
        for kind, other, layer, p, index in slots[a.name]:
            target = (approach_end if kind == "approach" else step_end)[other, layer, p]
            w_.lines[index] = directive(WaitFor(a.id, _arm_id(arms, other), line=target))
        removed, _ = read[a.name]
        programs[a.name] = ArmProgram(a, "concurrent", w_.lines, removed, n_layers, k, start_first=True)
    return programs


def _phase_of(band, colour, layer, k):
    """Phase in which an arm of ``colour`` prints ``band`` on ``layer``."""
    away = (colour + layer) % 2 == 0          # this arm sweeps away from the seam on this layer
    return band if away else k - 1 - band


def _arm_id(arms, name):
    return next(a.id for a in arms if a.name == name)


def _retreat(pos, planes, band, w):
    """A point on the same side as ``pos`` just inside ``band`` (mm)."""
    p = np.array(pos, dtype=float)
    if not planes:
        return tuple(p)
    d = _distance_to_planes(p[None], planes)[0]
    j = int(np.argmin(d))
    n = np.asarray(planes[j][0], dtype=float)
    want = band * w + min(2.0, w / 4)
    if d[j] >= want:
        return tuple(p)
    q = p + n * (want - d[j])
    return (float(q[0]), float(q[1]), float(p[2]))


# ----------------------------------------------------------- zone phases
def _zone_phases(arms, parts, read, park, n_layers, zone_mm, colour):
    """More than two colours: each layer has one phase per colour; in phase
    p the arms of colour p print their seam-zone moves while the others
    print their moves away from every seam."""
    zone, far = {}, {}
    for part in parts:
        name = part.arm.name
        _, layers = read[name]
        for k, segs in layers.items():
            pts = np.array([s.start for s in segs] + [s.end for s in segs], dtype=float)
            d = _distance_to_planes(pts, part.planes)
            in_zone = (np.abs(d) < zone_mm).reshape(2, len(segs), -1).any(axis=0).any(axis=1)
            zone[name, k] = [s for s, z in zip(segs, in_zone) if z]
            far[name, k] = [s for s, z in zip(segs, in_zone) if not z]
    k_phases = max(colour.values()) + 1
    # pass 1: the content of every (arm, layer, phase) step
    steps = {}
    for a in arms:
        own = colour[a.name]
        for k in range(n_layers):
            for p in range(k_phases):
                if k_phases == 1:
                    segs = zone.get((a.name, k), []) + far.get((a.name, k), [])
                elif p == own:
                    segs = zone.get((a.name, k), [])
                elif p == (own + 1) % k_phases:
                    segs = far.get((a.name, k), [])
                else:
                    segs = []
                steps[a.name, k, p] = segs
    # pass 2: write each program; a barrier after every step waits for all other arms
    writers, step_end = {}, {}
    n_wait = len(arms) - 1
    for a in arms:
        w = _Writer()
        for line in _header(a, "concurrent", ["; seam zone %.1f mm, %d phase(s) per layer, colour %d"
                                              % (zone_mm, k_phases, colour[a.name])]):
            w.emit(line)
        for k in range(n_layers):
            for p in range(k_phases):
                if p == 0:
                    w.emit(";LAYER_CHANGE")
                    segs_k = [s for q in range(k_phases) for s in steps[a.name, k, q]]
                    w.emit(";Z:%.3f" % (segs_k[-1].end[2] if segs_k else 0.0))
                w.segments(steps[a.name, k, p])
                step_end[a.name, k, p] = len(w.lines)          # last content line of this step
                w.lines.extend([None] * n_wait)                  # the barrier, filled in below
        _finish(w, a, park)
        writers[a.name] = w
    programs = {}
    for a in arms:
        w = writers[a.name]
        slots = iter(i for i, line in enumerate(w.lines) if line is None)
        for k in range(n_layers):
            for p in range(k_phases):
                for other in arms:
                    if other is not a:
                        w.lines[next(slots)] = directive(WaitFor(a.id, other.id, line=step_end[other.name, k, p]))
        removed, layers = read[a.name]
        programs[a.name] = ArmProgram(a, "concurrent", w.lines, removed, n_layers, k_phases, start_first=True)
    return programs
