"""Offline run of a whole cell (ambots.sim) and ``python -m ambots plan``: a
small two-arm concurrent job executed by both firmwares on one clock,
checked for collisions, with the deposit matching the programs; a slowed arm
still collides with nothing; a failing arm stops the run naming its line."""
import json

import numpy as np
import pytest
import trimesh

from ambots import cli
from ambots.config import default_cell_path, load_cell
from ambots.coordinate import ArmProgram
from ambots.gcode import Segment, parse_gcode_text, summarize
from ambots.job import run_job
from ambots.protocol import ArmState, ErrorReport
from ambots.runner import ArmRunner
from ambots.sim import check_motion, report, simulate

ARM_KEYS = {"moves", "extrude_mm", "travel_mm", "print_time_s", "idle_time_s", "ik_failures", "max_path_error_mm"}
REPORT_KEYS = {"model", "cell", "mode", "slicer", "arms", "makespan_s", "collisions", "min_clearance_mm",
               "deposit_volume_mm3", "model_volume_mm3", "wall_time_s"}
FILAMENT_AREA_MM2 = np.pi * 1.75 ** 2 / 4


@pytest.fixture(scope="module")
def cell():
    return load_cell(default_cell_path())


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    """A 200 x 20 x 0.6 mm block: three layers, across the seam between the arms."""
    path = tmp_path_factory.mktemp("model") / "block.stl"
    trimesh.creation.box((200.0, 20.0, 0.6)).export(str(path))
    return str(path)


@pytest.fixture(scope="module")
def job(model, cell):
    return run_job(model, cell)


@pytest.fixture(scope="module")
def run(job, cell):
    result = simulate(job.programs, cell)
    motion = check_motion(result, cell)
    return result, motion, report(result, motion, job)


def net_filament(program):
    return summarize(parse_gcode_text(program.text))["extruded_filament_mm"]


def bead_filament(runner):
    return float(sum(b.e_mm.sum() for b in runner.beads))


def test_concurrent_job_runs_to_the_end_without_collisions(run, job):
    result, motion, rep = run
    assert result.finished, result.reason
    assert set(job.programs) == {"kinova", "ur10"} and job.mode == "concurrent"
    assert all(r.state is ArmState.DONE for r in result.runners.values())
    assert not result.errors
    assert motion["collisions"] == {"arm_arm": 0, "arm_bed": 0, "arm_part": 0}
    assert motion["min_clearance_mm"] > 0
    assert motion["min_bed_clearance_mm"] > 0 and motion["min_part_clearance_mm"] > 0
    # both arms printed at the same time (concurrent), not one after the other
    spans = {n: (r.stats.first_motion_s, r.stats.done_s) for n, r in result.runners.items()}
    (a0, a1), (b0, b1) = spans.values()
    assert min(a1, b1) - max(a0, b0) > 0.5 * result.makespan_s
    assert result.makespan_s == pytest.approx(max(a1, b1) - min(a0, b0))


def test_executed_motion_is_continuous_and_within_joint_speed_limits(run):
    """Across the whole run (block boundaries, barriers, joint moves
    included): no joint moves faster than velocity x velocity_scaling and
    nothing jumps."""
    result, _, _ = run
    for name, r in result.runners.items():
        prof = r.arm.profile
        vmax = np.array([j.velocity for j in prof.joints]) * prof.velocity_scaling
        t = np.concatenate([[0.0], np.concatenate(r.trace_t)])
        Q = np.concatenate([np.asarray(prof.home, float)[None], np.concatenate(r.trace_q)])
        dt, dq = np.diff(t), np.abs(np.diff(Q, axis=0))
        assert np.all(dt >= 0), name
        assert np.all(dq[dt == 0] <= 1e-6), name
        moving = dt > 0
        assert np.all(dq[moving] / dt[moving, None] <= vmax * (1 + 1e-6)), name
        assert dq.max() <= 0.35, name


def test_report_has_every_key(run, model, cell):
    result, motion, rep = run
    assert REPORT_KEYS <= set(rep)
    assert set(rep["collisions"]) == {"arm_arm", "arm_part", "arm_bed"}
    assert rep["model"] == model and rep["cell"] == cell.name
    assert rep["mode"] == "concurrent" and rep["slicer"] == "builtin"
    assert set(rep["arms"]) == {"kinova", "ur10"}
    for name, a in rep["arms"].items():
        assert ARM_KEYS <= set(a), name
        r = result.runners[name]
        assert a["moves"] == r.stats.moves > 0
        assert a["extrude_mm"] > 0 and a["travel_mm"] > 0
        assert a["print_time_s"] > 0 and a["idle_time_s"] >= 0
        # three figures each rounded to 1 ms: the sum may pass the makespan by 1.5 ms
        assert a["print_time_s"] + a["idle_time_s"] <= rep["makespan_s"] + 1.5e-3 + 1e-9
        assert a["ik_failures"] == 0
        assert 0 < a["max_path_error_mm"] <= 0.1
    assert rep["makespan_s"] > 0
    assert rep["min_clearance_mm"] > 0
    assert rep["model_volume_mm3"] == pytest.approx(200 * 20 * 0.6, rel=1e-6)
    assert rep["deposit_volume_mm3"] == pytest.approx(rep["model_volume_mm3"], rel=0.05)
    assert rep["wall_time_s"] > 0
    json.dumps(rep)                          # a JSON document as it is


def test_deposit_is_the_programs_extrusion(run, job):
    result, _, rep = run
    total_beads, total_net = 0.0, 0.0
    for name, prog in job.programs.items():
        r = result.runners[name]
        net = net_filament(prog)
        laid = bead_filament(r)
        assert laid == pytest.approx(net, rel=0.01), name
        # exactly: the filament of the moves that lay a bead (retract/unretract excluded)
        moving = sum(s.e for s in parse_gcode_text(prog.text)
                     if type(s) is Segment and s.extrude and s.start != s.end)
        assert laid == pytest.approx(moving, abs=1e-6), name
        total_beads += laid
        total_net += net
    assert rep["deposit_volume_mm3"] == pytest.approx(total_beads * FILAMENT_AREA_MM2, abs=0.1)
    assert total_beads == pytest.approx(total_net, rel=0.01)


def test_a_slower_arm_still_collides_with_nothing(run, job, cell):
    base, _, base_rep = run
    result = simulate(job.programs, cell, slow={"ur10": 1.3})
    assert result.finished, result.reason
    motion = check_motion(result, cell)
    assert motion["collisions"] == {"arm_arm": 0, "arm_bed": 0, "arm_part": 0}
    assert motion["min_clearance_mm"] > 0
    assert result.makespan_s > base.makespan_s * 1.1
    # the slow arm moves the same way, 1.3 times slower; the other waits for it more
    slow, fast = result.runners["ur10"].stats, base.runners["ur10"].stats
    assert slow.print_time_s == pytest.approx(1.3 * fast.print_time_s, rel=1e-6)
    assert result.runners["kinova"].stats.idle_time_s > base.runners["kinova"].stats.idle_time_s
    for name in ("kinova", "ur10"):
        assert bead_filament(result.runners[name]) == pytest.approx(bead_filament(base.runners[name]), abs=1e-9)


def test_plan_command_writes_report_and_deposit(model, tmp_path, capsys):
    out = tmp_path / "plan"
    code = cli.main(["plan", model, "--out", str(out)])
    assert code == 0, capsys.readouterr()
    rep = json.loads((out / "report.json").read_text())
    assert REPORT_KEYS <= set(rep)
    assert rep["finished"] and sum(rep["collisions"].values()) == 0
    for a in rep["arms"].values():
        assert ARM_KEYS <= set(a)
    deposit = trimesh.load(str(out / "deposit.ply"), force="mesh")
    assert len(deposit.faces) > 0
    lo, hi = deposit.bounds                     # mm, world frame: around the bed centre (480 mm in x)
    assert hi[0] - lo[0] == pytest.approx(200.0, abs=2.0)
    assert 460 <= (lo[0] + hi[0]) / 2 <= 500
    for name in ("kinova.gcode", "ur10.gcode", "job.json"):
        assert (out / name).exists()
    printed = capsys.readouterr().out
    assert "finished" in printed and "makespan" in printed


# ------------------------------------------------------------ a failing arm
def program(arm, body):
    lines = ["G21", "G90", "M83", ";LAYER_CHANGE", ";Z:0.2"] + body
    return ArmProgram(arm, "concurrent", lines, start_first=True)


def test_an_unreachable_line_stops_the_run_and_the_other_arm_is_told(cell, monkeypatch):
    kinova, ur10 = cell.arm("kinova"), cell.arm("ur10")
    programs = {
        "kinova": program(kinova, ["G0 X-100 Y-100 Z0.2 F9000", "G1 X-60 Y-100 E1.5 F1200",
                                   ";@A9 R0 W1 N9",                           # waits for ur10's line 9
                                   "G1 X-60 Y-60 E1.5", "G1 X-100 Y-60 E1.5"]),
        "ur10": program(ur10, ["G0 X100 Y100 Z0.2 F9000", "G1 X60 Y100 E1.5 F1200",
                               "G1 X60 Y60 E1.5",
                               "G1 X3000 Y60 E50",                            # line 9: unreachable
                               "G1 X100 Y60 E1.5"]),
    }
    seen = []
    handle = ArmRunner.handle

    def spy(self, msg, now=None):
        seen.append((self.id, msg))
        return handle(self, msg, now)

    monkeypatch.setattr(ArmRunner, "handle", spy)
    result = simulate(programs, cell)
    assert not result.finished
    assert result.reason == "arm error"
    assert result.runners["ur10"].state is ArmState.ERROR
    assert result.runners["kinova"].state is not ArmState.DONE
    err = result.errors[0]
    assert err.robot == ur10.id and err.line == 9 and "unreachable" in err.message
    # the other arm got the error report
    assert any(rid == kinova.id and isinstance(m, ErrorReport) and m.robot == ur10.id and m.line == 9
               for rid, m in seen)
    # ... and its ERROR status (what the hub forwards to the other arms)
    assert result.runners["kinova"].peers[ur10.id].state is ArmState.ERROR
    # the ur10 laid its two reachable lines, nothing of the failing one
    lines = {int(l) for b in result.runners["ur10"].beads for l in b.line}
    assert lines == {7, 8}
    rep = report(result, check_motion(result, cell))
    assert rep["finished"] is False and rep["reason"] == "arm error"
    assert rep["errors"][0] == {"arm": ur10.id, "line": 9, "message": err.message}
    # an arm waiting for the failed one holds (PAUSED) and says why
    assert all(e["arm"] == kinova.id and "holding" in e["message"] for e in rep["errors"][1:])
    assert rep["arms"]["ur10"]["ik_failures"] == 1
    assert rep["arms"]["ur10"]["state"] == "ERROR"


def test_the_simulation_plans_joint_moves_against_the_bed_as_the_firmware_does(cell):
    """The offline run gives every arm's planner the firmware node's check
    (``ambots.collision.CollisionCheck``, the bed): an A7 into the bed is
    refused with what it would touch, as live, not executed into it."""
    kinova, ur10 = cell.arm("kinova"), cell.arm("ur10")
    programs = {
        "kinova": program(kinova, ["G0 X-100 Y-60 Z5 F9000", "G1 X-60 Y-60 E1.5 F1200",
                                   ";@A7 R%d X-60 Y-60 Z-30" % kinova.id,     # 30 mm into the bed
                                   "G1 X-100 Y-60 E1.5"]),
        "ur10": program(ur10, ["G0 X100 Y60 Z0.2 F9000", "G1 X60 Y60 E1.5 F1200"]),
    }
    result = simulate(programs, cell)
    assert result.runners["kinova"].state is ArmState.ERROR
    err = next(e for e in result.errors if e.robot == kinova.id)
    assert "no collision-free path" in err.message and "bed" in err.message, err.message
    assert check_motion(result, cell)["collisions"]["arm_bed"] == 0
    assert result.runners["ur10"].state is ArmState.DONE          # the other arm carries on
    # the same program without the check goes into the bed: the check is what keeps it out
    bare = simulate(programs, cell, planner_kw={"is_valid": None})
    assert check_motion(bare, cell)["collisions"]["arm_bed"] > 0


def test_an_arm_done_first_lifts_clear_of_the_part_while_its_neighbour_prints_on(cell, tmp_path):
    """A ramp 200 mm long rising from 0 to 20 mm towards the UR10: the
    Kinova's half ends at about 13 mm, and the UR10 prints on for about a
    thousand seconds, up to 20 mm.  The Kinova retracts and lifts straight
    up, above the whole part (its top from both programs' G-code), right
    after its last extrusion, before it waits for anything, and stays up
    there until its A7; run on one clock, no arm comes into contact with
    the part (the continuous check: the box of every bead laid so far), as
    a nozzle left at its last layer did (351 samples)."""
    ramp = trimesh.Trimesh([[-100, -20, 0], [100, -20, 0], [100, 20, 0], [-100, 20, 0], [100, -20, 20],
                            [100, 20, 20]],
                           [[0, 2, 1], [0, 3, 2], [1, 2, 5], [1, 5, 4], [0, 1, 4], [3, 5, 2], [0, 4, 5], [0, 5, 3]])
    ramp.fix_normals()
    path = str(tmp_path / "ramp.stl")
    ramp.export(path)
    job = run_job(path, cell, list(cell.arms))
    events = {n: list(parse_gcode_text(p.text, n + ".gcode")) for n, p in job.programs.items()}
    top = max(s.end[2] for ev in events.values() for s in ev if type(s) is Segment and s.extrude)
    lines = job.programs["kinova"].lines
    segs = [s for s in events["kinova"] if type(s) is Segment]
    last = max(s.line for s in segs if s.extrude and s.start[:2] != s.end[:2])
    assert max(s.end[2] for s in segs if s.extrude) < top - 5.0          # the Kinova's half ends lower
    after = [s for s in segs if s.line > last]
    first_wait = next(i for i in range(last, len(lines)) if lines[i].startswith(";@A9"))
    lifted = [s for s in after if s.line <= first_wait and s.end[2] > top]
    assert lifted and after[0].e < 0                                     # retracted, then up over the part
    assert all(s.end[2] >= lifted[0].end[2] for s in after if s.line > lifted[0].line)   # and up there
    motion = check_motion(simulate(job.programs, cell), cell)
    assert motion["collisions"] == {"arm_arm": 0, "arm_bed": 0, "arm_part": 0}
