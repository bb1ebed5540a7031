"""Menu choice 1 end to end, and choice 3 with programs named by robot id
(issue 16, items 6 and 1).

Choice 1 is driven as the operator drives it: the menu built from the
front end's own command line (:func:`ambots.frontend.menu_from_args`, no
``--slicer``), answers "1" then "5", the in-memory hub of
``test_frontend.FakeLink`` answering every A1 with DONE at the end of the
program it was sent.  Whether ``prusa-slicer`` is installed is set by
``PATH`` alone: a folder with a recording shim that runs the real
``/usr/bin/prusa-slicer``, or an empty folder.  The programs written are
then checked without the front end's code: read with :mod:`ambots.gcode`,
every extruding move must lie inside its arm's part (``<arm>.stl``), and
together they must cover the whole model.

Robot ids are always read from the loaded cell, never written here."""
import json
import os
import re
import shutil
import stat
import subprocess
from dataclasses import replace

import numpy as np
import pytest
import trimesh

from ambots import data_path
from ambots.config import default_cell_path, load_cell
from ambots.frontend import EXIT_OK, build_parser, load_programs, menu_from_args
from ambots.gcode import GCodeWarning, Segment, read_gcode
from ambots.job import DEMO_MODEL, run_job, write_job
from ambots.protocol import ArmState, LoadChunk, Start, Status, decode
from ambots.slicer import SliceSettings
from shapes import cube                             # tests/unit/shapes.py
from test_frontend import FakeLink, Session         # the in-memory hub and the scripted operator

#: the real PrusaSlicer (a declared dependency: Makefile APT_PACKAGES), found before any PATH change
REAL_PRUSA = shutil.which("prusa-slicer")


@pytest.fixture(scope="module")
def cell():
    return load_cell(default_cell_path())


class DoneLink(FakeLink):
    """The in-memory hub; each arm answers its A1 with PRINTING, then DONE at
    the last line of the program it was sent (A5)."""

    def _hub_receives(self, text):
        msg = decode(text)
        if isinstance(msg, LoadChunk):
            n = len(msg.gcode.splitlines())
            self.replies[msg.robot] = [Status(msg.robot, ArmState.PRINTING, 0, 1, 0.0),
                                       Status(msg.robot, ArmState.DONE, 0, n, 100.0)]
        super()._hub_receives(text)


def operator(answers, cell, argv, link=None):
    """A scripted operator at the menu that ``front_end ARGV`` shows."""
    s = Session(answers, cell, link=link or DoneLink())
    s.menu = menu_from_args(build_parser().parse_args(argv), s.link, cell, input=s.ask, output=s.lines.append,
                            error=s.errors.append, clock=s.link.clock)
    return s


@pytest.fixture
def prusa_on_path(tmp_path, monkeypatch):
    """PATH = a folder whose ``prusa-slicer`` records its arguments, one
    line per run, then runs the real one; returns (shim path, log path)."""
    assert REAL_PRUSA, "prusa-slicer is not installed (make setup installs it)"
    folder, log = tmp_path / "bin", tmp_path / "prusa_calls.log"
    folder.mkdir()
    shim = folder / "prusa-slicer"
    shim.write_text('#!/bin/sh\necho "$*" >> "%s"\nexec "%s" "$@"\n' % (log, REAL_PRUSA))
    shim.chmod(shim.stat().st_mode | stat.S_IXUSR)
    monkeypatch.setenv("PATH", "%s%s%s" % (folder, os.pathsep, os.environ.get("PATH", "")))
    return str(shim), log


@pytest.fixture
def no_prusa_on_path(tmp_path, monkeypatch):
    """PATH = an empty folder: no prusa-slicer anywhere on it."""
    empty = tmp_path / "empty_bin"
    empty.mkdir()
    monkeypatch.setenv("PATH", str(empty))


def prusa_version():
    """The version the real prusa-slicer states (first line of --help)."""
    out = subprocess.run([REAL_PRUSA, "--help"], capture_output=True, text=True, timeout=60)
    return re.search(r"PrusaSlicer-(\S+)", out.stdout + out.stderr).group(1)


def check_programs(out, cell, sent):
    """The programs in ``out`` are the ones sent, valid, and print the
    model: each arm's extrusion inside its own part, all of it covering
    the model.  Independent of the front end's slicing code."""
    summary = json.loads((out / "job.json").read_text())
    names = list(summary["arms"])
    assert names and set(names) <= {a.name for a in cell.arms}
    # valid for this cell (readable G-code, directives naming its arms), and what the hub was sent
    loaded = load_programs(str(out), cell)
    assert sorted(loaded) == sorted(names)
    assert {m.robot: m.gcode for m in sent} == {cell.arm(n).id: (out / (n + ".gcode")).read_text() for n in names}
    settings, lo, hi = SliceSettings(), [], []
    tol = settings.bead_width_mm / 2 + 0.05
    parts = {n: trimesh.load(str(out / (n + ".stl"))) for n in names}
    for name in names:
        events = list(read_gcode(str(out / (name + ".gcode"))))
        assert [e for e in events if type(e) is GCodeWarning] == []
        beads = np.array([e.start + e.end for e in events if type(e) is Segment and e.extrude
                          and e.start != e.end]).reshape(-1, 3)
        assert len(beads) > 100, name
        part_lo, part_hi = parts[name].bounds
        assert np.all(beads[:, :2] >= part_lo[:2] - tol) and np.all(beads[:, :2] <= part_hi[:2] + tol), name
        assert beads[:, 2].min() == pytest.approx(settings.first_layer_height_mm)
        assert beads[:, 2].max() == pytest.approx(part_hi[2], abs=settings.layer_height_mm / 2)
        layers = sorted(set(np.round(beads[:, 2], 3)))
        expected = 1 + round((part_hi[2] - settings.first_layer_height_mm) / settings.layer_height_mm)
        assert len(layers) == expected, name                  # every layer printed, none twice
        lo.append(beads.min(axis=0))
        hi.append(beads.max(axis=0))
    model_lo = np.min([p.bounds[0] for p in parts.values()], axis=0)
    model_hi = np.max([p.bounds[1] for p in parts.values()], axis=0)
    demo = trimesh.load(data_path(DEMO_MODEL))
    np.testing.assert_allclose(model_hi - model_lo, demo.extents, atol=1e-6)     # the parts are the demo block
    np.testing.assert_allclose(np.min(lo, axis=0)[:2], model_lo[:2], atol=2 * tol)
    np.testing.assert_allclose(np.max(hi, axis=0)[:2], model_hi[:2], atol=2 * tol)
    return summary


def finished(s, summary, cell):
    labels = ", ".join("%s (R%d)" % (n, cell.arm(n).id) for n in summary["arms"])
    return any(l.startswith("print finished: every arm is DONE (%s)" % labels) for l in s.lines)


# ------------------------------------------------------------------ choice 1

def test_choice_1_slices_the_demo_with_prusaslicer_where_it_is_installed(cell, tmp_path, prusa_on_path):
    shim, calls = prusa_on_path
    out = tmp_path / "demo"
    s = operator(["1", "5"], cell, ["--out", str(out)])
    assert s.run() == EXIT_OK and s.errors == [], s.text
    assert "slicer: PrusaSlicer %s (%s); --slicer auto: prusa-slicer is installed" % (prusa_version(), shim) \
        in s.lines, s.text
    assert any(l.startswith("slicing %s (cell %s, prusa slicer, " % (data_path(DEMO_MODEL), cell.name))
               for l in s.lines)
    runs = calls.read_text().splitlines()
    assert len([r for r in runs if "--export-gcode" in r]) >= 1          # the real PrusaSlicer sliced
    summary = check_programs(out, cell, s.link.messages(LoadChunk))
    assert summary["slicer"] == "prusa"
    assert sorted(m.robot for m in s.link.messages(Start)) == sorted(cell.arm(n).id for n in summary["arms"])
    assert finished(s, summary, cell), s.text


def test_choice_1_falls_back_to_the_builtin_slicer_without_prusaslicer(cell, tmp_path, no_prusa_on_path):
    out = tmp_path / "demo"
    s = operator(["1", "5"], cell, ["--out", str(out)])
    assert s.run() == EXIT_OK and s.errors == [], s.text
    assert "slicer: built-in slicer; --slicer auto: prusa-slicer not found on PATH" in s.lines, s.text
    assert not any("PrusaSlicer" in l for l in s.lines)
    assert any(l.startswith("slicing %s (cell %s, builtin slicer, " % (data_path(DEMO_MODEL), cell.name))
               for l in s.lines)
    summary = check_programs(out, cell, s.link.messages(LoadChunk))
    assert summary["slicer"] == "builtin"
    assert finished(s, summary, cell), s.text


def test_an_explicit_slicer_is_respected(cell, tmp_path, prusa_on_path, monkeypatch):
    _, calls = prusa_on_path
    model = tmp_path / "cube20.stl"
    cube().export(str(model))
    # --slicer builtin with PrusaSlicer installed: the built-in one, prusa-slicer never runs
    s = operator(["2", "", "5"], cell, ["--slicer", "builtin", "--model", str(model), "--out", str(tmp_path / "b")])
    assert s.run() == EXIT_OK and s.errors == [], s.text
    assert "slicer: built-in slicer; --slicer builtin" in s.lines
    assert not calls.exists()
    assert json.loads((tmp_path / "b" / "job.json").read_text())["slicer"] == "builtin"
    # --slicer prusa without PrusaSlicer: one line, no silent change of slicer, nothing written or sent
    monkeypatch.setenv("PATH", str(tmp_path / "nothing"))
    s = operator(["1", "5"], cell, ["--slicer", "prusa", "--out", str(tmp_path / "p")])
    assert s.run() == EXIT_OK
    assert s.errors == ["error: --slicer prusa: 'prusa-slicer' not found; install PrusaSlicer (apt install "
                        "prusa-slicer) or use --slicer builtin or auto"]
    assert not (tmp_path / "p").exists() and s.link.sent == [] and s.menus_shown() == 2


def test_the_menu_defaults_to_auto_and_a_scripted_print_to_builtin(cell):
    parse = build_parser().parse_args
    assert menu_from_args(parse([]), FakeLink(), cell).slicer == "auto"
    assert menu_from_args(parse(["--print"]), FakeLink(), cell).slicer == "builtin"
    assert menu_from_args(parse(["--print", "--slicer", "auto"]), FakeLink(), cell).slicer == "auto"
    assert menu_from_args(parse(["--slicer", "builtin"]), FakeLink(), cell).slicer == "builtin"


# ------------------------------------------------------------------ choice 3: files named by robot id

@pytest.fixture(scope="module")
def sequential(cell, tmp_path_factory):
    """A cube on both arms, sequential (the first program starts the second with ;@A1)."""
    model = tmp_path_factory.mktemp("models") / "cube20.stl"
    cube().export(str(model))
    return run_job(str(model), cell, list(cell.arms), mode="sequential")


def by_robot_id(directory, cell, names=None):
    """Rename ``<arm>.gcode`` to ``<robot id>.gcode`` (the cell's ids)."""
    for arm in cell.arms:
        if names is None or arm.name in names:
            os.rename(directory / (arm.name + ".gcode"), directory / ("%d.gcode" % arm.id))


def test_choice_3_loads_programs_named_by_robot_id(cell, sequential, tmp_path):
    write_job(sequential, str(tmp_path))
    texts = {a.id: (tmp_path / (a.name + ".gcode")).read_text() for a in cell.arms}
    by_robot_id(tmp_path, cell)
    s = Session(["3", str(tmp_path), "5"], cell)
    assert s.run() == EXIT_OK and s.errors == [], s.text
    assert "loaded %s from %s" % (", ".join("%d.gcode for %s (R%d)" % (a.id, a.name, a.id) for a in cell.arms),
                                  tmp_path) in s.lines
    a5 = s.link.messages(LoadChunk)
    assert {m.robot: m.gcode for m in a5} == texts              # each file to the arm of that id
    first = cell.arms[0]
    assert {n: p.start_first for n, p in s.menu.programs.items()} == {
        a.name: a is first for a in cell.arms}                 # the ;@A1 inside still counts
    assert "the hub acknowledged the G-code of %s" % ", ".join(a.name for a in cell.arms) in s.lines


def test_choice_3_mixes_names_and_ids_and_refuses_both_for_one_arm(cell, sequential, tmp_path):
    write_job(sequential, str(tmp_path))
    named, numbered = cell.arms
    by_robot_id(tmp_path, cell, [numbered.name])
    s = Session(["3", str(tmp_path), "5"], cell)
    assert s.run() == EXIT_OK and s.errors == [], s.text
    assert "loaded %s.gcode, %d.gcode for %s (R%d) from %s" % (named.name, numbered.id, numbered.name,
                                                               numbered.id, tmp_path) in s.lines
    assert sorted(m.robot for m in s.link.messages(LoadChunk)) == sorted(a.id for a in cell.arms)
    # both names for one arm: which is meant is not guessed, nothing is sent
    shutil.copyfile(tmp_path / ("%d.gcode" % numbered.id), tmp_path / (numbered.name + ".gcode"))
    s = Session(["3", str(tmp_path), "5"], cell)
    assert s.run() == EXIT_OK and s.link.sent == []
    assert s.errors == ["error: %s: both %s.gcode and %d.gcode are there for %s (R%d): which to send is not "
                        "guessed; remove one" % (tmp_path, numbered.name, numbered.id, numbered.name, numbered.id)]


def test_choice_3_takes_the_ids_from_the_cell(cell, tmp_path):
    """Plain G-code (no directives), as the original's files: with the
    arms' ids changed in the cell, the files follow the ids."""
    ids = [a.id + 40 for a in cell.arms]
    other = replace(cell, arms=tuple(replace(a, id=i) for a, i in zip(cell.arms, ids)))
    sample = open(data_path("gcode", "sample_square.gcode")).read()
    for a in cell.arms:                                    # the default cell's ids: not arms of `other`
        (tmp_path / ("%d.gcode" % a.id)).write_text(sample)
    s = Session(["3", str(tmp_path), "5"], other)
    assert s.run() == EXIT_OK and s.link.sent == []
    assert s.errors == ["error: %s: no program for any arm of cell %s (looked for %s)" % (
        tmp_path, other.name, ", ".join("%s.gcode or %d.gcode" % (a.name, a.id) for a in other.arms))]
    for a in other.arms:
        (tmp_path / ("%d.gcode" % a.id)).write_text(sample.replace("20 x 20 mm", "R%d's" % a.id))
    s = Session(["3", str(tmp_path), "5"], other)
    assert s.run() == EXIT_OK and s.errors == [], s.text
    a5 = s.link.messages(LoadChunk)
    assert sorted(m.robot for m in a5) == sorted(ids)
    for m in a5:
        assert "R%d's" % m.robot in m.gcode
    assert all(p.start_first for p in s.menu.programs.values())
