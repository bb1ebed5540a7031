"""Headless capture: RViz on a virtual X screen (Xvfb), screenshot to PNG."""
import os
import subprocess
import time

import rospy
import rosnode


def rviz_executable():
    """RViz's own executable, found as roslaunch finds a node's (Debian:
    /usr/lib/rviz/rviz; Noetic: /opt/ros/noetic/lib/rviz/rviz), with no shell
    helper such as rosrun in between."""
    from roslib.packages import find_node
    for path in find_node("rviz", "rviz"):
        if os.path.isfile(path) and os.access(path, os.X_OK):
            return path
    raise RuntimeError("rviz is not installed: `make setup` installs the Debian package rviz "
                       "(on Noetic: ros-noetic-rviz)")


class HeadlessRviz:
    """Starts Xvfb (a free display number) and RViz with ``config``; use as a
    context manager.  :meth:`grab` saves a PNG of RViz's 3D view.  ``env``:
    more environment variables for RViz (e.g. Mesa's ``GALLIUM_HUD``);
    ``log``: a file for what RViz prints (default: nowhere)."""

    def __init__(self, config, size=(1280, 800), node_name="capture_rviz", env=None, log=None):
        self.config, self.size, self.node_name, self.extra_env = config, size, node_name, dict(env or {})
        self.log = log
        self.xvfb = self.rviz = None
        self.display = None
        self.box = None           #: the 3D view's box on the screen (left, top, right, bottom), by grab()

    def __enter__(self):
        r, w = os.pipe()
        self.xvfb = subprocess.Popen(["Xvfb", "-displayfd", str(w), "-screen", "0",
                                      "%dx%dx24" % self.size, "-nolisten", "tcp"],
                                     pass_fds=(w,), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        os.close(w)
        with os.fdopen(r) as f:
            self.display = ":" + f.readline().strip()
        env = dict(os.environ, DISPLAY=self.display, **self.extra_env)
        out = open(self.log, "a") if self.log else subprocess.DEVNULL
        try:
            self.rviz = subprocess.Popen([rviz_executable(), "-d", self.config, "__name:=" + self.node_name],
                                         env=env, stdout=out, stderr=subprocess.STDOUT if self.log else out)
        finally:
            if self.log:
                out.close()
        return self

    def wait_ready(self, timeout=60.0, settle=4.0):
        """Wait until RViz is registered with the master, then ``settle`` s."""
        deadline = time.time() + timeout
        name = "/" + self.node_name
        while time.time() < deadline and not rospy.is_shutdown():
            if self.rviz.poll() is not None:
                raise RuntimeError("rviz exited with code %d" % self.rviz.returncode)
            if name in rosnode.get_node_names():
                time.sleep(settle)
                return
            time.sleep(0.5)
        raise RuntimeError("rviz did not come up within %.0f s" % timeout)

    def wait_still(self, box=None, period=1.0, timeout=40.0):
        """Until two pictures of ``box`` (the 3D view: RViz's status bar
        shows its changing frame rate) ``period`` s apart are the same (a
        still scene fully drawn), at most ``timeout`` s; returns whether it
        got there."""
        def picture():
            img = self.screen()
            return (img.crop(box) if box else img).tobytes()
        deadline = time.time() + timeout
        last = picture()
        while time.time() < deadline and not rospy.is_shutdown():
            time.sleep(period)
            now = picture()
            if now == last:
                return True
            last = now
        return False

    def screen(self):
        """The whole virtual screen (PIL image)."""
        from PIL import ImageGrab
        return ImageGrab.grab(xdisplay=self.display)

    def grab(self, path, background=(48, 48, 48), box=None):
        """Save a PNG of the 3D view: ``box`` (left, top, right, bottom), or
        the area of RViz's background colour (kept in :attr:`box`)."""
        import numpy as np
        img = self.screen()
        if box is None:
            a = np.asarray(img.convert("RGB"))
            bg = np.all(a == background, axis=2)
            rows, cols = np.where(bg.mean(axis=1) > 0.2)[0], np.where(bg.mean(axis=0) > 0.2)[0]
            if len(rows) and len(cols):
                box = (int(cols[0]), int(rows[0]), int(cols[-1]) + 1, int(rows[-1]) + 1)
        if box is not None:
            img = img.crop(box)
        self.box = box
        os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
        img.save(path)
        return path

    def __exit__(self, *exc):
        for p in (self.rviz, self.xvfb):
            if p and p.poll() is None:
                p.terminate()
                try:
                    p.wait(10)
                except subprocess.TimeoutExpired:
                    p.kill()


def _latest_copy(rows, col=0):
    """Rows (K, m) in time order (column ``col``) as published; a restarted
    firmware repeats what it had not checkpointed: of rows not earlier than
    a later one, keep the later copy."""
    import numpy as np
    t = rows[:, col]
    keep = np.ones(len(t), dtype=bool)
    keep[:-1] = t[:-1] < np.minimum.accumulate(t[::-1])[::-1][1:]
    return rows[keep]


class PrintRecorder:
    """Watches a live print: the beads every firmware laid (``~beads`` rows:
    the bead mesh, and the part's box for the arm-part check), every arm's
    joint states (arm-arm clearance with the capsule model, for pairs
    of states stamped with the same instant of the one clock), the firmware
    stats and the hub's progress.  :meth:`done`
    says when every arm of the job is DONE (or one is in ERROR);
    :meth:`write` writes the deposit mesh and ``report.json``."""

    def __init__(self, cell, job_dir=None):
        import json
        import threading
        from sensor_msgs.msg import JointState
        from std_msgs.msg import Float64MultiArray, String

        from ambots import topics
        from ambots.collision import ArmBody
        self.cell = cell
        #: where the front end writes the job (job.json: which arms have work, the plan chosen)
        self.job_dir = job_dir
        self._json = json
        self._lock = threading.RLock()
        self.stats = {}                        #: arm -> firmware stats dict
        self.progress = {}
        self.q = {}
        self.bodies = {a.name: ArmBody.from_arm(a) for a in cell.arms}
        self.min_clearance = float("inf")
        self.contacts = 0
        self.bed_contacts = self.part_contacts = 0
        self.part_lo = self.part_hi = None       #: box around every bead seen so far (m)
        self.checks = 0
        self._states = {}          #: arm -> {stamp ns: joints}, the latest states as they arrived
        self.started = time.time()
        self.traces = {}          #: arm -> [(K, 1 + 2n) rows of (ROS time, joints, joint speeds)] as executed
        self.bead_times = {}      #: arm -> [(K, 8) rows of (p0, p1, ROS time, e_mm)]
        self._row_seq = {}
        self.trace_gaps = 0       #: trace/bead chunks never received (numbered by the firmware)
        rospy.Subscriber(topics.PROGRESS_TOPIC, String, self._on_progress, queue_size=10)
        for arm in cell.arms:
            rospy.Subscriber(topics.joint_states_topic(arm.name), JointState, self._on_joints,
                             callback_args=arm, queue_size=10)
            rospy.Subscriber("/%s/firmware/stats" % arm.name, String, self._on_stats,
                             callback_args=arm.name, queue_size=10)
            rospy.Subscriber("/%s/firmware/trace" % arm.name, Float64MultiArray, self._on_rows,
                             callback_args=(self.traces, arm.name), queue_size=None)
            rospy.Subscriber("/%s/firmware/beads" % arm.name, Float64MultiArray, self._on_rows,
                             callback_args=(self.bead_times, arm.name), queue_size=None)

    def _on_rows(self, msg, where):
        from ambots.ros.firmware import rows_of
        store, name = where
        rows = rows_of(msg)
        with self._lock:
            key = (id(store), name)
            last = self._row_seq.get(key)
            seq = msg.layout.data_offset
            if last is not None and seq <= last:       # a respawned firmware numbers from 1 again
                last = 0
                self._restarted(store, name)
            if last is not None and seq > last + 1:
                self.trace_gaps += seq - last - 1      # chunks lost: the check would interpolate across
            self._row_seq[key] = seq
            store.setdefault(name, []).append(rows)
            if store is self.bead_times and len(rows):       # the nozzle path's box (p0, p1)
                import numpy as np
                P = rows[:, 0:6].reshape(-1, 3)
                lo, hi = P.min(axis=0), P.max(axis=0)
                self.part_lo = lo if self.part_lo is None else np.minimum(self.part_lo, lo)
                self.part_hi = hi if self.part_hi is None else np.maximum(self.part_hi, hi)

    def _restarted(self, store, name):
        """Firmware ``name`` was respawned: its rows in ``store`` are numbered
        from 1 again (it publishes its run so far again first)."""

    def check_executed(self):
        """Arm-arm, arm-bed and arm-part contacts of the executed motion in
        simulated time (:func:`ambots.sim.check_traces` on the firmware
        traces), or None without traces.  At speed max the arms' clocks are
        not the wall clock, so the joint states as they arrive pair poses of
        different moments; the traces do not."""
        import numpy as np
        from types import SimpleNamespace
        from ambots.sim import check_traces
        with self._lock:
            traces = {n: np.concatenate(v) for n, v in self.traces.items() if v}
            beads = {n: np.concatenate(v) for n, v in self.bead_times.items() if v}
        if not traces:
            return None
        out = {}
        for n, rows in traces.items():
            rows = _latest_copy(rows)
            dof = (rows.shape[1] - 1) // 2                 # rows (t, q..., v...): Hermite knots
            out[n] = (rows[:, 0], rows[:, 1:1 + dof], rows[:, 1 + dof:])
        arms = {a.name: a for a in self.cell.arms if a.name in out}
        bead_list = [SimpleNamespace(p0=b[:, 0:3], p1=b[:, 3:6], t=b[:, 6]) for b in beads.values()]
        return check_traces(out, arms, self.cell, beads=bead_list)

    def _on_progress(self, msg):
        with self._lock:
            self.progress = self._json.loads(msg.data).get("arms", {})

    def _on_stats(self, msg, name):
        data = self._json.loads(msg.data)
        flat = dict(data.get("stats", {}))          # the runner's RunStats, plus the node's state
        flat["state"] = data.get("state")
        with self._lock:
            self.stats[name] = flat

    def _on_joints(self, msg, arm):
        """The joint states as they arrive, checked in the one clock: each arm
        against the bed and the part, and two arms whenever both have published
        a state stamped with the same instant (never poses of two moments)."""
        import numpy as np
        from ambots.collision import bed_clearance, clearance_between, part_clearance
        names = [arm.prefix + j for j in arm.profile.joint_names]
        try:
            q = np.array([msg.position[list(msg.name).index(n)] for n in names])
        except ValueError:
            return
        stamp = msg.header.stamp.to_nsec()
        with self._lock:
            self.q[arm.name] = q
            seen = self._states.setdefault(arm.name, {})
            seen[stamp] = q
            if len(seen) > 400:
                del seen[min(seen)]
            self.bed_contacts += float(bed_clearance(self.bodies[arm.name], q[None], self.cell)[0]) < 0.0
            if self.part_lo is not None:
                lo = np.array([self.part_lo[0], self.part_lo[1], self.cell.bed.pose[2, 3]])
                self.part_contacts += float(part_clearance(self.bodies[arm.name], q[None], lo,
                                                           self.part_hi)[0]) < 0.0
            for other, states in self._states.items():
                if other == arm.name or stamp not in states:
                    continue
                c = float(clearance_between(self.bodies[arm.name], q[None], self.bodies[other],
                                            states[stamp][None])[0])
                self.checks += 1
                self.min_clearance = min(self.min_clearance, c)
                self.contacts += c < 0.0

    def job(self):
        """This run's job.json (written by the front end after this recorder
        started), or None."""
        import os
        path = os.path.join(self.job_dir, "job.json") if self.job_dir else None
        if not path or not os.path.exists(path) or os.path.getmtime(path) < self.started - 1.0:
            return None
        try:
            with open(path) as f:
                return self._json.load(f)
        except (OSError, ValueError):
            return None

    def timeout_s(self, speed):
        """The wall s this run's job may take by default
        (:func:`ambots.frontend.print_timeout_s` of job.json's makespan
        estimate, else its longest arm's print time, at the clock's pace
        ``speed``), or None before job.json is written."""
        from ambots.frontend import print_timeout_s
        job = self.job()
        if job is None:
            return None
        estimate = (job.get("plan") or {}).get("makespan_estimate_s")
        if not estimate:
            estimate = max((a.get("print_time_s", 0.0) for a in (job.get("arms") or {}).values()), default=0.0)
        return print_timeout_s(estimate, speed)

    def done(self, arms=None):
        """(finished, failed): every arm of ``arms`` (default: the arms with
        a program in this run's job.json -- the planner may give the whole
        model to one arm -- else the cell's) is DONE / some arm is in ERROR."""
        job = self.job() if arms is None else None
        names = arms or (list(job["arms"]) if job and job.get("arms") else [a.name for a in self.cell.arms])
        with self._lock:
            states = [self.progress.get(n, {}).get("state") for n in names]
        return all(s == "DONE" for s in states), any(s == "ERROR" for s in states)

    def closeup_view(self):
        """RViz view settings close to the seam of the part printed so far
        (:func:`ambots.rviz.closeup_view` on every arm's bead ends), or None."""
        import numpy as np
        from ambots.rviz import closeup_view
        from ambots.slicer import SliceSettings
        with self._lock:
            paths = {n: np.concatenate(v)[:, 3:6] for n, v in self.bead_times.items() if v}
        return closeup_view(paths, SliceSettings().layer_height_mm * 1e-3)

    def deposit(self):
        """The beads the firmware nodes published (``~beads`` rows), as a
        :class:`~ambots.deposit.Deposit` built as ``plan`` builds it
        (:func:`ambots.deposit.deposit_of_beads`); beads a restarted firmware
        published twice are counted once."""
        import numpy as np
        from ambots.deposit import deposit_of_beads
        from ambots.slicer import SliceSettings
        with self._lock:
            rows = {n: _latest_copy(np.concatenate(v), col=6) for n, v in self.bead_times.items() if v}
        return deposit_of_beads({n: (r[:, 0:3], r[:, 3:6], r[:, 7]) for n, r in rows.items()},
                                SliceSettings().layer_height_mm * 1e-3)

    def seam_figures(self, job, dep):
        """The seam figures of the deposit ``dep`` as ``plan`` reports them
        (:func:`ambots.seams.seam_figures`, by ``job.json``'s ``seams``, on
        the parts in the job folder; the lap order by the beads' times on
        the one clock): {} for a one-arm job or without a job folder."""
        setup = (job or {}).get("seams")
        if not setup or not self.job_dir:
            return {}
        import numpy as np

        from ambots.seams import beads_in_bed_mm, placed_model, seam_figures
        try:
            model = placed_model(self.job_dir, sorted({n for k in setup["planes"] for n in k.split("/")}))
            with self._lock:
                rows = {n: _latest_copy(np.concatenate(v), col=6) for n, v in self.bead_times.items() if v}
            by_arm = beads_in_bed_mm({n: (r[:, 0:3], r[:, 3:6], r[:, 6]) for n, r in rows.items()},
                                     self.cell.bed.pose)
            shares, order = seam_figures(setup, model, dep, self.cell.bed.pose, by_arm)
        except Exception as exc:           # the report is still written without them
            rospy.logwarn("seam figures of %s: %s", self.job_dir, exc)
            return {}
        return {"seam": setup["seam"], "seam_bonded_share": shares, "seam_lap_order": order}

    def write(self, out_dir, model=None, mode=None, slicer=None, model_volume_mm3=None):
        """Write ``deposit.ply`` and ``report.json`` into ``out_dir``; returns the report."""
        import os
        os.makedirs(out_dir, exist_ok=True)
        if model_volume_mm3 is None and model:
            try:
                from ambots.mesh import load_model
                model_volume_mm3 = round(float(load_model(model).volume), 1)
            except Exception as exc:          # the report is still written without it
                rospy.logwarn("model volume of %s: %s", model, exc)
        dep = self.deposit()
        colours = {a.name: a.profile.colour for a in self.cell.arms}
        if len(dep):
            dep.export(os.path.join(out_dir, "deposit.ply"), colours=colours, scale=1000.0)
        from ambots.report import arm_entry, build, makespan_s
        executed = self.check_executed()
        with self._lock:
            arms = {}
            for a in self.cell.arms:
                s = self.stats.get(a.name, {})
                p = self.progress.get(a.name, {})
                arms[a.name] = arm_entry(a.id, s.get("state", p.get("state")), s,
                                         len(dep.segments(a.name).starts) if a.name in dep.arms else 0,
                                         error=p.get("error"))
            live = {"arm_arm": int(self.contacts), "arm_bed": int(self.bed_contacts),
                    "arm_part": int(self.part_contacts)}
            live_min = round(self.min_clearance * 1000.0, 2) if self.checks else None
            extra = {"live_collisions": live, "live_min_clearance_mm": live_min,
                     "live_collision_checks": self.checks, "trace_gaps": self.trace_gaps}
            if executed is None:
                extra["note"] = "no firmware traces were received: contacts were not checked"
            else:
                extra["note"] = ("contacts: the executed trajectories the firmware nodes published, checked "
                                 "continuously (ambots.contact: clearance_bound_mm holds over the whole time "
                                 "line; near a contact or the closest approach no point moves more than "
                                 "check_resolution_mm between samples); trace_gaps: chunks not received, must "
                                 "be 0; live_*: the joint states as they arrived")
            job = self.job()
            if job and job.get("plan"):
                extra["plan"] = job["plan"]
            extra.update(self.seam_figures(job, dep))
            report = build({"model": model, "cell": self.cell.name, "mode": mode, "slicer": slicer},
                           self.done()[0], arms, makespan_s(self.stats), executed,
                           dep.volume_mm3() if len(dep) else 0.0, model_volume_mm3,
                           time.time() - self.started, deposit_mesh="deposit.ply", **extra)
        import json
        with open(os.path.join(out_dir, "report.json"), "w") as f:
            json.dump(report, f, indent=2)
        return report


