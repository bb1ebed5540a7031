"""``python -m ambots export`` (ambots.export): a small two-arm plan written
by hand (the UR10 waits at a barrier for the Kinova) is exported as joint
trajectories that are the planner's waypoints, within the speed limits,
re-timed (by default) within the acceleration limits; it is refused as
URScript (open loop: a script cannot wait for the other arm).  The UR10's
program planned alone is exported as URScript -- structurally valid, one
movel per G-code move whose pose is the G-code target in the UR base frame
and agrees with the published DH kinematics of the planned joints.  Non-UR
arms, missing folders and unknown formats are refused with typed errors."""
import csv
import json
import math
import re
import shutil

import numpy as np
import pytest
import yaml

import robot_facts as F
from ambots import cli
from ambots.config import default_cell_path, load_cell, pose_matrix
from ambots.coordinate import ArmProgram
from ambots.errors import AmbotsError, ExportError
from ambots.export import FORMATS, check_limits, export_plan, rotation_vector
from ambots.gcode import Segment, parse_gcode_text
from ambots.motion import MotionPlanner, Moves, read_program
from ambots.sim import check_motion, report, simulate

HEADER = ["G21", "G90", "M83", ";LAYER_CHANGE", ";Z:0.2"]
UR10 = HEADER + [
    "G0 X100 Y-20 Z0.2 F9000",        # 6: first travel: a joint move
    "G1 X140 Y-20 E1.5 F1200",        # 7
    "G1 X140 Y20 E1.5",               # 8
    ";@A9 R1 W0 N13",                 # 9: wait until the Kinova has done its line 13
    "G1 X100 Y20 E1.5",               # 10
    "G1 E-0.8 F2100",                 # 11: retraction (no motion)
    "G0 Z0.6 F9000",                  # 12
    "G0 X100 Y-10",                   # 13
    "G0 Z0.2",                        # 14
    "G1 E0.8 F2100",                  # 15
    "G1 X130 Y-10 E1.0 F1800",        # 16
    "G4 P500",                        # 17
    ";LAYER_CHANGE",
    ";Z:0.4",
    "G0 Z0.4 F9000",                  # 20: short lift from rest
    "G1 X130 Y10 E1.0 F1800",         # 21
    "G1 X100 Y10 E1.0",               # 22
]
#: the two arms print 200 mm apart at their nearest (x -100 and +100): with bodies
#: that cover the real arms they need about 150 mm facing each other
KINOVA = HEADER + [
    "G0 X-100 Y-20 Z0.2 F9000",
    "G1 X-140 Y-20 E1.5 F1200",
    "G1 X-140 Y20 E1.5",
    "G1 X-100 Y20 E1.5",
    "G1 X-100 Y-20 E1.5",
    "G1 X-140 Y-20 E1.5",
    "G1 X-140 Y0 E0.8",               # 12
    "G1 X-100 Y0 E1.5",               # 13
]
BARRIER_LINE, DWELL_LINE = 9, 17
#: the UR10's program printed alone: the barrier line is a plain comment (same line numbers, same motion)
UR10_ALONE = UR10[:BARRIER_LINE - 1] + ["; no barrier: printed alone"] + UR10[BARRIER_LINE:]
URSCRIPT_FUNCTIONS = {"movel", "movej", "movep", "movec", "set_tcp", "set_payload", "set_tool_digital_out",
                      "set_standard_digital_out", "sleep", "sync", "textmsg", "popup", "stopl", "stopj"}


@pytest.fixture(scope="module")
def cell():
    return load_cell(default_cell_path())


@pytest.fixture(scope="module")
def plan(tmp_path_factory, cell):
    """A plan folder as `plan` writes it (programs, job.json, report.json)
    and the plain simulation of it (the reference)."""
    path = tmp_path_factory.mktemp("plan")
    programs = {"kinova": ArmProgram(cell.arm("kinova"), "concurrent", KINOVA),
                "ur10": ArmProgram(cell.arm("ur10"), "concurrent", UR10)}
    result = simulate(programs, cell)
    rep = report(result, check_motion(result, cell), cell=cell, mode="concurrent")
    assert rep["finished"] and sum(rep["collisions"].values()) == 0
    for name, prog in programs.items():
        (path / (name + ".gcode")).write_text(prog.text)
    (path / "job.json").write_text(json.dumps({"cell": cell.name, "mode": "concurrent", "arms": {
        name: {"id": prog.arm.id} for name, prog in programs.items()}}))
    (path / "report.json").write_text(json.dumps(rep))
    return path, programs, result


@pytest.fixture(scope="module")
def solo(tmp_path_factory, cell):
    """A plan folder of the UR10 alone (what `plan --arms ur10` writes)."""
    path = tmp_path_factory.mktemp("solo")
    programs = {"ur10": ArmProgram(cell.arm("ur10"), "concurrent", UR10_ALONE)}
    result = simulate(programs, cell)
    rep = report(result, check_motion(result, cell), cell=cell, mode="concurrent")
    assert rep["finished"] and sum(rep["collisions"].values()) == 0
    (path / "ur10.gcode").write_text(programs["ur10"].text)
    (path / "job.json").write_text(json.dumps({"cell": cell.name, "mode": "concurrent",
                                               "arms": {"ur10": {"id": cell.arm("ur10").id}}}))
    (path / "report.json").write_text(json.dumps(rep))
    return path


@pytest.fixture(scope="module")
def script(solo, tmp_path_factory):
    """The UR10's URScript, written by the command line."""
    out = tmp_path_factory.mktemp("urscript")
    code = cli.main(["export", str(solo), "--format", "urscript", "--out", str(out)])
    assert code == 0
    assert sorted(p.name for p in out.iterdir()) == ["ur10.script"]
    return (out / "ur10.script").read_text()


def read_trajectory(out, arm):
    with open(out / (arm + ".trajectory.csv")) as f:
        rows = list(csv.reader(f))
    header = yaml.safe_load((out / (arm + ".trajectory.yaml")).read_text())
    return rows[0], np.array(rows[1:], dtype=float), header


@pytest.fixture(scope="module")
def planned(plan, tmp_path_factory):
    out = tmp_path_factory.mktemp("planned")
    summary = export_plan(str(plan[0]), "trajectory", out=str(out))
    return out, summary


# ------------------------------------------------------------- helpers
def dh_flange(q):
    """The UR10's flange (DH frame 6) in its base frame, from the published DH table."""
    T = np.eye(4)
    for qi, (d, a, alpha) in zip(q, F.UR10_DH):
        ca, sa, cq, sq = math.cos(alpha), math.sin(alpha), math.cos(qi), math.sin(qi)
        T = T @ np.array([[cq, -sq * ca, sq * sa, a * cq], [sq, cq * ca, -cq * sa, a * sq], [0, sa, ca, d],
                          [0, 0, 0, 1]])
    return T


def rodrigues(v):
    v = np.asarray(v, float)
    angle = np.linalg.norm(v)
    if angle < 1e-15:
        return np.eye(3)
    k = v / angle
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def angle_between(Ra, Rb):
    return math.acos(min(1.0, max(-1.0, (np.trace(Ra.T @ Rb) - 1) / 2)))


def reference_joints(cell, text):
    """{line: joints at the end of that line} by the firmware's planner, item after item."""
    arm = cell.arm("ur10")
    planner = MotionPlanner(arm, cell)
    q = np.array(arm.profile.home, float)
    out = {}
    for item in read_program(text)[0]:
        if isinstance(item, Moves):
            b = planner.plan_moves(item.segments, q)
            for k in range(len(b.t)):
                out[int(b.line[k])] = b.Q[k]
            q = b.Q[-1]
    return out


def parse_script(text):
    """Statements of a URScript program: (function name, argument text, comment)."""
    lines = text.rstrip("\n").split("\n")
    assert lines[0] == "def ambots_ur10():" and lines[-1] == "end"
    body = lines[1:-1]
    calls = []
    for line in body:
        assert line.startswith("  ") and not line.startswith("   "), line
        stmt = line.strip()
        assert not re.match(r"(def|end|if|while|for|thread)\b", stmt), line
        if stmt.startswith("#"):
            continue
        code, _, comment = stmt.partition("#")          # no string or argument here holds a '#'
        m = re.match(r"^(\w+)\((.*)\)$", code.strip())
        assert m, line
        name, args = m.groups()
        comment = comment.strip()
        assert args.count("(") == args.count(")") and args.count("[") == args.count("]"), line
        calls.append((name, args, comment))
    return calls


def numbers(args):
    return [float(x) for x in re.findall(r"-?\d+\.\d+(?:[eE][-+]?\d+)?|-?\d+", args)]


# ------------------------------------------------------------- URScript
def test_urscript_is_one_def_with_known_calls_and_finite_numbers(script):
    assert script.count("def ") == 1 and script.rstrip().endswith("\nend")
    assert not re.search(r"\b(nan|inf)\b", script, re.I)
    calls = parse_script(script)
    assert {name for name, _, _ in calls} <= URSCRIPT_FUNCTIONS
    for name, args, _ in calls:
        assert all(math.isfinite(x) for x in numbers(args)), args
    names = [name for name, _, _ in calls]
    assert names[:4] == ["textmsg", "set_tcp", "set_tool_digital_out", "movej"]
    assert names[-2:] == ["set_tool_digital_out", "textmsg"]
    # the TCP is the profile's tool offset
    assert calls[1][1] == "p[0.100000, 0.000000, 0.200000, 0.000000, 0.000000, 0.000000]"
    assert all(len(line) < 200 for line in script.split("\n"))


def test_every_movel_is_the_gcode_target_in_the_base_frame_and_the_fk_of_the_planned_joints(script, cell):
    arm = cell.arm("ur10")
    tool = pose_matrix(arm.profile.tool_xyz, arm.profile.tool_rpy)
    bed_to_base = np.linalg.inv(arm.base_pose) @ cell.bed.pose
    segs = {s.line: s for s in parse_gcode_text("\n".join(UR10) + "\n") if type(s) is Segment}
    ref = reference_joints(cell, "\n".join(UR10) + "\n")
    extruding, seen = None, []
    for name, args, comment in parse_script(script):
        if name == "set_tool_digital_out":
            assert args in ("0, True", "0, False")
            extruding = args.endswith("True")
        if name != "movel":
            continue
        m = re.match(r"p\[([^\]]*)\], a=([\d.]+), v=([\d.]+)$", args)
        assert m, args
        pose = np.array([float(x) for x in m.group(1).split(",")])
        a, v = float(m.group(2)), float(m.group(3))
        line = int(re.match(r"line (\d+)$", comment).group(1))
        seen.append(line)
        seg = segs[line]
        # position: the G-code target (bed frame, mm) in the UR base frame (m)
        target = bed_to_base @ np.append(np.asarray(seg.end) * 1e-3, 1.0)
        np.testing.assert_allclose(pose[:3], target[:3], atol=1e-6)
        # pose: forward kinematics (published DH table + tool offset) of the planned joints at the move's end
        T = dh_flange(ref[line]) @ tool
        assert np.linalg.norm(T[:3, 3] - pose[:3]) < 1e-4
        assert angle_between(T[:3, :3], rodrigues(pose[3:])) < 1e-3
        # extruder on exactly for the extruding moves; speed = the feedrate (m/s), nozzle pointing down
        assert extruding == seg.extrude, line
        assert 0 < v <= seg.feedrate / 60000.0 + 1e-9 and a > 0
        assert v == pytest.approx(seg.feedrate / 60000.0, rel=1e-4)
        assert rodrigues(pose[3:])[:, 2] == pytest.approx([0, 0, -1], abs=1e-6)
    # one movel per G-code move with motion, except the first travel (a joint move)
    moving = sorted(l for l, s in segs.items() if s.start != s.end)
    assert seen == [l for l in moving if l != 6]


def test_joint_moves_and_dwell(script, cell):
    calls = parse_script(script)
    movej = [(numbers(args), comment) for name, args, comment in calls if name == "movej"]
    ref = reference_joints(cell, "\n".join(UR10_ALONE) + "\n")
    home = cell.arm("ur10").profile.home
    assert len(movej) == 2
    np.testing.assert_allclose(movej[0][0][:6], home, atol=1e-6)
    np.testing.assert_allclose(movej[1][0][:6], ref[6], atol=1e-6)       # the travel of line 6, in joint space
    sleeps = [(numbers(args)[0], comment) for name, args, comment in calls if name == "sleep"]
    assert [s for s, c in sleeps if "G4" in c] == [0.5]
    assert not [c for s, c in sleeps if "barrier" in c]
    # the extruder is off while the arm waits
    names = [(n, a) for n, a, _ in calls]
    for i, (n, _) in enumerate(names):
        if n == "sleep":
            state = [a for m, a in names[:i] if m == "set_tool_digital_out"][-1]
            assert state.endswith("False")


def test_urscript_refuses_a_job_of_several_arms_open_loop(plan, tmp_path, capsys):
    """The two-arm plan: even the UR10 alone is refused (its script could not
    wait at the barrier of line 9), naming why and what to do instead."""
    with pytest.raises(ExportError, match=r"2 arms \(kinova, ur10, 1 barriers\).*open loop.*trajectory"):
        export_plan(str(plan[0]), "urscript", arms="ur10", out=str(tmp_path))
    assert cli.main(["export", str(plan[0]), "--format", "urscript", "--arms", "ur10", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "open loop" in err and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []                                 # nothing written


def test_urscript_refuses_a_kinova_arm_naming_it(plan, capsys):
    with pytest.raises(ExportError, match=r"arm kinova \(R0\).*Kinova.*not a Universal Robots arm"):
        export_plan(str(plan[0]), "urscript")
    with pytest.raises(ExportError, match="kinova"):
        export_plan(str(plan[0]), "urscript", arms="kinova")
    assert cli.main(["export", str(plan[0]), "--format", "urscript", "--arms", "kinova"]) == 2
    err = capsys.readouterr().err
    assert "ambots: error:" in err and "kinova" in err and "Traceback" not in err


# ------------------------------------------------------------- trajectory
def test_planned_trajectory_is_the_planners_motion(planned, plan, cell):
    out, summary = planned
    _, programs, result = plan
    assert set(summary["arms"]) == {"kinova", "ur10"} and summary["timing"] == "one law"
    for name in ("kinova", "ur10"):
        arm = cell.arm(name)
        prof = arm.profile
        names = list(prof.driver_joint_names)
        cols, data, header = read_trajectory(out, name)
        assert cols == ["time_s"] + names + ["extruding", "e_mm"] + [j + "_velocity" for j in names]
        assert header["arm"] == name and header["joint_names"] == names
        assert header["samples"] == len(data) and header["timing"] == "one law"
        assert header["duration_s"] == pytest.approx(data[-1, 0] - data[0, 0], abs=1e-6)
        assert set(header["limits"]) == set(prof.driver_joint_names)
        n = len(names)
        t, Q, ex, e, V = data[:, 0], data[:, 1:1 + n], data[:, 1 + n], data[:, 2 + n], data[:, 3 + n:]
        assert t[0] == 0.0 and np.all(np.diff(t) > 0)
        np.testing.assert_allclose(Q[0], prof.home, atol=1e-9)
        # every knot the firmware executed (plain simulation), at its time, with its speed
        r = result.runners[name]
        tt, qq, vv = (np.concatenate(x) for x in (r.trace_t, r.trace_q, r.trace_v))
        last = np.concatenate([np.diff(tt) > 1e-9, [True]])       # one row per time
        tt, qq, vv = tt[last], qq[last], vv[last]
        idx = np.searchsorted(t, tt - 1e-8)
        np.testing.assert_allclose(t[idx], tt, atol=1e-8)
        np.testing.assert_allclose(Q[idx], qq, atol=1e-8)
        np.testing.assert_allclose(V[idx], vv, atol=1e-8)
        # rows not executed by the firmware are holds (waits): the joints do not move
        extra = np.setdiff1d(np.arange(1, len(t)), idx)
        np.testing.assert_allclose(Q[extra], Q[extra - 1], atol=0)
        assert not V[extra].any()
        # the motion between the rows (Hermite, textbook basis) within the joint limits:
        # dense samples, finite differences
        vmax = np.array([j.velocity for j in prof.joints]) * prof.velocity_scaling
        amax = np.array([j.acceleration for j in prof.joints]) * prof.velocity_scaling
        h = np.diff(t)
        moving = np.any(np.diff(Q, axis=0) != 0, axis=1)
        ks = np.nonzero(moving)[0][:4000]
        S = np.linspace(0.0, 1.0, 41)
        H = h[ks][:, None, None]
        s3 = S[None, :, None]
        P = ((2 * s3**3 - 3 * s3**2 + 1) * Q[ks][:, None] + (s3**3 - 2 * s3**2 + s3) * H * V[ks][:, None]
             + (-2 * s3**3 + 3 * s3**2) * Q[ks + 1][:, None] + (s3**3 - s3**2) * H * V[ks + 1][:, None])
        dts = H[:, :, 0] / 40.0
        sp = np.abs(np.diff(P, axis=1)) / dts[:, :, None]
        assert np.all(sp <= vmax * (1 + 1e-3) + 1e-6)
        acc = np.abs(np.diff(P, n=2, axis=1)) / (dts[:, :, None] ** 2)
        assert np.all(acc <= amax * (1 + 1e-3) + 1e-3)
        assert header["checks"]["velocity_ok"] and header["checks"]["acceleration_ok"]
        # filament: the beads the firmware laid
        assert set(np.unique(ex)) <= {0.0, 1.0}
        beads = r.beads
        assert int(ex.sum()) == sum(len(b.e_mm) for b in beads)
        assert e[ex == 1].sum() == pytest.approx(sum(b.e_mm.sum() for b in beads), abs=1e-4)
    # the waits are in the trajectory: the UR10 stands still at the barrier
    assert summary["arms"]["ur10"]["duration_s"] > result.runners["ur10"].stats.print_time_s + 1.0
    assert summary["warnings"] == []


def test_rotation_vector_round_trips_near_pi_and_stays_continuous():
    rng = np.random.default_rng(7)
    angles = np.concatenate([rng.uniform(0, math.pi, 50), [0.0, 1e-9, math.pi - 1e-9, math.pi, 3.0]])
    for angle in angles:
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        R = rodrigues(axis * angle)
        v = rotation_vector(R)
        assert np.linalg.norm(v) <= math.pi + 1e-12
        np.testing.assert_allclose(rodrigues(v), R, atol=1e-9)
    # nozzle down, turning about the vertical through pi: no flip of the vector
    prev = None
    for yaw in np.linspace(0, 2 * math.pi, 73):
        R = pose_matrix((0, 0, 0), (math.pi, 0, yaw))[:3, :3]
        v = rotation_vector(R, prev)
        np.testing.assert_allclose(rodrigues(v), R, atol=1e-9)
        if prev is not None:
            assert np.linalg.norm(v - prev) < 0.2
        prev = v


def test_limits_check_reports_an_unscaled_profile():
    """check_limits measures against velocity/acceleration x velocity_scaling."""
    from ambots.export import Trajectory
    prof = load_cell(default_cell_path()).arm("ur10").profile
    t = np.array([0.0, 1.0, 2.0])
    Q = np.zeros((3, 6))
    Q[1, 0], Q[2, 0] = 0.5, 1.0
    traj = Trajectory(None, prof.driver_joint_names, t, Q, np.zeros(3, bool), np.zeros(3), np.zeros(3, int))
    c = check_limits(traj, prof)
    assert c["velocity_ok"] and c["max_velocity"]["shoulder_pan_joint"] == pytest.approx(0.5)
    assert c["velocity_limit"]["shoulder_pan_joint"] == pytest.approx(2.0944 * 0.5)
    assert c["acceleration_limit"]["shoulder_pan_joint"] == pytest.approx(4.0 * 0.5)
    assert c["max_acceleration"]["shoulder_pan_joint"] == pytest.approx(1.0)      # 0.5 rad/s over 0.5 s
    assert c["acceleration_ok"]


# ------------------------------------------------------------- errors
def test_bad_folders_formats_and_arms_are_typed_errors(plan, tmp_path, capsys):
    path = str(plan[0])
    assert FORMATS == ("trajectory", "urscript")
    with pytest.raises(ExportError, match="plan folder not found"):
        export_plan(str(tmp_path / "missing"), "trajectory")
    with pytest.raises(ExportError, match="unknown export format 'gcode'"):
        export_plan(path, "gcode")
    with pytest.raises(ExportError, match="no arm 'panda' in this plan"):
        export_plan(path, "trajectory", arms="panda")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ExportError, match="job.json: not found"):
        export_plan(str(tmp_path / "empty"), "trajectory")
    # a plan that collided is not exported (unless forced)
    bad = tmp_path / "collided"
    shutil.copytree(path, bad)
    rep = json.loads((bad / "report.json").read_text())
    rep["collisions"]["arm_arm"] = 3
    (bad / "report.json").write_text(json.dumps(rep))
    with pytest.raises(ExportError, match="collisions"):
        export_plan(str(bad), "trajectory")
    (bad / "report.json").unlink()
    with pytest.raises(ExportError, match="no report.json"):
        export_plan(str(bad), "trajectory")
    (bad / "ur10.gcode").unlink()
    with pytest.raises(ExportError, match="ur10.gcode: not found"):
        export_plan(str(bad), "trajectory", force=True)
    assert issubclass(ExportError, AmbotsError)
    for argv in (["export", str(tmp_path / "missing"), "--format", "trajectory"],
                 ["export", path, "--format", "gcode"]):
        assert cli.main(argv) == 2
        err = capsys.readouterr().err
        assert err.startswith("ambots: error:") and "Traceback" not in err
    assert "export" in cli.build_parser().format_help()
