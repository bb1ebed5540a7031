"""The thin ROS layer: rospy wrappers around the core.  Only nodes import this."""
