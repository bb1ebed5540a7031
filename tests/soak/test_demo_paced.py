"""The demo at ``speed:=4`` (about 40 minutes of wall time: `make soak`, not
part of `make test`): real roscore, clock paced at 4 simulated s per wall
s, hub, one firmware per arm, the front end and the capture (`make print`
of the demo block).  Live = checked on the one clock: no contact in the
joint states as they arrived nor in the executed motion, and the same
makespan as the offline run of the same job (`python -m ambots plan`)
within 1 %.  The demo at ``speed:=max`` is tests/ros/test_demo.py; models
of our own at speed 4 and 1 are tests/ros/test_one_clock.py."""
import json
import os
import subprocess

from ambots import data_path
from ambots.commands.plan import plan_job
from ambots.config import default_cell_path, load_cell
from ambots.job import DEMO_MODEL

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def test_demo_at_speed_4_live_equals_checked_and_plan(tmp_path):
    model = data_path(*DEMO_MODEL.split("/"))
    out = tmp_path / "print"
    env = dict(os.environ, ROS_HOME=str(tmp_path / "ros_home"))
    with open(tmp_path / "make.log", "w") as f:
        r = subprocess.run(["make", "-s", "print", "MODEL=%s" % model, "OUT=%s" % out, "SPEED=4"],
                           cwd=ROOT, stdout=f, stderr=subprocess.STDOUT, timeout=4 * 3600, env=env)
    log = (tmp_path / "make.log").read_text()
    assert r.returncode == 0, log[-3000:]
    live = json.loads((out / "report.json").read_text())
    assert live["finished"] and live["collisions"] == {"arm_arm": 0, "arm_bed": 0, "arm_part": 0}, live
    assert live["live_collisions"] == {"arm_arm": 0, "arm_bed": 0, "arm_part": 0}, live
    assert live["live_collision_checks"] > 1000 and live["live_min_clearance_mm"] > 0
    cell = load_cell(default_cell_path())
    offline = plan_job(model, cell)
    assert offline["finished"] and sum(offline["collisions"].values()) == 0
    assert abs(live["makespan_s"] - offline["makespan_s"]) <= 0.01 * offline["makespan_s"], \
        (live["makespan_s"], offline["makespan_s"])
    # it ran at the pace asked: the printing took about makespan / 4 of wall time
    assert live["wall_time_s"] > live["makespan_s"] / 4 * 0.9, live["wall_time_s"]
