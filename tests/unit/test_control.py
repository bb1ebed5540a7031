"""An operator's pause / stop / resume (ambots.control): which arms a
request names and what it sends; ``python -m ambots ctl`` refuses bad
requests with a clear message before it needs ROS."""
import subprocess
import sys

import pytest

from ambots.config import default_cell_path, load_cell
from ambots.control import ControlError, commands, parse_key_line, settled
from ambots.protocol import ArmState, Pause, Resume, Stop, encode


@pytest.fixture(scope="module")
def cell():
    return load_cell(default_cell_path())


def test_an_arm_is_named_by_name_id_or_all(cell):
    assert commands(cell, "pause") == [Pause(0), Pause(1)]
    assert commands(cell, "stop", "ur10") == commands(cell, "stop", "1") == commands(cell, "stop", "R1") \
        == [Stop(1)]
    assert commands(cell, "resume", "kinova") == [Resume(0)]
    # the original's strings, exactly
    assert [encode(m) for m in commands(cell, "pause")] == ["A2 R0", "A2 R1"]
    assert [encode(m) for m in commands(cell, "stop", "kinova")] == ["A12 R0"]


@pytest.mark.parametrize("action, target, words", [
    ("pause", "panda", ["no arm 'panda'", "kinova (R0), ur10 (R1), or all"]),
    ("pause", "7", ["no arm '7'"]),
    ("halt", "all", ["unknown action 'halt'", "pause, resume or stop"]),
])
def test_a_bad_request_says_what_is_expected(cell, action, target, words):
    with pytest.raises(ControlError) as err:
        commands(cell, action, target)
    for w in words:
        assert w in str(err.value)


def test_typed_lines(cell):
    assert parse_key_line(cell, "  \n") is None
    assert parse_key_line(cell, "p\n") == ("pause", [Pause(0), Pause(1)])
    assert parse_key_line(cell, "S ur10") == ("stop", [Stop(1)])
    assert parse_key_line(cell, "resume 0") == ("resume", [Resume(0)])
    for bad in ("q", "p a b", "stop panda"):
        with pytest.raises(ControlError):
            parse_key_line(cell, bad)


def test_obeyed_states():
    assert settled("pause", ArmState.PAUSED) and not settled("pause", ArmState.PRINTING)
    assert settled("stop", ArmState.PAUSED) and not settled("stop", ArmState.WAITING)
    assert settled("resume", ArmState.WAITING) and not settled("resume", ArmState.PAUSED)
    # nothing to obey: idle, done or failed arms count as settled
    assert all(settled(a, s) for a in ("pause", "stop", "resume")
               for s in (ArmState.IDLE, ArmState.DONE, ArmState.ERROR))


def test_ctl_command_line_refuses_an_unknown_action():
    r = subprocess.run([sys.executable, "-m", "ambots", "ctl", "halt"], capture_output=True, text=True)
    assert r.returncode == 2 and "invalid choice: 'halt'" in r.stderr
    r = subprocess.run([sys.executable, "-m", "ambots", "ctl", "--help"], capture_output=True, text=True)
    assert r.returncode == 0 and "/ambots_ctl" in r.stdout
