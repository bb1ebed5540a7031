"""The front end's menu and reliable link (ambots.frontend), without ROS.

The menu talks through :class:`FakeLink`: a real ReliableLink whose far side
is an in-memory stand-in for the hub that records every A-series string the
front end transmits, acknowledges its numbered messages as the hub does
(``A8 R1000 Q<q> S1001``) and, after an A1, feeds scripted A10/A11 replies as
the hub forwards them (``S1001`` and the hub's own numbering).  Time is fake:
a wait with nothing to deliver lets the clock run.
The default cell renumbered (fixture ``cell``): kinova = R1, ur10 = R2."""
import dataclasses
import itertools
import json
import os
from collections import deque
from dataclasses import replace

import numpy as np
import pytest
import trimesh

from ambots import topics
from ambots.config import default_cell_path, load_cell
from ambots.frontend import (CHOICES, EXIT_BAD_INPUT, EXIT_FAILED, EXIT_OK, Menu, ReliableLink,
                             Undelivered, build_parser, load_programs, menu_from_args, print_timeout_s)
from ambots.job import run_job, write_job
from ambots.protocol import (Ack, ArmState, ErrorReport, LoadChunk, Start, Status, decode, encode)
from shapes import cube  # tests/unit/shapes.py

FE = topics.FRONT_END_ID
HUB_FIRST_Q = 7000


class FakeLink(ReliableLink):
    """A ReliableLink wired to an in-memory hub (see the module docstring).
    ``replies``: {robot id: [Status / ErrorReport, ...]} fed after that
    arm's A1; ``ack``: whether the hub acknowledges; ``interrupt``: a wait
    with nothing to deliver raises KeyboardInterrupt (the user's Ctrl-C)."""

    def __init__(self, replies=None, ack=True, interrupt=False):
        self.now = 0.0
        super().__init__(self._hub_receives, clock=lambda: self.now, first_seq=500)
        self.sent = []                 # every string the front end transmitted
        self.replies, self.ack, self.interrupt = dict(replies or {}), ack, interrupt
        self._queue = deque()
        self._hub_q = itertools.count(HUB_FIRST_Q)

    def _hub_receives(self, text):
        self.sent.append(text)
        msg = decode(text)
        if isinstance(msg, Ack):
            return
        if self.ack:
            self._queue.append(encode(Ack(FE, msg.seq, topics.HUB_ID)))
        if isinstance(msg, Start):
            self.feed(*self.replies.pop(msg.robot, []))

    def feed(self, *messages):
        """Queue messages as the hub forwards them to the front end."""
        for m in messages:
            self._queue.append(encode(replace(m, sender=topics.HUB_ID, seq=next(self._hub_q))))

    def wait(self, timeout):
        if self._queue:
            while self._queue:
                self.receive_text(self._queue.popleft())
        elif self.interrupt:
            raise KeyboardInterrupt
        else:
            self.now += max(timeout, 1e-3)

    def messages(self, kind=None):
        """What the front end sent, decoded, A8s left out unless asked for."""
        out = [decode(t) for t in self.sent]
        return [m for m in out if (isinstance(m, kind) if kind else not isinstance(m, Ack))]


class Session:
    """A Menu over a FakeLink, answering from a list and recording its lines."""

    def __init__(self, answers, cell, link=None, **kw):
        self.answers = list(answers)
        self.prompts, self.lines, self.errors = [], [], []
        self.link = link or FakeLink()
        kw.setdefault("error", self.errors.append)
        self.menu = Menu(self.link, cell, input=self.ask, output=self.lines.append, clock=self.link.clock, **kw)

    def ask(self, prompt):
        self.prompts.append(prompt)
        if not self.answers:
            raise EOFError
        answer = self.answers.pop(0)
        if isinstance(answer, BaseException):
            raise answer
        return answer

    def run(self):
        return self.menu.run()

    @property
    def text(self):
        return "\n".join(self.lines + self.errors)

    def menus_shown(self):
        return self.lines.count("  5) quit")


@pytest.fixture(scope="module")
def cell():
    """The default cell with robot ids 1 and 2 (its own are the original's 0
    and 1): the menu takes every id from the cell, and the ids written below
    are these."""
    base = load_cell(default_cell_path())
    return dataclasses.replace(base, arms=tuple(dataclasses.replace(a, id=a.id + 1) for a in base.arms))


@pytest.fixture(scope="module")
def cube_stl(tmp_path_factory):
    path = tmp_path_factory.mktemp("models") / "cube20.stl"
    cube().export(str(path))
    return str(path)


@pytest.fixture(scope="module")
def jobs(cell, cube_stl):
    """The cube sliced once per mode (reused by the tests that do not slice)."""
    return {mode: run_job(cube_stl, cell, list(cell.arms), mode=mode) for mode in ("concurrent", "sequential")}


def with_job(session, job):
    session.menu.job, session.menu.programs = job, dict(job.programs)
    return session


def status(robot, state, layer=0, line=0, percent=0.0):
    return Status(robot, ArmState(state), layer, line, percent)


def done(robot, job):
    p = [p for p in job.programs.values() if p.arm.id == robot][0]
    return status(robot, ArmState.DONE, p.layers - 1, len(p.lines), 100.0)


# ------------------------------------------------------------------ the menu

def test_the_menu_has_the_original_five_choices_in_order(cell):
    s = Session(["5"], cell)
    assert s.run() == EXIT_OK
    assert [k for k, _ in CHOICES] == ["1", "2", "3", "4", "5"]
    assert s.lines[-6:-1] == ["  1) start demo (cut, slice, send and start the demo block)",
                              "  2) slice an STL file", "  3) send G-code to the arms",
                              "  4) start printing", "  5) quit"]
    for key, text in CHOICES:
        assert "  %s) %s" % (key, text) in s.lines
    assert s.prompts == ["choice [1-5]: "] and s.lines[-1] == "bye"
    assert s.link.sent == []


@pytest.mark.parametrize("answer, message", [
    ("9", "'9' is not a choice: answer 1, 2, 3, 4 or 5"),
    ("abc", "'abc' is not a choice: answer 1, 2, 3, 4 or 5"),
    ("", "no choice given: answer 1, 2, 3, 4 or 5"),
    ("   ", "no choice given: answer 1, 2, 3, 4 or 5"),
    ("0", "'0' is not a choice"),
])
def test_a_wrong_choice_gets_a_message_and_the_menu_again(cell, answer, message):
    s = Session([answer, "5"], cell)
    assert s.run() == EXIT_OK
    assert len(s.errors) == 1 and s.errors[0].startswith(message)
    assert s.menus_shown() == 2 and len(s.prompts) == 2
    assert s.link.sent == []


def test_end_of_input_and_ctrl_c_at_the_prompt_quit(cell):
    assert Session([], cell).run() == EXIT_OK
    assert Session([KeyboardInterrupt()], cell).run() == EXIT_OK
    s = Session(["2"], cell)                   # end of input at the file question
    assert s.run() == EXIT_OK and s.errors == [] and s.lines[-1] == "bye"
    s = Session(["2", KeyboardInterrupt(), "5"], cell)
    assert s.run() == EXIT_OK and "interrupted: back to the menu (a print that was started goes on)" in s.lines


def test_an_unexpected_exception_is_one_line_and_the_menu_goes_on(cell, monkeypatch):
    s = Session(["2", "x.stl", "5"], cell)
    monkeypatch.setattr(s.menu, "slice_model", lambda path: 1 / 0)
    assert s.run() == EXIT_OK
    assert s.errors == ["internal error (please report it): ZeroDivisionError: division by zero"]
    assert s.menus_shown() == 2


def test_a_missing_file_at_choice_2_names_the_path_and_the_menu_goes_on(cell, tmp_path):
    missing = str(tmp_path / "no such dir" / "nope.stl")
    s = Session(["2", missing, "5"], cell)
    assert s.run() == EXIT_OK
    assert s.errors == ["error: %s: no such file" % missing]
    assert s.prompts[1] == "model file (STL, OBJ, PLY, 3MF; mm): "
    assert s.menus_shown() == 2 and "Traceback" not in s.text


@pytest.mark.parametrize("content, name, expected", [
    (b"solid x\nendsolid x\n", "empty.stl", "contains no triangles"),
    (b"hello", "notes.txt", "unknown model format '.txt'"),
])
def test_a_bad_model_is_one_line_and_the_menu_goes_on(cell, tmp_path, content, name, expected):
    bad = tmp_path / name
    bad.write_bytes(content)
    s = Session(["2", str(bad), "9", "5"], cell)
    assert s.run() == EXIT_OK
    assert len(s.errors) == 2 and s.errors[0].startswith("error: ") and expected in s.errors[0]
    assert "\n" not in s.errors[0] and s.menus_shown() == 3


def test_a_model_too_large_for_the_bed_says_by_how_much_and_what_would_take_it(cell, tmp_path):
    big = tmp_path / "big.stl"
    cube().apply_scale([17.5, 1, 1]).export(str(big))
    s = Session(["2", str(big), "", "5"], cell)             # Enter at the scale question: back to the menu
    s.run()
    [error] = s.errors
    assert error.startswith("error: big.stl: does not fit: model is 350.0 mm wide in x, bed is 300.0 mm: "
                            "50.0 mm too large; it fits cell ")
    assert "cell eight_arms_beam (--cell config/cells/eight_arms_beam.yaml)" in error
    assert error.endswith("; cell kinova_ur10 takes it at --scale 0.857")       # 300 / 350, rounded down
    assert s.prompts[-2] == "scale factor to print it at (at most 0.857 here; Enter: back to the menu): "
    assert not s.menu.programs and s.menus_shown() == 2


def test_choice_2_prints_a_model_too_large_at_the_scale_given(cell, tmp_path):
    """The menu's --scale, asked for when the model does not fit: the parts
    are the model scaled (their extents, read back from the files written)."""
    big = tmp_path / "big.stl"
    trimesh.creation.box([400.0, 30.0, 2.0]).export(str(big))
    s = Session(["2", str(big), "0.7", "5"], cell, out=str(tmp_path / "out"))
    s.run()
    assert any("at scale 0.7 (cell kinova_ur10" in line for line in s.lines), s.lines
    parts = [trimesh.load(str(tmp_path / "out" / (name + ".stl"))) for name in s.menu.programs]
    lo = np.min([p.bounds[0] for p in parts], axis=0)
    hi = np.max([p.bounds[1] for p in parts], axis=0)
    np.testing.assert_allclose(hi - lo, [280.0, 21.0, 1.4], atol=0.01)


def test_no_file_given_at_choice_2(cell):
    s = Session(["2", "", "5"], cell)
    s.run()
    assert s.errors == ["no file given: back to the menu"]


def test_choice_2_slices_the_model_and_writes_the_programs(cell, cube_stl, tmp_path):
    out = tmp_path / "out"
    s = Session(["2", "", "5"], cell, model=cube_stl, out=str(out))      # empty answer: --model
    assert s.run() == EXIT_OK and s.errors == []
    assert s.prompts[1] == "model file (STL, OBJ, PLY, 3MF; mm) [%s]: " % cube_stl
    # a 20 mm cube lies inside the two arms' seam zone: the planner gives it to the faster arm
    assert sorted(os.listdir(out)) == ["job.json", "ur10.gcode", "ur10.stl"]
    menu = s.menu
    assert list(menu.programs) == ["ur10"] and not menu.sent
    assert (out / "ur10.gcode").read_text() == menu.programs["ur10"].text
    assert any(l.startswith("  ur10     R2 ") for l in s.lines)
    # the arm's own times are the plan's timing law (busy s, done s), as in job.json, not its feeds' time
    arm = json.loads((out / "job.json").read_text())["arms"]["ur10"]
    row = next(l for l in s.lines if l.startswith("  ur10     R2 "))
    assert row.split()[-4:-2] == ["{:,.0f}".format(arm["busy_s"]), "{:,.0f}".format(arm["done_s"])]
    assert arm["print_time_s"] < arm["busy_s"] and "busy s   done s" in "\n".join(s.lines)
    assert any(l.startswith("  plan: ur10 alone: {:,.0f} s".format(arm["done_s"])) for l in s.lines)
    assert any(l.startswith("    also considered: 2 arms concurrent (kinova, ur10): ") for l in s.lines)
    assert "programs: ur10 in %s, not sent" % out in s.lines
    assert s.link.sent == []            # slicing sends nothing
    # the arms given (--arms): both, nothing else considered; the earlier job's files are replaced
    s = Session(["2", "", "5"], cell, model=cube_stl, out=str(out), arms=list(cell.arms))
    assert s.run() == EXIT_OK and s.errors == []
    assert sorted(os.listdir(out)) == ["job.json", "kinova.gcode", "kinova.stl", "ur10.gcode", "ur10.stl"]
    assert list(s.menu.programs) == ["kinova", "ur10"]
    assert any("(arms given: no other plan considered)" in l for l in s.lines)
    # and back to the planner's choice: the kinova's program of the job before is gone
    s = Session(["2", "", "5"], cell, model=cube_stl, out=str(out))
    assert s.run() == EXIT_OK and sorted(os.listdir(out)) == ["job.json", "ur10.gcode", "ur10.stl"]


def test_the_default_output_folder_is_out_slash_the_model_stem(cell, cube_stl, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    s = Session(["2", "'%s'" % cube_stl, "5"], cell)        # quotes around a path are fine
    s.run()
    assert s.errors == [] and (tmp_path / "out" / "cube20" / "ur10.gcode").is_file()


def test_choice_3_sends_one_A5_per_arm_with_the_program_as_payload(cell, jobs):
    job = jobs["concurrent"]
    s = with_job(Session(["3", "5"], cell), job)
    assert s.run() == EXIT_OK and s.errors == []
    a5 = s.link.messages(LoadChunk)
    assert [m.robot for m in a5] == [1, 2] and len(s.link.messages()) == 2
    for m, text in zip(a5, s.link.sent):
        program = job.programs[cell.arms[m.robot - 1].name]
        assert decode(encode(m)) == m and encode(m) == text
        assert m.gcode == program.text                    # directives (;@A9 ...) included
        assert any(l.startswith(";@A9 ") for l in m.gcode.splitlines())
        assert m.sender == FE and m.chunk_id == a5[0].chunk_id
    assert a5[0].seq != a5[1].seq
    assert s.menu.sent and "the hub acknowledged the G-code of kinova, ur10" in s.lines


def test_choice_3_without_a_job_loads_the_programs_of_a_directory(cell, jobs, tmp_path):
    write_job(jobs["sequential"], str(tmp_path / "seq"))
    s = Session(["3", str(tmp_path / "seq"), "5"], cell)
    assert s.run() == EXIT_OK and s.errors == []
    assert s.prompts[1] == "directory with the programs (<arm>.gcode or <robot id>.gcode): "
    a5 = s.link.messages(LoadChunk)
    for m, arm in zip(a5, ("kinova", "ur10")):
        assert m.gcode == (tmp_path / "seq" / (arm + ".gcode")).read_text()
    # the ;@A1 R2 directive at the end of kinova's program: ur10 is started by kinova
    assert [p.start_first for p in s.menu.programs.values()] == [True, False]


def test_choice_3_with_a_bad_directory_is_one_line(cell, tmp_path):
    (tmp_path / "kinova.gcode").write_text("G1 X1 Y1\nA1 R2\n")
    s = Session(["3", str(tmp_path / "nothing here"), "3", str(tmp_path), "5"], cell)
    assert s.run() == EXIT_OK
    assert s.errors[0] == "error: %s: no such directory" % (tmp_path / "nothing here")
    assert s.errors[1].startswith("error: %s:2: A-series command in a program file" % (tmp_path / "kinova.gcode"))
    assert s.link.sent == []


def test_load_programs_checks_the_directives(cell, jobs, tmp_path):
    write_job(jobs["concurrent"], str(tmp_path))
    text = (tmp_path / "ur10.gcode").read_text()
    assert len(load_programs(str(tmp_path), cell)) == 2
    (tmp_path / "ur10.gcode").write_text(text.replace(";@A9 R2 W1", ";@A9 R2 W7", 1))
    with pytest.raises(Exception, match=r"ur10\.gcode:\d+: directive names R7, not an arm of cell kinova_ur10"):
        load_programs(str(tmp_path), cell)
    (tmp_path / "ur10.gcode").write_text(text.replace(";@A9 R2 W1", ";@A9 R2 W1 Q", 1))
    with pytest.raises(Exception, match=r"ur10\.gcode:\d+: bad directive"):
        load_programs(str(tmp_path), cell)


def test_choice_4_starts_every_arm_in_concurrent_mode_and_completes_when_all_are_done(cell, jobs):
    job = jobs["concurrent"]
    link = FakeLink(replies={1: [status(1, 1), status(1, 1, 40, 2000, 45.0), done(1, job)],
                             2: [status(2, 1), done(2, job)]})
    s = with_job(Session(["3", "4", "5"], cell, link=link), job)
    assert s.run() == EXIT_OK and s.errors == []
    sent = link.messages()
    assert [type(m).__name__ for m in sent] == ["LoadChunk", "LoadChunk", "Start", "Start"]
    assert [m.robot for m in link.messages(Start)] == [1, 2]
    assert any(l.startswith("print finished: every arm is DONE (kinova (R1), ur10 (R2))") for l in s.lines)
    progress = [l for l in s.lines if l.startswith("  kinova (R1):") and " layer " in l]
    assert len(progress) == 3 and "PRINTING" in progress[1] and "45.0 %" in progress[1]
    assert "DONE" in progress[2]
    # the front end acknowledged every status the hub forwarded (A8 R1001 Q<hub's q> S1000)
    acks = link.messages(Ack)
    assert [(a.robot, a.sender) for a in acks] == [(topics.HUB_ID, FE)] * 5
    assert sorted(a.acked_seq for a in acks) == list(range(HUB_FIRST_Q, HUB_FIRST_Q + 5))


def test_the_progress_view_pauses_stops_and_resumes_arms_typed_by_the_operator(cell, jobs):
    """While choice 4 follows the print, typed lines send A2 / A12 / A6
    through the hub (numbered like every command of the front end)."""
    job = jobs["concurrent"]
    typed = [["p"], [], ["s ur10", "x"], ["r 1", "r"], []]
    link = FakeLink(replies={1: [status(1, 1), status(1, 1, 40, 2000, 45.0)], 2: [status(2, 1)]})
    s = with_job(Session(["4", "5"], cell, link=link, timeout=30.0,
                         typed=lambda: typed.pop(0) if typed else []), job)
    s.run()
    sent = [m for m in link.messages() if not isinstance(m, (LoadChunk, Start))]
    assert [(type(m).__name__, m.robot) for m in sent] == [
        ("Pause", 1), ("Pause", 2), ("Stop", 2), ("Resume", 1), ("Resume", 1), ("Resume", 2)]
    assert all(m.sender == FE and m.seq is not None for m in sent)
    assert "  pause sent to kinova (R1), ur10 (R2)" in s.lines
    assert "  stop sent to ur10 (R2)" in s.lines
    assert any("'x': type p, r or s" in e for e in s.errors)
    assert any(l.startswith("  type p, s or r and Enter") for l in s.lines)


def test_choice_4_in_sequential_mode_starts_only_the_first_arm(cell, jobs):
    job = jobs["sequential"]
    link = FakeLink(replies={1: [status(1, 1), done(1, job), status(2, 1), done(2, job)]})
    s = with_job(Session(["4", "5"], cell, link=link), job)      # not sent yet: 4 sends first
    assert s.run() == EXIT_OK and s.errors == []
    assert "the G-code has not been sent yet: sending it first" in s.lines
    assert [type(m).__name__ for m in link.messages()] == ["LoadChunk", "LoadChunk", "Start"]
    assert link.messages(Start)[0].robot == 1
    assert any(l.startswith("A1 sent to kinova (R1); ur10 (R2) start") for l in s.lines)
    assert any(l.startswith("print finished") for l in s.lines)


def test_choice_4_is_not_finished_until_every_arm_is_done(cell, jobs):
    job = jobs["concurrent"]
    link = FakeLink(replies={1: [done(1, job)], 2: [status(2, 1)]}, interrupt=True)
    s = with_job(Session(["4", "5"], cell, link=link), job)
    assert s.run() == EXIT_OK
    assert not any(l.startswith("print finished") for l in s.lines)
    # Ctrl-C while following: back to the menu, which goes on
    assert "interrupted: back to the menu (a print that was started goes on)" in s.lines
    assert s.menus_shown() == 2


def test_choice_4_fails_on_an_A11_naming_the_line_of_the_program(cell, jobs):
    job = jobs["concurrent"]
    link = FakeLink(replies={1: [status(1, 1)],
                             2: [status(2, 1), ErrorReport(2, 120, "nozzle temperature \"low\"")]})
    s = with_job(Session(["3", "4", "5"], cell, link=link), job)
    assert s.run() == EXIT_OK
    [error] = s.errors
    assert error.startswith('print failed: ur10 (R2) error at G-code line 120: nozzle temperature "low"\n'
                            "    line 120 of ur10's program: %s" % job.programs["ur10"].lines[119])
    assert s.menus_shown() == 3


def test_an_error_status_waits_for_the_A11_that_says_why(cell, jobs):
    job = jobs["concurrent"]
    link = FakeLink(replies={1: [status(1, 1), status(1, 5, 3, 77, 10.0), ErrorReport(1, 77, "unreachable")]})
    s = with_job(Session(["4", "5"], cell, link=link), job)
    s.run()
    assert s.errors[0].startswith("print failed: kinova (R1) error at G-code line 77: unreachable")
    # without an A11: the status alone, after a grace period
    link = FakeLink(replies={1: [status(1, 5, 3, 77, 10.0)]})
    s = with_job(Session(["4", "5"], cell, link=link), job)
    s.run()
    assert s.errors[0].startswith("print failed: kinova (R1) error at G-code line 77: reported state ERROR")


def test_choice_4_with_nothing_to_start(cell):
    s = Session(["4", "5"], cell)
    s.run()
    assert s.errors == ["nothing to start: slice a model (2) or send G-code (3) first"]


def test_a_hub_that_does_not_acknowledge_is_reported(cell, jobs):
    s = with_job(Session(["3", "5"], cell, link=FakeLink(ack=False), ack_timeout=10.0), jobs["concurrent"])
    assert s.run() == EXIT_OK
    assert s.errors == ["error: the hub has not acknowledged the G-code after 10 s (is the communication "
                        "hub running?); still trying in the background"]
    assert not s.menu.sent


def test_statuses_of_an_earlier_job_are_not_taken_for_this_one(cell, jobs):
    job = jobs["concurrent"]
    link = FakeLink(replies={1: [done(1, job)], 2: [done(2, job)]})
    link.feed(status(1, 4, 0, 0, 100.0), status(2, 4, 0, 0, 100.0))      # old DONEs
    s = with_job(Session(["3", "4", "5"], cell, link=link, timeout=30), job)
    s.run()
    assert any(l.startswith("print finished") for l in s.lines)
    link = FakeLink(replies={1: [done(1, job)]})
    s = with_job(Session(["3", "4", "5"], cell, link=link, timeout=30), job)
    link.feed(status(2, 4, 0, 0, 100.0))
    s.run()
    assert s.errors and s.errors[0].startswith("print failed: timed out after 30 s waiting for ur10 (R2)")


# ------------------------------------------------------------------ --print

def test_print_job_exits_0_when_every_arm_is_done(cell, cube_stl, tmp_path):
    # replies are known only after slicing: answer the A1s with DONE at the program's end
    class DoneLink(FakeLink):
        def _hub_receives(self, text):
            msg = decode(text)
            if isinstance(msg, LoadChunk):
                n = len(msg.gcode.splitlines())
                self.replies[msg.robot] = [status(msg.robot, 1), status(msg.robot, 4, 99, n, 100.0)]
            super()._hub_receives(text)

    s = Session([], cell, link=DoneLink(), model=cube_stl, out=str(tmp_path))
    assert s.menu.print_job() == EXIT_OK and s.errors == []
    assert s.prompts == [] and any(l.startswith("print finished") for l in s.lines)


def test_print_job_exits_1_on_an_arm_error_and_on_the_timeout(cell, cube_stl, tmp_path):
    link = FakeLink(replies={2: [ErrorReport(2, 0, "emergency stop")]})
    s = Session([], cell, link=link, model=cube_stl, out=str(tmp_path))
    assert s.menu.print_job() == EXIT_FAILED
    assert s.errors == ["print failed: ur10 (R2) error at G-code line 0: emergency stop"]
    s = Session([], cell, model=cube_stl, out=str(tmp_path), arms=list(cell.arms))
    assert s.menu.print_job(timeout=60) == EXIT_FAILED
    assert s.errors == ["print failed: timed out after 60 s waiting for kinova (R1) silent, ur10 (R2) silent"]
    # the default: 600 s + twice the estimate at the clock's pace (here 4 simulated s per wall s)
    s = Session([], cell, model=cube_stl, out=str(tmp_path), arms=list(cell.arms), speed=4.0)
    assert s.menu.print_job() == EXIT_FAILED
    budget = 600 + 2 * max(s.menu.print_times.values()) / 4
    assert s.errors == ["print failed: timed out after %.0f s waiting for kinova (R1) silent, ur10 (R2) silent"
                        % budget], (s.errors, budget)


def test_print_job_exits_2_on_a_bad_model_with_one_line(cell, tmp_path):
    s = Session([], cell, model=str(tmp_path / "nope.stl"))
    assert s.menu.print_job() == EXIT_BAD_INPUT
    assert s.errors == ["error: %s: no such file" % (tmp_path / "nope.stl")]
    assert s.link.sent == []


def test_flags(cell):
    args = build_parser().parse_args(["--model", "m.stl", "--mode", "sequential", "--slicer", "prusa",
                                      "--out", "o", "--timeout", "5"])
    menu = menu_from_args(args, FakeLink(), cell)
    assert (menu.model, menu.mode, menu.slicer, menu.out, menu.timeout) == ("m.stl", "sequential", "prusa", "o", 5)
    args = build_parser().parse_args(["--print"])
    assert args.print_job and args.model is None and menu_from_args(args, FakeLink(), cell).timeout is None
    with pytest.raises(SystemExit):
        build_parser().parse_args(["--mode", "parallel"])
    menu = menu_from_args(build_parser().parse_args(["--support", "off", "--seam", "interlock"]), FakeLink(), cell)
    assert (menu.support, menu.seam) == (False, "interlock")
    assert menu_from_args(build_parser().parse_args([]), FakeLink(), cell).support is True


def test_the_default_timeout_follows_the_clocks_pace(cell):
    """demo.launch passes --timeout=auto: 600 s plus twice the estimate, in wall
    s at the clock's pace (the demo at speed:=4 was cut off by a fixed 1800 s
    after half of its 2,264 wall s)."""
    assert build_parser().parse_args(["--timeout=auto"]).timeout is None
    assert build_parser().parse_args(["--timeout=12.5"]).timeout == 12.5
    for bad in ("0", "-3", "soon"):
        with pytest.raises(SystemExit):
            build_parser().parse_args(["--timeout=" + bad])
    assert print_timeout_s(9055.0, 4.0) == pytest.approx(600 + 2 * 9055.0 / 4)
    assert print_timeout_s(9055.0, None) == pytest.approx(600 + 2 * 9055.0)     # max or real: as at speed 1
    assert print_timeout_s(100.0, 0.5) == pytest.approx(600 + 2 * 100.0 / 0.5)
    menu = menu_from_args(build_parser().parse_args(["--print"]), FakeLink(), cell, speed=4.0)
    assert menu.speed == 4.0


# ------------------------------------------------------------------ the link

def test_link_numbers_retries_until_acked_and_gives_up():
    sent, now = [], [0.0]
    link = ReliableLink(sent.append, clock=lambda: now[0], first_seq=41, max_tries=3)
    assert link.send(Start(2)) == 41 and sent == ["A1 R2 S1000 Q41"]
    link.send(Start(1))
    for t in (0.1, 0.25, 0.7):              # due after 0.2 s, then 0.4 s later
        now[0] = t
        link.tick()
    assert sent.count("A1 R2 S1000 Q41") == 3 and link.pending() == 2
    link.receive_text("A8 R1000 Q41 S1001")    # the hub's ack
    link.receive_text("A8 R7 Q42 S1001")       # not for us
    assert link.pending() == 1
    now[0] = 10.0
    link.tick()
    # as last transmitted: after Q41, which was then still unacknowledged
    assert link.poll() == [Undelivered("A1 R1 S1000 Q42 B41", 3)] and link.pending() == 0


def test_link_acknowledges_forwarded_reports_and_drops_duplicates():
    sent = []
    link = ReliableLink(sent.append, first_seq=1)
    text = "A10 R1 T1 L2 N30 P4.5 S1001 Q9"
    link.receive_text(text)
    link.receive_text(text)                  # a retry by the hub: acked again, delivered once
    link.receive_text('A11 R2 N5 S1001 Q10 "jam"')
    link.receive_text("A10 R1 T9 L0 N0 P0 S1001 Q11")   # malformed: not acknowledged
    assert sent == ["A8 R1001 Q9 S1000", "A8 R1001 Q9 S1000", "A8 R1001 Q10 S1000"]
    assert link.poll() == [Status(1, ArmState.PRINTING, 2, 30, 4.5, sender=1001, seq=9),
                           ErrorReport(2, 5, "jam", sender=1001, seq=10)]
    assert link.poll() == [] and len(link.malformed) == 1


# ------------------------------------------------------------------ --follow (a replacement front end)

def _progress(**arms):
    ids = {"kinova": 1, "ur10": 2}
    return json.dumps({"stamp": 1.0, "arms": {name: {"id": ids[name], "state": state, "layer": 3, "line": 40,
                                                    "percent": pct, "eta_s": None, "updated": 1.0,
                                                    "position": None, "error": err}
                                             for name, (state, pct, err) in arms.items()}})


def test_follow_attaches_to_a_running_job_and_sends_nothing(cell, jobs, tmp_path):
    write_job(jobs["concurrent"], str(tmp_path))
    link = FakeLink()
    s = Session([], cell, link=link)
    # the hub's latched progress: kinova finished before this front end came up
    link.receive_progress(_progress(kinova=("DONE", 100.0, None), ur10=("PRINTING", 60.0, None)))
    link.feed(Status(2, ArmState.PRINTING, 5, 80, 90.0), Status(2, ArmState.DONE, 6, 99, 100.0))
    assert s.menu.attach(str(tmp_path)) == EXIT_OK
    assert s.link.messages() == []                                   # no command sent
    assert len(s.link.sent) == 2 and all(isinstance(decode(t), Ack) for t in s.link.sent)   # A8s of the reports
    assert "print finished: every arm is DONE" in s.text and "attached to the job" in s.text


def test_follow_reports_an_arm_error_known_to_the_hub(cell, jobs, tmp_path):
    write_job(jobs["concurrent"], str(tmp_path))
    link = FakeLink()
    s = Session([], cell, link=link)
    link.receive_progress(_progress(kinova=("ERROR", 30.0, {"line": 7, "message": "unreachable", "time": 0.5}),
                                    ur10=("PRINTING", 60.0, None)))
    assert s.menu.attach(str(tmp_path), timeout=5) == EXIT_FAILED
    assert "kinova (R1) error at G-code line 7: unreachable" in s.errors[-1]


def test_follow_without_progress_times_out_naming_the_silent_arms(cell, jobs, tmp_path):
    write_job(jobs["concurrent"], str(tmp_path))
    s = Session([], cell)
    s.link.receive_progress("not json")
    assert s.menu.attach(str(tmp_path), timeout=3) == EXIT_FAILED
    assert "timed out" in s.errors[-1] and "silent" in s.errors[-1]


def test_follow_with_a_bad_directory_is_bad_input(cell, tmp_path):
    s = Session([], cell)
    assert s.menu.attach(str(tmp_path / "none")) == EXIT_BAD_INPUT and "no such directory" in s.errors[-1]


# ------------------------------------------------------------------ a start lost with a crashed front end

# the two arms' programs (default cell renumbered: kinova R1, ur10 R2), one layer each, on either side
# of the bed's middle
def _program(x0, x1):
    return ("G21\nG90\nM83\n;LAYER_CHANGE\n;Z:0.2\nG0 X%d Y-10 Z0.2 F9000\nG1 X%d Y-10 E2.0 F1800\n"
            "G1 X%d Y0 E0.4\nG1 X%d Y0 E2.0\n" % (x0, x1, x1, x0))


class RunnerHub(FakeLink):
    """A FakeLink whose hub delivers the front end's commands to real
    :class:`~ambots.runner.ArmRunner` s (``runners``: id -> runner) and
    forwards their reports back; ``lost``: (code, robot) of commands it
    never receives (neither acknowledged nor delivered: dropped on every
    try).  Each wait of the front end advances the arms by ``step`` s."""

    def __init__(self, runners, lost=(), step=2.0):
        super().__init__()
        self.runners, self.lost, self.step = runners, set(lost), step

    def _hub_receives(self, text):
        msg = decode(text)
        if not isinstance(msg, Ack) and (msg.CODE, msg.robot) in self.lost:
            self.sent.append(text)
            return
        super()._hub_receives(text)
        if not isinstance(msg, Ack):
            r = self.runners[msg.robot]
            r.handle(replace(msg, sender=None, seq=None, after=None), now=r.clock)
            self._forward()

    def _forward(self):
        for r in self.runners.values():
            out, r.outbox = r.outbox, []
            for _, m in out:
                self.feed(replace(m, clock=None) if isinstance(m, Status) else m)

    def wait(self, timeout):
        for r in self.runners.values():
            r.advance(r.clock + self.step)
        self._forward()
        super().wait(timeout)


def test_a_start_lost_with_the_front_end_is_sent_again_by_its_replacement_and_printed_once(cell, tmp_path):
    """The case CI met under load: the front end sends A1 to both arms, the
    UR10's is still being retried (never acknowledged) when the front end
    dies.  The replacement (--follow) sends the recorded start again with
    the chunk's id: the UR10 starts, the Kinova, which had started, ignores
    it, and each arm lays exactly the beads of an uninterrupted run of its
    program (run alone here, as the reference)."""
    from ambots.motion import MotionPlanner
    from ambots.runner import ArmRunner
    texts = {"kinova": _program(-60, -20), "ur10": _program(20, 60)}
    for name, text in texts.items():
        (tmp_path / (name + ".gcode")).write_text(text)
    planners = {a.name: MotionPlanner(a, cell) for a in cell.arms}

    def runners():
        return {a.id: ArmRunner(a, cell, planner=planners[a.name], record=True) for a in cell.arms}

    reference = runners()
    for r, a in zip(reference.values(), cell.arms):
        r.handle(LoadChunk(r.id, texts[a.name], chunk_id=1))
        r.handle(Start(r.id))
        while r.state is ArmState.PRINTING:
            r.advance(r.clock + 2.0)
        assert r.state is ArmState.DONE and r.beads
    arms = runners()
    first = Session(["3", str(tmp_path), "4", "5"], cell, link=RunnerHub(arms, lost={(1, 2)}), ack_timeout=6.0)
    assert first.run() == EXIT_OK
    assert "the hub has not acknowledged the start command" in first.text
    record = json.loads((tmp_path / "start.json").read_text())
    chunk = first.link.messages(LoadChunk)[0].chunk_id
    assert record == {"chunk": chunk, "started": ["kinova", "ur10"], "arms": {"kinova": 1, "ur10": 2}}
    assert [m.chunk_id for m in first.link.messages(Start)] == [chunk, chunk]
    assert arms[1].state is not ArmState.IDLE and arms[2].state is ArmState.IDLE      # the UR10's A1 lost
    # the front end is gone (so is its retrying); a new one attaches
    second = Session([], cell, link=RunnerHub(arms))
    assert second.menu.attach(str(tmp_path), timeout=600) == EXIT_OK, second.text
    assert [(m.robot, m.chunk_id) for m in second.link.messages()] == [(1, chunk), (2, chunk)]
    assert "A1 C%d sent again to kinova (R1), ur10 (R2)" % chunk in second.text
    for i, r in arms.items():
        assert r.state is ArmState.DONE and not [m for _, m in r.outbox if isinstance(m, ErrorReport)]
        ref = reference[i]
        for name in ("line", "p0", "p1", "e_mm"):
            got = np.concatenate([getattr(b, name) for b in r.beads])
            want = np.concatenate([getattr(b, name) for b in ref.beads])
            np.testing.assert_allclose(got, want, rtol=0, atol=1e-9, err_msg="%s %s" % (r.arm.name, name))


def test_without_a_record_the_follower_sends_nothing_and_a_later_start_is_plain(cell, jobs, tmp_path):
    """No start.json (programs sent by hand, or an older front end): --follow
    sends nothing.  In the menu, the second 4 of the same programs sends a
    plain A1 (a DONE arm prints again, as in the original)."""
    write_job(jobs["concurrent"], str(tmp_path))
    s = Session([], cell)
    s.link.feed(done(1, jobs["concurrent"]), done(2, jobs["concurrent"]))
    assert s.menu.attach(str(tmp_path)) == EXIT_OK and s.link.messages() == []
    job = jobs["concurrent"]

    class EveryStartDone(FakeLink):                 # the arms report DONE after every A1
        def _hub_receives(self, text):
            msg = decode(text)
            if isinstance(msg, Start):
                self.replies[msg.robot] = [done(msg.robot, job)]
            super()._hub_receives(text)
    link = EveryStartDone()
    s = with_job(Session(["3", "4", "4", "5"], cell, link=link), job)
    s.menu.directory = str(tmp_path)
    assert s.run() == EXIT_OK and s.errors == []
    starts = link.messages(Start)
    chunk = link.messages(LoadChunk)[0].chunk_id
    assert [m.chunk_id for m in starts] == [chunk, chunk, None, None]
    assert json.loads((tmp_path / "start.json").read_text())["chunk"] == chunk


def test_an_unreadable_start_record_is_said_and_nothing_is_sent(cell, jobs, tmp_path):
    write_job(jobs["concurrent"], str(tmp_path))
    (tmp_path / "start.json").write_text('{"chunk": "twelve"')
    s = Session([], cell)
    s.link.feed(done(1, jobs["concurrent"]), done(2, jobs["concurrent"]))
    assert s.menu.attach(str(tmp_path)) == EXIT_OK and s.link.messages() == []
    assert any(e.startswith("warning: %s is unreadable" % (tmp_path / "start.json")) for e in s.errors)


def test_a_folder_that_cannot_be_written_does_not_stop_the_print(cell, jobs, tmp_path, monkeypatch):
    job = jobs["concurrent"]
    link = FakeLink(replies={1: [done(1, job)], 2: [done(2, job)]})
    s = with_job(Session(["3", "4", "5"], cell, link=link), job)
    s.menu.directory = str(tmp_path / "not there")          # the record cannot be written
    assert s.run() == EXIT_OK
    assert [m.chunk_id is not None for m in link.messages(Start)] == [True, True]
    assert any("could not record the start" in e and "--follow" in e for e in s.errors)
