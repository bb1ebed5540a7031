"""Streaming G-code reader: text in, typed toolpath events out.

Everything here is in **millimetres, the G-code frame** (mm/min for feedrates,
mm of filament for E); conversion to metres happens in :mod:`ambots.units`.

Usage::

    for ev in read_gcode("part.gcode"):
        if type(ev) is Segment: ...        # a straight piece of toolpath
        elif type(ev) is Command: ...      # pass-through (M104, T0, A1, G28...)
        elif type(ev) is Dwell: ...        # G4
        elif type(ev) is GCodeWarning: ... # something the user should know

    summary = summarize_file("part.gcode")  # what ``python -m ambots info`` prints

The reader is a generator: memory stays constant whatever the file length.

Dialect (Marlin-like; every choice below is deliberate and tested):

* One command per line: ``G``/``M``/``T`` (or an A-series ``A<n>``) word
  first, then parameter words.  Any case.  Spaces between words are
  optional (``G1X10Y5`` == ``G1 X10 Y5``) except before ``E``: ``X1E5`` is
  X1 E5 to firmware but 1e5 to a script, so it is rejected as ambiguous.
  Numbers are plain decimals: no exponent, no ``nan``/``inf``, no ``_``.
  Outside comments only printable ASCII and tabs.
* Comments: ``;`` to end of line and ``( ... )`` (not nested).
* ``N<n>`` line numbers and ``*<checksum>``: the checksum is the XOR of the
  characters before the ``*`` once comments and surrounding blanks are
  removed; a wrong one is a :class:`~ambots.errors.GCodeError`.  Line
  numbers need not be consecutive (a file, unlike a serial stream, has no
  resends).
* Interpreted: G0/G1 (X Y Z E F), G2/G3 (XY-plane arcs, I/J centre or R form,
  optional Z helix and E, cut into chords within ``arc_tolerance_mm``), G4
  (P ms or S s), G17, G20/G21, G28, G90/G91, G92, M82/M83.  G18/G19 (other
  arc planes) are rejected.  As in Marlin, G90/G91 also switch E;
  M82/M83 switch E alone.
* Everything else (M-codes, T-codes, unknown G-codes, A-series lines) is a
  :class:`Command` event, never motion; unknown G-codes and A-series lines
  also raise a :class:`GCodeWarning`.  Parameters of pass-through commands
  are not interpreted.  (Lines after an ``A5`` are read as ordinary G-code:
  a file is not a protocol stream; see :mod:`ambots.program`.)
* Rejected with :class:`~ambots.errors.GCodeError` (file, line, text):
  malformed words, unknown or repeated parameters of interpreted commands,
  NaN/inf, any interpreted value or resulting position beyond
  :data:`MAX_ABS_MM` (1e6 mm), feedrate <= 0, negative dwell, impossible arcs.
* Positions are *physical*: ``G92`` renames the current position (an offset
  applied to later absolute coordinates) but does not move the nozzle, so
  segments stay continuous -- the end of one is the start of the next.  The
  only exception is ``G28`` (homing, reported as a :class:`Command`), after
  which the homed axes are at 0 and their G92 offsets are cleared.  The
  position before the first move is the origin, E = 0.
* Layers: if the file has slicer layer comments (``;LAYER_CHANGE``
  PrusaSlicer/SuperSlicer/Orca, ``;LAYER:<n>`` Cura, ``; layer <n>``
  Simplify3D) each starts a new layer; otherwise a new layer starts with the
  first extruding move at a new Z.  Layer indices count from 0; -1 means
  "before the first layer".  On the first layer comment the reader switches
  to comments for good (if something was already extruded, e.g. a purge
  line, it stays a layer of its own).
"""
import math
import re
from typing import NamedTuple, Tuple

from ambots.errors import GCodeError

#: Largest magnitude (mm, mm/min, s, ...) accepted for any interpreted value
#: or resulting position; beyond it the file is considered broken.
MAX_ABS_MM = 1e6
#: Default largest distance (mm) between an arc and the chords replacing it.
DEFAULT_ARC_TOLERANCE_MM = 0.01
#: An arc is never cut into more chords than this; if the tolerance would
#: need more, the arc is cut into this many and a warning says so.
MAX_ARC_SEGMENTS = 2000
INCH_MM = 25.4

Point = Tuple[float, float, float]


class Segment(NamedTuple):
    """A straight piece of toolpath in the G-code frame.

    ``start``/``end``: (x, y, z) in mm.  ``e``: filament pushed during the
    segment in mm (< 0 for a retraction).  ``feedrate``: mm/min (0.0 if the
    file never set one).  ``extrude``: ``e > 0`` (otherwise a travel).
    ``line``: 1-based source line.  ``layer``: index from 0 (-1 before the
    first layer).  Every G0/G1 yields exactly one segment, possibly of zero
    length (``G1 F1800``, ``G1 E-2``); a G2/G3 yields one per chord.
    """
    start: Point
    end: Point
    e: float
    feedrate: float
    extrude: bool
    line: int
    layer: int


class Command(NamedTuple):
    """A command passed through unchanged: ``code`` canonical (``M104``,
    ``T0``, ``G29``, ``G28``, ``A5``), ``text`` the command as written
    (comments, line number and checksum removed), ``line`` 1-based,
    ``layer`` as for :class:`Segment`."""
    code: str
    text: str
    line: int
    layer: int


class Dwell(NamedTuple):
    """``G4``: wait ``seconds`` (s) at ``line``."""
    seconds: float
    line: int
    layer: int


class GCodeWarning(NamedTuple):
    """Something a user should know about ``line`` that is not an error."""
    line: int
    message: str


_new_segment = tuple.__new__       # Segment(...) without the Python-level __new__
_LINEAR_KEYS = frozenset("XYZEF")
_ARC_KEYS = frozenset("XYZEFIJR")
_G92_KEYS = frozenset("XYZE")
_NUM = r"[+-]?(?:\d+\.?\d*|\.\d+)"
_WORD_RE = re.compile(r"([A-Z])(%s)?" % _NUM)
_COMMAND_RE = re.compile(r"([GMTA])(\d+)(\.\d+)?")
_COMMAND_START_RE = re.compile(r"[ \t]*([A-Z])(\d+(?:\.\d+)?)")
_LINE_NUMBER_RE = re.compile(r"[Nn][+-]?\d+")
_Z_EPS = 1e-9
# whitespace and control characters, with every Unicode space: str.strip()
# (the reader's) removes those, so "\xa0A1 R2" is read as A1 and must count as one
_BLANKS = "".join(map(chr, range(33))) + "\x7f" + "".join(
    c for c in map(chr, range(0x80, 0x3001)) if c.isspace())
_command_cache = {}


def is_a_series(code):
    """True if the G-code text ``code`` (comments already removed, any case)
    starts with an A-series command word ``A<digits>``, even glued to its
    parameters (``A1R2``) or after a line number (``N5 A1 R2``).  Leading
    blanks, Unicode spaces and control characters are skipped (conservative:
    a firmware might skip them too)."""
    s = code.lstrip(_BLANKS)
    if s[:1] in ("N", "n"):
        m = _LINE_NUMBER_RE.match(s)
        if m:
            s = s[m.end():].lstrip(_BLANKS)
    return s[:1] in ("A", "a") and s[1:2].isdigit()


def is_a_series_line(raw):
    """True if the raw G-code line ``raw`` carries an A-series command, judged
    conservatively: with ``( )`` comments removed *or* kept (a firmware may not
    know them), ``;`` comment ignored.  Used by the program builder and by
    the A5 decoder to keep A-series commands out of G-code payloads."""
    head = raw.partition(";")[0]
    if is_a_series(head):
        return True
    try:
        return is_a_series(split_comment(raw)[0])
    except ValueError:
        return False


def split_comment(raw):
    """``raw`` line -> ``(code, comment)``: ``code`` is the text with the
    ``;`` comment and ``( ... )`` comments removed (not stripped),
    ``comment`` the text after ``;`` ('' if none).
    Raises ``ValueError`` (with the reason) on an unbalanced parenthesis."""
    if "(" not in raw and ")" not in raw:
        i = raw.find(";")
        return (raw, "") if i < 0 else (raw[:i], raw[i + 1:])
    out, depth = [], False
    for i, c in enumerate(raw):
        if depth:
            if c == ")":
                depth = False
            elif c == "(":
                raise ValueError("nested '(' in a comment")
        elif c == "(":
            depth = True
        elif c == ")":
            raise ValueError("')' without '('")
        elif c == ";":
            return "".join(out), raw[i + 1:]
        else:
            out.append(c)
    if depth:
        raise ValueError("unclosed '(' comment")
    return "".join(out), ""


def _canonical_command(word):
    """``'g01'`` -> ``'G1'``; None if ``word`` is not a command word."""
    code = _command_cache.get(word)
    if code is None:
        m = _COMMAND_RE.fullmatch(word)
        if not m or (m.group(3) and m.group(1) in "TA"):
            return None
        code = m.group(1) + str(int(m.group(2))) + (m.group(3) or "")
        if len(_command_cache) < 4096:
            _command_cache[word] = code
    return code


class _LineReader:
    """Rare-path helpers bound to one file (for error messages)."""

    def __init__(self, path):
        self.path = path

    def error(self, lineno, raw, message):
        return GCodeError(self.path, lineno, raw.rstrip("\r\n"), message)

    def clean(self, raw, lineno):
        """Slow path for a line with parentheses, ``N`` or ``*``, tabs or
        anything unusual: returns the bare command text (may be empty)."""
        try:
            code, _ = split_comment(raw)
        except ValueError as exc:
            raise self.error(lineno, raw, str(exc))
        code = code.strip(" \t\r\n")
        for c in code:
            if not (" " <= c <= "~" or c == "\t"):
                what = "non-ASCII" if ord(c) > 127 else "control"
                raise self.error(lineno, raw, "%s character %r outside a comment" % (what, c))
        if "*" in code:
            body, _, digits = code.partition("*")
            digits = digits.strip(" \t")
            if not digits.isdigit():
                raise self.error(lineno, raw, "checksum after '*' must be digits")
            expected = 0
            for c in body:
                expected ^= ord(c)
            if int(digits) != expected:
                raise self.error(lineno, raw, "wrong checksum *%s (computed %d)" % (digits, expected))
            code = body.strip(" \t")
        if code[:1] in ("N", "n"):
            m = _LINE_NUMBER_RE.match(code)
            if not m:
                raise self.error(lineno, raw, "'N' must be followed by a line number")
            code = code[m.end():].strip(" \t")
        return code

    def command(self, ucode, raw, lineno):
        """Command word of an upper-cased line whose first word is glued to
        its parameters or malformed -> (code, rest of the text)."""
        m = _COMMAND_START_RE.match(ucode)
        code = m and _canonical_command(m.group(1) + m.group(2))
        if not code:
            first = ucode.split()[0]
            raise self.error(lineno, raw, "line must start with a G, M, T or A command, not %r" % first)
        return code, ucode[m.end():]

    def params(self, rest, keys, raw, lineno, cmd, need_values=True):
        """Strict tokenizer for the parameters of an interpreted command:
        ``{letter: value (float, or None if allowed)}``."""
        params, pos, n = {}, 0, len(rest)
        while pos < n:
            if rest[pos] in " \t":
                pos += 1
                continue
            m = _WORD_RE.match(rest, pos)
            if not m:
                raise self.error(lineno, raw, "%s: unexpected %r at column %d"
                                 % (cmd, rest[pos:pos + 12], pos + 1))
            letter, text = m.group(1), m.group(2)
            pos = m.end()
            if letter not in keys:
                raise self.error(lineno, raw, "%s does not take parameter %s" % (cmd, letter))
            if letter in params:
                raise self.error(lineno, raw, "%s: parameter %s given twice" % (cmd, letter))
            if text is None:
                if rest[pos:pos + 3] in ("NAN", "INF") or rest[pos:pos + 4] in ("-NAN", "-INF", "+INF"):
                    raise self.error(lineno, raw, "%s: %s is not finite" % (cmd, letter))
                if need_values:
                    raise self.error(lineno, raw, "%s: parameter %s has no value" % (cmd, letter))
                params[letter] = None
                continue
            if rest[pos:pos + 1] == "E":
                raise self.error(lineno, raw, "%s: ambiguous %r: exponents are not G-code and "
                                 "an E word needs a space before it" % (cmd, rest[m.start():pos + 4]))
            value = float(text)
            if not -MAX_ABS_MM <= value <= MAX_ABS_MM:
                raise self.error(lineno, raw, "%s: %s%s is beyond %g" % (cmd, letter, text, MAX_ABS_MM))
            params[letter] = value
        return params

    def strict_params(self, ucode, keys, raw, lineno, cmd):
        """Parameters of an upper-cased line the fast path could not read
        (glued words, exponents, bad values...): exact result or exact error."""
        return self.params(self.command(ucode, raw, lineno)[1], keys, raw, lineno, cmd)


def _arc_centre(x0, y0, x1, y1, p, clockwise, err):
    """Centre (cx, cy) of an XY arc from ``p`` (I/J or R), all in mm."""
    if "R" in p:
        if "I" in p or "J" in p:
            raise err("give either R or I/J, not both")
        r = p["R"]
        dx, dy = x1 - x0, y1 - y0
        d = math.hypot(dx, dy)
        if d < 1e-9:
            raise err("an R-form arc cannot end where it starts (use I/J for a full circle)")
        if r == 0 or d > 2 * abs(r) * (1 + 1e-9):
            raise err("radius R%g is too small for a chord of %g mm" % (r, d))
        h = math.sqrt(max(r * r - d * d / 4, 0.0))
        side = -1.0 if clockwise != (r < 0) else 1.0
        return (x0 + x1) / 2 - side * h * dy / d, (y0 + y1) / 2 + side * h * dx / d
    if "I" not in p and "J" not in p:
        raise err("an arc needs I/J (centre offset) or R (radius)")
    return x0 + p.get("I", 0.0), y0 + p.get("J", 0.0)


def arc_points(start, end, centre, clockwise, tolerance):
    """Cut an XY arc (Z moving linearly: helix) into chords.

    ``start``/``end``: (x, y, z) mm; ``centre``: (cx, cy) mm.  End == start
    means a full circle.  If the end radius differs slightly from the start
    radius the radius changes linearly (a spiral), so the last point is
    exactly ``end``.  Returns ``(points, capped)``: the chord end points
    (list of (x, y, z, fraction of the sweep), the last one ``end``), and
    whether :data:`MAX_ARC_SEGMENTS` limited the count.
    """
    (x0, y0, z0), (x1, y1, z1), (cx, cy) = start, end, centre
    r0, r1 = math.hypot(x0 - cx, y0 - cy), math.hypot(x1 - cx, y1 - cy)
    a0 = math.atan2(y0 - cy, x0 - cx)
    if abs(x1 - x0) < 1e-9 and abs(y1 - y0) < 1e-9:
        sweep = -2 * math.pi if clockwise else 2 * math.pi    # full circle, either way round
    else:
        sweep = (math.atan2(y1 - cy, x1 - cx) - a0) % (2 * math.pi)
        if clockwise:
            sweep -= 2 * math.pi
    r = max(r0, r1)
    step = 2 * math.acos(1 - tolerance / r) if tolerance < r else math.pi
    n = max(math.ceil(abs(sweep) / min(step, math.pi / 2) - 1e-9), 1)
    capped = n > MAX_ARC_SEGMENTS
    n = min(n, MAX_ARC_SEGMENTS)
    points = []
    for k in range(1, n):
        t = k / n
        a, rr = a0 + sweep * t, r0 + (r1 - r0) * t
        points.append((cx + rr * math.cos(a), cy + rr * math.sin(a), z0 + (z1 - z0) * t, t))
    points.append((x1, y1, z1, 1.0))
    return points, capped


def _layer_marker(comment):
    """True if a comment (text after ``;``) marks a slicer layer change."""
    c = comment.lstrip(" \t")[:13].upper()
    return c.startswith(("LAYER_CHANGE", "LAYER:")) or (c.startswith("LAYER ") and c[6:7].isdigit())


def read_gcode(path, arc_tolerance_mm=DEFAULT_ARC_TOLERANCE_MM):
    """Stream the events of the G-code file ``path`` (see :func:`iter_gcode`).
    A file that cannot be opened is a :class:`~ambots.errors.GCodeError` at
    line 0.  Bytes that are not UTF-8 become U+FFFD (harmless in comments,
    an error elsewhere)."""
    try:
        f = open(path, "r", encoding="utf-8", errors="replace")
    except OSError as exc:
        raise GCodeError(str(path), 0, "", "cannot open: %s" % (exc.strerror or exc))
    with f:
        yield from iter_gcode(f, str(path), arc_tolerance_mm)


def parse_gcode_text(text, path="<string>", arc_tolerance_mm=DEFAULT_ARC_TOLERANCE_MM):
    """Events of G-code given as one string (tests, small programs)."""
    return iter_gcode(text.splitlines(), path, arc_tolerance_mm)


def iter_gcode(lines, path="<string>", arc_tolerance_mm=DEFAULT_ARC_TOLERANCE_MM):
    """Generator of :class:`Segment`, :class:`Command`, :class:`Dwell` and
    :class:`GCodeWarning` events from an iterable of text lines.

    ``path`` only names the source in errors.  ``arc_tolerance_mm`` (> 0) is
    the largest chord-to-arc distance.  Raises
    :class:`~ambots.errors.GCodeError` (path, line, text, reason) at the
    first bad line; events before it have already been yielded.
    """
    if not arc_tolerance_mm > 0:
        raise ValueError("arc_tolerance_mm must be > 0")
    lr = _LineReader(path)
    lim = MAX_ABS_MM
    x = y = z = e = 0.0              # physical position (mm) and filament (mm)
    ox = oy = oz = oe = 0.0          # G92 offsets: coordinate = physical + offset
    rel_xyz = rel_e = False          # G91 / M83
    scale = 1.0                      # 25.4 after G20
    feed = 0.0                       # mm/min; 0 = not set yet
    layer, layer_z, markers = -1, -math.inf, False
    warned_no_feed = False
    lineno = 0
    for raw in lines:
        lineno += 1
        i = raw.find(";")
        if i >= 0:
            code = raw[:i].strip()
            if not code:
                if _layer_marker(raw[i + 1:]):
                    layer += 1           # -1 -> 0, or after Z-detected layers (purge line) +1
                    markers = True
                continue
        else:
            code = raw.strip()
            if not code:
                continue
        if not (code.isascii() and code.isprintable()) or "(" in code or ")" in code \
                or "*" in code or code[0] in "Nn":
            code = lr.clean(raw, lineno)
            if not code:
                continue
        ucode = code.upper()
        words = ucode.split()
        cmd = _command_cache.get(words[0]) or _canonical_command(words[0])
        if cmd is None:                               # glued (G1X5) or not a command
            cmd, rest = lr.command(ucode, raw, lineno)
            words = [cmd] + rest.split()              # params re-tokenized strictly below

        if cmd == "G1" or cmd == "G0":                 # --- hot path -------------
            p = {}
            try:
                for w in words[1:]:
                    v = float(w[1:])
                    if not -lim <= v <= lim:
                        raise ValueError
                    p[w[0]] = v
            except ValueError:
                p = None
            if (p is None or len(p) != len(words) - 1 or not p.keys() <= _LINEAR_KEYS
                    or ("E" in p) != ucode.count("E") or "_" in ucode):
                p = lr.strict_params(ucode, _LINEAR_KEYS, raw, lineno, cmd)
            nx, ny, nz, ne = x, y, z, e
            if p:
                v = p.get("X")
                if v is not None:
                    nx = x + v * scale if rel_xyz else v * scale - ox
                v = p.get("Y")
                if v is not None:
                    ny = y + v * scale if rel_xyz else v * scale - oy
                v = p.get("Z")
                if v is not None:
                    nz = z + v * scale if rel_xyz else v * scale - oz
                v = p.get("E")
                if v is not None:
                    ne = e + v * scale if rel_e else v * scale - oe
                v = p.get("F")
                if v is not None:
                    if v <= 0:
                        raise lr.error(lineno, raw, "feedrate F must be > 0")
                    feed = v * scale
                if not (-lim <= nx <= lim and -lim <= ny <= lim and -lim <= nz <= lim):
                    raise lr.error(lineno, raw, "position beyond %g mm" % lim)
            de = ne - e
            if de > 0.0 and not markers and (nx != x or ny != y) and abs(nz - layer_z) > _Z_EPS:
                layer += 1
                layer_z = nz
            if feed == 0.0 and not warned_no_feed and (nx != x or ny != y or nz != z or de):
                warned_no_feed = True
                yield GCodeWarning(lineno, "move before any feedrate F; its time is not counted")
            yield _new_segment(Segment, ((x, y, z), (nx, ny, nz), de, feed, de > 0.0, lineno, layer))
            x, y, z, e = nx, ny, nz, ne
            continue

        # --- rare path: everything but G0/G1 ---------------------------------
        rest = " ".join(words[1:])

        def err(message, _lineno=lineno, _raw=raw):
            return lr.error(_lineno, _raw, message)

        if cmd == "G2" or cmd == "G3":
            p = lr.params(rest, _ARC_KEYS, raw, lineno, cmd)
            for k in p:
                p[k] *= scale
            nx = x if "X" not in p else x + p["X"] if rel_xyz else p["X"] - ox
            ny = y if "Y" not in p else y + p["Y"] if rel_xyz else p["Y"] - oy
            nz = z if "Z" not in p else z + p["Z"] if rel_xyz else p["Z"] - oz
            ne = e if "E" not in p else e + p["E"] if rel_e else p["E"] - oe
            if "F" in p:
                if p["F"] <= 0:
                    raise err("feedrate F must be > 0")
                feed = p["F"]
            if not (-lim <= nx <= lim and -lim <= ny <= lim and -lim <= nz <= lim):
                raise err("position beyond %g mm" % lim)
            cx, cy = _arc_centre(x, y, nx, ny, p, cmd == "G2", err)
            r0, r1 = math.hypot(x - cx, y - cy), math.hypot(nx - cx, ny - cy)
            if r0 < 1e-9:
                raise err("arc radius is zero")
            if abs(r1 - r0) > 0.05 + 1e-3 * r0:
                raise err("arc end is not on the circle (start radius %.4f, end radius %.4f)" % (r0, r1))
            pts, capped = arc_points((x, y, z), (nx, ny, nz), (cx, cy), cmd == "G2", arc_tolerance_mm)
            if any(not (-lim <= q[0] <= lim and -lim <= q[1] <= lim) for q in pts):
                raise err("arc leaves the +-%g mm range" % lim)
            if capped:
                yield GCodeWarning(lineno, "arc cut into %d chords, coarser than the %g mm tolerance"
                                   % (MAX_ARC_SEGMENTS, arc_tolerance_mm))
            de_total = ne - e
            if de_total > 0.0 and not markers and abs(nz - layer_z) > _Z_EPS:
                layer += 1
                layer_z = nz
            if feed == 0.0 and not warned_no_feed:
                warned_no_feed = True
                yield GCodeWarning(lineno, "move before any feedrate F; its time is not counted")
            px, py, pz, done = x, y, z, 0.0
            for qx, qy, qz, t in pts:
                de = de_total * t - done
                done += de
                yield _new_segment(Segment, ((px, py, pz), (qx, qy, qz), de, feed, de_total > 0.0,
                                             lineno, layer))
                px, py, pz = qx, qy, qz
            x, y, z, e = nx, ny, nz, ne
        elif cmd == "G92":
            p = lr.params(rest, _G92_KEYS, raw, lineno, cmd)
            if not p:
                yield GCodeWarning(lineno, "G92 without axes is firmware-dependent; ignored")
            if "X" in p:
                ox = p["X"] * scale - x
            if "Y" in p:
                oy = p["Y"] * scale - y
            if "Z" in p:
                oz = p["Z"] * scale - z
            if "E" in p:
                oe = p["E"] * scale - e
        elif cmd == "M83" or cmd == "M82":
            lr.params(rest, (), raw, lineno, cmd)
            rel_e = cmd == "M83"
        elif cmd == "G91" or cmd == "G90":
            lr.params(rest, (), raw, lineno, cmd)
            rel_xyz = rel_e = cmd == "G91"
        elif cmd == "G21" or cmd == "G20":
            lr.params(rest, (), raw, lineno, cmd)
            scale = INCH_MM if cmd == "G20" else 1.0
        elif cmd == "G4":
            p = lr.params(rest, "PS", raw, lineno, cmd)
            if len(p) > 1:
                raise err("G4 takes P (ms) or S (s), not both")
            seconds = p["S"] if "S" in p else p.get("P", 0.0) / 1000.0
            if seconds < 0:
                raise err("negative dwell")
            yield Dwell(seconds, lineno, layer)
        elif cmd == "G28":
            axes = lr.params(rest, "XYZWORL", raw, lineno, cmd, need_values=False).keys() & set("XYZ")
            for a in axes or "XYZ":
                if a == "X":
                    x = ox = 0.0
                elif a == "Y":
                    y = oy = 0.0
                else:
                    z = oz = 0.0
            yield Command(cmd, code, lineno, layer)
        elif cmd == "G17":
            lr.params(rest, (), raw, lineno, cmd)
        elif cmd == "G18" or cmd == "G19":
            raise err("only XY-plane arcs (G17) are supported")
        else:
            if cmd[0] == "A":
                yield GCodeWarning(lineno, "A-series command %s in G-code; the program builder strips "
                                           "it unless the file is trusted" % cmd)
            elif cmd[0] == "G":
                yield GCodeWarning(lineno, "%s is not interpreted (passed through, not part of the "
                                           "toolpath)" % cmd)
            yield Command(cmd, code, lineno, layer)


def summarize(events, max_warnings=100):
    """Totals of an event stream (what ``ambots info --json`` prints).

    Returns a dict: ``moves`` (G0/G1/G2/G3 commands), ``segments``,
    ``extruded_filament_mm`` (net: sum of E, retractions subtracted),
    ``retracted_at_end_mm`` (filament still retracted at the end; PrusaSlicer's
    "filament used" = net + this), ``extrude_path_mm``/``travel_path_mm``
    (nozzle path of segments with E > 0 / E <= 0), ``layers`` (layers that
    extrude), ``bbox_mm`` ([[xmin, ymin, zmin], [xmax, ymax, zmax]] of
    extruding segments that move, or None), ``print_time_s`` (length /
    feedrate, E-only moves at their E speed, plus dwells; no acceleration),
    ``commands`` (pass-through commands), ``a_commands`` (A-series lines),
    ``warnings`` (list of {line, message}, at most ``max_warnings`` plus one
    saying how many were left out).
    """
    dist = math.dist
    moves = segments = a_commands = commands = n_warn = 0
    last_line = -1
    filament = extrude_len = travel_len = time_s = retracted = 0.0
    inf = math.inf
    xmin = ymin = zmin = inf
    xmax = ymax = zmax = -inf
    layers = set()
    warnings = []
    for ev in events:
        t = type(ev)
        if t is Segment:
            start, end, de, feed, extrude, line, layer = ev
            segments += 1
            if line != last_line:
                moves += 1
                last_line = line
            length = dist(start, end)
            if de:
                filament += de
                retracted = retracted - de if de < 0 else max(retracted - de, 0.0)
            if feed > 0.0:
                time_s += (length or abs(de)) * 60.0 / feed
            if extrude:
                extrude_len += length
                if length > 0.0:
                    layers.add(layer)
                    for px, py, pz in (start, end):
                        if px < xmin: xmin = px
                        if px > xmax: xmax = px
                        if py < ymin: ymin = py
                        if py > ymax: ymax = py
                        if pz < zmin: zmin = pz
                        if pz > zmax: zmax = pz
            else:
                travel_len += length
        elif t is Command:
            commands += 1
            if ev.code[0] == "A":
                a_commands += 1
        elif t is Dwell:
            time_s += ev.seconds
        elif t is GCodeWarning:
            n_warn += 1
            if n_warn <= max_warnings:
                warnings.append({"line": ev.line, "message": ev.message})
    if n_warn > max_warnings:
        warnings.append({"line": None, "message": "%d more warnings not listed" % (n_warn - max_warnings)})
    bbox = None if xmin == inf else [[xmin, ymin, zmin], [xmax, ymax, zmax]]
    return {
        "moves": moves, "segments": segments,
        "extruded_filament_mm": filament, "retracted_at_end_mm": retracted,
        "extrude_path_mm": extrude_len, "travel_path_mm": travel_len,
        "layers": len(layers), "bbox_mm": bbox, "print_time_s": time_s,
        "commands": commands, "a_commands": a_commands, "warnings": warnings,
    }


def summarize_file(path, arc_tolerance_mm=DEFAULT_ARC_TOLERANCE_MM):
    """:func:`summarize` of the file ``path`` (plus ``"file": path``)."""
    summary = {"file": str(path)}
    summary.update(summarize(read_gcode(path, arc_tolerance_mm)))
    return summary
