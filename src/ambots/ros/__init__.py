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
                if rospy.is_shutdown():          # a topic closed under us: going down
                    return
                raise

    def shutdown(self):
        self._stop.set()
