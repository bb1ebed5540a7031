"""Per-arm program builder: the safety gate between user G-code and arms.

G-code from a user or a slicer must never carry an A-series command (start,
move, load chunk... see :mod:`ambots.protocol`) into an arm, by accident or
on purpose.  :func:`sanitize_gcode` strips or rejects such lines unless the
caller explicitly trusts the file, and says which lines it removed.
"""
from typing import Iterable, List, Tuple, Union

from ambots.errors import GCodeError
from ambots.gcode import is_a_series_line

MODES = ("strip", "reject")


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
            if is_a_series_line(line):
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
