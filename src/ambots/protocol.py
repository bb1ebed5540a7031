"""The A-series protocol: the messages between the hub and the arms.

A1..A7 are the commands of the original design and their strings stay valid
exactly as they were (``A1 R0``, ``A7 R1 X100 Y50 Z10``, ``A5 R0\\n<G-code>``;
the default cell keeps the original's ids, Kinova 0 and UR10 1).
A8..A11 and the optional words below are what reliable cooperation adds;
A12 is the operator's stop.
One message = one dataclass (``Start``, ``LoadChunk``...);
:func:`encode` / :func:`decode` convert between them and text, and
``decode(encode(m)) == m`` for every valid message ``m``.

Grammar (case-insensitive letters; words separated by one or more spaces, in
any order on decode, in the canonical order below on encode)::

    message = header [ LF payload ]          ; payload: A5 only (a trailing LF
                                             ; alone is allowed on the others)
    header  = "A" code *( SP word ) [ SP text ]      ; text: A11 only, last
    word    = letter value                   ; each letter at most once
    int     = 1*10 DIGIT                     ; ranges per letter, see below
    num     = ["+" / "-"] (1*DIGIT ["." *DIGIT] / "." 1*DIGIT)   ; no exponent
    text    = a JSON string literal in ASCII (json.dumps(s, ensure_ascii=True))

The header is printable ASCII only; the payload is ASCII (printable, tab,
LF).  A message therefore never spans more lines than its payload, and a
text field can never smuggle a newline or a second command in.

====  ===============================  ==============================================
code  words (``[]`` = optional)          meaning
====  ===============================  ==============================================
A1    R [C]                            start arm R; with C, start chunk C once:
                                       refused (A11) if another chunk is loaded,
                                       ignored once chunk C has started (so it may
                                       be sent again); without C a DONE arm runs
                                       its chunk again from the top
A2    R                                pause arm R
A3    R                                send this arm's current position to arm R
                                       (the reply is an A10 with X Y Z; from an
                                       arm, the hub returns it to that arm)
A4    R                                clear arm R's chunk
A5    R [C L K] LF payload             load the G-code payload into arm R; C chunk
                                       id, L payload length (bytes), K CRC-32 of
                                       the payload (decimal).  L/K are checked when
                                       present (always written by :func:`encode`);
                                       a payload line that is an A-series command
                                       is rejected.  Chunk identity = (C, K).
A6    R                                resume arm R
A7    R X Y Z                          move arm R to (X, Y, Z), mm
A8    R Q                              acknowledge message Q of node R
A9    R W (L | N)                      arm R waits until arm W reports (A10) layer
                                       >= L, or line >= N, or state DONE
A10   R T L N P [X Y Z] [M]            status of arm R: state T (:class:`ArmState`),
                                       current layer L (0-based), last completed
                                       G-code line N (0 = none), percent done P,
                                       position X Y Z (mm, all three or none), M the
                                       arm's (simulated) clock in s when it made
                                       the report (barriers release at that time)
A11   R N "text"                       arm R reports an error at G-code line N
                                       (0 = not tied to a line); text <= 512 chars
A12   R                                stop arm R at once (brake), resumable by A6
====  ===============================  ==============================================

Any command may also carry the header words ``S<sender>``, ``Q<seq>`` and ``B<seq>``
(A8 uses Q for the acknowledged number and is never itself acknowledged).
Reliable delivery: a sender numbers its messages with Q (0..2**32-1,
increasing, wrapping); a receiver answers every message that has a Q with
``A8 R<sender> Q<seq>`` -- also for a duplicate -- and executes a given
(sender, Q) at most once; the sender retries until acknowledged.  A corrupt
message (e.g. an A5 whose K does not match) is not acknowledged, so it is
retried.  Order: a numbered message may also carry ``B<seq>``, the Q of the
sender's previous message to the same destination if that one is not yet
acknowledged; the receiver holds the message (no A8) until it has executed
(sender, B), so each sender's commands take effect in the order sent even
when the network reorders them (an A1 can never overtake its A5).

Ranges: robot ids (R except in A8, W) are 0..999 (:data:`MAX_ROBOT`); node ids (S, and R in
A8) are 0..2**31-1: the robots, 1000 the front end (:data:`FRONT_END`), 1001 the hub (:data:`HUB`); Q, B, C, K 0..2**32-1;
L, N 0..2**31-1; X Y Z |v| <= 1e6 mm; P 0..100; M 0..1e10 s (ROS time: a simulated clock from 0, or Unix time).
"""
import json
import re
import zlib
from dataclasses import dataclass, fields
from decimal import Decimal
from enum import IntEnum
from typing import ClassVar, Optional, Tuple

from ambots.errors import ProtocolError
from ambots.gcode import MAX_ABS_MM, is_a_series_line

MAX_ROBOT = 999          #: robot ids are 0..999 (the cell's ``id``; the original's Kinova 0, UR10 1)
FRONT_END = 1000         #: node id of the front end
HUB = 1001               #: node id of the hub
MAX_ID = 2 ** 31 - 1
MAX_U32 = 2 ** 32 - 1
MAX_TEXT = 512           #: longest A11 message text (characters)


class ArmState(IntEnum):
    """State of an arm in an A10 status report (``T`` word)."""
    IDLE = 0
    PRINTING = 1
    PAUSED = 2
    WAITING = 3          # in an A9 barrier
    DONE = 4
    ERROR = 5


# --- value kinds: parse text, format value, check range ---------------------

_INT_RE = re.compile(r"\d{1,10}")
_NUM_RE = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)")
_CODE_RE = re.compile(r"[Aa](\d{1,3})")


class _Int:
    def __init__(self, lo, hi, what):
        self.lo, self.hi, self.what = lo, hi, what

    def parse(self, text):
        if not _INT_RE.fullmatch(text):
            raise ValueError("expected %s, got %r" % (self.what, text))
        return self.check(int(text))

    def check(self, v):
        if isinstance(v, bool) or not isinstance(v, int) or not self.lo <= v <= self.hi:
            raise ValueError("expected %s, got %r" % (self.what, v))
        return v

    @staticmethod
    def format(v):
        return str(int(v))


class _Num:
    def __init__(self, lo, hi, what):
        self.lo, self.hi, self.what = lo, hi, what

    def parse(self, text):
        if not _NUM_RE.fullmatch(text):
            raise ValueError("expected %s (plain decimal), got %r" % (self.what, text))
        return self.check(float(text))

    def check(self, v):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not self.lo <= v <= self.hi:
            raise ValueError("expected %s, got %r" % (self.what, v))
        return v

    @staticmethod
    def format(v):
        """Shortest text that reads back as the same float, never exponent."""
        s = repr(float(v))
        if "e" in s:
            s = format(Decimal(s), "f")
        return s[:-2] if s.endswith(".0") else s


class _State(_Int):
    def parse(self, text):
        return ArmState(super().parse(text))

    def check(self, v):
        return ArmState(super().check(v))


_ROBOT = _Int(0, MAX_ROBOT, "a robot id 0..%d" % MAX_ROBOT)
_NODE = _Int(0, MAX_ID, "a node id 0..%d (robots 0..%d, front end %d, hub %d)" % (MAX_ID, MAX_ROBOT, FRONT_END, HUB))
_U32 = _Int(0, MAX_U32, "an integer 0..%d" % MAX_U32)
_COUNT = _Int(0, MAX_ID, "an integer 0..%d" % MAX_ID)
_MM = _Num(-MAX_ABS_MM, MAX_ABS_MM, "a coordinate within +-%g mm" % MAX_ABS_MM)
_PERCENT = _Num(0.0, 100.0, "a percentage 0..100")
_CLOCK = _Num(0.0, 1e10, "a time 0..1e10 s")       # ROS time: simulated from 0, or the wall (Unix time)
_STATE = _State(0, max(ArmState), "an arm state 0..%d" % max(ArmState))
_HEADER = (("S", "sender", _NODE), ("Q", "seq", _U32), ("B", "after", _U32))


class _Message:
    """Common behaviour; subclasses are frozen dataclasses with ``CODE`` and
    ``WORDS`` (letter, field, kind) in canonical order.  A field whose
    default is None is optional.  Invalid values raise ProtocolError."""
    CODE: ClassVar[int]
    WORDS: ClassVar[Tuple]

    def __post_init__(self):
        for letter, name, kind in self.WORDS:
            v = getattr(self, name)
            if v is None:
                if _required(type(self), name):
                    raise ProtocolError(repr(self), "A%d needs %s (%s)" % (self.CODE, letter, name))
                continue
            try:
                object.__setattr__(self, name, kind.check(v))
            except ValueError as exc:
                raise ProtocolError(repr(self), "A%d %s: %s" % (self.CODE, letter, exc))
        if getattr(self, "after", None) is not None and getattr(self, "seq", None) is None:
            raise ProtocolError(repr(self), "A%d: B (execute after) needs Q" % self.CODE)
        self._check()

    def _check(self):
        """Rules across fields (overridden where needed)."""


def _required(cls, name):
    return next(f for f in fields(cls) if f.name == name).default is not None


@dataclass(frozen=True)
class Start(_Message):
    """A1: start arm ``robot``.  With ``chunk_id`` (C) the start is of that
    chunk and happens once per load: the arm refuses it (A11) if another
    chunk is loaded and ignores it once that chunk has started, so a start
    may be sent again safely (by a front end that replaces a crashed one).
    Without C an arm that is DONE runs its chunk again from the top."""
    robot: int
    chunk_id: Optional[int] = None
    sender: Optional[int] = None
    seq: Optional[int] = None
    after: Optional[int] = None
    CODE: ClassVar[int] = 1
    WORDS: ClassVar[Tuple] = (("R", "robot", _ROBOT), ("C", "chunk_id", _U32)) + _HEADER


@dataclass(frozen=True)
class Pause(_Message):
    """A2: pause arm ``robot``."""
    robot: int
    sender: Optional[int] = None
    seq: Optional[int] = None
    after: Optional[int] = None
    CODE: ClassVar[int] = 2
    WORDS: ClassVar[Tuple] = (("R", "robot", _ROBOT),) + _HEADER


@dataclass(frozen=True)
class SendPosition(_Message):
    """A3: the receiving arm sends its current position (an A10 with X Y Z)
    to arm ``robot``."""
    robot: int
    sender: Optional[int] = None
    seq: Optional[int] = None
    after: Optional[int] = None
    CODE: ClassVar[int] = 3
    WORDS: ClassVar[Tuple] = (("R", "robot", _ROBOT),) + _HEADER


@dataclass(frozen=True)
class ClearChunk(_Message):
    """A4: clear arm ``robot``'s chunk."""
    robot: int
    sender: Optional[int] = None
    seq: Optional[int] = None
    after: Optional[int] = None
    CODE: ClassVar[int] = 4
    WORDS: ClassVar[Tuple] = (("R", "robot", _ROBOT),) + _HEADER


@dataclass(frozen=True)
class LoadChunk(_Message):
    """A5: load ``gcode`` (ASCII text, lines separated by LF, no A-series
    line) into arm ``robot`` as chunk ``chunk_id``.  The length (L) and
    CRC-32 (K) of the payload are derived, written by :func:`encode` and
    checked by :func:`decode`."""
    robot: int
    gcode: str
    chunk_id: Optional[int] = None
    sender: Optional[int] = None
    seq: Optional[int] = None
    after: Optional[int] = None
    CODE: ClassVar[int] = 5
    WORDS: ClassVar[Tuple] = (("R", "robot", _ROBOT), ("C", "chunk_id", _U32)) + _HEADER

    def _check(self):
        problem = _payload_problem(self.gcode)
        if problem:
            raise ProtocolError(repr(self), problem)

    @property
    def crc32(self):
        """CRC-32 of the payload bytes (the K word)."""
        return zlib.crc32(self.gcode.encode("ascii"))

    @property
    def identity(self):
        """(chunk id, CRC-32, length in bytes): what the firmware checkpoints;
        a chunk with the same identity is a duplicate."""
        return self.chunk_id, self.crc32, len(self.gcode)


@dataclass(frozen=True)
class Resume(_Message):
    """A6: resume arm ``robot``."""
    robot: int
    sender: Optional[int] = None
    seq: Optional[int] = None
    after: Optional[int] = None
    CODE: ClassVar[int] = 6
    WORDS: ClassVar[Tuple] = (("R", "robot", _ROBOT),) + _HEADER


@dataclass(frozen=True)
class MoveTo(_Message):
    """A7: move arm ``robot`` to (``x``, ``y``, ``z``) in mm."""
    robot: int
    x: float
    y: float
    z: float
    sender: Optional[int] = None
    seq: Optional[int] = None
    after: Optional[int] = None
    CODE: ClassVar[int] = 7
    WORDS: ClassVar[Tuple] = (("R", "robot", _ROBOT), ("X", "x", _MM), ("Y", "y", _MM),
                              ("Z", "z", _MM)) + _HEADER


@dataclass(frozen=True)
class Ack(_Message):
    """A8: ``sender`` acknowledges message ``acked_seq`` (its Q) of node
    ``robot`` (0 = the hub).  Never acknowledged itself."""
    robot: int
    acked_seq: int
    sender: Optional[int] = None
    CODE: ClassVar[int] = 8
    WORDS: ClassVar[Tuple] = (("R", "robot", _NODE), ("Q", "acked_seq", _U32),
                              ("S", "sender", _NODE))


@dataclass(frozen=True)
class WaitFor(_Message):
    """A9: arm ``robot`` waits until arm ``other`` reports (A10) ``layer``
    or more, or ``line`` or more (exactly one of the two), or DONE.  To wait
    until ``other`` has *finished* layer k, use ``layer=k + 1``."""
    robot: int
    other: int
    layer: Optional[int] = None
    line: Optional[int] = None
    sender: Optional[int] = None
    seq: Optional[int] = None
    after: Optional[int] = None
    CODE: ClassVar[int] = 9
    WORDS: ClassVar[Tuple] = (("R", "robot", _ROBOT), ("W", "other", _ROBOT),
                              ("L", "layer", _COUNT), ("N", "line", _COUNT)) + _HEADER

    def _check(self):
        if (self.layer is None) == (self.line is None):
            raise ProtocolError(repr(self), "A9 needs exactly one of L (layer) and N (line)")
        if self.other == self.robot:
            raise ProtocolError(repr(self), "A9: an arm cannot wait for itself")


@dataclass(frozen=True)
class Status(_Message):
    """A10: status of arm ``robot``: ``state``, current ``layer`` (0-based),
    last completed G-code ``line`` (0 = none), ``percent`` done (0..100),
    and optionally its position ``x``, ``y``, ``z`` (mm; all or none)."""
    robot: int
    state: ArmState
    layer: int
    line: int
    percent: float
    x: Optional[float] = None
    y: Optional[float] = None
    z: Optional[float] = None
    clock: Optional[float] = None
    sender: Optional[int] = None
    seq: Optional[int] = None
    after: Optional[int] = None
    CODE: ClassVar[int] = 10
    WORDS: ClassVar[Tuple] = (("R", "robot", _ROBOT), ("T", "state", _STATE),
                              ("L", "layer", _COUNT), ("N", "line", _COUNT),
                              ("P", "percent", _PERCENT), ("X", "x", _MM), ("Y", "y", _MM),
                              ("Z", "z", _MM), ("M", "clock", _CLOCK)) + _HEADER

    def _check(self):
        if len({self.x is None, self.y is None, self.z is None}) != 1:
            raise ProtocolError(repr(self), "A10 position needs all of X, Y, Z or none")

    @property
    def position(self):
        """(x, y, z) in mm, or None."""
        return None if self.x is None else (self.x, self.y, self.z)


@dataclass(frozen=True)
class ErrorReport(_Message):
    """A11: arm ``robot`` reports an error at G-code ``line`` (0 = none) with
    ``message`` (any text up to :data:`MAX_TEXT` characters; escaped on the
    wire as a JSON string)."""
    robot: int
    line: int
    message: str
    sender: Optional[int] = None
    seq: Optional[int] = None
    after: Optional[int] = None
    CODE: ClassVar[int] = 11
    WORDS: ClassVar[Tuple] = (("R", "robot", _ROBOT), ("N", "line", _COUNT)) + _HEADER

    def _check(self):
        if not isinstance(self.message, str) or len(self.message) > MAX_TEXT:
            raise ProtocolError(repr(self), "A11 message must be a str of at most %d characters"
                                % MAX_TEXT)


@dataclass(frozen=True)
class Stop(_Message):
    """A12: stop arm ``robot`` now -- an operator's stop: it brakes at once
    (the acceleration limits allow, along its path, to the first waypoint it
    can rest on; a pause, A2, goes on to the end of the G-code line) and is
    then PAUSED, so A6 resumes the job from there."""
    robot: int
    sender: Optional[int] = None
    seq: Optional[int] = None
    after: Optional[int] = None
    CODE: ClassVar[int] = 12
    WORDS: ClassVar[Tuple] = (("R", "robot", _ROBOT),) + _HEADER


COMMANDS = {cls.CODE: cls for cls in (Start, Pause, SendPosition, ClearChunk, LoadChunk, Resume,
                                      MoveTo, Ack, WaitFor, Status, ErrorReport, Stop)}


def _payload_problem(gcode):
    """Why ``gcode`` cannot be an A5 payload, or None."""
    if not isinstance(gcode, str):
        return "A5 payload must be a str"
    if not gcode.isascii():
        return "A5 payload must be ASCII"
    lines = gcode.split("\n")
    for i, line in enumerate(lines, 1):
        if not line.replace("\t", " ").isprintable():
            return "A5 payload line %d has a control character" % i
        if is_a_series_line(line):
            return "A5 payload line %d is an A-series command: %r" % (i, line)
    return None


def encode(cmd):
    """Message dataclass -> protocol text (see the module grammar)."""
    if not isinstance(cmd, _Message):
        raise ProtocolError(repr(cmd), "not an A-series message")
    def words(spec):
        return [letter + kind.format(getattr(cmd, name))
                for letter, name, kind in spec if getattr(cmd, name) is not None]

    parts = ["A%d" % cmd.CODE] + words(w for w in cmd.WORDS if w not in _HEADER)
    if isinstance(cmd, LoadChunk):
        parts += ["L%d" % len(cmd.gcode), "K%d" % cmd.crc32]
    parts += words(w for w in cmd.WORDS if w in _HEADER)
    if isinstance(cmd, LoadChunk):
        return " ".join(parts) + "\n" + cmd.gcode
    if isinstance(cmd, ErrorReport):
        parts.append(json.dumps(cmd.message, ensure_ascii=True))
    return " ".join(parts)


def printable(text):
    """``text`` with every character that is not printable (newlines,
    control characters, a lone surrogate that no UTF-8 publisher can send)
    written as its escape: one line, safe for a log or the error topic."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


def one_line(text, limit=200):
    """A message's text on one printable line, for logs (``debug:=true``):
    an A5's command line with its payload counted, ``A5 R0 C3 L21 K38 S1001 Q41
    (+2 G-code lines)``; anything else as is, escaped and cut to ``limit``
    characters.  Never raises (malformed text is logged too)."""
    if not isinstance(text, str):
        text = repr(text)
    header, newline, payload = text.partition("\n")
    extra = " (+%d G-code lines)" % len(payload.splitlines()) if newline and payload else ""
    shown = printable(header)
    if len(shown) > limit:
        shown = shown[:limit] + "..."
    return shown + extra


def decode(text):
    """Protocol text -> message dataclass.  Raises
    :class:`~ambots.errors.ProtocolError` saying what is wrong."""
    if not isinstance(text, str):
        raise ProtocolError(repr(text), "a message must be a str")

    def fail(message):
        return ProtocolError(text, message)

    header, newline, payload = text.partition("\n")
    if header.endswith("\r"):
        header = header[:-1]
    if not header.isascii() or not header.isprintable():
        raise fail("non-ASCII or control character in the command line")
    header, quote, quoted = header.partition('"')
    words = header.split()
    if not words:
        raise fail("empty message")
    m = _CODE_RE.fullmatch(words[0])
    if not m:
        raise fail("a message starts with A<code>, not %r" % words[0])
    code = int(m.group(1))
    cls = COMMANDS.get(code)
    if cls is None:
        raise fail("unknown command A%d (known: A1..A%d)" % (code, max(COMMANDS)))

    spec = {letter: (name, kind) for letter, name, kind in cls.WORDS}
    if cls is LoadChunk:
        spec["L"], spec["K"] = ("_length", _COUNT), ("_crc", _U32)
    values = {}
    for word in words[1:]:
        letter = word[0].upper()
        if letter not in spec:
            raise fail("A%d does not take %r" % (code, word))
        name, kind = spec[letter]
        if name in values:
            raise fail("A%d: %s given twice" % (code, letter))
        try:
            values[name] = kind.parse(word[1:])
        except ValueError as exc:
            raise fail("A%d %s: %s" % (code, letter, exc))

    if cls is ErrorReport:
        if not quote:
            raise fail('A11 needs a quoted message text ("...") at the end')
        try:
            values["message"] = json.loads(quote + quoted)
        except ValueError as exc:
            raise fail("A11 message is not a valid JSON string: %s" % exc)
        if not isinstance(values["message"], str):
            raise fail("A11 message is not a string")
    elif quote:
        raise fail("only A11 takes quoted text")

    if cls is LoadChunk:
        if not newline:
            raise fail("A5 must be followed by a newline and the G-code data")
        length, crc = values.pop("_length", None), values.pop("_crc", None)
        if length is not None and length != len(payload):
            raise fail("A5 payload is %d bytes, header says L%d" % (len(payload), length))
        problem = _payload_problem(payload)
        if problem:
            raise fail(problem)
        if crc is not None and crc != zlib.crc32(payload.encode("ascii")):
            raise fail("A5 payload CRC-32 does not match K%d (corrupt chunk)" % crc)
        values["gcode"] = payload
    elif payload:
        raise fail("A%d is one line; unexpected text after the newline" % code)

    missing = [letter for letter, (name, _) in spec.items()
               if name not in values and not name.startswith("_") and _required(cls, name)]
    if missing:
        raise fail("A%d needs %s" % (code, ", ".join(missing)))
    try:
        return cls(**values)
    except ProtocolError as exc:
        raise fail(exc.message)


def ack(cmd, sender=None):
    """The A8 acknowledging ``cmd`` (which must carry a Q), sent by ``sender``."""
    if getattr(cmd, "seq", None) is None:
        raise ProtocolError(repr(cmd), "only a message with a sequence number Q can be acknowledged")
    return Ack(cmd.sender if cmd.sender is not None else HUB, cmd.seq, sender)
