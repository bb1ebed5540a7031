"""The one intermediate form between the strategies and the emitter.

* The sliced G-code of each part, read once (:class:`Sliced`: the lines
  stripped from it, and its extrusion and travel :class:`~ambots.gcode.
  Segment` s by layer; :func:`read_sliced`).
* *Pieces*: those segments, cut where bands or planes cut them
  (:func:`cut_segment`) and ordered for short travels (:func:`_order_runs`).
* *Steps*: what an arm's program does, in order (:class:`Step`): the layer
  changes that open it, the *waits* before it (:class:`Wait`: for a *mark*
  of another arm's program, or its end), a travel, the pieces printed, a
  move to the park position, a *report* (``;@A3``) and the mark that names
  the line reached.  :mod:`ambots.coordinate.emit` writes steps as G-code
  and directives and turns waits into ``;@A9`` lines naming the other
  arm's lines.

Units: mm and mm/min in the bed frame, as the G-code."""
import re
from dataclasses import dataclass, field
from typing import Dict, List, NamedTuple, Optional

import numpy as np

from ambots.gcode import Segment, _new_segment, parse_gcode_text
from ambots.program import sanitize_gcode

__all__ = ["Sliced", "Features", "read_sliced", "Wait", "Step", "END", "cut_segment", "seg_time", "seg_times"]


class Sliced(NamedTuple):
    """One part's sliced G-code, read: ``removed`` the (line, text) stripped
    from it (A-series lines), ``layers`` {layer: [Segment]}, ``features``
    the slicer's ``;TYPE:`` comments (:class:`Features`)."""
    removed: list
    layers: Dict[int, List[Segment]]
    features: Optional["Features"] = None


#: line breaks of str.splitlines other than "\n"
_ODD_BREAKS = re.compile("[\r\x0b\x0c\x1c\x1d\x1e\x85\u2028\u2029]")


class Features:
    """The feature (``;TYPE:`` comment: ``Internal infill``, ``Perimeter``,
    ...) each line of a G-code text belongs to: the last one written before
    it (None before the first)."""

    def __init__(self, text):
        starts, names = [], []
        if _ODD_BREAKS.search(text):         # lines as str.splitlines counts them (the parser's)
            for i, ln in enumerate(text.splitlines(), 1):
                k = ln.find(";TYPE:")
                if k >= 0:
                    starts.append(i)
                    names.append(ln[k + 6:].strip())
            self.starts, self.names = np.array(starts, dtype=np.int64), names
            return
        line, pos = 1, 0
        k = text.find(";TYPE:")
        while k >= 0:
            line += text.count("\n", pos, k)
            end = text.find("\n", k)
            names.append(text[k + 6:end if end >= 0 else len(text)].strip())
            starts.append(line)
            pos = k
            k = text.find(";TYPE:", k + 1)
        self.starts = np.array(starts, dtype=np.int64)
        self.names = names

    def __eq__(self, other):
        return (isinstance(other, Features) and np.array_equal(self.starts, other.starts)
                and self.names == other.names)

    def __repr__(self):
        return "Features(%d)" % len(self.names)

    def of(self, line):
        """The feature of G-code line ``line`` (1-based), or None."""
        i = int(np.searchsorted(self.starts, line, side="right")) - 1
        return self.names[i] if i >= 0 else None

    def infill(self, line):
        """Whether line ``line`` is infill laid on the layer below (a
        feature whose name says infill: the built-in slicer's and
        PrusaSlicer's sparse, solid and top solid infill; not bridge infill,
        which spans a gap)."""
        name = (self.of(line) or "").lower()
        return "infill" in name and "bridge" not in name


def read_sliced(text, path):
    """Sanitised slicer G-code -> :class:`Sliced` (parsed once: a job passes
    this on instead of the text when several plans use the same G-code).
    The built-in slicer's text (:class:`ambots.sliced.SlicedText`) is not
    parsed: its writer's reading of it is taken (the same segments; it has
    no A-series line to strip)."""
    layers = getattr(text, "layers", None)
    if layers is not None:
        return Sliced([], {k: list(v) for k, v in layers.items()}, Features(text))
    clean, removed = sanitize_gcode(text, path, trusted=False, mode="strip")
    layers: Dict[int, List[Segment]] = {}
    for ev in parse_gcode_text(clean, path):
        if type(ev) is Segment:
            layers.setdefault(max(ev.layer, 0), []).append(ev)
    return Sliced(removed, layers, Features(clean))


def close(a, b, atol=1e-8):
    """``np.allclose(a, b, atol=atol)`` for two points (3 floats), without
    numpy's cost per call (half a million calls on a 300,000-triangle
    model's programs): |a - b| <= atol + 1e-5 |b| for each coordinate."""
    return all(abs(x - y) <= atol + 1e-5 * abs(y) for x, y in zip(a, b))


#: the mark of a program's last line (an arm reports it when it is done)
END = "end"


@dataclass
class Wait:
    """Wait (``;@A9``) until arm ``other`` has reached its ``mark`` (or END)."""
    other: str
    mark: object


@dataclass
class Step:
    """One step of an arm's program; the emitter writes its parts in this
    order: directives, layer changes, waits, travel, pieces, park, report,
    mark."""
    directives: list = field(default_factory=list)   #: protocol messages for other arms (A7, A1)
    layers: List[float] = field(default_factory=list)  #: a ``;LAYER_CHANGE`` / ``;Z:`` pair per z (mm)
    waits: List[Wait] = field(default_factory=list)
    travel: Optional[tuple] = None                   #: travel here first (mm)
    #: the first move from wherever the arm stands (home, park position): over the
    #: travel's point (or the first piece's start) at this height (mm), then straight down
    approach: Optional[float] = None
    pieces: list = field(default_factory=list)       #: segments printed
    park: Optional[tuple] = None                     #: then go to this park position (mm; A7)
    #: lift the nozzle straight up to this height (mm) before the park's A7 (default: 10 mm up);
    #: without a park: retract and lift to it, and stay there
    lift_to: Optional[float] = None
    report: Optional[int] = None                     #: then report (A3) to this robot id (None: no report)
    mark: object = None                              #: then name the line reached (for other arms' waits)


def cut_segment(seg, cuts):
    """``seg`` cut at the fractions ``cuts`` (0 < u < 1) of its length; E is
    shared in proportion to length."""
    if not cuts:
        return [seg]
    a, b = np.array(seg.start, dtype=float), np.array(seg.end, dtype=float)
    ts = [0.0] + sorted(set(cuts)) + [1.0]
    return [seg._replace(start=tuple(a + (b - a) * t0), end=tuple(a + (b - a) * t1), e=seg.e * (t1 - t0))
            for t0, t1 in zip(ts[:-1], ts[1:])]


def seg_time(segs):
    """Seconds of ``segs`` at their feedrates (E-only moves at their E speed)."""
    if not segs:
        return 0.0
    return float(sum(seg_times([s.start for s in segs], [s.end for s in segs], [s.e for s in segs],
                               [s.feedrate for s in segs]).tolist()))


def seg_times(starts, ends, e, feedrate):
    """Seconds (S,) of each segment, from its ends (S, 3) mm, E (S,) mm and
    feedrate (S,) mm/min, at its feedrate (1800 mm/min if none was set):
    its length, or |E| for an E-only move."""
    D = np.subtract(np.asarray(ends, dtype=float).reshape(-1, 3), np.asarray(starts, dtype=float).reshape(-1, 3))
    L = np.linalg.norm(D, axis=1)
    f = np.asarray(feedrate, dtype=float)
    return np.where(L > 0, L, np.abs(np.asarray(e, dtype=float))) / np.where(f > 0, f, 1800.0) * 60.0


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
    R = len(runs)
    # heads then tails; a run visited gets both ends at infinity (fewer numpy
    # calls per run than masking: the timeline orders many pieces)
    ends = np.array([r[0].start for r in runs] + [r[-1].end for r in runs], dtype=float)
    here = np.asarray(pos if pos is not None else runs[0][0].start, dtype=float)
    out = []
    for _ in range(R):
        d = ends - here
        d = np.sqrt(np.add.reduce(d * d, axis=1))      # np.linalg.norm(axis=1)'s arithmetic, without its overhead
        i, j = int(np.argmin(d[:R])), int(np.argmin(d[R:]))
        if d[R + j] < d[i] - 1e-9:
            out.extend(reversed_segments(runs[j]))
            here = ends[j].copy()
            ends[j] = ends[R + j] = np.inf
        else:
            out.extend(runs[i])
            here = ends[R + i].copy()
            ends[i] = ends[R + i] = np.inf
    return out


def reversed_segments(segs):
    """``segs`` walked the other way: each segment's start and end swapped,
    in reverse order (a Segment made as a tuple: ``_replace`` costs 2 us a
    segment, 0.13 s of a 300,000-triangle model's plan together)."""
    return [_new_segment(Segment, (s.end, s.start) + s[2:]) for s in reversed(segs)]


def first_start(segs):
    """Where :func:`_order_runs` of ``segs`` from nowhere (``pos`` None) starts:
    the start of the first extruding segment that moves (its first run goes
    first, as it is), or None if there is none."""
    return next((s.start for s in segs if s.extrude and s.start != s.end), None)
