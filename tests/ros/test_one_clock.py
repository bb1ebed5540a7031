"""One clock, live = checked: models of our own (an 80 x 25 x 2 mm plate at
speed:=4 with an interlocking seam, a 40 x 12 x 0.4 mm strip at speed:=1,
the wall's pace; made here)
printed live (`make print`, real roscore, clock, hub, firmware, front end,
capture) have no contact in the joint states as they
arrived (paired by the instant of the one clock) nor in the executed
motion, and the same makespan as the offline run (`python -m ambots plan`)
of the same job within 1 %, and the seam figures of the offline run.  The demo at speed:=max is checked the same way
in test_demo.py (at speed:=4 it would take an hour of wall time)."""
import json
import os
import subprocess

import pytest
import trimesh

from ambots.commands.plan import plan_job
from ambots.config import default_cell_path, load_cell

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


@pytest.mark.parametrize("dims, speed, seam", [((80.0, 25.0, 2.0), 4, "interlock"), ((40.0, 12.0, 0.4), 1, "straight")],
                         ids=["plate_80x25x2_speed_4_interlock", "strip_40x12x0.4_speed_1"])
def test_own_model_live_equals_checked_and_plan(tmp_path, dims, speed, seam):
    model = tmp_path / ("box_%gx%gx%g.stl" % dims)
    trimesh.creation.box(dims).export(model)
    out = tmp_path / "print"
    env = dict(os.environ, ROS_HOME=str(tmp_path / "ros_home"))
    with open(tmp_path / "make.log", "w") as f:
        # both arms (the planner would give a part this small to one arm): two arms on one clock
        r = subprocess.run(["make", "-s", "print", "MODEL=%s" % model, "OUT=%s" % out, "SPEED=%d" % speed,
                            "ARMS=kinova,ur10", "SEAM=%s" % seam],
                           cwd=ROOT, stdout=f, stderr=subprocess.STDOUT, timeout=1500, env=env)
    log = (tmp_path / "make.log").read_text()
    assert r.returncode == 0, log[-3000:]
    live = json.loads((out / "report.json").read_text())
    assert live["finished"] and live["collisions"] == {"arm_arm": 0, "arm_bed": 0, "arm_part": 0}, live
    assert live["live_collisions"] == {"arm_arm": 0, "arm_bed": 0, "arm_part": 0}, live
    assert live["live_collision_checks"] > 50 and live["live_min_clearance_mm"] > 0
    cell = load_cell(default_cell_path())
    offline = plan_job(str(model), cell, list(cell.arms), seam=seam)
    assert offline["finished"] and sum(offline["collisions"].values()) == 0
    assert abs(live["makespan_s"] - offline["makespan_s"]) <= 0.01 * offline["makespan_s"], \
        (live["makespan_s"], offline["makespan_s"])
    # the seam as the offline run measures it: the share of the seam face one bead bonds (an
    # interlock nearly all of it; a straight seam where the solid layers' zig-zag lanes, cut at
    # the plane, are joined along it: every layer of the 0.4 mm strip is solid), and every
    # arm's lap laid after the neighbour's layer below, by the beads' times on the one clock
    assert live["seam"] == seam
    (pair, share), = live["seam_bonded_share"].items()
    assert share["samples"] == offline["seam_bonded_share"][pair]["samples"]
    assert share["bonded_share"] == pytest.approx(offline["seam_bonded_share"][pair]["bonded_share"], abs=0.01)
    assert share["bonded_share"] >= (0.9 if seam == "interlock" else 0.5)
    assert live["seam_lap_order"][pair]["early"] == offline["seam_lap_order"][pair]["early"]
    if seam == "interlock":
        assert live["seam_lap_order"][pair]["early"] == 0
