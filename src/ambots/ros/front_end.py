"""ROS side of the front end: moves the strings of
:class:`ambots.frontend.ReliableLink` -- a publisher on ``topics.HUB_TOPIC``
(the hub knows the front end by its node name ``/front_end``), a subscriber
on ``topics.FRONT_END_TOPIC`` (the hub's acks of our messages, and the arms'
A10/A11 it forwards, which the link acknowledges with ``A8 R1001 Q<q> S1000``
back to the hub), a subscriber on the hub's progress (``--follow``), and a
timer for retransmissions."""
import time

import rospy
from std_msgs.msg import String

from ambots import topics
from ambots.frontend import ReliableLink
from ambots.ros import ASeriesLog, WallTimer, going_down


class RosLink(ReliableLink):
    """A :class:`~ambots.frontend.ReliableLink` over ROS topics; call after
    ``rospy.init_node(topics.FRONT_END_NODE...)``.  ``retry_period`` (s):
    how often due retransmissions are looked for; other keywords go to
    :class:`~ambots.frontend.ReliableLink`."""

    def __init__(self, retry_period=0.05, debug=False, **kw):
        self.log = ASeriesLog("front end", debug)
        self._pub = rospy.Publisher(topics.HUB_TOPIC, String, queue_size=100)
        super().__init__(self._publish, **kw)
        self._sub = rospy.Subscriber(topics.FRONT_END_TOPIC, String, self._on_message, queue_size=1000)
        self._progress_sub = rospy.Subscriber(topics.PROGRESS_TOPIC, String,
                                              lambda msg: self.receive_progress(msg.data), queue_size=1)
        self._timer = WallTimer(retry_period, self.tick)      # wall time: a simulated clock may stand still

    _closed = False

    def _publish(self, text):
        if self._closed:                 # closing: a message that came in meanwhile is not answered
            return
        self.log.sent(topics.HUB_TOPIC, text)
        try:
            self._pub.publish(String(text))
        except rospy.ROSException:
            # the topic closed under a subscriber's callback (close() or the node going down)
            if self._closed or going_down():
                return
            raise

    def _on_message(self, msg):
        self.log.received("hub via " + topics.FRONT_END_TOPIC, msg.data)
        self.receive_text(msg.data)

    def wait_for_hub(self, timeout):
        """Wait up to ``timeout`` s until the hub is connected both ways;
        False if it is not (messages are retried anyway)."""
        deadline = time.monotonic() + timeout
        while not rospy.is_shutdown() and time.monotonic() < deadline:
            if self._pub.get_num_connections() > 0 and self._sub.get_num_connections() > 0:
                return True
            time.sleep(0.02)
        return False

    def close(self):
        self._closed = True
        self._timer.shutdown()
        self._sub.unregister()
        self._progress_sub.unregister()
        self._pub.unregister()
