"""The full demo, as `make demo` runs it: real roscore, hub, one firmware per
arm at speed max, the front end printing the demo block, and the capture.
The print must finish with zero collisions, and the capture must show both
arms' filament colours."""
import json
import os
import subprocess

import numpy as np


def test_demo_prints_with_both_arms_concurrently_without_collision(tmp_path):
    env = dict(os.environ, ROS_HOME=str(tmp_path / "ros_home"))
    out = tmp_path / "demo"
    log = tmp_path / "demo.log"
    with open(log, "w") as f:      # a file, not a pipe (see test_rostests.py)
        r = subprocess.run(["roslaunch", "ambots", "demo.launch", "out:=%s" % out], stdout=f,
                           stderr=subprocess.STDOUT, text=True, timeout=900, env=env)
    assert r.returncode == 0 and (out / "report.json").exists(), log.read_text()[-6000:]
    report = json.loads((out / "report.json").read_text())
    assert report["finished"] is True, report
    assert report["collisions"] == {"arm_arm": 0, "arm_bed": 0, "arm_part": 0}
    assert report["collision_checks"] > 100 and report["min_clearance_mm"] > 0
    for name, arm in report["arms"].items():
        assert arm["state"] == "DONE" and arm["beads"] > 1000 and arm["ik_failures"] == 0, name
        assert arm["max_path_error_mm"] <= 0.1
    # concurrent: each arm spent most of the makespan printing, not waiting for the other
    busy = [a["print_time_s"] for a in report["arms"].values()]
    assert max(busy) < 0.8 * sum(busy)
    assert report["makespan_s"] < 0.8 * sum(busy)
    for f in ("deposit.ply", "kinova.gcode", "ur10.gcode", "capture.png"):
        assert (out / f).stat().st_size > 0
    # both filament colours (profiles: kinova orange, ur10 blue) are in the picture
    from PIL import Image
    img = np.asarray(Image.open(out / "capture.png").convert("RGB")).astype(int)
    orange = (img[..., 0] > 200) & (img[..., 1] > 60) & (img[..., 1] < 160) & (img[..., 2] < 80)
    blue = (img[..., 2] > 180) & (img[..., 0] < 80) & (img[..., 1] > 60) & (img[..., 1] < 160)
    assert orange.sum() > 50 and blue.sum() > 50, (orange.sum(), blue.sum())
