"""Per-arm programs: the safety gate between user G-code and arms, and the
directive lines that carry coordination inside a program.

G-code from a user or a slicer must never carry an A-series command (start,
move, load chunk... see :mod:`ambots.protocol`) into an arm, by accident or
on purpose.  :func:`sanitize_gcode` strips or rejects such lines unless the
caller explicitly trusts the file, and says which lines it removed.

Coordination that must happen at an exact point of an arm's program (wait
at a barrier, park an arm, start the next arm) is written by the program
builder as a *directive*: an A-series message in a comment that starts with
``;@`` (``;@A9 R1 W2 N120``).  To any other G-code reader it is a comment;
an ambots firmware executes it when it reaches that line of a chunk it was
given by A5.  Directives are ours only: the sanitiser strips them from
untrusted G-code like bare A-series lines.
"""
from typing import Iterable, List, Tuple, Union

from ambots.errors import GCodeError, ProtocolError
from ambots.gcode import is_a_series_line

MODES = ("strip", "reject")
#: prefix of a directive line
DIRECTIVE = ";@"


def directive(message):
    """A protocol message -> its directive line (``;@A9 R1 W2 N120``)."""
    from ambots.protocol import encode
    text = encode(message)
    if "\n" in text:
        raise ProtocolError(text, "a directive is one line (A5 cannot be a directive)")
    return DIRECTIVE + text


def is_directive(line):
    """True if ``line`` (one line of G-code) is a directive line."""
    return line.lstrip(" \t").startswith(DIRECTIVE)


def parse_directive(line, path="<string>", lineno=0):
    """A directive line -> its protocol message; a malformed one raises
    :class:`~ambots.errors.GCodeError` naming ``path`` and ``lineno``."""
    from ambots.protocol import decode
    body = line.lstrip(" \t")[len(DIRECTIVE):].rstrip("\r")
    try:
        return decode(body)
    except ProtocolError as exc:
        raise GCodeError(path, lineno, line, "bad directive: %s" % exc.message)


#: a line that starts with one of these (no blank before) is neither an
#: A-series line nor a directive: its first command word is G or M (most of
#: a slicer's lines, skipped without the full check)
_SAFE_FIRST = frozenset("GM")


def _unsafe(line):
    if line[:1] in _SAFE_FIRST:
        return False
    return is_a_series_line(line) or is_directive(line)


def sanitize_gcode(lines_or_text: Union[str, Iterable[str]], path="<string>", trusted=False,
                   mode="strip") -> Tuple[str, List[Tuple[int, str]]]:
    """Remove A-series lines from G-code.

    ``lines_or_text``: the G-code as one string or as an iterable of lines.
    Lines are split with :meth:`str.splitlines` (every line break Python
    knows, so a lone CR cannot hide a command) and re-joined with LF; a
    trailing line break is kept.  A line is an A-series line if its first
    command word, after blanks, an ``N`` line number and ``( )`` comments
    (with or without them), is ``A<digits>``, any case (see
    :func:`ambots.gcode.is_a_series_line`).

    ``trusted=True`` keeps every line (for the hub's own programs).
    ``mode="strip"`` removes the lines; ``mode="reject"`` raises
    :class:`~ambots.errors.GCodeError` naming the first one and listing all.

    Returns ``(clean_text, removed)``, ``removed`` a list of
    ``(line number 1-based, line text)``.
    """
    if mode not in MODES:
        raise ValueError("mode must be one of %s, not %r" % (MODES, mode))
    if isinstance(lines_or_text, str):
        text = lines_or_text
    else:
        text = "\n".join(line.rstrip("\r\n") for line in lines_or_text)
    lines = text.splitlines()
    if trusted:
        kept, removed = lines, []
    else:
        kept, removed = [], []
        for number, line in enumerate(lines, 1):
            if _unsafe(line):
                removed.append((number, line))
            else:
                kept.append(line)
    if removed and mode == "reject":
        number, line = removed[0]
        raise GCodeError(path, number, line, "A-series command in untrusted G-code (%d such line(s): %s)"
                         % (len(removed), ", ".join(str(n) for n, _ in removed[:20])))
    clean = "\n".join(kept)
    if kept and text[-1:] in ("\n", "\r"):
        clean += "\n"
    return clean, removed
