"""The A-series protocol (ambots.protocol): original strings, new commands,
round trips, malformed input."""
import random
import zlib

import pytest

from ambots.errors import ProtocolError
from ambots.protocol import (HUB, MAX_ID, MAX_ROBOT, one_line, MAX_TEXT, MAX_U32, Ack, ArmState, ClearChunk,
                             ErrorReport, LoadChunk, MoveTo, Pause, Resume, SendPosition, Start,
                             Status, WaitFor, ack, decode, encode)


def bad(text):
    with pytest.raises(ProtocolError) as info:
        decode(text)
    assert info.value.text == text
    return info.value.message


# --- the original design's strings, exactly --------------------------------

@pytest.mark.parametrize("text, cmd", [
    ("A1 R2", Start(2)), ("A2 R1", Pause(1)), ("A3 R2", SendPosition(2)), ("A4 R1", ClearChunk(1)),
    ("A6 R3", Resume(3)), ("A7 R1 X100 Y50 Z10", MoveTo(1, 100, 50, 10)),
    ("A7 R2 X-12.5 Y0.25 Z.5", MoveTo(2, -12.5, 0.25, 0.5)),
])
def test_original_one_line_commands(text, cmd):
    assert decode(text) == cmd
    assert encode(cmd) == text.replace("Z.5", "Z0.5")
    assert decode(text.lower()) == cmd and decode(text + "\n") == cmd


def test_original_a5_chunk():
    cmd = decode("A5 R1\nG1 X1 Y2 E0.1\nG1 X3")
    assert cmd == LoadChunk(1, "G1 X1 Y2 E0.1\nG1 X3")
    assert decode(encode(cmd)) == cmd


# --- new commands and header words -------------------------------------------

def test_new_commands_wire_format():
    assert encode(Start(2, sender=HUB, seq=17)) == "A1 R2 S1001 Q17"
    assert encode(Start(0)) == "A1 R0"                     # the original's Kinova
    assert encode(Start(1, chunk_id=1764316800, sender=1000, seq=3)) == "A1 R1 C1764316800 S1000 Q3"
    assert decode("a1 c9 r2") == Start(2, chunk_id=9)
    assert encode(Ack(0, 17, sender=2)) == "A8 R0 Q17 S2"
    assert encode(WaitFor(1, 2, layer=5)) == "A9 R1 W2 L5"
    assert encode(WaitFor(1, 2, line=1200)) == "A9 R1 W2 N1200"
    assert encode(Status(1, ArmState.PRINTING, 3, 120, 12.5, 1.0, -2.5, 3e-7)) == \
        "A10 R1 T1 L3 N120 P12.5 X1 Y-2.5 Z0.0000003"
    assert encode(ErrorReport(2, 17, 'nozzle "clog"\nA1 R2')) == \
        'A11 R2 N17 "nozzle \\"clog\\"\\nA1 R2"'
    gcode = "G1 X1\nG1 Y2"
    assert encode(LoadChunk(1, gcode, chunk_id=4, seq=9)) == \
        "A5 R1 C4 L11 K%d Q9\n%s" % (zlib.crc32(gcode.encode()), gcode)


def test_words_in_any_order_and_spacing():
    assert decode("A10  Q5 P50 N7 L2 T4 R3") == Status(3, ArmState.DONE, 2, 7, 50.0, seq=5)


def test_ack_helper():
    assert ack(Start(2, seq=7), sender=2) == Ack(HUB, 7, 2)
    assert ack(Status(2, 1, 0, 0, 0, sender=2, seq=3), sender=HUB) == Ack(2, 3, HUB)
    with pytest.raises(ProtocolError):
        ack(Start(2))


def test_chunk_integrity_and_identity():
    a = LoadChunk(1, "G1 X1\nG1 X2", chunk_id=7)
    text = encode(a)
    assert decode(text) == a
    corrupt = text[:-1] + "3"
    assert "CRC-32" in bad(corrupt)
    assert "bytes" in bad(text + "\nG1 X4")                  # truncated or extended payload
    assert a.identity == (7, zlib.crc32(b"G1 X1\nG1 X2"), 11)
    assert LoadChunk(1, "G1 X1\nG1 X2", chunk_id=7).identity == a.identity
    assert LoadChunk(1, "G1 X1\nG1 X3", chunk_id=7).identity != a.identity


def test_text_cannot_smuggle_a_command():
    for message in ["x\nA1 R2", '" A1 R2', "\\", "\r\n\x00", "é✓\u2028", "\ud800", ""]:
        text = encode(ErrorReport(1, 0, message))
        assert "\n" not in text and "\r" not in text and text.isascii()
        assert decode(text).message == message
    assert "after the newline" in bad('A11 R1 N0 "a"\nA1 R2')
    assert "JSON" in bad('A11 R1 N0 "a" A1 R2')
    assert "A-series" in bad("A5 R1\nG1 X1\nA1 R2")
    assert "A-series" in bad("A5 R1\n(c) a7r1x1y1z1")
    with pytest.raises(ProtocolError):
        LoadChunk(1, "G1 X1\nA2 R1")


@pytest.mark.parametrize("text, why", [
    ("", "empty"), ("   ", "empty"), ("G1 X1", "starts with A"), ("A", "starts with A"),
    ("A0 R1", "unknown command"), ("A13 R1", "unknown command"), ("A1R2", "starts with A"),
    ("A1", "needs R"), ("A1 R1000", "robot id 0..999"), ("A1 R-1", "robot id"), ("A1 R1.5", "robot id"),
    ("A1 R99999999999", "robot id"), ("A1 R2 R3", "twice"), ("A1 R2 X1", "does not take"),
    ("A1 R2\nA2 R3", "after the newline"), ("A1 R2 Q-1", "integer"), ("A1 R2 Q4294967296", "integer"),
    ("A1 R\u00e92", "non-ASCII"), ("A1 R2\x00", "control"), ("A1 R2 \"x\"", "only A11"),
    ("A5 R1", "newline"), ("A5 R1 L3\nG1 X1", "bytes"), ("A5 R1\nG1 X\u00e9", "ASCII"),
    ("A5 R1\nG1\rX1", "control"), ("A7 R1 X1 Y2", "needs Z"), ("A7 R1 X1 Y2 Znan", "plain decimal"),
    ("A7 R1 X1 Y2 Z1e3", "plain decimal"), ("A7 R1 X1 Y2 Z2000000", "within"),
    ("A7 R1 X1 Y2 Z-", "plain decimal"), ("A8 R1", "needs Q"), ("A9 R1 W2", "exactly one"),
    ("A9 R1 W2 L1 N5", "exactly one"), ("A9 R1 W1 L3", "itself"), ("A9 R1 L3", "needs W"),
    ("A10 R1 T9 L0 N0 P0", "arm state"), ("A10 R1 T1 L0 N0 P101", "percentage"),
    ("A10 R1 T1 L0 N0 P5 X1", "all of X, Y, Z"), ("A10 R1 T1 L0 N0", "needs P"),
    ("A11 R1 N0", "quoted"), ('A11 R1 N0 "x', "JSON"), ('A11 R1 N0 "a\tb"', "control"),
    ('A11 R1 N0 "%s"' % ("x" * (MAX_TEXT + 1)), "at most"), ("A11 R1 N0 123", "does not take"),
])
def test_malformed_messages_say_what_is_wrong(text, why):
    assert why in bad(text)


def test_invalid_dataclasses_are_refused():
    for make in (lambda: Start(MAX_ROBOT + 1), lambda: Start(-1), lambda: Start(True), lambda: MoveTo(1, float("nan"), 0, 0),
                 lambda: MoveTo(1, 0, 0, float("inf")), lambda: Status(1, 7, 0, 0, 0),
                 lambda: WaitFor(1, 2), lambda: ErrorReport(1, 0, 5), lambda: LoadChunk(1, b"G1"),
                 lambda: Ack(-1, 0), lambda: Start(2, seq=MAX_U32 + 1)):
        with pytest.raises(ProtocolError):
            make()
    with pytest.raises(ProtocolError):
        encode("A1 R2")


# --- property-style: random valid commands round-trip --------------------------

def random_text(rng, n):
    pool = "abc XYZ;*\"'\\/\n\r\t\x00\x7fé✓\u2028A1 R2"
    return "".join(rng.choice(pool) for _ in range(rng.randint(0, n)))


def random_number(rng):
    return rng.choice([0.0, -0.0, 1e-7, -123.456, 1e6, -1e6, 0.1 + 0.2, 42,
                       rng.uniform(-1e6, 1e6), rng.uniform(-1, 1), round(rng.uniform(-500, 500), 3)])


def random_command(rng):
    robot = rng.choice([0, 1, 2, MAX_ROBOT, rng.randint(0, MAX_ROBOT)])
    header = {}
    if rng.random() < 0.5:
        header["sender"] = rng.choice([HUB, 1, MAX_ID])
    if rng.random() < 0.5:
        header["seq"] = rng.choice([0, 1, MAX_U32, rng.randint(0, MAX_U32)])
    kind = rng.randint(1, 11)
    if kind in (1, 2, 3, 4, 6):
        return {1: Start, 2: Pause, 3: SendPosition, 4: ClearChunk, 6: Resume}[kind](robot, **header)
    if kind == 5:
        lines = ["G1 X%.3f Y%.3f E%.5f" % (rng.uniform(0, 200), rng.uniform(0, 200), rng.random())
                 for _ in range(rng.randint(0, 20))] + rng.choice([[], [""], ["; comment\twith tab"]])
        return LoadChunk(robot, "\n".join(lines), rng.choice([None, 0, MAX_U32, rng.randint(0, 99)]),
                         **header)
    if kind == 7:
        return MoveTo(robot, random_number(rng), random_number(rng), random_number(rng), **header)
    if kind == 8:
        return Ack(rng.choice([HUB, robot]), rng.randint(0, MAX_U32), header.get("sender"))
    if kind == 9:
        other = (robot + 1) % (MAX_ROBOT + 1)
        if rng.random() < 0.5:
            return WaitFor(robot, other, layer=rng.randint(0, 10 ** 6), **header)
        return WaitFor(robot, other, line=rng.randint(0, MAX_ID), **header)
    if kind == 10:
        pos = [random_number(rng) for _ in range(3)] if rng.random() < 0.5 else [None] * 3
        return Status(robot, rng.choice(list(ArmState)), rng.randint(0, 9999), rng.randint(0, MAX_ID),
                      rng.choice([0, 100, rng.uniform(0, 100)]), *pos, **header)
    return ErrorReport(robot, rng.randint(0, MAX_ID), random_text(rng, 80), **header)


def test_random_valid_commands_round_trip():
    rng = random.Random(20240601)
    seen = set()
    for _ in range(5000):
        cmd = random_command(rng)
        text = encode(cmd)
        assert decode(text) == cmd, text
        assert encode(decode(text)) == text
        header = text.partition("\n")[0]
        assert header.isascii() and header.isprintable()
        assert ("\n" in text) == isinstance(cmd, LoadChunk)
        seen.add(type(cmd))
    assert len(seen) == 11


# --- robustness: 10,000 random and mutated strings --------------------------------

_JUNK = ["nan", "inf", "1e9", "99999999999999999999", "-", ".", "\"", "\\", "\n", "\r", "\x00",
         "é", "\u2028", " ", "R", "Q", "S", "A5", "A1 R2", "\nG1 X1", "L", "K", "*"]


def mutate(rng, text):
    for _ in range(rng.randint(1, 3)):
        pos = rng.randint(0, len(text))
        k = rng.random()
        if k < 0.3:
            text = text[:pos]
        elif k < 0.6:
            text = text[:pos] + rng.choice(_JUNK) + text[pos:]
        elif k < 0.85:
            text = text[:pos] + chr(rng.randint(0, 0x24F)) + text[pos + 1:]
        else:
            text = text[:pos] + text[pos + 1:]
    return text


def test_random_and_mutated_strings_never_crash_the_decoder():
    rng = random.Random(99)
    ok = rejected = 0
    for _ in range(10000):
        text = mutate(rng, encode(random_command(rng)))
        try:
            cmd = decode(text)
        except ProtocolError:
            rejected += 1
            continue
        ok += 1
        assert decode(encode(cmd)) == cmd
    # both branches well exercised (robot ids are 0..999, so a digit inserted into R is often refused)
    assert ok > 800 and rejected > 3000


def test_one_line_for_the_debug_log():
    assert one_line("A10 R0 T1 L3 N120 P12.5 S0 Q5") == "A10 R0 T1 L3 N120 P12.5 S0 Q5"
    assert one_line("A5 R1 C3 L21 K9\nG1 X1 Y2 E0.1\nG1 X3") == "A5 R1 C3 L21 K9 (+2 G-code lines)"
    assert one_line("A1 R0\x07 \u2713") == "A1 R0\\x07 \u2713"                    # escaped, never raises
    assert one_line(b"A1 R0") == "b'A1 R0'" and len(one_line("A1 " + "9" * 5000)) == 203
