"""ROS side of the one clock (:mod:`ambots.clock`): reads the arms' and the
hub's readiness on ``topics.CLOCK_READY_TOPIC`` and publishes ``/clock``
(rosgraph_msgs/Clock) whenever :class:`~ambots.clock.Lockstep` says it may
move on.  Every node of the cell runs with ``/use_sim_time`` true."""
import json
import threading
import time

import rospy
from rosgraph_msgs.msg import Clock
from std_msgs.msg import String

from ambots import topics
from ambots.clock import ArmReady, HubState
from ambots.ros import going_down


class ClockNode:
    """Publishes the lockstep clock; ``poll`` (wall s): how often the pace is
    looked at when nothing arrives (the steps of a paced clock: 50 Hz)."""

    def __init__(self, lockstep, poll=0.02, log_period=10.0):
        self.lockstep = lockstep
        self.poll, self.log_period = poll, log_period
        self._lock = threading.Lock()
        self._news = threading.Event()

    def start(self):
        # latched: a node that starts (or is respawned) late gets the instant at once, even
        # while the clock waits for it and publishes nothing new
        self._pub = rospy.Publisher("/clock", Clock, queue_size=10, latch=True)
        rospy.Subscriber(topics.CLOCK_READY_TOPIC, String, self._on_ready, queue_size=1000)

    def _on_ready(self, msg):
        try:
            doc = json.loads(msg.data)
            with self._lock:
                if "arm" in doc:
                    self.lockstep.arm_ready(doc["arm"], ArmReady.from_dict(doc))
                elif "hub" in doc:
                    self.lockstep.hub_ready(HubState.from_dict(doc["hub"]))
        except (ValueError, KeyError, TypeError) as exc:
            rospy.logwarn("clock: ignored a malformed readiness %r: %s", msg.data[:120], exc)
            return
        self._news.set()

    def spin(self):
        self._publish(self.lockstep.now)
        next_log = time.monotonic() + self.log_period
        while not rospy.is_shutdown():
            self._news.wait(self.poll)
            self._news.clear()
            wall = time.monotonic()
            with self._lock:
                t = self.lockstep.next(wall)
                late = self.lockstep.waiting_for() if wall >= next_log else None
            if t is not None:
                try:
                    self._publish(t)
                except rospy.ROSException:
                    if going_down():             # the topic closed under us: going down
                        return
                    raise
            if late is not None:
                next_log = wall + self.log_period
                if late:
                    rospy.loginfo("clock at %.3f s (steps %s), waiting for %s", self.lockstep.now,
                                  self.lockstep.reasons, ", ".join(late))

    def _publish(self, t):
        self._pub.publish(Clock(clock=rospy.Time.from_sec(t)))
