"""The thin ROS layer: rospy wrappers around the core.  Only nodes import this."""


def state_dir(value):
    """The directory for the nodes' crash-safe state (made if needed) from a
    ``~state_dir`` param ``value``: "" means ``$ROS_HOME/ambots/state``,
    "none" None (nothing saved)."""
    import os
    import rospkg
    d = str(value).strip()
    if d.lower() == "none":
        return None
    d = d or os.path.join(rospkg.get_ros_home(), "ambots", "state")
    os.makedirs(d, exist_ok=True)
    return d


class ASeriesLog:
    """``debug:=true``: one log line for every A-series message a node sends
    or receives, as the original printed them (``hub <- /ambots/kinova_topic:
    A10 R0 ...``); a no-op when ``enabled`` is false.  ``who``: the node, as
    shown (``hub``, ``kinova firmware``, ``front end``)."""

    def __init__(self, who, enabled):
        self.who, self.enabled = who, bool(enabled)

    def sent(self, topic, text):
        if self.enabled:
            self._log("->", topic, text)

    def received(self, peer, text):
        if self.enabled:
            self._log("<-", peer, text)

    def _log(self, arrow, peer, text):
        import rospy
        from ambots.protocol import one_line
        rospy.loginfo("[A-series] %s %s %s: %s", self.who, arrow, peer, one_line(text))


def debug_param():
    """The node's ``~debug`` param as a bool ("true", "1", True...)."""
    import rospy
    return str(rospy.get_param("~debug", False)).strip().lower() in ("true", "1", "yes", "on")


def going_down():
    """True once the node has begun shutting down.  rospy closes every topic
    in a pre-shutdown hook, before ``rospy.is_shutdown()`` turns true, so a
    publish in that window raises "publish() to a closed topic" while
    ``is_shutdown()`` is still False: this asks for both states."""
    import rospy
    return rospy.is_shutdown() or rospy.core.is_shutdown_requested()


class WallTimer:
    """Calls ``callback()`` every ``period`` wall seconds in a daemon thread
    until ROS shuts down or :meth:`shutdown`.  For retransmissions and other
    work that must go on while a simulated clock (``/clock``) stands still,
    which ``rospy.Timer`` would wait for."""

    def __init__(self, period, callback):
        import threading
        self._stop = threading.Event()
        self._period, self._callback = float(period), callback
        self._thread = threading.Thread(target=self._run, name="wall-timer", daemon=True)
        self._thread.start()

    def _run(self):
        import rospy
        while not self._stop.wait(self._period) and not rospy.is_shutdown():
            try:
                self._callback()
            except rospy.ROSException:
                if going_down():                 # a topic closed under us: going down
                    return
                raise

    def shutdown(self):
        self._stop.set()
