"""ROS side of the communication hub: one subscriber on ``topics.HUB_TOPIC``
feeding :class:`ambots.hub.Hub` with each message's caller id, publishers
for every post it returns, a timer for retransmissions and a timer that
republishes the progress (latched) even without news."""
import threading

import rospy
from std_msgs.msg import String

from ambots import topics


class HubNode:
    """Connects ``hub`` to ROS.  ``retry_period`` (s) is how often due
    retransmissions are looked for; ``progress_period`` (s) how often the
    progress is republished.  rospy calls back from several threads, so
    every call into the hub holds one lock."""

    def __init__(self, hub, retry_period=0.05, progress_period=1.0):
        self.hub = hub
        self.retry_period, self.progress_period = retry_period, progress_period
        self._lock = threading.Lock()
        self._pubs = {}

    def start(self):
        """Advertise, subscribe and start the timers."""
        for topic in self.hub.registry.inboxes + [topics.ERROR_TOPIC]:
            self._pubs[topic] = rospy.Publisher(topic, String, queue_size=100)
        self._pubs[topics.PROGRESS_TOPIC] = rospy.Publisher(topics.PROGRESS_TOPIC, String,
                                                            queue_size=1, latch=True)
        rospy.Subscriber(topics.HUB_TOPIC, String, self._on_message, queue_size=1000)
        rospy.Timer(rospy.Duration(self.retry_period), self._on_retry_timer)
        rospy.Timer(rospy.Duration(self.progress_period), self._on_progress_timer)

    def _on_message(self, msg):
        with self._lock:
            self._publish(self.hub.handle(msg.data, msg._connection_header["callerid"],
                                          rospy.get_time()))

    def _on_retry_timer(self, _event):
        with self._lock:
            self._publish(self.hub.tick(rospy.get_time()))

    def _on_progress_timer(self, _event):
        with self._lock:
            self._pubs[topics.PROGRESS_TOPIC].publish(String(self.hub.progress_json(rospy.get_time())))

    def _publish(self, posts):
        for post in posts:
            if post.topic == topics.ERROR_TOPIC:
                rospy.logwarn(post.text)
            self._pubs[post.topic].publish(String(post.text))
