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
from ambots.protocol import MoveTo, Start, WaitFor

__all__ = ["ArmProgram", "build_programs", "park_positions_mm", "DEFAULT_ZONE_MM"]

#: default width (mm) of the seam zone on each side of a seam: two nozzles
#: printing at the same time stay at least this far apart
DEFAULT_ZONE_MM = 60.0


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

    def __init__(self, retract_mm=0.8, retract_feed=2100.0, travel_feed=9000.0):
        self.lines = []
        self.pos = None
        self.retract_mm, self.retract_feed, self.travel_feed = retract_mm, retract_feed, travel_feed

    def emit(self, line):
        self.lines.append(line)

    def travel_to(self, p, feed=None):
        if self.pos is not None and np.allclose(self.pos, p, atol=1e-6):
            return
        if self.pos is not None:
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


def build_programs(sliced, parts, cell, mode="concurrent", zone_mm=DEFAULT_ZONE_MM, park=None):
    """Build every arm's program.

    Parameters
    ----------
    sliced : {arm name: G-code text} of each part, bed frame, mm
    parts : the :class:`~ambots.partition.Part` list (gives arm order and seam planes)
    cell : the cell (park positions come from the arms' home poses)
    mode : ``"concurrent"`` or ``"sequential"``
    zone_mm : seam-zone width on each side of a seam (concurrent mode)
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
    return _concurrent(arms, parts, read, park, n_layers, zone_mm)


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
    # classify every segment: in the seam zone of a neighbour, or away from every seam
    zone, far, adjacent = {}, {}, {n: set() for n in names}
    for part in parts:
        name = part.arm.name
        others = [a for a in arms if a is not part.arm]
        _, layers = read[name]
        for k, segs in layers.items():
            pts = np.array([s.start for s in segs] + [s.end for s in segs], dtype=float)
            d = _distance_to_planes(pts, part.planes)
            near = (np.abs(d) < zone_mm).reshape(2, len(segs), -1).any(axis=0)     # (S, P)
            in_zone = near.any(axis=1)
            for j in np.where(near.any(axis=0))[0]:
                adjacent[name].add(others[j].name)
                adjacent[others[j].name].add(name)
            zone[name, k] = [s for s, z in zip(segs, in_zone) if z]
            far[name, k] = [s for s, z in zip(segs, in_zone) if not z]
    colour = _colours(arms, adjacent)
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
