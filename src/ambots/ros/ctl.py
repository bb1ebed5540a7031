"""ROS side of ``python -m ambots ctl``: node ``/ambots_ctl`` publishes the
operator's A2 / A6 / A12 (unnumbered: a tool has no inbox) to the hub, then
reads the hub's progress until every arm named has obeyed, and the error
topic for a refusal of its own messages."""
import json
import sys
import time

import rospy
from std_msgs.msg import String

from ambots import topics
from ambots.config import default_cell_path, load_cell
from ambots.control import commands, settled
from ambots.protocol import ArmState, encode

#: the ctl tool's ROS node name (both_arms.launch lists it among the hub's callers)
NODE = "/ambots_ctl"
#: how long after sending the tool waits at least for a refusal on the error topic (s)
REFUSAL_GRACE_S = 1.0


def main(action, target, cell_path=None, timeout=60.0, node=NODE, out=print, err=None):
    """Send ``action`` to ``target`` as ROS node ``node`` and wait up to
    ``timeout`` s (wall) for the arms to obey.  Returns 0 (done), 1
    (refused, no hub, timeout)."""
    node = "/" + node.lstrip("/")
    err = err or (lambda line: print(line, file=sys.stderr, flush=True))
    import rosgraph
    if not rosgraph.is_master_online():
        err("ctl: no ROS master at %s (is the cell running?)" % rosgraph.get_master_uri())
        return 1
    rospy.init_node(node.lstrip("/"), disable_signals=True)
    try:
        cell = load_cell(cell_path or rospy.get_param(topics.HUB_NODE + "/cell", default_cell_path()))
        msgs = commands(cell, action, target)
        names = {m.robot: cell.arm_by_id(m.robot).name for m in msgs}
        docs, refusals = [], []
        pub = rospy.Publisher(topics.HUB_TOPIC, String, queue_size=10)
        subs = [rospy.Subscriber(topics.PROGRESS_TOPIC, String, lambda m: docs.append(json.loads(m.data))),
                rospy.Subscriber(topics.ERROR_TOPIC, String,
                                 lambda m: refusals.append(m.data) if "from %s:" % node in m.data else None)]
        t0 = time.monotonic()
        while pub.get_num_connections() == 0 or any(s.get_num_connections() == 0 for s in subs):
            if time.monotonic() - t0 > 5.0:
                err("ctl: no communication hub on %s (is the cell running?)" % topics.HUB_TOPIC)
                return 1
            time.sleep(0.05)
        for m in msgs:
            pub.publish(String(encode(m)))
        out("%s sent to %s" % (" ".join(encode(m) for m in msgs),
                               ", ".join("%s (R%d)" % (n, i) for i, n in names.items())))
        if timeout <= 0:
            time.sleep(0.5)               # let the messages leave
            return 0
        sent = time.monotonic()
        n_docs, state = 0, {}
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and not rospy.is_shutdown():
            if refusals:
                err("ctl: %s" % refusals[0])
                return 1
            for doc in docs[n_docs:]:
                for name, arm in doc.get("arms", {}).items():
                    state[name] = arm.get("state")
            n_docs = len(docs)
            # a refusal takes the hub a moment: never report success before REFUSAL_GRACE
            if n_docs and time.monotonic() >= sent + REFUSAL_GRACE_S \
                    and all(_obeyed(action, state.get(n)) for n in names.values()):
                out("; ".join("%s %s" % (n, state[n]) for n in names.values()))
                return 0
            time.sleep(0.05)
        err("ctl: timed out after %.0f s: %s" % (timeout, "; ".join(
            "%s %s" % (n, state.get(n, "unknown")) for n in names.values())))
        return 1
    finally:
        rospy.signal_shutdown("ctl done")


def _obeyed(action, state_name):
    try:
        return settled(action, ArmState[state_name])
    except KeyError:
        return False
