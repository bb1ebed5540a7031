"""The G-code reader (ambots.gcode) and ``python -m ambots info``."""
import io
import itertools
import json
import math
import random
import re
import subprocess
import sys
import tracemalloc
import types
from contextlib import redirect_stderr, redirect_stdout

import pytest
import trimesh

from ambots import data_path
from ambots.cli import main as cli_main
from ambots.errors import GCodeError
from ambots.gcode import (MAX_ABS_MM, Command, Dwell, GCodeWarning, Segment, iter_gcode,
                          parse_gcode_text, read_gcode, summarize, summarize_file)


def events(text, **kw):
    return list(parse_gcode_text(text, "t.gcode", **kw))


def segs(text, **kw):
    return [ev for ev in events(text, **kw) if type(ev) is Segment]


def of(kind, evs):
    return [ev for ev in evs if type(ev) is kind]


def error(text):
    with pytest.raises(GCodeError) as info:
        events(text)
    return info.value


def checksum(body):
    x = 0
    for c in body:
        x ^= ord(c)
    return "%s*%d" % (body, x)


# --- linear moves, modes, units ---------------------------------------------

def test_linear_moves_are_typed_segments_in_mm():
    s = segs("G21\nG90\nM83\nG0 X10 Y5 F3000\nG1 X20 E1.5 F1200\nG1 Z0.4\nG1 E-2\n")
    assert [type(x) for x in s] == [Segment] * 4
    assert s[0] == Segment((0.0, 0.0, 0.0), (10.0, 5.0, 0.0), 0.0, 3000.0, False, 4, -1)
    assert s[1].start == (10.0, 5.0, 0.0) and s[1].end == (20.0, 5.0, 0.0)
    assert s[1].e == 1.5 and s[1].extrude and s[1].feedrate == 1200.0 and s[1].line == 5
    assert s[2].end == (20.0, 5.0, 0.4) and not s[2].extrude
    assert s[3].e == -2.0 and not s[3].extrude and s[3].start == s[3].end


def test_every_g0_g1_gives_one_segment_even_without_motion():
    s = segs("G1 F1800\nG1 X1\nG1 X1\n")
    assert [x.line for x in s] == [1, 2, 3]
    assert s[0].start == s[0].end and s[0].feedrate == 1800.0


def test_absolute_and_relative_axes_and_extrusion():
    s = segs("G1 X1 Y1 E1 F600\nG91\nG1 X1 Y2 E0.5\nG90\nG1 X5 E3\nM83\nG1 E0.25\nM82\nG1 E4\n")
    assert [x.end[:2] for x in s] == [(1, 1), (2, 3), (5, 3), (5, 3), (5, 3)]
    # G91 makes E relative too (Marlin), G90 absolute again; M83/M82 switch E alone
    assert [x.e for x in s] == [1.0, 0.5, 1.5, 0.25, 0.75]


def test_inches():
    s = segs("G20\nG1 X1 Y-0.5 Z0.1 E0.01 F10\nG21\nG1 X1\n")
    assert s[0].end == pytest.approx((25.4, -12.7, 2.54))
    assert s[0].e == pytest.approx(0.254) and s[0].feedrate == pytest.approx(254.0)
    assert s[1].end[0] == 1.0


def test_g92_renames_position_without_moving_and_segments_stay_continuous():
    s = segs("G1 X10 Y10 E5 F600\nG92 X0 Y0 E0\nG1 X5 E1\nG92 E0\nG1 X6 E0.5\n")
    assert s[1].start == (10.0, 10.0, 0.0) and s[1].end == (15.0, 10.0, 0.0)
    assert s[1].e == pytest.approx(1.0) and s[2].e == pytest.approx(0.5)
    for a, b in zip(s, s[1:]):
        assert a.end == b.start


def test_g28_homes_to_origin_and_is_passed_through():
    evs = events("G1 X10 Y20 Z3 F600\nG92 X0\nG28 X\nG1 Y21\nG28\nG1 X1\n")
    home = of(Command, evs)
    assert [(c.code, c.text, c.line) for c in home] == [("G28", "G28 X", 3), ("G28", "G28", 5)]
    s = of(Segment, evs)
    assert s[1].start == (0.0, 20.0, 3.0) and s[1].end == (0.0, 21.0, 3.0)
    assert s[2].start == (0.0, 0.0, 0.0) and s[2].end == (1.0, 0.0, 0.0)   # G92 offset cleared


def test_dwell():
    d = of(Dwell, events("G4 P250\nG4 S1.5\nG4\n"))
    assert [x.seconds for x in d] == [0.25, 1.5, 0.0]
    assert "not both" in error("G4 P1 S1").message
    assert "negative" in error("G4 P-5").message


def test_comments_case_blank_lines_and_compact_words():
    s = segs("\n  \n; a comment\ng1 x1 y2 f100 ; trailing\n(paren) G1 (in between) X3 (end)\n"
             "G1X4Y5 E.5\n\tG1\tX6\n")
    assert [x.end[:2] for x in s] == [(1, 2), (3, 2), (4, 5), (6, 5)]
    assert [x.line for x in s] == [4, 5, 6, 7] and s[2].e == 0.5


def test_paren_comment_errors():
    assert "unclosed" in error("G1 X1 (oops").message
    assert "nested" in error("G1 (a (b) c) X1").message
    assert "without" in error("G1 X1 )").message


def test_line_numbers_and_checksums():
    good = checksum("N10 G1 X5 Y6 F900")
    s = segs(good + "\n" + checksum("N11 G1 X7") + "\nN12 G1 X8\n")
    assert [x.end[0] for x in s] == [5.0, 7.0, 8.0]
    bad = good[:-1] + str((int(good[-1]) + 1) % 10)
    exc = error("G1 X1\n" + bad + "\n")
    assert (exc.path, exc.line, exc.text) == ("t.gcode", 2, bad) and "checksum" in exc.message
    assert "checksum" in error("N1 G1 X1*").message
    assert "line number" in error("Nx G1 X1").message


def test_arcs_ij_within_chord_tolerance():
    tol = 0.01
    for code, side in (("G2", 1), ("G3", -1)):      # CW from (0,0) to (20,0) about (10,0) goes up
        s = segs("G1 X0 Y0 F600\n%s X20 Y0 I10 J0 E3" % code, arc_tolerance_mm=tol)[1:]
        assert len(s) > 10 and {x.line for x in s} == {2}
        assert s[0].start == (0.0, 0.0, 0.0) and s[-1].end == (20.0, 0.0, 0.0)
        for a, b in zip(s, s[1:]):
            assert a.end == b.start
        for x in s:
            assert math.hypot(x.end[0] - 10, x.end[1]) == pytest.approx(10, abs=1e-9)
            mid = ((x.start[0] + x.end[0]) / 2 - 10, (x.start[1] + x.end[1]) / 2)
            assert 10 - math.hypot(*mid) <= tol + 1e-12          # sagitta within tolerance
            assert side * x.end[1] >= -1e-9
        assert sum(x.e for x in s) == pytest.approx(3.0, rel=1e-12) and all(x.extrude for x in s)
        assert sum(math.dist(x.start, x.end) for x in s) == pytest.approx(10 * math.pi, rel=1e-3)


def test_arc_full_circle_helix_and_r_form():
    s = segs("G1 X10 Y0 F600\nG3 X10 Y0 I-10 J0 Z2 E6")[1:]      # full circle rising 2 mm
    assert s[-1].end == (10.0, 0.0, 2.0)
    assert sum(math.dist(x.start[:2], x.end[:2]) for x in s) == pytest.approx(20 * math.pi, rel=1e-3)
    assert all(b.end[2] > a.end[2] for a, b in zip(s, s[1:]))
    ij = segs("G1 X0 Y0 F600\nG2 X10 Y10 I10 J0")[1:]
    r = segs("G1 X0 Y0 F600\nG2 X10 Y10 R10")[1:]
    assert len(r) == len(ij)
    for a, b in zip(r, ij):
        assert a.end == pytest.approx(b.end)
    long = segs("G1 X0 Y0 F600\nG2 X10 Y10 R-10")[1:]             # R < 0: the long way round
    assert sum(math.dist(x.start, x.end) for x in long) == pytest.approx(15 * math.pi, rel=1e-3)


def test_arc_errors():
    assert "I/J" in error("G2 X1 Y1").message
    assert "not both" in error("G2 X1 Y1 R1 I1").message
    assert "too small" in error("G2 X10 Y0 R2").message
    assert "cannot end where it starts" in error("G2 X0 Y0 R5").message
    assert "not on the circle" in error("G2 X30 Y0 I10 J0").message
    assert "zero" in error("G2 X0 Y0 I0 J0").message
    assert "XY-plane" in error("G18").message


def test_pass_through_commands_keep_line_numbers_and_never_move():
    evs = events("M104 S200\nM106 S255\nT0\nG29 W\nM117 Hello X100 Y100\nA7 R1 X100 Y50 Z10\n"
                 "a1 r2\nG1 X1 F100\n")
    cmds = of(Command, evs)
    assert [(c.code, c.line) for c in cmds] == [("M104", 1), ("M106", 2), ("T0", 3), ("G29", 4),
                                                ("M117", 5), ("A7", 6), ("A1", 7)]
    assert cmds[4].text == "M117 Hello X100 Y100"
    s = of(Segment, evs)
    assert len(s) == 1 and s[0].start == (0.0, 0.0, 0.0)             # A7 did not move anything
    assert {w.line for w in of(GCodeWarning, evs)} >= {4, 6, 7}       # G29 and A-series warned


def test_layers_from_z_changes():
    s = segs("M83\nG1 Z0.2 F600\nG1 X10 E1\nG1 Z0.6\nG1 X0\nG1 Z0.2\nG1 X10 E1\nG1 Z0.4\nG1 X0 E1\n")
    # the Z-hop to 0.6 without extrusion is not a layer
    assert [x.layer for x in s] == [-1, 0, 0, 0, 0, 0, 0, 1]


def test_layers_from_slicer_comments():
    text = ("M83\nG1 Z0.2 F600\nG1 X1 E1\n;LAYER_CHANGE\n;Z:0.2\nG1 X2 E1\nG1 Z5\nG1 X3 E1\n"
            ";LAYER:7\nG1 X4 E1\n; layer 3, Z = 0.6\nG1 X5 E1\n;LAYER_COUNT:9\nG1 X6 E1\n")
    # purge line before the first comment is a layer of its own; Z-hops no longer count
    assert [x.layer for x in segs(text)] == [-1, 0, 1, 1, 1, 2, 3, 3]


def test_errors_name_file_line_and_text():
    exc = error("G1 X1\nG1 X2 Y\n")
    assert (exc.path, exc.line, exc.text) == ("t.gcode", 2, "G1 X2 Y")
    assert str(exc).startswith("t.gcode:2: ")


@pytest.mark.parametrize("line, why", [
    ("G1 Xnan", "not finite"), ("G1 X-inf", "not finite"),
    ("G1 X1000000000", "beyond"), ("G1 X2000000", "beyond"), ("G1 X1e9", "ambiguous"),
    ("G1 X1E-05", "ambiguous"), ("G1 E1E5", "ambiguous"), ("G1 F0", "F must be > 0"), ("G1 X1 F-5", "F must be > 0"),
    ("G1 X1 Q2", "does not take"), ("G1 X1 X2", "twice"), ("G1 X1_0", "unexpected"),
    ("G1 X1.2.3", "unexpected"), ("G1 X--1", "no value"), ("G1 X", "no value"),
    ("G1 X\u0661", "non-ASCII"), ("G1 X1\x00", "control"), ("X10 Y10", "must start with"),
    ("Hello", "must start with"), ("G90 X1", "does not take"), ("G92 Q1", "does not take"),
    ("G1 X\u00df", "non-ASCII"),
])
def test_bad_values_are_rejected(line, why):
    exc = error("G1 F600\n" + line + "\n")
    assert exc.line == 2 and why in exc.message


def test_position_beyond_limit_by_relative_moves():
    assert "beyond" in error("G91\nG1 X900000 F1\nG1 X900000\n").message


def test_compact_words_need_a_space_before_e():
    # firmware reads X1E5 as X1 E5, a script meant 1e5: neither is guessed
    assert "ambiguous" in error("G1X1E5").message
    assert segs("G1X1Y2 E5 F600\n")[0].e == 5.0


def test_non_ascii_is_fine_in_comments():
    assert len(segs("G1 X1 F600 ; température ✓\n(naïve) G1 X2\n")) == 2


def test_a_series_lines_are_not_motion_even_glued():
    evs = events("G1 X1 F600\nA7R1X100Y50Z10\nN5 A1 R2\n")
    assert [c.code for c in of(Command, evs)] == ["A7", "A1"]
    assert len(of(Segment, evs)) == 1


# --- streaming ----------------------------------------------------------------

def test_reader_is_a_lazy_generator():
    lines = itertools.cycle(["G1 X1 Y1 E0.1 F600\n", "G1 X0 Y0 E0.1\n"])   # endless input
    gen = iter_gcode(lines)
    assert isinstance(gen, types.GeneratorType)
    first = list(itertools.islice(gen, 1000))
    assert len(first) == 1000 and first[-1].line == 1000


def test_memory_does_not_grow_with_file_length(tmp_path):
    def peak(n):
        path = tmp_path / ("m%d.gcode" % n)
        with open(path, "w") as f:
            f.write("G1 F600\n" + "".join("G1 X%d Y%d E0.01\n" % (i % 100, i % 37) for i in range(n)))
        tracemalloc.start()
        count = sum(1 for _ in read_gcode(path))
        _, top = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        assert count == n + 1
        return top
    small, big = peak(2000), peak(40000)
    assert big < small * 1.5 + 20000


# --- summary and CLI -------------------------------------------------------------

SAMPLE = """; hand-made
G21
G90
M83
M104 S200
G1 Z0.2 F600
G1 X10 Y0 F1200
G1 E1 F1200
G1 X10 Y10 E2 F600
G3 X0 Y10 I-5 J0 E1
G1 E-0.5 F1200
G0 X0 Y0 F6000
G4 P500
A2 R1
"""


def test_summary_of_a_hand_written_file(tmp_path):
    path = tmp_path / "s.gcode"
    path.write_text(SAMPLE)
    s = summarize_file(path)
    assert s["moves"] == 7 and s["a_commands"] == 1 and s["layers"] == 1
    assert s["extruded_filament_mm"] == pytest.approx(3.5)
    assert s["retracted_at_end_mm"] == pytest.approx(0.5)
    assert s["extrude_path_mm"] == pytest.approx(10 + 5 * math.pi, rel=1e-3)   # chords
    assert s["travel_path_mm"] == pytest.approx(0.2 + 10 + 10)
    assert s["bbox_mm"][0] == pytest.approx([0, 0, 0.2], abs=1e-3)
    assert s["bbox_mm"][1] == pytest.approx([10, 15, 0.2], abs=0.01)   # chord tolerance
    expected_t = (0.2 / 600 + 10 / 1200 + 1 / 1200 + 10 / 600
                  + 5 * math.pi / 600 + 0.5 / 1200 + 10 / 6000) * 60 + 0.5
    assert s["print_time_s"] == pytest.approx(expected_t, rel=1e-3)
    assert [w["line"] for w in s["warnings"]] == [14]


def test_summary_caps_warnings():
    s = summarize(parse_gcode_text("G29\n" * 150), max_warnings=100)
    assert len(s["warnings"]) == 101 and "50 more" in s["warnings"][-1]["message"]


def run_cli(*argv):
    out, err = io.StringIO(), io.StringIO()
    with redirect_stdout(out), redirect_stderr(err):
        rc = cli_main(list(argv))
    return rc, out.getvalue(), err.getvalue()


def test_info_json_and_text(tmp_path):
    path = tmp_path / "s.gcode"
    path.write_text(SAMPLE)
    rc, out, _ = run_cli("info", str(path), "--json")
    data = json.loads(out)
    assert rc == 0 and out.count("\n") == 1
    for key in ("moves", "extruded_filament_mm", "extrude_path_mm", "travel_path_mm", "layers",
                "bbox_mm", "print_time_s", "a_commands", "warnings"):
        assert key in data
    assert data["warnings"][0] == {"line": 14, "message": data["warnings"][0]["message"]}
    rc, out, _ = run_cli("info", str(path))
    assert rc == 0 and "moves            7" in out


def test_info_bad_file_exits_2_naming_file_and_line(tmp_path):
    path = tmp_path / "bad.gcode"
    path.write_text("G1 X1 F600\nG1 X1 Ynan\n")
    rc, out, err = run_cli("info", str(path), "--json")
    assert rc == 2 and out == ""
    assert "%s:2:" % path in err and err.count("\n") == 1
    rc, _, err = run_cli("info", str(tmp_path / "missing.gcode"))
    assert rc == 2 and "cannot open" in err


def test_info_entry_point(tmp_path):
    path = tmp_path / "s.gcode"
    path.write_text(SAMPLE)
    out = subprocess.run([sys.executable, "-m", "ambots", "info", str(path), "--json"],
                         capture_output=True, text=True, check=True).stdout
    assert json.loads(out)["moves"] == 7


def test_shipped_sample_reads():
    s = summarize_file(data_path("gcode", "sample_square.gcode"))
    assert s["layers"] == 3 and s["a_commands"] == 0 and not s["warnings"]
    assert s["bbox_mm"] == [[-10, -10, 0.2], [10, 10, 0.6]]


# --- real PrusaSlicer output ---------------------------------------------------

@pytest.fixture(scope="module")
def sliced(tmp_path_factory):
    """A 20 x 30 x 5 mm box sliced with config/prusa/ambots_pla.ini."""
    tmp = tmp_path_factory.mktemp("slice")
    stl, out = tmp / "box.stl", tmp / "box.gcode"
    trimesh.creation.box((20.0, 30.0, 5.0)).export(stl)
    subprocess.run(["prusa-slicer", "--export-gcode", "--load",
                    data_path("config", "prusa", "ambots_pla.ini"), "-o", str(out), str(stl)],
                   check=True, capture_output=True)
    return out


def test_prusaslicer_output_agrees_with_the_file(sliced):
    text = sliced.read_text()
    s = summarize_file(sliced)
    assert not s["warnings"] and s["a_commands"] == 0
    # the file's own numbers: footer, and a naive sum of E words (relative E, M83)
    footer = float(re.search(r"^; filament used \[mm\] = ([\d.]+)$", text, re.M).group(1))
    assert "\nM83" in text
    code = [line.split(";")[0] for line in text.splitlines()]
    e_words = [float(m.group(1)) for c in code for m in [re.search(r"\bE([-\d.]+)", c)]
               if c.startswith("G1") and m]
    assert s["extruded_filament_mm"] == pytest.approx(sum(e_words), rel=1e-6)
    # PrusaSlicer's "filament used" counts the final retraction as used; it is
    # printed to 0.01 mm and sums E values before their rounding to 0.00001 mm
    used = s["extruded_filament_mm"] + s["retracted_at_end_mm"]
    assert used == pytest.approx(footer, abs=0.005 + 0.5e-5 * len(e_words))
    assert s["moves"] == sum(1 for c in code if c.startswith(("G0 ", "G1 ")))
    assert s["layers"] == text.count(";LAYER_CHANGE") == 25
    # bbox vs the model: centred on the bed (100, 100), within a bead width (0.45 mm)
    (x0, y0, z0), (x1, y1, z1) = s["bbox_mm"]
    bead = 0.45
    for got, want in ((x0, 90), (x1, 110), (y0, 85), (y1, 115)):
        assert abs(got - want) <= bead
    assert (z0, z1) == pytest.approx((0.2, 5.0))
    assert x0 >= 90 and x1 <= 110 and y0 >= 85 and y1 <= 115       # inside the footprint
    # no acceleration in our time, so at most PrusaSlicer's estimate
    m = re.search(r"estimated printing time \(normal mode\) = (?:(\d+)h )?(\d+)m (\d+)s", text)
    est = int(m.group(1) or 0) * 3600 + int(m.group(2)) * 60 + int(m.group(3))
    assert 0.6 * est < s["print_time_s"] <= est + 1


# --- robustness: 10,000 random and mutated lines ----------------------------------

_CORPUS = [
    "G1 X10.5 Y-3 Z0.2 E0.0123 F1800", "G0 X0 Y0", "G1 E-0.8 F2100", "G2 X10 Y0 I5 J0 E0.3",
    "G3 X0 Y10 R10", "G2 X5 Y5 R-5", "G4 P200", "G4 S1", "G20", "G21", "G28", "G28 X Y",
    "G90", "G91", "M82", "M83", "G92 E0", "G92 X1 Y2", "M104 S200", "M106 S255", "T1",
    "M117 Hello there", ";LAYER_CHANGE", "; layer 2, Z = 0.4", "(note) G1 X1", "N12 G1 X3*1",
    "A1 R2", "A7 R1 X100 Y50 Z10", "A5 R1", "g1 x1 y1", "G1X1Y1E1", "G17", "G29 W",
]
_JUNK = ["nan", "NaN", "inf", "-inf", "1e9", "1e400", "99999999999", "-0", ".", "-", "+", "*",
         ";", "(", ")", "\u00e9", "\u00df", "\u0661", "\u2028", "\x00", "\t", " ", "E", "X",
         "N", "A", "R", "Q", "*255", "_", "0x10", "1,5"]


def mutate(rng, line):
    for _ in range(rng.randint(0, 3)):
        k = rng.random()
        pos = rng.randint(0, len(line))
        if k < 0.25:
            line = line[:pos]
        elif k < 0.5:
            line = line[:pos] + rng.choice(_JUNK) + line[pos:]
        elif k < 0.7:
            line = line[:pos] + chr(rng.randint(32, 126)) + line[pos + 1:]
        elif k < 0.8:
            line = line[:pos] + line[pos + 1:]
        elif k < 0.9:
            line = "".join(chr(rng.randint(0, 0x2FF)) for _ in range(rng.randint(0, 12)))
        else:
            line = ""
    return line


def test_random_and_mutated_lines_never_crash_the_reader():
    rng = random.Random(1234)
    read = rejected = 0
    for i in range(10000):
        line = mutate(rng, rng.choice(_CORPUS))
        try:
            evs = list(iter_gcode(["G1 X1 Y1 F1200", line], "fuzz"))
        except GCodeError as exc:
            assert exc.line == 2 and exc.path == "fuzz"
            rejected += 1
            continue
        read += 1
        for ev in evs:
            assert type(ev) in (Segment, Command, Dwell, GCodeWarning)
            if type(ev) is Segment:
                for v in ev.start + ev.end:
                    assert math.isfinite(v) and abs(v) <= MAX_ABS_MM
                assert math.isfinite(ev.e) and ev.feedrate > 0
            elif type(ev) is Dwell:
                assert 0 <= ev.seconds <= MAX_ABS_MM
    assert read > 2000 and rejected > 2000
