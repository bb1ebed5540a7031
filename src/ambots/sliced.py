"""The built-in slicer's G-code read as it is written.

:class:`MoveRecord` keeps, for every ``G1`` line the built-in slicer's
writer (:class:`ambots.slicer.GcodeWriter`) puts in its text, the line
number and the numbers as the text has them (each parsed back from its
formatted digits, so equal to what :func:`ambots.gcode.iter_gcode` reads),
and the line numbers of its ``;LAYER_CHANGE`` comments.  From these,
:meth:`MoveRecord.layers` gives the extrusion and travel segments by layer
exactly as :func:`ambots.coordinate.read_sliced` gets them by parsing the
text, in a few numpy calls instead of a parser step per line (1.9 s of a
300,000-triangle model's job, which reads its sliced G-code three times).

:class:`SlicedText` is the G-code text (a ``str``) carrying that reading;
:func:`ambots.coordinate.read_sliced` uses it instead of parsing.  The
reading is given up (None: the text is parsed) whenever the record and the
text might differ: a line count or a ``G1`` count that does not match the
text's, a number beyond the parser's limits, a feedrate that is not > 0, or
an extrusion before the first layer marker.  Tests compare the two
readings segment by segment."""
import numpy as np

from ambots.gcode import MAX_ABS_MM, Segment, _new_segment

__all__ = ["MoveRecord", "SlicedText"]

_NAN = float("nan")


class SlicedText(str):
    """G-code text with the writer's own reading of it: :attr:`layers`
    ({layer index (>= 0): [Segment]}, as :func:`ambots.coordinate.read_sliced`
    parses them) or None."""
    layers = None

    def __new__(cls, text, layers=None):
        obj = super().__new__(cls, text)
        obj.layers = layers
        return obj


class MoveRecord:
    """The ``G1`` lines and layer markers of a text being written, in order.

    :meth:`text` counts every chunk's lines; :meth:`move` records one
    ``G1`` line (its words as written: strings of digits); :meth:`block`
    records a run of ``G1 X.. Y.. E..`` lines formatted at once."""

    def __init__(self):
        self.lines = 0              #: lines written so far
        self.markers = []           #: line numbers of ;LAYER_CHANGE
        self.rows = []              #: [line, X, Y, Z, E, F] of single moves (NaN: word absent)
        self.blocks = []            #: (first line, number of lines) of each block
        self.chunks = []            #: the blocks' text
        self.moves = 0

    def text(self, chunk):
        """A chunk without moves (comments, header, commands)."""
        self.lines += chunk.count("\n")

    def marker(self):
        """The next line is a ``;LAYER_CHANGE`` comment."""
        self.markers.append(self.lines + 1)

    def move(self, x, y, z, e, f):
        """One ``G1`` line and its words as written (strings; None: absent), the next line."""
        self.lines += 1
        self.moves += 1
        self.rows.append((self.lines, _NAN if x is None else float(x), _NAN if y is None else float(y),
                          _NAN if z is None else float(z), _NAN if e is None else float(e),
                          _NAN if f is None else float(f)))

    def block(self, chunk, n):
        """``n`` lines ``G1 X.. Y.. E..`` written as ``chunk`` (read at the end, all at once)."""
        self.blocks.append((self.lines + 1, n))
        self.chunks.append(chunk)
        self.lines += n
        self.moves += n

    def _table(self):
        """(N, 6) [line, X, Y, Z, E, F] of every move, in line order."""
        single = np.array(self.rows, dtype=float).reshape(-1, 6)
        nums = np.array("".join(self.chunks).replace("G1 X", "").replace(" Y", " ").replace(" E", " ").split(),
                        dtype=float).reshape(-1, 3)
        run = np.full((len(nums), 6), np.nan)
        if self.blocks:
            first, n = np.array(self.blocks, dtype=np.int64).T
            run[:, 0] = np.repeat(first - np.cumsum(n) + n, n) + np.arange(len(nums))
        run[:, 1], run[:, 2], run[:, 4] = nums[:, 0], nums[:, 1], nums[:, 2]
        M = np.concatenate([single, run])
        return M[np.argsort(M[:, 0], kind="stable")]

    def layers(self, text):
        """{layer (>= 0): [Segment]} of ``text`` (the text written), or None."""
        if len(text.splitlines()) != self.lines:       # the parser's lines
            return None
        if text.count("\nG1 ") + text.startswith("G1 ") != self.moves:
            return None
        M = self._table()
        if not len(M) or len(np.unique(M[:, 0])) != len(M):
            return None if len(M) else {}
        vals = M[:, 1:]
        if (np.abs(vals[~np.isnan(vals)]) > MAX_ABS_MM).any():
            return None
        f = M[:, 5]
        if (f[~np.isnan(f)] <= 0).any():
            return None
        x, y, z, feed = (_filled(M[:, k], 0.0) for k in (1, 2, 3, 5))
        # relative E: the parser adds each E to its running total and takes
        # the difference, so do the same (sequentially, as np.cumsum does)
        e = np.cumsum(np.concatenate([[0.0], np.nan_to_num(M[:, 4], nan=0.0)]))
        de = e[1:] - e[:-1]
        lineno = M[:, 0].astype(np.int64)
        layer = np.searchsorted(np.asarray(self.markers, dtype=np.int64), lineno) - 1
        if ((de > 0.0) & (layer < 0)).any():          # the parser would find layers by Z there
            return None
        xl, yl, zl = x.tolist(), y.tolist(), z.tolist()
        starts = list(zip(xl[:-1], yl[:-1], zl[:-1]))
        ends = list(zip(xl[1:], yl[1:], zl[1:]))
        segs = [_new_segment(Segment, (s, t, d, fr, d > 0.0, ln, ly))
                for s, t, d, fr, ln, ly in zip(starts, ends, de.tolist(), feed[1:].tolist(), lineno.tolist(),
                                               layer.tolist())]
        key = np.maximum(layer, 0)                    # read_sliced's key: moves before the first layer in 0
        out = {}
        cuts = np.flatnonzero(np.diff(key)) + 1
        for a, b in zip([0] + cuts.tolist(), cuts.tolist() + [len(segs)]):
            out.setdefault(int(key[a]), []).extend(segs[a:b])
        return out


def _filled(col, first):
    """``col`` (N,) with each NaN replaced by the last value before it
    (``first`` before any): (N + 1,), ``first`` then the N values."""
    v = np.concatenate([[first], col])
    idx = np.where(np.isnan(v), 0, np.arange(len(v)))
    return v[np.maximum.accumulate(idx)]
