"""The program builder's safety gate (ambots.program.sanitize_gcode)."""
import random

import pytest

from ambots.errors import GCodeError
from ambots.gcode import Command, iter_gcode
from ambots.program import sanitize_gcode

UNTRUSTED = """G21
A1 R2
G1 X1 Y1 F600 ; A1 R2 in a comment is harmless
a7 r1 x100 y50 z10
  N5 A3 R1*99
(sneaky) A5 R1
A5R1
M117 A1 R2
G1 X2\rA2 R1
G1 X3
"""


def test_strip_removes_a_series_lines_and_says_which():
    clean, removed = sanitize_gcode(UNTRUSTED, "u.gcode")
    assert [n for n, _ in removed] == [2, 4, 5, 6, 7, 10]
    assert removed[-1] == (10, "A2 R1")              # the lone CR could not hide it
    assert clean == ("G21\nG1 X1 Y1 F600 ; A1 R2 in a comment is harmless\nM117 A1 R2\n"
                     "G1 X2\nG1 X3\n")


def test_reject_names_the_first_line_and_counts_all():
    with pytest.raises(GCodeError) as info:
        sanitize_gcode(UNTRUSTED, "u.gcode", mode="reject")
    exc = info.value
    assert (exc.path, exc.line, exc.text) == ("u.gcode", 2, "A1 R2")
    assert "6 such line(s): 2, 4, 5, 6, 7, 10" in exc.message


def test_trusted_keeps_everything_and_clean_files_pass_unchanged():
    clean, removed = sanitize_gcode(UNTRUSTED, trusted=True)
    assert removed == [] and clean.count("A") == UNTRUSTED.count("A")
    text = "G21\nG1 X1 F600\nM104 S200\n"
    assert sanitize_gcode(text) == (text, [])
    assert sanitize_gcode(text, mode="reject") == (text, [])
    assert sanitize_gcode(["G1 X1\n", "A1 R2\n", "G1 X2\n"]) == ("G1 X1\nG1 X2", [(2, "A1 R2")])
    with pytest.raises(ValueError):
        sanitize_gcode(text, mode="drop")


def test_sanitized_random_files_never_reach_the_reader_with_a_series():
    rng = random.Random(7)
    pieces = ["G1 X1 F600", "A1 R2", "a2r1", "N3 A4 R1", "(c)A6 R1", " \tA7 R1 X1 Y1 Z1", "M105",
              "; A1 R2", "\r", "\x0b", "\x1c", "\u2028", "\x85", "N", "(", ")", " ", "\x00"]
    n_removed = n_read = 0
    for _ in range(300):
        text = "".join(rng.choice(pieces) + rng.choice(["\n", "", " "]) for _ in range(12))
        clean, removed = sanitize_gcode(text)
        n_removed += len(removed)
        assert all("A" in line.upper() for _, line in removed)
        for line in clean.split("\n"):             # each line as the reader sees it
            try:
                evs = list(iter_gcode([line]))
            except GCodeError:
                continue
            n_read += 1
            assert not any(type(ev) is Command and ev.code.startswith("A") for ev in evs), line
    assert n_removed > 300 and n_read > 1000


def test_directive_round_trip_and_sanitiser_strips_it():
    from ambots.program import directive, is_directive, parse_directive
    from ambots.protocol import WaitFor
    line = directive(WaitFor(1, 2, line=120))
    assert line == ";@A9 R1 W2 N120" and is_directive("  " + line)
    assert parse_directive(line) == WaitFor(1, 2, line=120)
    # a comment to every other G-code reader
    from ambots.gcode import parse_gcode_text
    assert not [e for e in parse_gcode_text("G1 X1 F600\n" + line + "\n") if type(e).__name__ != "Segment"]
    clean, removed = sanitize_gcode("G1 X1\n" + line + "\n;@A1 R2\n; ordinary comment\n")
    assert clean == "G1 X1\n; ordinary comment\n" and [n for n, _ in removed] == [2, 3]


def test_malformed_directive_names_file_and_line():
    from ambots.program import parse_directive
    with pytest.raises(GCodeError) as e:
        parse_directive(";@A9 R1 W1 N3", "arm.gcode", 42)
    assert e.value.path == "arm.gcode" and e.value.line == 42 and "wait for itself" in str(e.value)
