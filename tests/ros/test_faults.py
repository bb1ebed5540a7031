"""The fault suite (real roscore, hub, firmware nodes, front end): a clean
print of a small two-arm job is the reference; then the same job with
20 % drop + 10 % duplication + reordering on every hub topic (seeded),
with the Kinova's firmware killed (SIGKILL) mid-print and respawned, with
the hub killed (respawned) and the front end killed (a new one follows the
job with --follow), and with the UR10 running 30 % slower than planned; and
the sequential hand-over (A7/A1/A2/A6 through the hub, two turns per arm)
under the same faults with the Kinova killed while it waits for its next
turn.  Every run must finish
with the same deposit (per arm: same beads in the same order under faults;
per G-code line the same filament and bead length after a kill), and no
contact in the executed motion, every knot of which reached the recorder
(which forgets all a killed firmware had sent: faults.py)."""
import os
import re
import subprocess
import sys
import time

import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from ambots.ros.capture import _latest_copy  # noqa: E402
from faults import compare_lines, coverage, run_print, sequential_model, small_model, unused_port  # noqa: E402

FAULTS = "drop=0.2 dup=0.1 reorder=0.3 reorder_window=0.05 delay=0.002 seed=%d"
NO_CONTACT = {"arm_arm": 0, "arm_bed": 0, "arm_part": 0}


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    return small_model(str(tmp_path_factory.mktemp("model") / "block.stl"))


@pytest.fixture(scope="module")
def clean(tmp_path_factory, model):
    run = run_print(tmp_path_factory.mktemp("clean"), 11611, model)
    assert run["front_end_rc"] == 0, run["tmp"]
    assert run["report"]["finished"] and run["report"]["collisions"] == NO_CONTACT, run["report"]
    for arm, j in run["journals"].items():
        assert len(j) > 500, arm
    return run


def _same_beads(a, b):
    assert a.shape == b.shape
    np.testing.assert_allclose(a[:, :9], b[:, :9], rtol=0, atol=1e-9)    # positions, filament, line, layer


def _check_deposit(clean, run, arms=("kinova", "ur10")):
    """The front end built the same programs as in the clean run (the job
    pipeline is deterministic), every extrusion of each arm's program was
    printed exactly once, and the beads are the clean run's, in the same
    order."""
    for arm in arms:
        path = os.path.join(run["tmp"], "job", arm + ".gcode")
        assert open(path).read() == open(os.path.join(clean["tmp"], "job", arm + ".gcode")).read(), arm
        missing, extra, diff = coverage(run["journals"][arm], path)
        assert not missing and not extra and diff < 1e-5, (arm, missing[:5], extra[:5], diff)
        _same_beads(clean["journals"][arm], run["journals"][arm])
    _check_knots(run, arms)


def _check_knots(run, arms):
    """Every knot of the motion each firmware executed (its trace journal)
    reached the recorder that checked the contacts, once."""
    assert run["report"]["trace_gaps"] == 0, run["report"]
    for arm in arms:
        recorded, knots = run["recorded_knots"].get(arm), _latest_copy(run["knots"][arm])
        assert recorded is not None and len(knots) > 100, arm
        np.testing.assert_array_equal(recorded, knots, err_msg=arm)


@pytest.mark.parametrize("seed", [7])
def test_dropped_duplicated_reordered_messages_change_nothing(tmp_path, model, clean, seed):
    run = run_print(tmp_path, 11612, model, faults=FAULTS % seed)
    assert run["front_end_rc"] == 0, run["tmp"]
    rep = run["report"]
    assert rep["finished"] and rep["collisions"] == NO_CONTACT, rep
    faults = rep["hub_progress"]["faults"]
    assert faults["in"]["dropped"] > 10 and faults["out"]["dropped"] > 10, faults
    assert faults["in"]["duplicated"] > 5 and faults["out"]["reordered"] > 5, faults
    _check_deposit(clean, run)


@pytest.mark.parametrize("seed", [3])
def test_a_firmware_killed_mid_print_resumes_from_its_checkpoint(tmp_path, model, clean, seed):
    run = run_print(tmp_path, 11613, model, faults=FAULTS % seed, kill_after=0.8)
    assert run["kills"] == 1, run["tmp"]
    assert run["report"]["forgotten_streams"] >= 1, run["report"]      # the recorder lost what it had of the Kinova
    assert run["front_end_rc"] == 0, run["tmp"]
    rep = run["report"]
    assert rep["finished"] and rep["collisions"] == NO_CONTACT, rep
    launch_log = open(os.path.join(run["tmp"], "launch.log")).read()
    assert "resumed from its checkpoint" in launch_log
    # every extrusion of both programs printed exactly once (the killed arm too); the other
    # arm, which waited at its barriers, laid the clean run's beads (same program)
    _check_deposit(clean, run, arms=("ur10",))
    _check_knots(run, ("kinova",))
    path = os.path.join(run["tmp"], "job", "kinova.gcode")
    assert open(path).read() == open(os.path.join(clean["tmp"], "job", "kinova.gcode")).read()
    missing, extra, diff = coverage(run["journals"]["kinova"], path)
    assert not missing and not extra and diff < 1e-5, (missing[:5], extra[:5], diff)
    # the same path as the clean run, line by line (the cut line is split differently)
    missing, extra, de, dl = compare_lines(clean["journals"]["kinova"], run["journals"]["kinova"])
    assert not missing and not extra and de < 1e-5 and dl < 2e-5, (de, dl)


@pytest.mark.parametrize("seed", [5])
def test_the_hub_and_the_front_end_killed_mid_print_lose_nothing(tmp_path, model, clean, seed):
    """kill -9 of the hub (respawned: it resumes from its state file) and of
    the front end (a new one attaches with --follow) during a faulty print."""
    run = run_print(tmp_path, 11615, model, faults=FAULTS % seed, kill_hub_after=0.3,
                    replace_front_end_after=0.8)
    assert run["kills"] == 2, run["tmp"]
    assert run["front_end_rc"] == 0, run["tmp"]          # the replacement saw every arm DONE
    rep = run["report"]
    assert rep["finished"] and rep["collisions"] == NO_CONTACT, rep
    launch_log = open(os.path.join(run["tmp"], "launch.log")).read()
    assert "communication hub: resumed from its checkpoint" in launch_log
    fe_log = open(os.path.join(run["tmp"], "front_end.log")).read()
    assert "attached to the job" in fe_log and "print finished: every arm is DONE" in fe_log
    assert rep["hub_progress"]["hub"]["resumed"] is True
    _check_deposit(clean, run)


def test_an_arm_30_percent_slower_than_planned_never_collides(tmp_path, model, clean):
    run = run_print(tmp_path, 11614, model, slowdown="ur10=1.3")
    assert run["front_end_rc"] == 0, run["tmp"]
    rep = run["report"]
    assert rep["finished"] and rep["collisions"] == NO_CONTACT, rep
    assert rep["min_clearance_mm"] > 0
    # the slow arm took longer, the barriers held the other one
    assert rep["arms"]["ur10"]["print_time_s"] > 1.2 * clean["report"]["arms"]["ur10"]["print_time_s"]
    assert rep["arms"]["kinova"]["idle_time_s"] > clean["report"]["arms"]["kinova"]["idle_time_s"]
    _check_deposit(clean, run)


def test_the_demo_print_under_faults_is_the_clean_demo(tmp_path_factory):
    """The issue's own scenario: the demo model, both arms, 20 % drop + 10 %
    duplication + reordering on every hub topic: it completes, and each arm
    lays the clean run's beads in the same order."""
    from ambots import data_path
    from ambots.job import DEMO_MODEL
    model = data_path(DEMO_MODEL)
    clean = run_print(tmp_path_factory.mktemp("demo_clean"), 11616, model, timeout=1500)
    assert clean["front_end_rc"] == 0 and clean["report"]["finished"], clean["tmp"]
    # on the one clock every lost message holds both arms until its retry: 7-8 min wall on a
    # busy 2-core machine (600 s was the limit before)
    run = run_print(tmp_path_factory.mktemp("demo_faults"), 11617, model, faults=FAULTS % 7, timeout=1500)
    assert run["front_end_rc"] == 0, run["tmp"]
    rep = run["report"]
    assert rep["finished"] and rep["collisions"] == NO_CONTACT, rep
    assert rep["hub_progress"]["faults"]["in"]["dropped"] > 50, rep["hub_progress"]["faults"]
    _check_deposit(clean, run)


def _ctl(env, *args):
    """``python -m ambots ctl args...`` on this print's master: (exit status, output)."""
    r = subprocess.run([sys.executable, "-m", "ambots", "ctl", *args], capture_output=True, text=True,
                       env=env, timeout=120)
    return r.returncode, r.stdout + r.stderr


def _journal_sizes(state):
    return {arm: os.path.getsize(os.path.join(state, arm + ".beads")) if os.path.exists(
        os.path.join(state, arm + ".beads")) else 0 for arm in ("kinova", "ur10")}


def test_an_operator_stops_pauses_and_resumes_a_live_print(tmp_path, model, clean):
    """Issue "Original users": `python -m ambots ctl` during a live
    concurrent print.  The Kinova is stopped (it brakes at once; the UR10
    goes on, and waits at its barriers for the stopped arm), then every arm
    is paused; nothing is laid while they are paused; a caller the hub does
    not list is refused; resume finishes the job with the uninterrupted
    run's deposit and no contact."""
    def operate(env, state):
        at_stop = _journal_sizes(state)
        steps = {"stop": _ctl(env, "stop", "kinova")}
        # the UR10 goes on until a barrier holds it for the stopped Kinova: its deposit stops growing
        sizes = [_journal_sizes(state)]
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and (len(sizes) < 16 or sizes[-16]["ur10"] != sizes[-1]["ur10"]):
            time.sleep(0.2)                                 # 3 s without a new UR10 bead
            sizes.append(_journal_sizes(state))
        steps["held"] = (at_stop, sizes[0], sizes[-1], len(sizes) >= 16 and sizes[-16] == sizes[-1])
        steps["pause"] = _ctl(env, "pause")
        before = _journal_sizes(state)
        time.sleep(2.0)
        steps["still"] = (before, _journal_sizes(state))
        steps["intruder"] = _ctl(env, "resume", "--node-name", "/intruder", "--timeout", "3")
        steps["resume"] = _ctl(env, "resume")
        return steps

    run = run_print(tmp_path, unused_port(), model, during=operate)
    steps = run["during"]
    rc, out = steps["stop"]
    assert rc == 0 and "A12 R0 sent to kinova (R0)" in out and "kinova PAUSED" in out, out
    rc, out = steps["pause"]
    assert rc == 0 and "A2 R0 A2 R1 sent" in out and "kinova PAUSED" in out, out
    assert "ur10 PAUSED" in out or "ur10 DONE" in out, out
    before, after = steps["still"]
    assert before == after                                  # paused: nothing laid
    rc, out = steps["intruder"]
    assert rc == 1 and "/intruder is not a registered node" in out, out
    rc, out = steps["resume"]
    assert rc == 0 and "A6 R0 A6 R1 sent" in out, out
    assert run["front_end_rc"] == 0, run["tmp"]
    rep = run["report"]
    assert rep["finished"] and rep["collisions"] == NO_CONTACT, rep
    assert rep["live_collisions"] == NO_CONTACT, rep
    _check_deposit(clean, run)
    assert "[A-series]" not in open(os.path.join(run["tmp"], "launch.log")).read()      # debug is off by default
    # while the Kinova was stopped the UR10 printed on, then a barrier held it for the Kinova
    at_stop, stopped, last, held = steps["held"]
    assert held and last["ur10"] > at_stop["ur10"] and last["kinova"] == stopped["kinova"], steps["held"]


def test_the_sequential_hand_over_survives_faults_and_a_kill_while_paused(tmp_path_factory):
    """Sequential mode on a block that takes two turns per arm: the hand-over
    commands go through the hub (A7, A1, then A6 and A2 between turns) under
    20 % drop + 10 % duplication + reordering, and the Kinova's firmware is
    killed (SIGKILL) while it is paused for the UR10's turn.  It comes back
    PAUSED from its checkpoint, the UR10's A6 resumes it, the print ends
    without contact, and both arms lay the clean sequential run's beads."""
    model = sequential_model(str(tmp_path_factory.mktemp("seq_model") / "block.stl"))
    clean = run_print(tmp_path_factory.mktemp("seq_clean"), unused_port(), model, mode="sequential")
    assert clean["front_end_rc"] == 0, clean["tmp"]
    assert clean["report"]["finished"] and clean["report"]["collisions"] == NO_CONTACT, clean["report"]
    run = run_print(tmp_path_factory.mktemp("seq_faults"), unused_port(), model, faults=FAULTS % 11, mode="sequential",
                    kill_when="PAUSED")
    assert run["kills"] == 1, run["tmp"]
    assert run["report"]["forgotten_streams"] >= 1, run["report"]      # the recorder lost what it had of the Kinova
    assert run["front_end_rc"] == 0, run["tmp"]
    rep = run["report"]
    assert rep["finished"] and rep["collisions"] == NO_CONTACT, rep
    launch_log = open(os.path.join(run["tmp"], "launch.log")).read()
    assert "kinova firmware: resumed from its checkpoint: PAUSED" in launch_log
    faults = rep["hub_progress"]["faults"]
    assert faults["in"]["dropped"] > 5 and faults["out"]["dropped"] > 5, faults
    _check_deposit(clean, run)
