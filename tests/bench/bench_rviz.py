"""RViz's frame rate with the whole demo deposit shown, under Xvfb, as the
capture runs it (goal: at least 10 frames per second).

The deposit: the demo model's beads as the firmware lays them (the offline
run of `python -m ambots plan`: the same runners, the same beads), turned
into markers by the firmware's own DepositMarkers, as the firmware sends
them once the print is done.  For comparison the same beads as the
LINE_LIST markers the firmware sent before, and as tubes with nothing left
out.  The scene: the cell (roslaunch cell.launch: both arms' models, the
bed) on a master of its own (port 11393), RViz with the cell's shipped
config (the overview of the capture; its Frame Rate setting caps RViz at
30 frames per second) and with the capture's close-up of the seam.

The measurement: Mesa's software renderer (llvmpipe, what RViz draws with
under Xvfb) counts the frames RViz presents when RViz runs with
GALLIUM_HUD=fps (GALLIUM_HUD_DUMP_DIR: one figure every 0.5 s, the HUD
itself not drawn); RViz keeps redrawing at its frame rate while the scene
is still, so the count is its drawing speed.  Measured over 15 s after the
markers have arrived and been drawn (the deposit's pixels are counted
against the scene without it, so an empty view cannot pass for a fast
one); also RViz's CPU time per frame (/proc, all its threads: the renderer
runs in them), which depends less on what else the machine is doing.  The
machine's load average is printed with it: on a shared 2-core machine the
frame rate falls with the load."""
import json
import os
import signal
import subprocess
import sys
import tempfile
import time

PORT = 11393
WINDOW_S = 15.0
SETTLE_S = 12.0


def demo_beads(path):
    """The demo's beads per arm (as the firmware lays them) -> ``path`` (npz)."""
    import numpy as np
    from ambots.config import default_cell_path, load_cell
    from ambots.job import run_job
    from ambots import data_path
    from ambots.sim import simulate
    cell = load_cell(default_cell_path())
    job = run_job(data_path("config", "models", "demo_block.stl"), cell, None, "builtin", "concurrent",
                  "straight", 1.0)
    result = simulate(job.programs, cell)
    out = {}
    for name, r in result.runners.items():
        beads = [b for b in r.beads if len(b.e_mm)]
        for k in ("p0", "p1", "e_mm", "line", "layer", "t"):
            out["%s:%s" % (name, k)] = np.concatenate([getattr(b, k) for b in beads])
    np.savez(path, **out)
    return {n: int(len(r.beads) and sum(len(b.e_mm) for b in r.beads)) for n, r in result.runners.items()}


def main():
    tmp = tempfile.mkdtemp(prefix="ambots-bench-rviz-")
    t = time.perf_counter()
    beads = demo_beads(os.path.join(tmp, "beads.npz"))
    print("demo beads (offline run, %.0f s): %s" % (time.perf_counter() - t,
                                                  ", ".join("%s %d" % kv for kv in beads.items())), flush=True)
    env = dict(os.environ, ROS_MASTER_URI="http://localhost:%d" % PORT, ROS_HOME=os.path.join(tmp, "ros"))
    with open(os.path.join(tmp, "cell.log"), "w") as log:
        cell = subprocess.Popen(["roslaunch", "-p", str(PORT), "ambots", "cell.launch"], env=env, stdout=log,
                                stderr=subprocess.STDOUT, start_new_session=True)
    try:
        _wait_for_cell(env)
        out = os.path.join(tmp, "result.json")
        subprocess.run([sys.executable, os.path.abspath(__file__), "child", tmp, out], env=env, check=True)
        with open(out) as f:
            rows = json.load(f)
    finally:
        os.killpg(cell.pid, signal.SIGINT)
        try:
            cell.wait(20)
        except subprocess.TimeoutExpired:
            os.killpg(cell.pid, signal.SIGKILL)
    print("%-9s %-34s %8s %9s %6s %6s %6s %9s %8s %6s" % (
        "view", "deposit", "markers", "triangles", "MB", "fps", "min", "ms CPU/f", "pixels", "load"))
    for r in rows:
        print("%-9s %-34s %8d %9d %6.2f %6.1f %6.1f %9.0f %8d %6.1f" % (
            r["view"], r["what"], r["markers"], r["triangles"], r["bytes"] / 1e6, r["fps"], r["fps_min"],
            r["cpu_ms_per_frame"], r["deposit_pixels"], r["load"]))
    best = [r for r in rows if r["view"] == "overview" and r["what"].startswith("tubes, buried left out")]
    if best:
        r = best[0]
        print("RViz under Xvfb, whole demo deposit as the firmware sends it, overview: %.1f frames per second "
              "(min %.1f; goal >= 10; capped at 30 by the config), %.0f ms of RViz CPU per frame, load %.1f"
              % (r["fps"], r["fps_min"], r["cpu_ms_per_frame"], r["load"]))
    print("(pictures and logs in %s)" % tmp)


def _wait_for_cell(env, timeout=60.0):
    """Until the master is up and every arm's robot description is set
    (RViz started before its master is up aborts)."""
    import rosgraph
    from ambots.config import default_cell_path, load_cell
    names = ["/%s/robot_description" % a.name for a in load_cell(default_cell_path()).arms]
    master = rosgraph.Master("/bench_rviz_wait", master_uri=env["ROS_MASTER_URI"])
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            if all(master.hasParam(n) for n in names):
                return
        except OSError:
            pass
        time.sleep(0.5)
    raise RuntimeError("the cell did not come up on port %d within %.0f s" % (PORT, timeout))


# ----------------------------------------------------------------- the child: a ROS node
def _deposits(cell, tmp):
    """[(name, MarkerArray)] of the scenes to measure."""
    import numpy as np
    from visualization_msgs.msg import Marker
    from ambots.ros.firmware import DepositMarkers
    from ambots.ros.markers import ArrayMarker, ArrayMarkers
    from ambots.runner import Bead
    from ambots.slicer import SliceSettings
    data = dict(np.load(os.path.join(tmp, "beads.npz")))
    h = SliceSettings().layer_height_mm * 1e-3
    tubes_all, tubes, lines = ArrayMarkers(), ArrayMarkers(), ArrayMarkers()
    for arm in cell.arms:
        b = Bead(*(data["%s:%s" % (arm.name, k)] for k in ("p0", "p1", "e_mm", "line", "layer", "t")))
        dm = DepositMarkers(arm.name, cell.world_frame, arm.profile.colour, h, floor_z=float(cell.bed.pose[2, 3]))
        dm.add(b)
        tubes_all.markers += dm.all().markers
        dm.update_exposure(force=True)
        tubes.markers += dm.all().markers
        # the LINE_LIST markers of before: one per layer, 2000 beads at most, 0.45 mm wide
        for layer in np.unique(b.layer):
            idx = np.nonzero(b.layer == layer)[0]
            for k in range(0, len(idx), 2000):
                sel = idx[k:k + 2000]
                m = ArrayMarker(xyz=np.stack([b.p0[sel], b.p1[sel]], axis=1).reshape(-1, 3))
                m.header.frame_id, m.ns, m.id = cell.world_frame, arm.name + "_lines", len(lines.markers)
                m.type, m.action, m.pose.orientation.w, m.scale.x = Marker.LINE_LIST, Marker.ADD, 1.0, 0.45e-3
                m.color.r, m.color.g, m.color.b, m.color.a = (float(c) for c in arm.profile.colour)
                lines.markers.append(m)
    return [("none (the arms alone)", ArrayMarkers()), ("LINE_LIST, before", lines),
            ("tubes, all drawn", tubes_all), ("tubes, buried left out (sent)", tubes)], data


def _size(arr):
    from io import BytesIO
    b = BytesIO()
    arr.serialize(b)
    return len(b.getvalue())


def _cpu_s(pid):
    with open("/proc/%d/stat" % pid) as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _measure(config, deposit, pub, tmp, tag, baseline=None):
    import numpy as np
    import rospy
    from visualization_msgs.msg import Marker
    from ambots.ros.capture import HeadlessRviz
    from ambots.ros.markers import ArrayMarkers
    clear = Marker(action=Marker.DELETEALL)
    pub.publish(ArrayMarkers(markers=[clear] + list(deposit.markers)))      # latched: RViz gets it on start
    hud = os.path.join(tmp, "hud-" + tag)
    os.makedirs(hud, exist_ok=True)
    env = {"GALLIUM_HUD": "fps", "GALLIUM_HUD_DUMP_DIR": hud, "GALLIUM_HUD_VISIBLE": "false"}
    with HeadlessRviz(config, node_name="bench_rviz_" + tag, env=env, log=os.path.join(tmp, tag + ".log")) as rviz:
        rviz.wait_ready(settle=SETTLE_S)
        fps_file = os.path.join(hud, "fps")
        n0 = len(open(fps_file).read().split())
        c0, t0 = _cpu_s(rviz.rviz.pid), time.monotonic()
        rospy.sleep(WINDOW_S)
        c1, t1 = _cpu_s(rviz.rviz.pid), time.monotonic()
        fps = np.array([float(v) for v in open(fps_file).read().split()[n0:]])
        load = os.getloadavg()[0]
        rviz.grab(os.path.join(tmp, tag + ".png"))
        img = np.asarray(rviz.screen().convert("RGB")).astype(int)
    frames = fps.mean() * (t1 - t0) if len(fps) else 0.0
    changed = 0 if baseline is None else int((np.abs(img - baseline).sum(axis=2) > 30).sum())
    return img, {"fps": float(fps.mean()) if len(fps) else 0.0, "fps_min": float(fps.min()) if len(fps) else 0.0,
                 "cpu_ms_per_frame": 1000.0 * (c1 - c0) / frames if frames else float("nan"),
                 "deposit_pixels": changed, "load": load}


def child(tmp, out):
    import rospy
    from visualization_msgs.msg import MarkerArray
    from ambots.config import default_cell_path, load_cell
    from ambots.ros.cell import CellPublisher
    from ambots.rviz import DEPOSIT_TOPIC, closeup_view, rviz_config
    rospy.init_node("bench_rviz")
    cell = load_cell(default_cell_path())
    scenes, data = _deposits(cell, tmp)
    pub = rospy.Publisher(DEPOSIT_TOPIC, MarkerArray, queue_size=1, latch=True)
    overview = CellPublisher(cell).rviz_config_path()
    from ambots.slicer import SliceSettings
    view = closeup_view({a.name: data["%s:p1" % a.name] for a in cell.arms}, SliceSettings().layer_height_mm * 1e-3)
    closeup = os.path.join(tmp, "closeup.rviz")
    with open(closeup, "w") as f:
        f.write(rviz_config(cell, view))
    rows = []
    plan = [("overview", overview, scenes), ("close-up", closeup, [scenes[0], scenes[-1]])]
    for view_name, config, todo in plan:
        baseline = None
        for i, (what, deposit) in enumerate(todo):
            tag = "%s_%d" % (view_name.replace("-", ""), i)
            img, r = _measure(config, deposit, pub, tmp, tag, baseline)
            if baseline is None:
                baseline = img
            elif r["deposit_pixels"] < 200:
                raise AssertionError("%s, %s: the deposit is not drawn (%d pixels differ from the arms alone)"
                                     % (view_name, what, r["deposit_pixels"]))
            drawn = [m for m in deposit.markers if m.action == m.ADD]
            r.update(view=view_name, what=what, markers=len(drawn), bytes=_size(deposit),
                     triangles=sum(len(m.xyz) // 3 for m in drawn if m.type == m.TRIANGLE_LIST)
                     + sum(len(m.xyz) // 2 * 2 for m in drawn if m.type == m.LINE_LIST))
            rows.append(r)
            print("  %s, %s: %.1f fps" % (view_name, what, r["fps"]), flush=True)
    with open(out, "w") as f:
        json.dump(rows, f)


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "child":
        child(sys.argv[2], sys.argv[3])
    else:
        main()
