"""The full demo, run as the README says (`make demo`, into a temporary
folder): real roscore, hub, one firmware per arm at speed max, the front end
printing the demo block, and the capture.  The print must finish with zero
collisions, the capture must show both arms' filament colours, and make must
end with the summary and exit 0."""
import json
import os
import subprocess

import numpy as np
import pytest

from ambots.commands.plan import plan_job
from ambots.config import default_cell_path, load_cell

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def _tail(path, n=6000):
    return path.read_text()[-n:] if path.exists() else ""


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """`make demo` into a temporary folder: (exit status, make's output, folder)."""
    tmp_path = tmp_path_factory.mktemp("demo")
    env = dict(os.environ, ROS_HOME=str(tmp_path / "ros_home"))
    out = tmp_path / "demo"
    log = tmp_path / "make.log"
    with open(log, "w") as f:      # a file, not a pipe (see test_rostests.py)
        r = subprocess.run(["make", "-s", "demo", "DEMO_OUT=%s" % out], cwd=ROOT, stdout=f,
                           stderr=subprocess.STDOUT, text=True, timeout=1500, env=env)
    return r, log.read_text(), out


def test_demo_prints_with_both_arms_concurrently_without_collision(demo):
    r, text, out = demo
    assert r.returncode == 0 and (out / "report.json").exists(), text[-3000:] + _tail(out / "launch.log")
    # the summary: finished, makespan, speed-up against one arm alone, contacts, where the files are
    summary = text[text.index("FINISHED"):]
    for needle in ("makespan", "plan: 2 arms concurrent (kinova, ur10)", "best single arm", "speed-up",
                   "contacts      0", "closest approach",
                   str(out / "capture.png"), str(out / "report.json")):
        assert needle in summary, (needle, summary)
    report = json.loads((out / "report.json").read_text())
    assert report["finished"] is True, report
    assert report["collisions"] == {"arm_arm": 0, "arm_bed": 0, "arm_part": 0}
    # live = checked: the joint states as they arrived, paired by the instant of the one clock
    assert report["live_collisions"] == {"arm_arm": 0, "arm_bed": 0, "arm_part": 0}, report
    assert report["live_collision_checks"] > 100 and report["live_min_clearance_mm"] > 0
    # the same motion as the offline run of the same job (python -m ambots plan)
    offline = plan_job(os.path.join(ROOT, "config", "models", "demo_block.stl"), load_cell(default_cell_path()))
    assert abs(report["makespan_s"] - offline["makespan_s"]) <= 0.01 * offline["makespan_s"], \
        (report["makespan_s"], offline["makespan_s"])
    assert report["collision_checks"] > 100 and report["min_clearance_mm"] > 0
    for name, arm in report["arms"].items():
        assert arm["state"] == "DONE" and arm["beads"] > 1000 and arm["ik_failures"] == 0, name
        assert arm["max_path_error_mm"] <= 0.1
    # concurrent: the planner chose both arms, faster than the best arm alone, and the arms
    # printed at the same time (measured: a makespan of 0.81 of the two arms' moving times)
    plan = report["plan"]
    assert plan["arms"] == ["kinova", "ur10"] and plan["speedup"] > 1.0, plan
    assert report["makespan_s"] < plan["best_single_arm_s"]
    busy = [a["print_time_s"] for a in report["arms"].values()]
    assert max(busy) < 0.8 * sum(busy)
    assert report["makespan_s"] < 0.9 * sum(busy)
    for f in ("deposit.ply", "kinova.gcode", "ur10.gcode", "capture.png"):
        assert (out / f).stat().st_size > 0
    # both filament colours (profiles: kinova orange, ur10 blue) are in the picture
    from PIL import Image
    img = np.asarray(Image.open(out / "capture.png").convert("RGB")).astype(int)
    orange = (img[..., 0] > 200) & (img[..., 1] > 60) & (img[..., 1] < 160) & (img[..., 2] < 80)
    blue = (img[..., 2] > 180) & (img[..., 0] < 80) & (img[..., 1] > 60) & (img[..., 1] < 160)
    assert orange.sum() > 50 and blue.sum() > 50, (orange.sum(), blue.sum())

