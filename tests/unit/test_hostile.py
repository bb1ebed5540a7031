"""Hostile and broken input ("Nothing lost", part 3).

Every bad input is answered with a typed error (:mod:`ambots.errors`) that
names the file, line or field -- or, where the input arrives at run time
(the hub, an arm's firmware), with a line on the error topic / an A11 report
and an unchanged state -- never a traceback, a hang or GBs of memory.

Sections: 1. A-series strings through the hub; 2. A-series commands hidden
in user G-code; 3. G-code (reader, firmware planner and runner); 4. model
files; 5. cell and arm configs; 6. file names with shell metacharacters
(built-in slicer, PrusaSlicer wrapper).  The cases extend, and do not
repeat, those of test_hub, test_protocol, test_program, test_gcode,
test_mesh and test_cell.  HOSTILE.md summarises them.
"""
import json
import random
import shutil
import stat
import struct
import time
import tracemalloc

import numpy as np
import pytest
import trimesh
import yaml

from ambots import data_path, topics
from ambots.config import default_cell_path, load_arm_profile, load_cell
from ambots.errors import AmbotsError, ConfigError, GCodeError, MeshError
from ambots.gcode import Command, Segment, parse_gcode_text, read_gcode
from ambots.hub import Hub
from ambots.model import arm_urdf
from ambots.job import prepare_model, run_job, write_job
from ambots.mesh import load_model, place_on_bed
from ambots.motion import MotionPlanner, read_program
from ambots.program import is_directive, sanitize_gcode
from ambots.protocol import (ArmState, ClearChunk, ErrorReport, LoadChunk, MoveTo, Start, decode)
from ambots.reliable import Sender
from ambots.runner import ArmRunner
from ambots.slicer import PrusaSlicer, SlicerError, slice_mesh

#: a file name a shell would execute: quotes, $( ), ;, spaces
NASTY = "a b'$(touch pwned)\";.stl"


@pytest.fixture(scope="module")
def cell():
    return load_cell(default_cell_path())


def no_pwned(root):
    """No file named pwned* anywhere under ``root`` (a shell never ran our names)."""
    return not [p for p in root.rglob("pwned*")]


# =============================================================================
# 1. A-series strings through the hub
# =============================================================================

FRONT_END, KINOVA, INTRUDER = "/front_end", "/kinova/firmware", "/intruder"
KINOVA_IN, ERR = "/ambots/kinova_topic", topics.ERROR_TOPIC


def _random_bytes(seed):
    return random.Random(seed).randbytes(64).decode("latin-1")


def _random_unicode(seed):
    rng = random.Random(seed)
    return "".join(chr(rng.choice([rng.randrange(32, 127), rng.randrange(0x80, 0x30000)]))
                   for _ in range(40))


#: (case id, text, words of the reason given to a registered caller)
BAD_STRINGS = [
    ("empty", "", "empty message"),
    ("blanks", "    ", "empty message"),
    ("prose", "hello world", "a message starts with A<code>"),
    ("unknown code", "A0 R1", "unknown command A0"),
    ("four digit code", "A1000 R1", "a message starts with A<code>"),
    ("missing R", "A7 X1 Y2 Z3", "A7 needs R"),
    ("missing fields", "A10 R1 T1", "A10 needs L, N, P"),
    ("missing W", "A9 R1 L3", "A9 needs W"),
    ("negative id", "A1 R-1", "expected a robot id"),
    ("id of the front end", "A1 R1000", "expected a robot id 0..999"),
    ("id beyond int32", "A1 R2147483648", "expected a robot id"),
    ("huge id", "A1 R" + "9" * 40, "expected a robot id"),
    ("NaN coordinate", "A7 R1 Xnan Y0 Z0", "plain decimal"),
    ("inf coordinate", "A7 R1 X0 Yinf Z0", "plain decimal"),
    ("exponent", "A7 R1 X1e3 Y0 Z0", "plain decimal"),
    ("huge coordinate", "A7 R1 X" + "9" * 400 + " Y0 Z0", "within +-1e+06 mm"),
    ("seq beyond u32", "A1 R1 Q4294967296", "A1 Q"),
    ("NaN percent", "A10 R1 T1 L0 N0 Pnan", "A10 P"),
    ("state out of range", "A10 R1 T77 L0 N0 P0", "an arm state 0..5"),
    ("word twice", "A1 R1 R2", "R given twice"),
    ("word not taken", "A2 R1 X5", "A2 does not take 'X5'"),
    ("A11 without text", "A11 R1 N0", "needs a quoted message"),
    ("A11 bad JSON", 'A11 R1 N0 "\\x41"', "not a valid JSON string"),
    ("A5 without payload", "A5 R1", "must be followed by a newline"),
    ("A5 length lie", "A5 R1 L99\nG1 X1", "header says L99"),
    ("A5 control char", "A5 R1\nG1 X1\x07", "control character"),
    ("A5 non-ASCII", "A5 R1\nG1 X1 ; \u00e9", "must be ASCII"),
    ("NUL", "A1 R1\x00", "control character"),
    ("unicode", "A1 R1 \u2713", "non-ASCII"),
    ("second line", "A1 R1\nA2 R1", "A1 is one line"),
    ("10 kB word", "A1 R" + "1" * 10000, "expected a robot id"),
    ("10 kB junk", "A1 " + "X" * 10000, "A1 does not take"),
    ("10 kB chunk, bad CRC", "A5 R1 K1\n" + "G1 X1\n" * 1700, "CRC-32"),
    ("random bytes 1", _random_bytes(1), "malformed"),
    ("random bytes 2", _random_bytes(2), "malformed"),
    ("random unicode 1", _random_unicode(1), "malformed"),
    ("random unicode 2", _random_unicode(2), "malformed"),
    ("None", None, "a message must be a str"),
    ("bytes", b"A1 R1", "a message must be a str"),
    ("int", 42, "a message must be a str"),
]


@pytest.fixture
def busy_hub(cell):
    """A hub in the middle of a job: a command in flight to each arm and a
    status report from the Kinova."""
    hub = Hub(cell, extra_callers=["/tool"], sender=Sender(topics.HUB_ID, first_seq=100))
    hub.handle("A1 R1 S1000 Q1", FRONT_END, 0.0)
    hub.handle("A4 R0 S1000 Q2", FRONT_END, 0.0)
    hub.handle("A10 R0 T1 L3 N40 P12.5 S0 Q7", KINOVA, 0.5)
    return hub


def hub_state(hub):
    """Everything the hub remembers: registry, messages in flight, duplicate
    windows, progress."""
    reg = hub.registry
    return (dict(reg._by_caller), dict(reg.arms), hub.sender._next_seq, repr(hub.sender.pending),
            {k: (w.top, w.seen) for k, w in hub.receiver._windows.items()},
            hub.progress_json(1.0))


@pytest.mark.parametrize("caller", [INTRUDER, KINOVA], ids=["unregistered", "registered"])
@pytest.mark.parametrize("text, reason", [c[1:] for c in BAD_STRINGS], ids=[c[0] for c in BAD_STRINGS])
def test_hub_refuses_bad_strings_and_keeps_its_state(busy_hub, caller, text, reason):
    before = hub_state(busy_hub)
    posts = busy_hub.handle(text, caller, 1.0)                 # never raises
    assert [p.topic for p in posts] == [ERR]                  # no ack, nothing routed
    [line] = [p.text for p in posts]
    assert line.startswith("hub refused ") and ("from %s: " % caller) in line
    assert "\n" not in line and len(line) < 700               # one short line, even for 10 kB
    if caller == INTRUDER:
        assert "not a registered node" in line
    else:
        assert "malformed: " in line and reason in line, line
    assert hub_state(busy_hub) == before
    # the next good message is routed as usual
    posts = busy_hub.handle("A6 R0 S1000 Q3", FRONT_END, 1.1)
    assert [decode(p.text).CODE for p in posts if p.topic == KINOVA_IN] == [6]


def test_hub_survives_a_seeded_fuzz_from_every_kind_of_caller(busy_hub):
    rng = random.Random(2024)
    alphabet = "A0123456789 RSQXYZLNKCTPW-+.e\"\\\n\r\t\x00\u00e9"
    before = hub_state(busy_hub)
    for i in range(1500):
        text = "A" + "".join(rng.choice(alphabet) for _ in range(rng.randrange(30)))
        for caller in (INTRUDER, KINOVA, "/tool"):
            for p in busy_hub.handle(text, caller, 1.0):
                if p.topic == ERR:
                    assert "\n" not in p.text
    assert hub_state(busy_hub)[:2] == before[:2]          # the registry never changes
    posts = busy_hub.handle("A6 R0 S1000 Q3", FRONT_END, 1.1)
    assert [decode(p.text).CODE for p in posts if p.topic == KINOVA_IN] == [6]


@pytest.mark.parametrize("message, shown", [
    ("line one\nA1 R1 fake second line", "line one\\nA1 R1 fake second line"),
    ("bell \x07 and escape \x1b[31m", "bell \\x07 and escape \\x1b[31m"),
    ("lone surrogate \ud800", "lone surrogate \\ud800"),
], ids=["newline", "control", "surrogate"])
def test_an_arms_error_text_stays_one_printable_line_on_the_error_topic(busy_hub, message, shown):
    text = "A11 R0 N5 S0 Q8 %s" % json.dumps(message)       # valid A11: JSON carries anything
    posts = busy_hub.handle(text, KINOVA, 1.0)
    [line] = [p.text for p in posts if p.topic == ERR]
    assert line == "arm kinova (R0) error at G-code line 5: " + shown
    line.encode("utf-8")                                    # publishable by ROS


# =============================================================================
# 2. A-series commands hidden in a user's G-code
# =============================================================================

#: lines the sanitiser must remove (a firmware would, or might, execute them)
HIDDEN = [
    ("bare A5", "A5 R1 C1 L5 K0"),
    ("directive", ";@A1 R2"),
    ("indented directive", " \t;@A9 R1 W2 L3"),
    ("malformed directive", ";@ not even a command"),
    ("empty directive", ";@"),
    ("no-break space", "\u00a0A1 R2"),
    ("ideographic space", "\u3000A7 R1 X1 Y1 Z1"),
    ("em space after N", "N5\u2003A1 R2"),
    ("NUL first", "\x00A1 R2"),
    ("DEL first", "\x7fA1 R2"),
    ("comment inside", "A1(x)R2"),
    ("glued after N", "N10A1R2"),
    ("tab first", "\tA7 R1 X1 Y1 Z1"),
    ("non-ASCII digit", "A\u0661 R2"),
]


@pytest.mark.parametrize("line", [c[1] for c in HIDDEN], ids=[c[0] for c in HIDDEN])
def test_hidden_a_series_lines_are_stripped_or_refused_with_their_line(line):
    text = "G21\nG1 X0 Y0 F600\n%s\nG1 X2 Y0\n" % line
    clean, removed = sanitize_gcode(text, "user part.gcode")
    assert removed == [(3, line)]
    assert clean == "G21\nG1 X0 Y0 F600\nG1 X2 Y0\n"
    evs = list(parse_gcode_text(clean))
    assert not [e for e in evs if type(e) is Command and e.code.startswith("A")]
    with pytest.raises(GCodeError) as info:
        sanitize_gcode(text, "user part.gcode", mode="reject")
    assert (info.value.path, info.value.line, info.value.text) == ("user part.gcode", 3, line)
    assert str(info.value).startswith("user part.gcode:3: A-series command in untrusted G-code")


@pytest.mark.parametrize("line", ["M117 A1 R2", "G1 X1 (A1 R2)", "; @A1 R2 (a comment, not a directive)",
                                  "G1 X1 ;@A1 R2"])
def test_look_alikes_that_no_firmware_executes_are_kept(line):
    text = "G1 X0 F600\n%s\n" % line
    assert sanitize_gcode(text) == (text, [])
    assert not is_directive(line)


def test_a_bom_is_not_hidden_it_is_refused_by_the_reader_with_its_line():
    clean, removed = sanitize_gcode("G21\n\ufeffA1 R2\n", "bom.gcode")
    assert removed == []                   # not a command any reader would run ...
    with pytest.raises(GCodeError) as info:
        list(parse_gcode_text(clean, "bom.gcode"))
    assert info.value.line == 2 and "non-ASCII character '\\ufeff'" in str(info.value)


# =============================================================================
# 3. G-code: the reader, the firmware's program reader and planner, the runner
# =============================================================================

#: (case id, line 3 of a program, words of the GCodeError)
BAD_GCODE = [
    ("F1e12", "G1 X1 F1e12", "ambiguous"),
    ("F beyond 1e6", "G1 X1 F1000000000000", "beyond"),
    ("F0.0 on G0", "G0 X1 F0.0", "feedrate F must be > 0"),
    ("F-5 on an arc", "G2 X10 Y0 I5 J0 F-5", "feedrate F must be > 0"),
    ("F NaN", "G1 Fnan", "not finite"),
    ("Z inf", "G0 Zinf", "not finite"),
    ("1e9 Z", "G0 Z1000000000", "beyond"),
    ("1e9 E", "G1 X1 E1000000000", "beyond"),
    ("400-digit X", "G1 X" + "9" * 400, "beyond"),
    ("NaN arc centre", "G2 X1 Y1 Inan J0", "not finite"),
    ("arc beyond 1e6", "G2 X0 Y0 I900000 J0", "arc leaves the +-1e+06 mm range"),
    ("NaN dwell", "G4 Snan", "not finite"),
    ("negative dwell", "G4 S-1", "negative dwell"),
    ("G92 beyond", "G92 X1000000000", "beyond"),
    ("garbage token", "G1 X1 @#$", "unexpected '@#$'"),
    ("equals sign", "G1 X=5", "parameter X has no value"),
    ("hex number", "G1 X0x1F", "parameter X given twice"),
    ("decimal comma", "G1 X1,5", "unexpected"),
    ("ANSI escape", "\x1b[31mG1 X5", "control character"),
    ("RTL override", "G1 X5\u202e", "non-ASCII character"),
    ("doubled letter", "GG1 X1", "must start with a G, M, T or A command"),
    ("only numbers", "1 2 3", "must start with a G, M, T or A command"),
    ("nested comment", "G1 X1 ((a))", "nested '('"),
    ("stray paren", "G1 X1 )", "')' without '('"),
    ("wrong checksum", "N12 G1 X1*999", "wrong checksum"),
    ("10 kB line", "G1 X1 " + "Y" * 10000, "G1"),
]


@pytest.mark.parametrize("line, why", [c[1:] for c in BAD_GCODE], ids=[c[0] for c in BAD_GCODE])
def test_bad_gcode_is_a_gcode_error_naming_file_and_line(line, why):
    with pytest.raises(GCodeError) as info:
        list(parse_gcode_text("G21\nG1 X0 Y0 F600\n%s\nG1 X2\n" % line, "user part.gcode"))
    exc = info.value
    assert (exc.path, exc.line) == ("user part.gcode", 3)
    assert why in exc.message, exc.message
    assert str(exc).startswith("user part.gcode:3: ")


def test_a_clockwise_full_circle_is_a_circle():
    # found while writing these tests: G2 back to its start was one zero-length chord
    segs = [e for e in parse_gcode_text("G1 X0 Y0 F600\nG2 X0 Y0 I10 J0") if type(e) is Segment][1:]
    assert len(segs) > 10
    assert sum(((s.end[0] - s.start[0]) ** 2 + (s.end[1] - s.start[1]) ** 2) ** 0.5
               for s in segs) == pytest.approx(20 * 3.141592653589793, rel=1e-3)


@pytest.mark.parametrize("content, line", [
    (b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR", 1),
    (b"G21\nG1 X1 F600\n\xff\xfe G1 X2\n", 3),
], ids=["png bytes", "invalid utf-8"])
def test_a_gcode_file_that_is_not_text_names_file_and_line(tmp_path, content, line):
    path = tmp_path / "my print.gcode"
    path.write_bytes(content)
    with pytest.raises(GCodeError) as info:
        list(read_gcode(str(path)))
    assert (info.value.path, info.value.line) == (str(path), line)
    assert "non-ASCII character '\ufffd' outside a comment" in info.value.message


def test_a_folder_as_gcode_file_cannot_be_opened(tmp_path):
    with pytest.raises(GCodeError, match="cannot open"):
        list(read_gcode(str(tmp_path)))


@pytest.mark.parametrize("line, why", [
    (";@A9 R1 W1 L2", "cannot wait for itself"),
    (";@A5 R1", "must be followed by a newline"),
    (";@A7 R1 Xnan Y0 Z0", "plain decimal"),
    (";@A1 R1 S99999999999", "A1 S"),
])
def test_read_program_names_chunk_and_line_of_a_bad_directive(line, why):
    with pytest.raises(GCodeError) as info:
        read_program("G21\nG1 X0 Y0 F600\n%s\n" % line, "chunk 7")
    assert (info.value.path, info.value.line) == ("chunk 7", 3) and why in info.value.message


# --- the firmware: ArmRunner -------------------------------------------------

HEAD = "G21\nG90\nM83\nG0 X0 Y0 Z5 F3000\n"          # lines 1-4; the case is line 5
GOOD = HEAD + "G1 X10 Y0 Z5 F3000\n"


@pytest.fixture(scope="module")
def planner(cell):
    return MotionPlanner(cell.arm("kinova"), cell)


def runner(cell, planner):
    return ArmRunner(cell.arm("kinova"), cell, planner=planner)


def run(r, text, t_max=200.0):
    r.handle(LoadChunk(r.id, text, chunk_id=len(text)), now=r.clock)
    r.handle(Start(r.id), now=r.clock)
    t = r.clock
    while r.state is ArmState.PRINTING and t < t_max:
        t += 5.0
        r.advance(t)
    return [m for _, m in r.outbox if isinstance(m, ErrorReport)]


def recovers(r):
    """After an error the arm takes the next good chunk and prints it."""
    r.handle(ClearChunk(r.id), now=r.clock)
    r.outbox.clear()
    assert run(r, GOOD) == [] and r.state is ArmState.DONE
    return True


#: (case id, lines from 5 on, line of the A11)
UNREACHABLE = [
    ("1e6 mm", "G1 X1000000 Y0 Z5\n", 5),
    ("1e6 mm back and forth x200", "G1 X1000000 Y0\nG1 X-1000000 Y0\n" * 200, 5),
    ("far travel first", "G0 X-999999 Y0 Z5\nG1 X999999 Y0 E1\n", 5),
    ("arc out of reach", "G2 X0 Y0 I400 J0 F3000\n", 5),
    ("directive move out of reach", ";@A7 R0 X1000000 Y0 Z0\n", 5),
    ("unreachable on line 6", "G1 X10 Y0\nG1 X2000 Y0\n", 6),
]


@pytest.mark.parametrize("body, line", [c[1:] for c in UNREACHABLE], ids=[c[0] for c in UNREACHABLE])
def test_unreachable_points_stop_the_arm_with_an_error_naming_the_line(cell, planner, body, line):
    r = runner(cell, planner)
    tracemalloc.start()
    t0 = time.monotonic()
    errors = run(r, HEAD + body)                   # never raises
    elapsed = time.monotonic() - t0
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert r.state is ArmState.ERROR
    assert [e.line for e in errors] == [line] and "unreachable" in errors[0].message
    assert elapsed < 3.0 and peak < 200e6        # was a 1.8 GB MemoryError for the x200 case
    assert recovers(r)


def test_an_absurdly_fast_feedrate_is_capped_by_the_joint_speed_limits(cell, planner):
    """F1000000 runs within the joint limits, at least as fast as a feedrate
    the arm can follow (the timing law's look-ahead first guess caps the
    speed by the joints, not by an impossible feedrate: measured 1 % faster
    than F3000; before it, 7.5 % slower)."""
    r = runner(cell, planner)
    assert run(r, HEAD + "G1 X10 Y0 Z5 F1000000\n") == [] and r.state is ArmState.DONE
    slow = runner(cell, planner)
    run(slow, HEAD + "G1 X10 Y0 Z5 F3000\n")
    assert r.stats.print_time_s > 0 and r.stats.print_time_s <= slow.stats.print_time_s * (1 + 1e-9)


#: (case id, line 5, words of the refusal)
REFUSED_CHUNKS = [
    ("F0", "G1 X1 F0", "feedrate F must be > 0"),
    ("F-5", "G1 X1 F-5", "feedrate F must be > 0"),
    ("F1e12", "G1 X1 F1e12", "ambiguous"),
    ("NaN", "G1 Xnan Y0", "not finite"),
    ("1e9", "G1 X1000000000", "beyond"),
    ("garbage", "G1 X1 @#$", "unexpected"),
    ("bad directive", ";@A9 R1 W1 L2", "cannot wait for itself"),
]


@pytest.mark.parametrize("line, why", [c[1:] for c in REFUSED_CHUNKS], ids=[c[0] for c in REFUSED_CHUNKS])
def test_a_chunk_with_bad_gcode_is_refused_with_its_line_and_the_arm_stays_usable(cell, planner, line,
                                                                                 why):
    r = runner(cell, planner)
    errors = run(r, HEAD + line + "\n")
    assert r.state is ArmState.IDLE
    first = errors[0]
    assert first.line == 5 and first.message.startswith("A5 refused: chunk ") and why in first.message
    assert ":5: " in first.message
    assert recovers(r)


@pytest.mark.parametrize("xyz", [(1e6, -1e6, 1e6), (0.0, 0.0, -2000.0)], ids=["1e6", "deep below"])
def test_a_manual_move_out_of_reach_is_reported_and_changes_nothing(cell, planner, xyz):
    r = runner(cell, planner)
    q = r.q.copy()
    r.handle(MoveTo(r.id, *xyz), now=0.0)
    r.advance(10.0)
    [err] = [m for _, m in r.outbox if isinstance(m, ErrorReport)]
    assert err.line == 0 and err.message.startswith("A7 ") and "unreachable" in err.message
    assert r.state is ArmState.IDLE and (r.q == q).all()


# =============================================================================
# 4. Model files
# =============================================================================

def _box():
    return trimesh.creation.box((20.0, 20.0, 20.0))


def _without(normal_axes):
    """The 20 mm cube without its faces whose normal is along one of ``normal_axes``."""
    box = _box()
    drop = (box.face_normals[:, normal_axes] > 0.9).any(axis=1)
    return trimesh.Trimesh(box.vertices, box.faces[~drop], process=False)


def _stl(mesh):
    return trimesh.exchange.stl.export_stl(mesh)


def _two(offset):
    a, b = _box(), _box()
    b.apply_translation(offset)
    return _stl(trimesh.util.concatenate([a, b]))


def _spike():
    """One shell crossing itself: the cube's top centre pushed through its bottom."""
    box = _box().subdivide().subdivide()
    vertices = box.vertices.copy()
    vertices[np.argmin(np.linalg.norm(vertices - (0.0, 0.0, 10.0), axis=1))] = (0.0, 0.0, -15.0)
    return _stl(trimesh.Trimesh(vertices, box.faces, process=False))


#: (case id, file name, content, kwargs, words of the MeshError)
BAD_MODELS = [
    ("empty", "empty.stl", b"", {}, "file is empty"),
    ("zero triangles, binary", "none.stl", b"\0" * 80 + struct.pack("<I", 0), {}, "contains no triangles"),
    ("zero triangles, ASCII", "none.stl", b"solid empty\nendsolid empty\n", {}, "contains no triangles"),
    ("only vertices, OBJ", "points.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\n", {}, "contains no triangles"),
    ("zero faces, PLY", "none.ply", b"ply\nformat ascii 1.0\nelement vertex 0\nelement face 0\n"
     b"property list uchar int vertex_indices\nend_header\n", {}, "contains no triangles"),
    ("open: a square face off, no repair", "open box.stl", _stl(_without([2])), {"repair": False},
     "not a closed volume: 4 open edges"),
    ("open: two faces off", "open box.stl", _stl(_without([0, 2])), {}, "not a closed volume: 6 open edges"),
    ("touching cubes", "touching.stl", _two((20.0, 0.0, 0.0)), {}, "4 non-manifold edges"),
    ("one shell crossing itself", "spike.stl", _spike(), {},
     "the surface crosses itself: 8 pairs of triangles intersect, at (-0.50, 0.50, -10.00)"),
    ("PNG bytes", "photo.stl", b"\x89PNG\r\n\x1a\n" + bytes(range(256)) * 2, {}, "not a readable STL file"),
    ("G-code text", "part.stl", b"G21\nG1 X1 Y1 F600\n" * 20, {}, "not a readable STL file"),
    ("truncated 10^7 header", "big.stl", b"\0" * 80 + struct.pack("<I", 10 ** 7) + b"\0" * 1000, {},
     "announces 10,000,000 triangles (500,000,084 bytes) but the file has 1,084 bytes"),
    ("header only", "big.stl", b"\0" * 80 + struct.pack("<I", 10 ** 7), {}, "announces 10,000,000"),
    ("bad vertex index", "bad.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 99\n", {}, "not a readable OBJ file"),
    ("1e300 coordinates", "far.obj", b"v 0 0 0\nv 1e300 0 0\nv 0 1e300 0\nv 0 0 1e300\n"
     b"f 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n", {}, "3 vertices lie beyond +-1e+06 mm"),
    ("scale to 1e7 mm", "cube.stl", _stl(_box()), {"scale": 1e6}, "vertices lie beyond +-1e+06 mm"),
    ("scale NaN", "cube.stl", _stl(_box()), {"scale": float("nan")}, "scale must be a positive number"),
    ("scale 0", "cube.stl", _stl(_box()), {"scale": 0}, "scale must be a positive number"),
    ("extension .gcode", "cube.gcode", _stl(_box()), {}, "unknown model format '.gcode'"),
    ("extension .png", "cube.png", _stl(_box()), {}, "unknown model format '.png'"),
    ("no extension", "cube", _stl(_box()), {}, "unknown model format '(no extension)'"),
    ("double extension", "cube.stl.bak", _stl(_box()), {}, "unknown model format '.bak'"),
]


@pytest.mark.parametrize("name, content, kwargs, why", [c[1:] for c in BAD_MODELS],
                         ids=[c[0] for c in BAD_MODELS])
def test_bad_models_are_a_mesh_error_naming_the_file(tmp_path, name, content, kwargs, why):
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(MeshError) as info:
        load_model(str(path), **kwargs)
    message = str(info.value)
    assert message.startswith(name + ": ") and why in message, message


def test_a_folder_named_like_a_model_is_refused(tmp_path):
    (tmp_path / "cube.stl").mkdir()
    with pytest.raises(MeshError, match="cube.stl: is a folder, not a model file"):
        load_model(str(tmp_path / "cube.stl"))


@pytest.mark.parametrize("truncated", [True, False], ids=["truncated", "full size (sparse)"])
def test_a_ten_million_triangle_claim_fails_fast_without_reading(tmp_path, truncated):
    path = tmp_path / "huge.stl"
    with open(path, "wb") as f:
        f.write(b"\0" * 80 + struct.pack("<I", 10 ** 7))
        if not truncated:
            f.truncate(84 + 50 * 10 ** 7)      # 500 MB, sparse: the size matches the header
    tracemalloc.start()
    t0 = time.monotonic()
    with pytest.raises(MeshError) as info:
        load_model(str(path))
    elapsed, peak = time.monotonic() - t0, tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert elapsed < 2.0 and peak < 10e6
    assert str(info.value).startswith("huge.stl: ")
    assert ("not a readable STL file" if truncated else "more than the limit of 5,000,000") in str(info.value)


def test_upper_case_extension_is_fine_and_a_face_hole_is_filled(tmp_path):
    path = tmp_path / "OPEN BOX.STL"
    path.write_bytes(_stl(_without([2])))
    mesh = load_model(str(path))                 # a 4-edge hole is filled (documented repair)
    assert mesh.volume == pytest.approx(8000.0)
    (note,) = mesh.metadata["ambots_repairs"]
    assert note.startswith("closed 1 hole with 2 triangles (400.0 mm^2 of fill)")


@pytest.mark.parametrize("offset, volume", [((10.0, 0.0, 0.0), 12000.0), ((5.0, 5.0, 5.0), 16000.0 - 15.0 ** 3)],
                         ids=["half overlap", "corner overlap"])
def test_self_intersecting_cubes_are_merged_and_the_job_runs(tmp_path, cell, offset, volume):
    # documented behaviour: shells that overlap are united by manifold3d, with a note
    path = tmp_path / "two cubes.stl"
    path.write_bytes(_two(offset))
    job = run_job(str(path), cell, list(cell.arms))          # both arms (a compact part: not the planner's choice)
    assert job.mesh.volume == pytest.approx(volume)
    assert any("self-intersection" in n for n in job.mesh.metadata["ambots_repairs"])
    assert sum(p.volume for p in job.parts) == pytest.approx(volume, rel=1e-6)
    assert set(job.programs) == {"kinova", "ur10"}


@pytest.mark.parametrize("name, content, why", [
    ("empty.stl", b"", "empty.stl: file is empty"),
    ("notes.stl", b"buy filament\n" * 10, "notes.stl: not a readable STL file"),
    ("missing.stl", None, "missing.stl: no such file"),
    ("spike.stl", _spike(), "spike.stl: the surface crosses itself"),
])
def test_the_job_names_the_model_file(tmp_path, cell, name, content, why):
    path = tmp_path / name
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(MeshError, match=why.replace(".", r"\.")):
        prepare_model(str(path), cell)


@pytest.mark.parametrize("jobs", ["1", "2"])
def test_the_job_refuses_a_large_crossing_whether_the_search_runs_aside_or_not(tmp_path, cell, monkeypatch, jobs):
    """run_job with the search for a crossing beside the planning (two
    processes) gives the load's refusal, as with one."""
    monkeypatch.setenv("AMBOTS_JOBS", jobs)
    path = tmp_path / "spike.stl"
    path.write_bytes(_spike())
    with pytest.raises(MeshError, match=r"spike\.stl: the surface crosses itself: 8 pairs"):
        run_job(str(path), cell)


# =============================================================================
# 5. Cell and arm configs
# =============================================================================

def _cell_data():
    with open(default_cell_path()) as f:
        data = yaml.safe_load(f)
    for arm in data["arms"]:
        arm["profile"] = data_path(arm["profile"])
    return data


def _profile_data():
    with open(data_path("config", "arms", "ur10.yaml")) as f:
        data = yaml.safe_load(f)
    data["model"] = data_path(data["model"])
    return data


def _write(path, data):
    """Write ``data`` (bytes, text, or a YAML document as Python objects) to ``path``."""
    if isinstance(data, bytes):
        path.write_bytes(data)
    else:
        path.write_text(data if isinstance(data, str) else yaml.safe_dump(data))
    return str(path)


def _set(*keys_value):
    """A mutation setting data[k1][k2]... = value."""
    *keys, value = keys_value

    def mutate(data):
        for k in keys[:-1]:
            data = data[k]
        data[keys[-1]] = value
    return mutate


def _pop(*keys):
    def mutate(data):
        for k in keys[:-1]:
            data = data[k]
        del data[keys[-1]]
    return mutate


NAN, INF = float("nan"), float("inf")

#: (case id, mutation of the default cell, field, words)
BAD_CELLS = [
    ("NaN in a base pose", _set("arms", 0, "base", "xyz", [NAN, 0.0, 0.0]), "arms[0].base.xyz", "finite"),
    ("inf in the bed pose", _set("bed", "pose", "xyz", [INF, 0.0, 0.0]), "bed.pose.xyz", "finite"),
    ("NaN bed height", _set("bed", "max_height", NAN), "bed.max_height", "finite"),
    ("missing base", _pop("arms", 0, "base"), "arms[0].base", "missing field"),
    ("missing id", _pop("arms", 1, "id"), "arms[1].id", "missing field"),
    ("missing name", _pop("name"), "name", "missing field"),
    ("id as text", _set("arms", 0, "id", "1"), "arms[0].id", "expected an integer"),
    ("id as float", _set("arms", 0, "id", 1.0), "arms[0].id", "expected an integer"),
    ("id beyond the protocol", _set("arms", 0, "id", 2 ** 40), "arms[0].id", "0..999"),
    ("duplicate name", _set("arms", 1, "name", "kinova"), "arms[1].name", "duplicate arm name 'kinova'"),
    ("same base", _set("arms", 1, "base", "xyz", [0.0, 0.0, 0.0]), "arms",
     "bases of 'kinova' and 'ur10' overlap: 0.000 m apart (minimum 0.25 m)"),
    ("unknown profile", _set("arms", 0, "profile", "config/arms/no_such_robot.yaml"), "arms[0].profile",
     "no_such_robot.yaml: arm profile file not found"),
    ("profile is a folder", _set("arms", 0, "profile", "/"), "arms[0].profile", "file not found"),
    ("profile as number", _set("arms", 0, "profile", 5), "arms[0].profile", "non-empty string"),
    ("arm as text", _set("arms", 0, "kinova"), "arms[0]", "expected a mapping, got str"),
    ("arms as mapping", _set("arms", {"kinova": 1}), "arms", "non-empty list"),
    ("bed as list", _set("bed", [0.3, 0.4]), "bed", "expected a mapping, got list"),
    ("short rpy", _set("arms", 0, "base", "rpy", [0.0, 0.0]), "arms[0].base.rpy", "3 finite numbers"),
    ("world frame as number", _set("world_frame", 3), "world_frame", "non-empty string"),
]


@pytest.mark.parametrize("mutate, field, why", [c[1:] for c in BAD_CELLS], ids=[c[0] for c in BAD_CELLS])
def test_bad_cells_name_the_file_and_field_path(tmp_path, mutate, field, why):
    data = _cell_data()
    mutate(data)
    path = _write(tmp_path / "my cell.yaml", data)
    with pytest.raises(ConfigError) as info:
        load_cell(path)
    exc = info.value
    assert (exc.path, exc.field) == (path, field) and why in exc.message, str(exc)
    assert str(exc).startswith("%s: %s: " % (path, field))


#: (case id, file content, words)
BAD_FILES = [
    ("empty file", "", "expected a mapping, got NoneType"),
    ("a list", "- 1\n- 2\n", "expected a mapping, got list"),
    ("binary", b"\xff\xfe\x00\x80garbage", "not UTF-8 text (byte 0)"),
    ("tab indentation", "name: x\n\tbed: 1\n", "not valid YAML"),
    ("python tag", "!!python/object/apply:os.system ['touch pwned']\n", "not valid YAML"),
    ("duplicate key", "name: a\nname: b\n", "duplicate key 'name'"),
]


@pytest.mark.parametrize("content, why", [c[1:] for c in BAD_FILES], ids=[c[0] for c in BAD_FILES])
def test_a_cell_file_that_is_no_config_names_the_file(tmp_path, monkeypatch, content, why):
    monkeypatch.chdir(tmp_path)
    path = _write(tmp_path / "cell.yaml", content)
    with pytest.raises(ConfigError) as info:
        load_cell(path)
    assert info.value.path == path and why in str(info.value)
    assert no_pwned(tmp_path)


def test_duplicate_key_says_which_line(tmp_path):
    text = open(default_cell_path()).read() + "\nname: another_cell\n"
    path = _write(tmp_path / "cell.yaml", text)
    with pytest.raises(ConfigError, match=r"duplicate key 'name'\n  in .*cell.yaml\", line %d"
                       % (text.count("\n"))):
        load_cell(path)


@pytest.mark.parametrize("distance, why", [
    (2.0, "bases of 'kinova' and 'ur10' overlap: 1.500 m apart (minimum 2.00 m)"),
    (NAN, "min_base_distance: must be a finite number >= 0 (m), got nan"),
    (-1.0, "min_base_distance: must be a finite number >= 0 (m), got -1.0"),
    ("0.3", "min_base_distance: must be a finite number >= 0 (m), got '0.3'"),
], ids=["2 m", "NaN", "negative", "text"])
def test_min_base_distance_is_checked_and_used(distance, why):
    with pytest.raises(ConfigError) as info:
        load_cell(default_cell_path(), min_base_distance=distance)
    assert why in str(info.value) and default_cell_path() in str(info.value)


#: (case id, mutation of the UR10 profile, field, words)
BAD_PROFILES = [
    ("continuous as text", _set("joints", 0, "continuous", "no"), "joints[0].continuous",
     "expected true or false, got 'no'"),
    ("duplicate joint", _set("joints", 1, "name", "shoulder_pan_joint"), "joints[1].name",
     "duplicate joint name 'shoulder_pan_joint'"),
    ("NaN limit", _set("joints", 2, "upper", NAN), "joints[2].upper", "finite number"),
    ("zero velocity", _set("joints", 0, "velocity", 0), "joints[0].velocity", "must be > 0"),
    ("short home", _set("home", [0.0, 0.0]), "home", "6 finite numbers"),
    ("tool null", _set("tool", None), "tool", "expected a mapping, got NoneType"),
    ("no driver", _pop("driver"), "driver", "missing field"),
    ("zero sample period", _set("driver", "sample_period", 0), "driver.sample_period", "must be > 0"),
    ("max joint speed as text", _set("driver", "max_joint_speed", "50 deg/s"), "driver.max_joint_speed",
     "finite number"),
    ("empty extruder topic", _set("driver", "extruder_topic", ""), "driver.extruder_topic", "non-empty string"),
    ("missing model", _set("model", "urdf/no_such_robot.xacro"), "model", "no_such_robot.xacro not found"),
    ("colour as text", _set("filament_colour", "blue"), "filament_colour", "4 finite numbers"),
    ("inf reach", _set("reach", INF), "reach", "finite number"),
    ("no print head", _pop("tool", "head"), "tool.head", "missing field"),
    ("empty print head", _set("tool", "head", []), "tool.head", "non-empty list"),
    ("head at the tip", _set("tool", "head", 0, "tube", [[0, 0, -0.001], [0, 0, -0.02]]), "tool.head[0]",
     "must stay at least 2 mm behind it"),
    ("head typo", _set("tool", "heads", []), "tool.heads", "unknown field"),
    ("body of two kinds", _set("bodies", "base_link", 0, "ball", [0, 0, 0]), "bodies.base_link[0]",
     "exactly one of tube, housing, ball"),
    ("body without kind", _set("bodies", "base_link", 0, {"radius": 0.1}), "bodies.base_link[0]",
     "exactly one of tube, housing, ball, got none"),
    ("zero body radius", _set("bodies", "base_link", 0, "radius", 0), "bodies.base_link[0].radius", "must be > 0"),
    ("tube of one point", _set("bodies", "base_link", 0, "tube", [[0, 0, 0]]), "bodies.base_link[0].tube",
     "expected two points"),
    ("NaN in a tube", _set("bodies", "base_link", 0, "tube", [[0, 0, 0], [0, NAN, 0]]),
     "bodies.base_link[0].tube[1]", "3 finite numbers"),
    ("housing without axis", _set("bodies", "shoulder_link", 1, "axis", [0, 0, 0]), "bodies.shoulder_link[1].axis",
     "must not be zero"),
    ("negative reach", _set("bodies", "shoulder_link", 1, "reach", -0.01), "bodies.shoulder_link[1].reach",
     "must be >= 0"),
    ("body field typo", _set("bodies", "shoulder_link", 1, "raduis", 0.1), "bodies.shoulder_link[1].raduis",
     "unknown field"),
    ("bodies of nothing", _set("bodies", "wrist_3_link", []), "bodies.wrist_3_link", "non-empty list"),
]


@pytest.mark.parametrize("mutate, field, why", [c[1:] for c in BAD_PROFILES], ids=[c[0] for c in BAD_PROFILES])
def test_bad_arm_profiles_name_the_file_and_field_also_through_the_cell(tmp_path, mutate, field, why):
    data = _profile_data()
    mutate(data)
    prof = _write(tmp_path / "my arm.yaml", data)
    with pytest.raises(ConfigError) as info:
        load_arm_profile(prof)
    assert (info.value.path, info.value.field) == (prof, field) and why in info.value.message
    cell = _cell_data()
    cell["arms"][1]["profile"] = prof
    path = _write(tmp_path / "my cell.yaml", cell)
    with pytest.raises(ConfigError) as info:
        load_cell(path)
    assert (info.value.path, info.value.field) == (path, "arms[1].profile")
    assert "%s: %s: " % (prof, field) in info.value.message and why in info.value.message


def test_bodies_on_a_link_the_model_does_not_have_are_refused(tmp_path):
    # a misspelt link would leave its bodies out of the collision model unnoticed
    data = _profile_data()
    data["bodies"]["wrist3_link"] = data["bodies"].pop("wrist_3_link")
    prof = load_arm_profile(_write(tmp_path / "my arm.yaml", data))
    with pytest.raises(ConfigError) as info:
        arm_urdf(prof)
    assert info.value.field == "bodies.wrist3_link" and "has no link 'wrist3_link'" in info.value.message


# =============================================================================
# 6. File names with spaces, quotes and shell metacharacters
# =============================================================================

def test_builtin_job_with_a_nasty_file_name(tmp_path, monkeypatch, cell):
    monkeypatch.chdir(tmp_path)
    path = tmp_path / NASTY
    trimesh.creation.box((20.0, 20.0, 4.0)).export(str(path))
    job = run_job(str(path), cell, list(cell.arms))
    summary = write_job(job, str(tmp_path / "out $(touch pwned2) ;'\""))
    assert summary["model"] == str(path) and set(summary["arms"]) == {"kinova", "ur10"}
    assert no_pwned(tmp_path)


def test_a_line_break_in_a_file_name_cannot_inject_gcode(tmp_path):
    # found while writing these tests: the built-in slicer wrote the name raw into its header
    name = "x\nG1 Z-50 F100\n;@A1 R2\n.stl"
    path = tmp_path / name
    trimesh.creation.box((10.0, 10.0, 2.0)).export(str(path))
    gcode = slice_mesh(place_on_bed(load_model(str(path))))
    assert gcode.splitlines()[1] == "; model: x\\nG1 Z-50 F100\\n;@A1 R2\\n.stl"
    assert "G1 Z-50" not in gcode.splitlines() and not any(is_directive(l) for l in gcode.splitlines())
    assert min(e.end[2] for e in parse_gcode_text(gcode) if type(e) is Segment) >= 0


FAKE_PRUSA = """#!/bin/sh
printf '%s\\n' "$@" > "$AMBOTS_TEST_ARGV"
if [ -n "$AMBOTS_TEST_FAIL" ]; then echo "Error: cannot read model.stl" >&2; exit 3; fi
printf 'G21\\nG1 X1 Y1 F600\\n' > model.gcode
"""


@pytest.fixture
def fake_prusa(tmp_path, monkeypatch):
    """A stand-in prusa-slicer, in a folder whose name a shell would
    execute, that records its arguments one per line."""
    folder = tmp_path / "bin $(touch pwned3);'"
    folder.mkdir()
    exe = folder / "prusa-slicer"
    exe.write_text(FAKE_PRUSA)
    exe.chmod(exe.stat().st_mode | stat.S_IXUSR)
    monkeypatch.setenv("AMBOTS_TEST_ARGV", str(tmp_path / "argv.txt"))
    monkeypatch.chdir(tmp_path)
    calls = []
    real_run = __import__("subprocess").run

    def spy(args, **kw):
        calls.append((args, kw))
        return real_run(args, **kw)
    monkeypatch.setattr("ambots.slicer.subprocess.run", spy)
    return str(exe), calls


def test_prusa_wrapper_passes_an_argument_list_never_a_shell(tmp_path, fake_prusa):
    exe, calls = fake_prusa
    ini = tmp_path / "my $(touch pwned4) 'profile'.ini"
    shutil.copyfile(data_path("config", "prusa", "ambots_pla.ini"), ini)
    stl = tmp_path / NASTY
    trimesh.creation.box((10.0, 10.0, 2.0)).export(str(stl))
    out = tmp_path / "out $(touch pwned5);'\".gcode"
    slicer = PrusaSlicer(executable=exe, ini_path=ini)
    slicer.slice_file(str(stl), str(out))
    [(args, kw)] = calls
    assert isinstance(args, list) and not kw.get("shell") and args == slicer.command()
    # no user path on the command line: the files are copied to fixed names
    assert not any(NASTY in a or "pwned" in a for a in args[1:])
    assert (tmp_path / "argv.txt").read_text().splitlines() == args[1:]
    assert out.read_text().startswith("G21") and no_pwned(tmp_path)


def test_prusa_failure_names_the_users_file(tmp_path, fake_prusa, monkeypatch):
    exe, _ = fake_prusa
    monkeypatch.setenv("AMBOTS_TEST_FAIL", "1")
    stl = tmp_path / NASTY
    trimesh.creation.box((10.0, 10.0, 2.0)).export(str(stl))
    with pytest.raises(SlicerError) as info:
        PrusaSlicer(executable=exe).slice_file(str(stl), str(tmp_path / "out.gcode"))
    assert str(info.value).startswith(NASTY + ": prusa-slicer failed (exit status 3)")
    assert "Error: cannot read %s" % NASTY in str(info.value) and no_pwned(tmp_path)


@pytest.mark.parametrize("executable", ["prusa-slicer; touch pwned", "$(touch pwned)"])
def test_an_executable_name_with_shell_syntax_is_not_found_not_run(tmp_path, monkeypatch, executable):
    monkeypatch.chdir(tmp_path)
    stl = tmp_path / "cube.stl"
    trimesh.creation.box((10.0, 10.0, 2.0)).export(str(stl))
    with pytest.raises(SlicerError, match="not found"):
        PrusaSlicer(executable=executable).slice_file(str(stl), str(tmp_path / "o.gcode"))
    assert no_pwned(tmp_path)


def test_real_prusa_slicer_with_nasty_names(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    stl = tmp_path / NASTY
    trimesh.creation.box((10.0, 10.0, 2.0)).export(str(stl))
    out = tmp_path / ("out " + NASTY[:-4] + ".gcode")
    PrusaSlicer().slice_file(str(stl), str(out))
    assert any(type(e) is Segment and e.extrude for e in read_gcode(str(out)))
    mesh = place_on_bed(load_model(str(stl)))
    assert "G1 " in slice_mesh(mesh, backend="prusa")
    assert no_pwned(tmp_path)


def test_every_error_class_used_here_is_an_ambots_error():
    for cls in (ConfigError, GCodeError, MeshError, SlicerError):
        assert issubclass(cls, AmbotsError)
