"""Shared by the rostest nodes firmware_test and both_arms_test (imported from
their folder): a front end on the real transport (ambots.ros.front_end.RosLink,
so the node must run as /front_end), recorders of the firmware's topics, and
G-code for small test programs."""
import json
import threading
import time

import numpy as np
import rosgraph
import rospy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, String
from visualization_msgs.msg import MarkerArray

from ambots import topics
from ambots.protocol import ArmState, ErrorReport, Status
from ambots.rviz import DEPOSIT_TOPIC

TIMEOUT = 20.0       # s; generous for a loaded 2-core machine


def wait_until(condition, what, timeout=TIMEOUT, period=0.02):
    """Poll ``condition`` until it returns something true; fail naming ``what``."""
    deadline = time.monotonic() + timeout      # wall time: a simulated clock may run fast or stand still
    while not rospy.is_shutdown():
        result = condition()
        if result:
            return result
        if time.monotonic() > deadline:
            break
        time.sleep(period)
    raise AssertionError("timed out after %.0f s waiting for %s" % (timeout, what))


def square_gcode(x0, y0, side, z=0.2, layers=1, feed=1200):
    """A ``side`` mm square (bed frame, mm) from (x0, y0), ``layers`` layers
    0.2 mm apart, in the canonical style (absolute XYZ, relative E).
    Returns (text, corners (5, 2) of the first layer)."""
    lines = ["; test square", "G21", "G90", "M83"]
    corners = [(x0, y0), (x0 + side, y0), (x0 + side, y0 + side), (x0, y0 + side), (x0, y0)]
    for k in range(layers):
        zz = z + 0.2 * k
        lines += [";LAYER_CHANGE", ";Z:%.1f" % zz, "G0 X%.3f Y%.3f Z%.3f F6000" % (x0, y0, zz)]
        for x, y in corners[1:]:
            lines.append("G1 X%.3f Y%.3f E%.5f F%d" % (x, y, side * 0.033, feed))
    return "\n".join(lines) + "\n", np.array(corners, dtype=float)


def point_segment_distance(P, A, B):
    """Distances (N,) of points P (N, 3) to the nearest of segments A[i]-B[i] (M, 3)."""
    d = B - A
    L2 = np.maximum(np.einsum("ij,ij->i", d, d), 1e-30)
    u = np.clip(np.einsum("nij,ij->ni", P[:, None, :] - A[None], d) / L2, 0, 1)
    X = A[None] + u[..., None] * d[None]
    return np.linalg.norm(P[:, None, :] - X, axis=2).min(axis=1)


class FrontEnd:
    """The front end (node id 1000) on its real transport: sends numbered
    commands through the hub, acknowledges and records what the hub forwards."""

    def __init__(self):
        from ambots.ros.front_end import RosLink
        self.link = RosLink()
        self._lock = threading.Lock()
        self._got = []

    def send(self, message):
        return self.link.send(message)

    def messages(self):
        with self._lock:
            self._got += [m for m in self.link.poll() if isinstance(m, (Status, ErrorReport))]
            return list(self._got)

    def mark(self):
        """Index to pass to :meth:`since` / :meth:`wait_status`."""
        return len(self.messages())

    def since(self, mark):
        return self.messages()[mark:]

    def wait_status(self, robot, state, mark=0, with_position=False, timeout=TIMEOUT):
        """The first A10 of ``robot`` in ``state`` received after ``mark``."""
        return wait_until(lambda: next((m for m in self.since(mark) if isinstance(m, Status) and
                                        m.robot == robot and m.state == state and
                                        (not with_position or m.position is not None)), None),
                          "A10 R%d %s" % (robot, ArmState(state).name), timeout)

    def wait_error(self, robot, mark=0, timeout=TIMEOUT):
        return wait_until(lambda: next((m for m in self.since(mark) if isinstance(m, ErrorReport) and
                                        m.robot == robot), None), "A11 R%d" % robot, timeout)


class Recorder:
    """What the firmware nodes publish: deposit markers (latest by (ns, id)),
    the beads laid (``~beads`` rows: p0, p1, time, filament), joint states
    per arm, stats per arm (latest JSON), the hub's error lines."""

    def __init__(self, cell):
        self.cell = cell
        self._lock = threading.Lock()
        self.markers = {}
        self.joints = {a.name: [] for a in cell.arms}
        self.stats = {a.name: None for a in cell.arms}
        self.beads = {a.name: [] for a in cell.arms}
        self.errors = []
        self.subs = [rospy.Subscriber(DEPOSIT_TOPIC, MarkerArray, self._on_markers, queue_size=100)]
        for arm in cell.arms:
            self.subs.append(rospy.Subscriber(topics.joint_states_topic(arm.name), JointState,
                                              self._on_joints, callback_args=arm, queue_size=100))
            self.subs.append(rospy.Subscriber(topics.arm_node(arm.name) + "/stats", String,
                                              self._on_stats, callback_args=arm.name, queue_size=10))
            self.subs.append(rospy.Subscriber(topics.arm_node(arm.name) + "/beads", Float64MultiArray,
                                              self._on_beads, callback_args=arm.name, queue_size=None))
        self.subs.append(rospy.Subscriber(topics.ERROR_TOPIC, String, self._on_error, queue_size=100))

    def _on_markers(self, msg):
        with self._lock:
            for m in msg.markers:
                self.markers[m.ns, m.id] = m

    def _on_joints(self, msg, arm):
        index = {n: i for i, n in enumerate(msg.name)}
        try:
            q = [msg.position[index[arm.prefix + j]] for j in arm.profile.joint_names]
        except KeyError:           # a controller's joint states on the same topic (driver's names)
            return
        with self._lock:
            self.joints[arm.name].append(np.array(q))

    def _on_beads(self, msg, name):
        from ambots.ros.firmware import rows_of
        rows = rows_of(msg)
        with self._lock:
            self.beads[name].extend(rows)

    def _on_stats(self, msg, name):
        with self._lock:
            self.stats[name] = json.loads(msg.data)

    def _on_error(self, msg):
        with self._lock:
            self.errors.append(msg.data)

    def marker_ids(self, ns):
        with self._lock:
            return sorted(i for n, i in self.markers if n == ns)

    def marker(self, ns, mid):
        with self._lock:
            return self.markers[ns, mid]

    def n_beads(self, name):
        with self._lock:
            return len(self.beads[name])

    def bead_path(self, name, start=0):
        """(p0 (K, 3), p1 (K, 3)) world m of the beads ``name`` laid, from the ``start``-th on."""
        with self._lock:
            rows = np.array(self.beads[name][start:], dtype=float).reshape(-1, 8)
        return rows[:, 0:3], rows[:, 3:6]

    def points(self, ns, ids):
        """(N, 3) points of markers ``ids`` of ``ns``, in id order (a
        TRIANGLE_LIST: three per triangle)."""
        with self._lock:
            pts = [[(p.x, p.y, p.z) for p in self.markers[ns, i].points] for i in sorted(ids)]
        return np.array([p for ps in pts for p in ps], dtype=float).reshape(-1, 3)

    def n_joint_states(self, name):
        with self._lock:
            return len(self.joints[name])

    def joint_states(self, name, start=0):
        with self._lock:
            return list(self.joints[name][start:])

    def last_joints(self, name):
        with self._lock:
            return self.joints[name][-1] if self.joints[name] else None

    def stat(self, name):
        with self._lock:
            return self.stats[name]


def wait_for_firmware(cell, timeout=60.0):
    """Until the hub and every arm's firmware are subscribed where they must be."""
    master = rosgraph.Master(rospy.get_name())

    def up():
        try:
            pubs, subs, _ = master.getSystemState()
        except Exception:          # noqa: BLE001 -- master busy
            return False
        subs, pubs = dict(subs), dict(pubs)
        return topics.HUB_NODE in subs.get(topics.HUB_TOPIC, []) and all(
            topics.arm_node(a.name) in subs.get(topics.arm_topic(a), []) and
            topics.arm_node(a.name) in pubs.get(topics.HUB_TOPIC, []) for a in cell.arms)
    wait_until(up, "the hub and the firmware of %s" % ", ".join(a.name for a in cell.arms), timeout, 0.1)


def bed_mm(cell, P):
    """World points (N, 3) m -> bed frame mm."""
    T = np.linalg.inv(cell.bed.pose)
    return (np.asarray(P) @ T[:3, :3].T + T[:3, 3]) * 1000.0


def nozzle_world(arm, q):
    """Forward kinematics of the arm's model at joint vector q: nozzle (3,) world, m."""
    from ambots.model import arm_kinematics
    kin = arm_kinematics(arm)
    T = arm.base_pose @ kin.fk_batch(np.asarray(q, dtype=float)[None])[0]
    return T[:3, 3]


def turns_gcode(rounds=4, wait_x=170.0, zone_x=20.0, y0=-30.0, dy=15.0, feed=600, ids=(1, 2)):
    """Two facing arms (ids[0] on the -x side of the bed, ids[1] on the +x
    side) that take turns in a shared zone across the seam (bed x = 0): in
    each round the first arm travels from its waiting point (x = -wait_x)
    into the zone, prints a line across it (x -zone_x .. +zone_x), travels
    back out to its next waiting point and reports (the A10 before its next
    ;@A9); the second arm waits for that report (;@A9 on the first arm's
    travel out), then does the same from its side (x = +wait_x), and the
    first arm waits for it in the next round.  With ``wait_x`` 170 and
    ``zone_x`` 20 the arm in the zone and the waiting arm are 150 mm apart
    across the seam: their real-size bodies at least 24.8 mm apart at the
    ends of the line (at 110 they overlap by 34.6 mm); without the barriers
    they meet in the zone.

    Returns ``({id: text}, barriers)``: every barrier as (waiting id,
    awaited id, the awaited line, the awaited arm's bed xy at the end of
    that line, the waiting arm's bed xy while it waits)."""
    a, b = ids
    head = ["G21", "G90", "M83", ";LAYER_CHANGE", ";Z:0.2"]
    prog = {a: list(head), b: list(head)}
    where = {a: (-wait_x, y0), b: (wait_x, y0 + 5.0)}
    for i in (a, b):
        prog[i].append("G0 X%.3f Y%.3f Z0.2 F6000" % where[i])
    barriers = []
    last_exit = None
    for r in range(rounds):
        for i, side, off in ((a, -1.0, 0.0), (b, 1.0, 5.0)):
            y = y0 + dy * r + off
            if last_exit is not None:
                other, line, end = last_exit
                prog[i].append(";@A9 R%d W%d N%d" % (i, other, line))
                barriers.append((i, other, line, end, where[i]))
            out = (side * wait_x, y + dy)
            prog[i] += ["G0 X%.3f Y%.3f Z0.2 F6000" % (side * zone_x, y),
                        "G1 X%.3f Y%.3f E%.5f F%d" % (-side * zone_x, y, 2 * zone_x * 0.033, feed),
                        "G0 X%.3f Y%.3f Z0.2 F6000" % out]
            last_exit = (i, len(prog[i]), out)
            where[i] = out
    return {i: "\n".join(p) + "\n" for i, p in prog.items()}, barriers
