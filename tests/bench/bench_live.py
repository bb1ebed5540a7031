"""Live simulation speed: the running system (roslaunch both_arms.launch
speed:=max -> roscore, hub, one firmware node per arm, robot_state_publisher)
prints the demo model, started by the front end (`--print`).  Measured from
the firmware nodes' stats topics: simulated makespan (first motion to last
arm done, the arms' own clocks) divided by the wall time from the first arm
printing to the last arm done (goal >= 200 simulated seconds per wall
second).  Slicing is not timed (the front end slices before it starts the
arms).  Runs on its own master port so it cannot disturb another ROS."""
import json
import os
import subprocess
import sys
import tempfile

import rospkg

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "ros"))
from faults import cpu_seconds, firmware_processes, start_cell, stop_cell  # noqa: E402

PORT = 11391


def main():
    env = dict(os.environ, ROS_MASTER_URI="http://localhost:%d" % PORT)
    tmp = tempfile.mkdtemp(prefix="ambots-bench-live-")
    env["ROS_HOME"] = os.path.join(tmp, "ros_home")
    pkg = rospkg.RosPack().get_path("ambots")
    with open(os.path.join(tmp, "launch.log"), "w") as log:
        launch = start_cell(PORT, env, log)
    try:
        stats = _watch_print(env, pkg, tmp)
        cpu = {arm: cpu_seconds(pid) for arm, pid in firmware_processes().items()}
    finally:
        stop_cell(launch)
    first = min(s["stats"]["first_motion_s"] for s in stats["final"].values())
    done = max(s["stats"]["done_s"] for s in stats["final"].values())
    wall = stats["t_done"] - stats["t_printing"]
    for name, s in sorted(stats["final"].items()):
        print("live %-7s %s: %6.0f s printing, %6.0f s idle (simulated); firmware process CPU %.1f s "
              "(whole life)" % (name, s["state"], s["stats"]["print_time_s"], s["stats"]["idle_time_s"],
                                cpu.get(name, float("nan"))))
    print("live speed:=max, demo model, both arms: makespan %.0f s simulated in %.1f s wall "
          "-> %.0f simulated s per wall s (goal >= 200)" % (done - first, wall, (done - first) / wall))


def _watch_print(env, pkg, tmp):
    """Start the front end's print job and follow the arms' stats until every arm is done."""
    code = r"""
import json, sys, time, rospy
from std_msgs.msg import String
from ambots.config import default_cell_path, load_cell
cell = load_cell(default_cell_path())
rospy.init_node("bench_live", anonymous=True)
last, t_printing = {}, [None]
def on(msg):
    s = json.loads(msg.data)
    if s["state"] == "PRINTING" and t_printing[0] is None:
        t_printing[0] = time.monotonic()
    last[s["arm"]] = s
for a in cell.arms:
    rospy.Subscriber("/%s/firmware/stats" % a.name, String, on, queue_size=100)
print("ready", flush=True)
deadline = time.monotonic() + float(sys.argv[1])
while time.monotonic() < deadline and not rospy.is_shutdown():
    if len(last) == len(cell.arms) and all(s["state"] in ("DONE", "ERROR") for s in last.values()) \
            and t_printing[0] is not None:
        t_done = time.monotonic()
        print(json.dumps({"final": last, "t_printing": t_printing[0], "t_done": t_done}), flush=True)
        break
    time.sleep(0.005)
"""
    watcher = subprocess.Popen([sys.executable, "-c", code, "1200"], stdout=subprocess.PIPE, text=True,
                               env=env)
    for line in watcher.stdout:          # rospy says it is waiting for the master first
        if line.strip() == "ready":
            break
    else:
        raise RuntimeError("the stats watcher did not start")
    with open(os.path.join(tmp, "front_end.log"), "w") as log:
        fe = subprocess.run([sys.executable, os.path.join(pkg, "nodes", "front_end"), "--print",
                             "--out", os.path.join(tmp, "job"), "--timeout", "1200"],
                            stdout=log, stderr=subprocess.STDOUT, env=env, timeout=1300)
    out, _ = watcher.communicate(timeout=60)
    if fe.returncode != 0 or not out.strip():
        raise RuntimeError("live print failed (front end exit %d); logs in %s" % (fe.returncode, tmp))
    return json.loads(out.strip().splitlines()[-1])


if __name__ == "__main__":
    main()
