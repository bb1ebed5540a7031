"""A node going down with a real ROS master: rospy closes every topic in a
pre-shutdown hook (the registration manager's cleanup), before
``rospy.is_shutdown()`` turns true.  A publish in that window raises
"publish() to a closed topic" while ``is_shutdown()`` is still False; CI saw
it once as a traceback from `rosrun ambots front_end` quitting (its
retransmission timer published as the node went down).

The child process below makes the front end's link, then publishes through
it from a pre-shutdown hook registered after rospy's own, i.e. in that
window, and reports what it saw."""
import json
import os
import signal
import socket
import subprocess
import sys
import time

CHILD = r"""
import json, sys
import rospy
from std_msgs.msg import String
rospy.init_node("shutdown_probe", disable_signals=True)
from ambots.ros.front_end import RosLink
link = RosLink()
seen = {}

def hook(reason):
    # rospy's cleanup ran first: the topic is closed, the node not yet "shut down"
    seen["is_shutdown"] = rospy.is_shutdown()
    from ambots.ros import going_down
    seen["going_down"] = going_down()
    seen["closed"] = link._pub.impl is None or bool(link._pub.impl.closed)
    raw = None
    try:
        link._pub.publish(String("A2 R0"))
    except rospy.ROSException as exc:
        raw = str(exc)
    seen["raw_publish"] = raw
    try:
        link._publish("A2 R0")
        seen["link"] = "quiet"
    except Exception as exc:  # noqa: BLE001 -- the test's finding
        seen["link"] = "%s: %s" % (type(exc).__name__, exc)

rospy.core.add_preshutdown_hook(hook)
rospy.signal_shutdown("probe done")
print("SEEN " + json.dumps(seen))
"""


def _free_port():
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def test_a_publish_while_the_node_goes_down_is_dropped_quietly(tmp_path):
    port = _free_port()
    env = dict(os.environ, ROS_MASTER_URI="http://localhost:%d" % port, ROS_HOME=str(tmp_path / "ros_home"))
    master = subprocess.Popen(["roscore", "-p", str(port)], env=env, stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        deadline = time.monotonic() + 20
        while True:
            with socket.socket() as s:
                if s.connect_ex(("localhost", port)) == 0:
                    break
            assert time.monotonic() < deadline, "no ROS master on port %d after 20 s" % port
            time.sleep(0.1)
        run = subprocess.run([sys.executable, "-c", CHILD], env=env, capture_output=True, text=True,
                             timeout=60)
    finally:
        os.killpg(master.pid, signal.SIGINT)      # roscore and the master and rosout it started
        try:
            master.wait(20)
        except subprocess.TimeoutExpired:
            os.killpg(master.pid, signal.SIGKILL)
            master.wait(10)
    out = run.stdout + run.stderr
    assert run.returncode == 0, out
    seen = json.loads(out.split("SEEN ", 1)[1].splitlines()[0])
    # the window exists: rospy itself refuses a publish there, and is_shutdown() says False
    assert seen["is_shutdown"] is False and seen["closed"] is True, seen
    assert seen["raw_publish"] == "publish() to a closed topic", seen
    # ours knows the node is going down and drops the message without a word
    assert seen["going_down"] is True, seen
    assert seen["link"] == "quiet", seen
    assert "Traceback" not in out, out
