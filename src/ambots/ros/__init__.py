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
