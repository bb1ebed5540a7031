"""The emitter: steps (:mod:`ambots.coordinate.steps`) -> an arm's program,
canonical G-code plus coordination directives.

:class:`_Writer` writes canonical G-code for runs of segments (absolute XYZ,
relative E, mm and mm/min in the bed frame), inserting a retracted travel
wherever a run does not start where the nozzle is; :class:`Emitter` writes
an arm's steps with it (layer changes, waits, travels, pieces, parks,
reports), and :func:`resolve_waits` turns every wait into the ``;@A9``
directive naming the line of the other arm's program it waits for, once
every program is written."""
import math
from dataclasses import dataclass, field
from typing import List, Optional

import numpy as np

from ambots.gcode import _Z_EPS, MAX_ABS_MM, GCodeWarning, Segment, _layer_marker, _new_segment
from ambots.program import directive
from ambots.protocol import MoveTo, SendPosition, WaitFor

from ambots.coordinate.steps import END, close

__all__ = ["ArmProgram", "Emitter", "resolve_waits"]


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
    #: the events of :attr:`lines` as the emitter wrote them (:meth:`_Events.result`),
    #: or None: :meth:`parse` then parses the text
    events: Optional[tuple] = None
    #: a scheduled timeline's chunk bands per seam (:func:`~ambots.coordinate.build_programs`'s
    #: ``chunk_bands``), None for the other plans
    chunk_bands: Optional[int] = None

    @property
    def text(self):
        return "\n".join(self.lines) + "\n"

    def __getstate__(self):
        """Pickled (sent back by a worker process) without :attr:`events`:
        the plan's :class:`ambots.job.Candidate` sends what the job writes
        of them, and :meth:`parse` parses the text if they are asked for."""
        return dict(self.__dict__, events=None)

    def parse(self):
        """The program's G-code events (a list, :func:`ambots.gcode.parse_gcode_text`
        of :attr:`text` as ``<arm>.gcode``): parse it once and pass the list on
        (:func:`ambots.estimate.estimate_programs`, :func:`ambots.gcode.summarize`).
        A program from the emitter has them already (the same events: the
        emitter keeps the parser's state as it writes; tests compare the two),
        unless its lines were changed since."""
        from ambots.gcode import parse_gcode_text
        if self.events is not None:
            events, n_lines, digest = self.events
            if len(self.lines) == n_lines and hash(self.text) == digest:
                return list(events)
        return list(parse_gcode_text(self.text, "%s.gcode" % self.arm.name))


class _Events:
    """The G-code events of the lines an emitter writes, as
    :func:`ambots.gcode.iter_gcode` would read them (its state for the
    canonical lines written here: absolute XYZ, relative E after the
    header's ``G21``/``G90``/``M83``, layer changes from ``;LAYER_CHANGE``),
    so a job need not parse its own programs again.  A number the parser
    would refuse, a line break inside a line, or a line this does not know
    makes :meth:`result` None (the text is parsed then, and the parser
    reports the error)."""

    def __init__(self):
        self.lim = MAX_ABS_MM
        self.x = self.y = self.z = self.e = 0.0
        self.feed = 0.0
        self.rel_e = False
        self.layer, self.layer_z, self.markers = -1, -math.inf, False
        self.warned = False
        self.out = []
        self.ok = True

    def line(self, line):
        """A line that is not a move: a comment (a layer change?) or the header's modes."""
        if line is None:                      # a wait, written later as a directive (a comment)
            return
        if any(c in line for c in _BREAKS):
            self.ok = False
        elif line[:1] == ";":
            if _layer_marker(line[1:]):
                self.layer += 1
                self.markers = True
        elif line == "G90":
            self.rel_e = False
        elif line == "M83":
            self.rel_e = True
        elif line != "G21":
            self.ok = False

    def move(self, lineno, x=None, y=None, z=None, e=None, f=None):
        """A G0/G1 line at ``lineno`` with these words (the values before
        formatting: X, Y, Z to 3 decimals, E to 5, F to 0, as written)."""
        lim = self.lim
        ox, oy, oz, oe = self.x, self.y, self.z, self.e
        nx = ox if x is None else round(float(x), 3)
        ny = oy if y is None else round(float(y), 3)
        nz = oz if z is None else round(float(z), 3)
        ne = oe
        if e is not None:
            v = round(float(e), 5)
            if not self.rel_e or not -lim <= v <= lim:
                self.ok = False
            ne = oe + v
        if f is not None:
            v = round(float(f), 0)
            if not 0 < v <= lim:
                self.ok = False
            self.feed = v
        if not (-lim <= nx <= lim and -lim <= ny <= lim and -lim <= nz <= lim):
            self.ok = False
        de = ne - oe
        if de > 0.0 and not self.markers and (nx != ox or ny != oy) and abs(nz - self.layer_z) > _Z_EPS:
            self.layer += 1
            self.layer_z = nz
        if self.feed == 0.0 and not self.warned and (nx != ox or ny != oy or nz != oz or de):
            self.warned = True
            self.out.append(GCodeWarning(lineno, "move before any feedrate F; its time is not counted"))
        self.out.append(_new_segment(Segment, ((ox, oy, oz), (nx, ny, nz), de, self.feed, de > 0.0, lineno,
                                               self.layer)))
        self.x, self.y, self.z, self.e = nx, ny, nz, ne

    def run(self, lineno, text, k):
        """``k`` lines ``G1 X.. Y.. Z.. E.. F..`` (``text``, each ending in a
        line break) from line ``lineno`` on: :meth:`move` of each, its
        numbers read back from the text at once.  Only after the first layer
        marker (:meth:`move` finds the layers before it by Z)."""
        lim = self.lim
        nums = np.array(text.replace("G1 X", "").replace(" Y", " ").replace(" Z", " ").replace(" E", " ")
                        .replace(" F", " ").split(), dtype=float).reshape(k, 5)
        if not self.rel_e or (np.abs(nums) > lim).any() or (nums[:, 4] <= 0).any():
            self.ok = False
        # the running filament total, added up in order as :meth:`move` does
        e = np.cumsum(np.concatenate([[self.e], nums[:, 3]]))
        de = (e[1:] - e[:-1]).tolist()
        x, y, z = nums[:, 0].tolist(), nums[:, 1].tolist(), nums[:, 2].tolist()
        f = nums[:, 4].tolist()
        ends = list(zip(x, y, z))
        starts = [(self.x, self.y, self.z)] + ends[:-1]
        layer, new = self.layer, _new_segment
        self.out += [new(Segment, (a, b, d, fr, d > 0.0, n, layer))
                     for a, b, d, fr, n in zip(starts, ends, de, f, range(lineno, lineno + k))]
        self.x, self.y, self.z = ends[-1]
        self.e, self.feed = float(e[-1]), f[-1]

    def result(self, lines):
        """(events, number of lines, hash of the text) for :class:`ArmProgram`, or None."""
        if not self.ok:
            return None
        return tuple(self.out), len(lines), hash("\n".join(lines) + "\n")


#: characters that end a line for :meth:`str.splitlines` (the parser's)
_BREAKS = "\n\r\x0b\x0c\x1c\x1d\x1e\x85\u2028\u2029"


#: extrusions chained end to start that :meth:`_Writer.segments` writes at
#: once (fewer: one by one, cheaper than numpy's cost per call)
_RUN = 8
_RUN_LINE = "G1 X%.3f Y%.3f Z%.3f E%.5f F%.0f\n"


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
        #: the filament is retracted now (by a park, or an E-only move of the slicer's)
        self.retracted = False
        self.retract_mm, self.retract_feed, self.travel_feed = retract_mm, retract_feed, travel_feed
        #: travels shorter than this within a layer are not retracted or lifted
        #: (the slicers' ``retract_before_travel``)
        self.short_travel_mm = short_travel_mm
        #: lift during a retracted travel (the slicers' ``z_hop``; 0 as the
        #: built-in slicer's default: two more moves from rest to rest per travel
        #: under the one timing law, about 0.1 s each)
        self.hop_mm = hop_mm
        #: the events of the lines written, as the parser would read them
        self.events = _Events()
        #: lifted straight up off the part, retracted (:meth:`lift`): a travel at that
        #: height only moves aside, without priming
        self.lifted = False

    def emit(self, line):
        """A line that is not a move (a comment, a directive, the header's modes)."""
        self.lines.append(line)
        self.events.line(line)

    def move(self, code, x=None, y=None, z=None, e=None, f=None):
        """A ``G0``/``G1`` line with these words, in the order X Y Z E F (mm,
        3 decimals; E 5; F mm/min, none)."""
        words = [code]
        if x is not None:
            words.append("X%.3f" % x)
        if y is not None:
            words.append("Y%.3f" % y)
        if z is not None:
            words.append("Z%.3f" % z)
        if e is not None:
            words.append("E%.5f" % e)
        if f is not None:
            words.append("F%.0f" % f)
        self.lines.append(" ".join(words))
        self.events.move(len(self.lines), x, y, z, e, f)

    def travel_to(self, p, feed=None):
        if self.lifted and self.pos is not None and abs(self.pos[2] - p[2]) < 1e-6:
            if not close(self.pos, p, atol=1e-6):      # aside, at the height lifted to
                self.move("G0", p[0], p[1], f=feed or self.travel_feed)
                self.pos = tuple(p)
            return
        self.lifted = False
        if self.parked:
            self.move("G0", p[0], p[1], p[2] + 10.0, f=feed or self.travel_feed)
            self.move("G0", z=p[2])
            self.move("G1", e=self.retract_mm, f=self.retract_feed)
            self.parked = self.retracted = False
            self.pos = tuple(p)
            return
        if self.pos is not None and close(self.pos, p, atol=1e-6):
            return
        if (self.pos is not None and abs(self.pos[2] - p[2]) < 1e-6
                and np.hypot(self.pos[0] - p[0], self.pos[1] - p[1]) < self.short_travel_mm):
            self.move("G0", p[0], p[1], f=feed or self.travel_feed)
        elif self.pos is not None:
            if not self.retracted:
                self.move("G1", e=-self.retract_mm, f=self.retract_feed)
            if self.hop_mm > 0 or abs(self.pos[2] - p[2]) > 1e-6:
                lift = max(self.pos[2], p[2]) + self.hop_mm        # clear what was printed
                self.move("G0", z=lift, f=feed or self.travel_feed)
                self.move("G0", p[0], p[1], f=feed or self.travel_feed)
                if lift != p[2]:
                    self.move("G0", z=p[2])
            else:
                self.move("G0", p[0], p[1], f=feed or self.travel_feed)
            self.move("G1", e=self.retract_mm, f=self.retract_feed)
            self.retracted = False
        else:
            self.move("G0", p[0], p[1], p[2], f=feed or self.travel_feed)
        self.pos = tuple(p)

    def approach(self, p, z_safe):
        """The first move to ``p`` (mm) from wherever the arm is (its home
        pose, its park position): over ``p`` at height ``z_safe`` (mm; a
        joint move of the firmware's planner, as the nozzle is not where
        the G-code was), then straight down; unretract if a park retracted."""
        feed = self.travel_feed
        self.move("G0", p[0], p[1], max(float(z_safe), p[2]), f=feed)
        if max(float(z_safe), p[2]) != p[2]:
            self.move("G0", z=p[2], f=feed)
        if self.retracted:
            self.move("G1", e=self.retract_mm, f=self.retract_feed)
        self.parked = self.retracted = self.lifted = False
        self.pos = tuple(p)

    def park(self, arm, xyz, lift_mm=10.0, lift_to=None):
        """Retract, lift clear of the part (``lift_mm`` over the nozzle, or
        to the height ``lift_to``, mm) and go to ``xyz`` (mm; an A7
        directive: a joint move of the firmware's planner).  A program that
        ends retracted (the slicer's last retraction) is not retracted twice."""
        if self.pos is not None and not self.parked:
            if not self.retracted:
                self.move("G1", e=-self.retract_mm, f=self.retract_feed)
            z = self.pos[2] + lift_mm if lift_to is None else max(float(lift_to), self.pos[2])
            if z != self.pos[2]:                 # not lifted there already (:meth:`lift`)
                self.move("G0", z=z, f=self.travel_feed)
        x, y, z = xyz
        self.emit(directive(MoveTo(arm.id, round(float(x), 3), round(float(y), 3), round(float(z), 3))))
        self.lifted = False
        self.parked = self.pos is not None
        self.retracted = self.retracted or self.parked

    def lift(self, z):
        """Retract (unless retracted) and lift the nozzle straight up to
        ``z`` (mm), over where it is: off the part while the arm waits
        (an arm done printing whose neighbours print on).  A travel at that
        height then only moves aside, retracted; one to a lower point comes
        down as any travel does; a later :meth:`park` goes on from there."""
        if self.pos is None or self.parked:
            return
        if not self.retracted:
            self.move("G1", e=-self.retract_mm, f=self.retract_feed)
            self.retracted = True
        z = max(float(z), self.pos[2])
        if z != self.pos[2]:
            self.move("G0", z=z, f=self.travel_feed)
            self.pos = (self.pos[0], self.pos[1], z)
        self.lifted = True

    def segments(self, segs):
        lines, move = self.lines, self.events.move
        n, i = len(segs), 0
        while i < n:
            s = segs[i]
            i += 1
            moved = s.start != s.end
            if not moved:
                if s.e:
                    self.move("G1", e=s.e, f=s.feedrate or self.retract_feed)
                    self.retracted = s.e < 0
                continue
            if self.pos is None or (self.pos != s.start and not close(self.pos, s.start, atol=1e-6)):
                self.travel_to(s.start)
            x, y, z = s.end
            if s.extrude:
                self.retracted = False
                j = i                   # a chain of extrusions from here: written at once
                while j < n and segs[j].extrude and segs[j].start == segs[j - 1].end and segs[j].start != segs[j].end:
                    j += 1
                if j - i + 1 >= _RUN and self.events.markers:
                    run = segs[i - 1:j]
                    text = (_RUN_LINE * len(run)) % tuple([v for q in run for v in (*q.end, q.e, q.feedrate)])
                    first = len(lines) + 1
                    lines += text.split("\n")[:-1]
                    self.events.run(first, text, len(run))
                    self.pos = run[-1].end
                    i = j
                    continue
                lines.append("G1 X%.3f Y%.3f Z%.3f E%.5f F%.0f" % (x, y, z, s.e, s.feedrate))
                move(len(lines), x, y, z, s.e, s.feedrate)
            else:
                f = s.feedrate or self.travel_feed
                lines.append("G0 X%.3f Y%.3f Z%.3f F%.0f" % (x, y, z, f))
                move(len(lines), x, y, z, None, f)
            self.pos = s.end


def _header(arm, mode, extra=()):
    return ["; ambots program for arm %s (R%d), mode %s" % (arm.name, arm.id, mode),
            "; frame: print bed, mm; absolute XYZ, relative E", *extra, "G21", "G90", "M83"]


def _report_line(lines, is_wait, target):
    """The line at which an arm reports having done ``target`` (1-based): an
    arm reports its last completed line when it reaches the first barrier
    line of a run of them, never while it waits there, so a target inside a
    run of barrier lines is moved back to the line before the run (the same
    motion done)."""
    while target > 0 and is_wait[target - 1]:
        target -= 1
    return target


#: the :class:`_Writer`'s and its :class:`_Events`' state that what
#: :meth:`_Writer.segments` writes depends on (:meth:`Emitter._state`)
_WRITER_STATE = ("pos", "parked", "retracted", "lifted")
_EVENTS_STATE = ("x", "y", "z", "e", "feed", "rel_e", "layer", "layer_z", "markers", "warned", "ok")


class Emitter:
    """One arm's program, written step by step (:class:`~ambots.coordinate.
    steps.Step`).  A wait is a placeholder (None) in ``lines`` until
    :func:`resolve_waits`; ``pos`` is where the nozzle is (mm; None before
    the first move), which a strategy may need to order its next pieces."""

    def __init__(self, arm, mode, extra=(), written=None):
        self.arm = arm
        self.writer = _Writer()
        for line in _header(arm, mode, extra):
            self.writer.emit(line)
        self.marks = {}          #: mark -> line number reached (1-based)
        self.waits = []          #: (index in lines, Wait)
        #: ``written``: a list shared by the programs of one G-code (the
        #: model's, for each arm alone): the first emitter records in it
        #: what each step's pieces wrote (:meth:`_pieces`); a later one
        #: copies those lines and events where its step has the same pieces
        #: and its writer the same state, instead of writing them again
        #: (arms alone differ in their header, directives and first and last
        #: moves only: 0.25 s of the 60 mm sphere's 0.3 s program)
        self.written = written
        self._copy = bool(written)
        self._n_pieces = 0

    def _state(self):
        """What the lines and events :meth:`_Writer.segments` writes depend
        on besides the pieces: how many lines and events there are, the
        writer's state and its parser state's (:data:`_WRITER_STATE`,
        :data:`_EVENTS_STATE`)."""
        w, ev = self.writer, self.writer.events
        return ((len(w.lines), len(ev.out)) + tuple(getattr(w, a) for a in _WRITER_STATE)
                + tuple(getattr(ev, a) for a in _EVENTS_STATE))

    def _pieces(self, pieces):
        """Write ``pieces`` (:meth:`_Writer.segments`), or copy them from
        :attr:`written` (the same segment objects, from the same state)."""
        w, k = self.writer, self._n_pieces
        self._n_pieces += 1
        if self.written is None:
            w.segments(pieces)
            return
        before = self._state()
        if self._copy and k < len(self.written):
            seen, was, lines, events, after = self.written[k]
            if was == before and len(seen) == len(pieces) and all(a is b for a, b in zip(seen, pieces)):
                w.lines += lines
                w.events.out += events
                n = len(_WRITER_STATE)
                for a, v in zip(_WRITER_STATE, after[2:2 + n]):
                    setattr(w, a, v)
                for a, v in zip(_EVENTS_STATE, after[2 + n:]):
                    setattr(w.events, a, v)
                return
            self._copy = False           # once apart, written here from then on
        w.segments(pieces)
        if not self._copy and k == len(self.written):       # the first program of the G-code: recorded
            self.written.append((pieces, before, w.lines[before[0]:], w.events.out[before[1]:], self._state()))

    @property
    def lines(self):
        return self.writer.lines

    @property
    def pos(self):
        return self.writer.pos

    def events(self):
        """The events of the program written (for :class:`ArmProgram`'s
        ``events``; after :func:`resolve_waits`), or None."""
        return self.writer.events.result(self.lines)

    def step(self, st):
        w = self.writer
        for msg in st.directives:
            w.emit(directive(msg))
        for z in st.layers:
            w.emit(";LAYER_CHANGE")
            w.emit(";Z:%.3f" % z)
        for wait in st.waits:
            self.waits.append((len(w.lines), wait))
            w.lines.append(None)
        if st.approach is not None:
            w.approach(st.travel if st.travel is not None else st.pieces[0].start, st.approach)
        elif st.travel is not None:
            w.travel_to(st.travel)
        if st.pieces:
            self._pieces(st.pieces)
        if st.park is not None:
            w.park(self.arm, st.park, lift_to=st.lift_to)
        elif st.lift_to is not None:
            w.lift(st.lift_to)
        if st.report is not None:
            w.emit(directive(SendPosition(st.report)))
        if st.mark is not None:
            self.marks[st.mark] = len(w.lines)

    def steps(self, steps):
        for st in steps:
            self.step(st)
        return self


def resolve_waits(emitters):
    """Fill in every emitter's waits ({arm name: :class:`Emitter`}): the
    line of the other arm's program at its mark (or its last line), moved
    back before a run of waits (:func:`_report_line`)."""
    is_wait = {n: [line is None for line in e.lines] for n, e in emitters.items()}
    for e in emitters.values():
        for index, wait in e.waits:
            other = emitters[wait.other]
            target = len(other.lines) if wait.mark == END else other.marks[wait.mark]
            target = _report_line(other.lines, is_wait[wait.other], target)
            e.lines[index] = directive(WaitFor(e.arm.id, other.arm.id, line=target))
