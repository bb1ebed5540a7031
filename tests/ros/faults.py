"""Shared by the fault suite (tests/ros/test_faults.py) and `make faults`
(tests/bench/bench_faults.py): one print of a small model by the running
system (roslaunch both_arms.launch speed:=max on its own master port: hub,
firmware nodes with their state directory, robot_state_publisher), started
by the front end, watched by a recorder (ambots.ros.capture.PrintRecorder:
the executed trajectories in simulated time -> contacts) -- with hub fault
injection, a kill -9 of a firmware node mid-print (roslaunch respawns it;
it resumes from its checkpoint) and/or a slowed arm.

The recorder forgets every trace and bead row a killed firmware had
published (as if all of it had died in the publisher's queue of the killed
process): the respawned firmware must publish the run so far again from
its journals, or the contact check interpolates across the hole.

Result: the per-arm deposit and trace journals (ambots.checkpoint), the
executed motion as the recorder received it, the recorder's report, the
hub's last progress JSON (fault and retry counts), the number of kills."""
import json
import os
import random
import signal
import subprocess
import sys
import time

import numpy as np

from ambots.checkpoint import StateStore

_WATCH = r"""
import json, sys, time, rospy
from std_msgs.msg import String
from ambots.config import default_cell_path, load_cell
from ambots.ros.capture import PrintRecorder, _latest_copy
import numpy as np


class Forgetful(PrintRecorder):
    # forgets every trace and bead row a firmware published before it was
    # killed, as if all of it had died in its publisher's queue: the
    # respawned firmware (its rows numbered from 1 again) must publish the
    # run so far again, or the check would interpolate across the hole
    forgotten = 0

    def _restarted(self, store, name):
        store[name] = []
        self.forgotten += 1


rospy.init_node("fault_watch", anonymous=True)
cell = load_cell(default_cell_path())
rec = Forgetful(cell)
hub = {}
def on_progress(msg):
    hub["last"] = json.loads(msg.data)
rospy.Subscriber("/ambots/progress", String, on_progress, queue_size=10)
print("ready", flush=True)
deadline = time.monotonic() + float(sys.argv[2])
while time.monotonic() < deadline and not rospy.is_shutdown():
    finished, failed = rec.done()
    if finished or failed:
        break
    time.sleep(0.1)
time.sleep(1.5)                       # the last traces and progress
report = rec.write(sys.argv[1])
report["hub_progress"] = hub.get("last")
report["forgotten_streams"] = rec.forgotten
with rec._lock:
    np.savez(sys.argv[1] + "/traces.npz", **{n: _latest_copy(np.concatenate(v)) for n, v in rec.traces.items() if v})
json.dump(report, open(sys.argv[1] + "/report.json", "w"), indent=1)
print("written", flush=True)
"""


def small_model(path):
    """A 160 x 40 x 1.2 mm block (6 layers): a real two-arm job in seconds."""
    import trimesh
    box = trimesh.creation.box(extents=(160.0, 40.0, 1.2))
    box.apply_translation((0.0, 0.0, 0.6))
    box.export(path)
    return path


def run_print(tmp, port, model, faults="", kill_after=None, slowdown="1.0", seed=0, timeout=600,
              kill_hub_after=None, replace_front_end_after=None, during=None, mode="concurrent",
              kill_when=None):
    """One print (see the module docstring).  ``kill_after``: wall seconds
    after the first motion at which the Kinova's firmware is killed with
    SIGKILL (None: no kill); ``kill_when``: instead, the first time its
    checkpoint shows this state (e.g. "PAUSED": waiting for its next turn
    in sequential mode); ``kill_hub_after``: the same for the hub;
    ``replace_front_end_after``: the front end is killed then, and a new
    one (``--follow``) follows the job to its end.  ``during(env, state)``:
    called once the Kinova has laid its first bead (``env``: the
    environment of this ROS master; ``state``: the nodes' state directory);
    what it returns is the result's ``"during"``.  ``mode``: the front
    end's --mode."""
    tmp = str(tmp)
    os.makedirs(tmp, exist_ok=True)
    env = dict(os.environ, ROS_MASTER_URI="http://localhost:%d" % port, ROS_HOME=os.path.join(tmp, "ros_home"))
    state = os.path.join(tmp, "state")
    out = os.path.join(tmp, "out")
    os.makedirs(out, exist_ok=True)
    logs = {n: open(os.path.join(tmp, n + ".log"), "w") for n in ("launch", "watch", "front_end")}
    launch = start_cell(port, env, logs["launch"], "faults:=%s" % faults, "state_dir:=%s" % state,
                        "slowdown:=%s" % slowdown, "retry_timeout:=0.05")
    kills = 0
    try:
        watch = subprocess.Popen([sys.executable, "-c", _WATCH, out, str(timeout)], stdout=subprocess.PIPE,
                                 stderr=logs["watch"], text=True, env=env)
        for line in watch.stdout:
            if line.strip() == "ready":
                break
        import rospkg
        node = os.path.join(rospkg.RosPack().get_path("ambots"), "nodes", "front_end")
        fe = subprocess.Popen([sys.executable, node, "--print", "--model", model, "--out",
                               os.path.join(tmp, "job"), "--timeout", str(timeout), "--arms", "kinova,ur10",
                               "--mode", mode], stdout=logs["front_end"], stderr=subprocess.STDOUT, env=env)
        if kill_when is not None and _wait_for_state(state, fe, "kinova", kill_when):
            pid = node_processes("firmware").get("kinova")
            if pid is not None:
                os.kill(pid, signal.SIGKILL)
                kills += 1
        events = sorted((t, what) for t, what in ((kill_after, "kinova"), (kill_hub_after, "hub"),
                                                  (replace_front_end_after, "front_end")) if t is not None)
        during_result = None
        if during is not None:
            _wait_for_beads(state, fe)
            during_result = during(env, state)
        if events:
            _wait_for_beads(state, fe)
            t0 = time.monotonic()
            for t, what in events:
                time.sleep(max(0.0, t0 + t - time.monotonic()))
                if fe.poll() is not None:
                    break
                if what == "front_end":
                    fe.kill()
                    fe.wait()
                    logs["front_end"].write("\n--- killed (SIGKILL); a new front end follows the job ---\n")
                    logs["front_end"].flush()
                    fe = subprocess.Popen([sys.executable, node, "--follow", os.path.join(tmp, "job"), "--timeout",
                                           str(timeout)], stdout=logs["front_end"], stderr=subprocess.STDOUT, env=env)
                    kills += 1
                else:
                    pid = node_processes("firmware" if what != "hub" else "communication_hub").get(what)
                    if pid is not None:
                        os.kill(pid, signal.SIGKILL)
                        kills += 1
        rc = fe.wait(timeout + 60)
        watch.wait(120)
    finally:
        stop_cell(launch)
        for f in logs.values():
            f.close()
    report_path = os.path.join(out, "report.json")
    report = json.load(open(report_path)) if os.path.exists(report_path) else None
    journals, knots = {}, {}
    for arm in ("kinova", "ur10"):
        store = StateStore(state, arm, dof=_dof(arm))
        cp = store.load()
        journals[arm] = store.read_journal(cp["records"] if cp else None)
        knots[arm] = store.read_trace(cp["trace_records"] if cp else None)
    traces_path = os.path.join(out, "traces.npz")
    recorded = dict(np.load(traces_path)) if os.path.exists(traces_path) else {}
    return {"front_end_rc": rc, "report": report, "journals": journals, "kills": kills, "tmp": tmp,
            "during": during_result, "knots": knots, "recorded_knots": recorded}


def _dof(arm):
    from ambots.config import default_cell_path, load_cell
    return len(next(a for a in load_cell(default_cell_path()).arms if a.name == arm).profile.joint_names)


def start_cell(port, env, log, *args):
    """``roslaunch -p port ambots both_arms.launch speed:=max args...`` in its
    own process group (its own master on ``port``), output to ``log``.
    A master already on ``port`` (someone else's roscore) would be joined
    silently and its nodes would clash with ours: refused."""
    import socket
    with socket.socket() as sock:
        if sock.connect_ex(("localhost", port)) == 0:
            raise AssertionError("port %d is taken (another ROS master?): the test needs its own" % port)
    return subprocess.Popen(["roslaunch", "-p", str(port), "ambots", "both_arms.launch", "speed:=max", *args],
                            stdout=log, stderr=subprocess.STDOUT, env=env, start_new_session=True)


def stop_cell(launch):
    """SIGINT the launch's process group (SIGKILL if it is not gone in 30 s)."""
    os.killpg(launch.pid, signal.SIGINT)
    try:
        launch.wait(30)
    except subprocess.TimeoutExpired:
        os.killpg(launch.pid, signal.SIGKILL)


def _command_lines():
    """(pid, argv as a list of bytes) of every process on this machine."""
    for pid in os.listdir("/proc"):
        try:
            yield int(pid), open("/proc/%s/cmdline" % pid, "rb").read().split(b"\0")
        except (OSError, ValueError):
            continue


def node_processes(name):
    """{arm name (or "hub"): pid} of the running ``firmware`` or
    ``communication_hub`` nodes on this machine (by their roslaunch command
    line: ``__name:=<name>``, log ``[<arm>-]<name>-N.log``)."""
    if name == "firmware":
        return firmware_processes()
    return {"hub" if name == "communication_hub" else name: pid for pid, cmd in _command_lines()
            if ("__name:=%s" % name).encode() in cmd}


def firmware_processes():
    """{arm name: pid} of the firmware nodes running on this machine (by
    their roslaunch command line: ``__name:=firmware``, log ``<arm>-firmware-N.log``)."""
    out = {}
    for pid, cmd in _command_lines():
        logs = [c.decode() for c in cmd if c.startswith(b"__log:=")]
        if b"__name:=firmware" in cmd and logs and "-firmware" in logs[0]:
            out[os.path.basename(logs[0]).split("-firmware")[0]] = pid
    return out


def cpu_seconds(pid):
    """User + system CPU time (s) of process ``pid`` so far."""
    stat = open("/proc/%d/stat" % pid).read().rsplit(")", 1)[1].split()
    return (int(stat[11]) + int(stat[12])) / os.sysconf("SC_CLK_TCK")


def _wait_for_beads(state, fe, arm="kinova"):
    """Wait until the arm's deposit journal has beads (the print is under way)."""
    journal = os.path.join(state, "%s.beads" % arm)
    t_end = time.monotonic() + 300
    while time.monotonic() < t_end and fe.poll() is None:
        if os.path.exists(journal) and os.path.getsize(journal) > 0:
            break
        time.sleep(0.05)


def unused_port():
    """A TCP port nobody listens on right now (the kernel's choice), for a
    master of our own (a fixed port may be another run's)."""
    import socket
    with socket.socket() as sock:
        sock.bind(("localhost", 0))
        return sock.getsockname()[1]


def _wait_for_state(state, fe, arm, name, timeout=300.0):
    """Wait until the arm's checkpoint (written at every change of state)
    shows state ``name``; False if the front end ended or time ran out."""
    store = StateStore(state, arm)
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end and fe.poll() is None:
        cp = store.load() if os.path.exists(store.checkpoint_file) else None
        if cp and cp.get("runner", {}).get("state") == name:
            return True
        time.sleep(0.01)
    return False


def sequential_model(path):
    """A 60 x 20 x 5 mm block: in sequential mode two turns per arm (its
    5 mm are more than a print head passes over in one)."""
    import trimesh
    box = trimesh.creation.box(extents=(60.0, 20.0, 5.0))
    box.apply_translation((0.0, 0.0, 2.5))
    box.export(path)
    return path


def by_line(journal):
    """{line: (filament mm, bead length m)} of a deposit journal."""
    out = {}
    for rec in journal:
        line = int(rec[7])
        e, length = out.get(line, (0.0, 0.0))
        out[line] = (e + rec[6], length + float(np.linalg.norm(rec[3:6] - rec[0:3])))
    return out


def compare_lines(clean, other):
    """(missing lines, extra lines, largest filament difference mm, largest length difference m)."""
    a, b = by_line(clean), by_line(other)
    missing, extra = sorted(set(a) - set(b)), sorted(set(b) - set(a))
    common = set(a) & set(b)
    de = max([abs(a[k][0] - b[k][0]) for k in common] or [0.0])
    dl = max([abs(a[k][1] - b[k][1]) for k in common] or [0.0])
    return missing, extra, de, dl


def free_port(seed):
    return 11600 + random.Random(seed).randrange(0, 300)


def program_filament(path):
    """{line: filament mm} of the moving extrusions of a program file."""
    from ambots.gcode import Segment, parse_gcode_text
    out = {}
    for s in parse_gcode_text(open(path).read(), path):
        if type(s) is Segment and s.extrude and s.start != s.end:
            out[s.line] = out.get(s.line, 0.0) + s.e
    return out


def coverage(journal, program_path):
    """(lines of the program never printed, lines printed that lay no
    filament in the program, largest |filament printed - programmed| mm):
    each extrusion exactly once means ([], [], ~0)."""
    want = program_filament(program_path)
    got = {k: v[0] for k, v in by_line(journal).items()}
    missing = sorted(set(want) - set(got))
    extra = sorted(set(got) - set(want))
    diff = max([abs(got[k] - want[k]) for k in set(want) & set(got)] or [0.0])
    return missing, extra, diff
